"""The networks' configurations and the models' metadata as typed dataclasses: torch-free, so that training
(which builds the nets from them) and the runtime (which reads them back from an ONNX file) share one
definition.

An exported graph carries its metadata as ``egoposevr.<field>`` string properties (:func:`to_properties`):
strings as they are, everything else as JSON. :func:`from_properties` validates them back into the dataclass
with pydantic: a wrong type, a missing field or a field this version does not know is a ``ValueError`` that
names it, so a model made by a newer version is refused instead of served wrongly.
"""

from __future__ import annotations

import dataclasses
import json
import typing
from typing import Any, Final, TypeVar

import pydantic

FORMAT_VERSION: Final = "1"
# train --keep-joints: the joints a fine-tune's kept term holds against the net it starts from (the training
# module maps each choice to its joints), and the choices that leave the trunk under the head free, the only
# ones a fine-tune that moves the head joint (--reanchor) may keep. Here, torch-free, so that the command line
# checks them before torch and the data load.
KEEP_JOINTS_CHOICES: Final = ("upper", "arms", "arms_legs")
TRUNK_FREE_KEEPS: Final = ("arms", "arms_legs")
_STRICT = pydantic.ConfigDict(extra="forbid")
T = TypeVar("T")


@dataclasses.dataclass(frozen=True)
class FusionConfig:
    """The fusion net (paper §3.3): window lengths and widths."""

    __pydantic_config__ = _STRICT

    window: int = 40  # T: HMD samples
    visual_window: int = 8  # Tv: camera frames (1: single-frame model); ignored when fusion == "none"
    fusion: typing.Literal["cross", "concat", "none"] = "cross"
    d_model: int = 64  # frame-wise transformer width
    joint_dim: int = 32  # S
    heads: int = 4
    frame_layers: int = 2
    joint_layers: int = 2
    dropout: float = 0.1
    joints: int = 22
    device_validity: bool = False  # x_t followed by each device's valid flag and time since tracked (hmd.py)
    contact_head: bool = False  # a second output: each foot's contact probability (runtime/contact.py)
    # Training only, never exported or served: each foot's time to its next contact change and since its last
    # (training/plausibility.contact_timing), an auxiliary target that asks the net for the step's rhythm.
    timing_head: bool = False

    def __post_init__(self) -> None:
        if self.fusion not in ("cross", "concat", "none"):
            raise ValueError(f"fusion must be cross, concat or none, got {self.fusion!r}")

    @property
    def uses_camera(self) -> bool:
        return self.fusion != "none"

    @property
    def served(self) -> FusionConfig:
        """This config as an exported file records it: without the training-only heads, which its graph
        leaves out (the same net, as the runtime and a fine-tune from the file see it)."""
        return dataclasses.replace(self, timing_head=False)


@dataclasses.dataclass(frozen=True)
class VisualConfig:
    """The keypoint net (paper §3.3): input size and channels, backbone and FPN widths."""

    __pydantic_config__ = _STRICT

    channels: int = 4  # 3: RGB, 4: RGB-D
    width: int = 80
    height: int = 64
    widths: tuple[int, ...] = (16, 32, 64, 128)  # backbone stages, strides 2, 4, 8, 16 (after the stem)
    fpn_channels: int = 32
    joints: int = 22
    # > 0: a strided 3x3 convolution of this many channels first, so that a larger input (160x128) costs about
    # what the smaller one did while the first layer still sees every pixel; heatmaps are then at stride 4.
    stem_channels: int = 0

    @property
    def input_stride(self) -> int:
        return 2 if self.stem_channels else 1

    @property
    def heatmap_wh(self) -> tuple[int, int]:
        return self.width // (2 * self.input_stride), self.height // (2 * self.input_stride)

    @property
    def input_wh(self) -> tuple[int, int]:
        return self.width, self.height


@dataclasses.dataclass(frozen=True)
class CameraInfo:
    """The camera a visual encoder was trained with (a dataset split's ``camera`` entry). The runtime uses
    ``cam_from_head`` when a frame names no mount of its own."""

    __pydantic_config__ = _STRICT

    width: int
    height: int
    intrinsics: tuple[float, float, float, float]  # fx, fy, cx, cy of the width×height image, pixels
    hfov_deg: float
    pitch_down_deg: float
    cam_from_head: tuple[float, ...]  # (16,) row-major 4×4 rigid transform
    depth_units: str
    min_depth_m: float
    max_depth_m: float


@dataclasses.dataclass(frozen=True)
class ModelMetadata:
    """What a model file ``<name>.onnx`` (a fusion net) says about itself."""

    __pydantic_config__ = _STRICT

    format: str
    kind: typing.Literal["model"]
    name: str
    description: str
    inputs: tuple[str, ...]  # "hmd" [+ "rgb" [+ "depth"]]
    config: FusionConfig
    kpo: bool
    visual_encoder: str  # file name beside this one; "" for none
    joint_names: tuple[str, ...]
    rig_offsets_m: tuple[tuple[float, float, float], ...]  # (3, 3) device -> joint, rows head/left/right
    training: dict[str, Any]
    units: str
    # The runtime's lean gate (runtime/stance.py) on for this model: the nets were chosen served with it, and
    # a net that was not can freeze wrong early guesses under it (MODEL_CARD.md, rules 37 and 44).
    lean_gate: bool = False
    # The body estimate's quiet-head lift (runtime/body.py, QuietHead) on for this model: its nets hang the
    # body from the head joint where the eyes are, so a body too short for the wearer floats its feet
    # (MODEL_CARD.md, rules 77 and 78). Files written before the field read False.
    quiet_lift: bool = False


@dataclasses.dataclass(frozen=True)
class EncoderMetadata:
    """What a visual encoder file ``visual-<kind>.onnx`` says about itself."""

    __pydantic_config__ = _STRICT

    format: str
    kind: typing.Literal["visual"]
    name: str
    config: VisualConfig
    camera: CameraInfo
    joint_names: tuple[str, ...]
    training: dict[str, Any]
    units: str


def parse(cls: type[T], fields: dict[str, Any]) -> T:
    """A dataclass from plain fields (JSON-like values). Raises ValueError naming what is wrong."""
    try:
        return pydantic.TypeAdapter(cls).validate_python(fields)
    except pydantic.ValidationError as exc:
        raise ValueError(_first_problem(cls, exc)) from None


def to_fields(config: Any) -> dict[str, Any]:
    """A dataclass -> plain JSON-able fields (tuples as lists)."""
    return json.loads(json.dumps(dataclasses.asdict(config)))


def from_properties(cls: type[T], properties: dict[str, str]) -> T:
    """Metadata properties (prefix already removed) -> the dataclass. Raises ValueError."""
    text_fields = {name for name, hint in typing.get_type_hints(cls).items() if _is_text(hint)}
    fields: dict[str, Any] = {}
    for key, value in properties.items():
        try:
            fields[key] = value if key in text_fields else json.loads(value)
        except ValueError:
            raise ValueError(f"metadata field {key!r} is not JSON: {value[:60]!r}") from None
    return parse(cls, fields)


def to_properties(metadata: Any) -> dict[str, str]:
    """The dataclass -> metadata properties: strings as they are, the rest as sorted JSON."""
    return {
        key: value if isinstance(value, str) else json.dumps(value, sort_keys=True)
        for key, value in to_fields(metadata).items()
    }


def _is_text(hint: Any) -> bool:
    """Whether a field is written as a bare string property: ``str`` or a Literal of strings."""
    if typing.get_origin(hint) is typing.Literal:
        return all(isinstance(a, str) for a in typing.get_args(hint))
    return hint is str


def _first_problem(cls: type, exc: pydantic.ValidationError) -> str:
    error = exc.errors()[0]
    where = ".".join(str(p) for p in error["loc"]) or "(all)"
    if error["type"] in ("extra_forbidden", "unexpected_keyword_argument"):
        return f"{cls.__name__}: unknown field {where!r} (made by a newer version?)"
    if error["type"] == "missing":
        return f"{cls.__name__}: field {where!r} is missing"
    return f"{cls.__name__}: field {where!r}: {error['msg']}"
