"""Loading servable models: a fusion graph ``<name>.onnx`` plus the visual encoder its metadata names, with
their metadata read into typed dataclasses (:mod:`egoposevr.model.config`) and the encoder's body regressor.

Shape legend: ``B`` batch, ``C`` channels, ``h``×``w`` encoder input, ``J`` = 22 joints.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from pathlib import Path
from typing import Any, Final

import numpy as np
import onnxruntime as ort

from ..config import CameraInfo, EncoderMetadata, FusionConfig, ModelMetadata, VisualConfig, from_properties
from . import kernels
from .body import BodyRegressor, load_regressor_for

RGBD_CHANNELS = 4  # RGB + depth: the encoder input that measures bone lengths


class ModelError(Exception):
    """A model file that cannot be served: unreadable, not an EgoPoseVR graph, or missing its encoder."""


class ProviderError(ValueError):
    """Execution providers asked for that this onnxruntime cannot give (and no allowed fallback can)."""


# Short names people type -> onnxruntime's execution provider names (full names are accepted as well).
PROVIDER_NAMES: Final = {
    "cpu": "CPUExecutionProvider",
    "cuda": "CUDAExecutionProvider",
    "tensorrt": "TensorrtExecutionProvider",
    "openvino": "OpenVINOExecutionProvider",
    "rocm": "ROCMExecutionProvider",
    "migraphx": "MIGraphXExecutionProvider",
    "directml": "DmlExecutionProvider",
    "coreml": "CoreMLExecutionProvider",
}
DEFAULT_PROVIDERS: Final = ("CPUExecutionProvider",)
# Providers that load CUDA and cuDNN from the process: onnxruntime-gpu finds them in the nvidia-* wheels
# (onnxruntime-gpu[cuda,cudnn]) only when asked to preload them; a system CUDA needs no help.
_CUDA_PROVIDERS: Final = frozenset({"CUDAExecutionProvider", "TensorrtExecutionProvider"})
_log = logging.getLogger(__name__)


def resolve_providers(spec: str, available: list[str] | None = None) -> tuple[str, ...]:
    """A comma-separated preference (``"cuda,cpu"``) -> onnxruntime provider names, most preferred first.

    Every name must be one onnxruntime knows. Those this installation lacks are dropped only when a later one
    in the list is installed: listing ``cpu`` after ``cuda`` is what allows falling back to it. Raises
    ProviderError naming what is missing and what is installed."""
    available = ort.get_available_providers() if available is None else available
    wanted = [part.strip() for part in spec.split(",") if part.strip()]
    if not wanted:
        raise ProviderError("no execution provider given (e.g. cpu, or cuda,cpu)")
    names = []
    for part in wanted:
        name = PROVIDER_NAMES.get(part.lower(), part)
        if name not in PROVIDER_NAMES.values() and not name.endswith("ExecutionProvider"):
            known = ", ".join(PROVIDER_NAMES)
            raise ProviderError(
                f"unknown execution provider {part!r}; known: {known} (or onnxruntime's names)"
            )
        names.append(name)
    usable = [n for n in names if n in available]
    if not usable or names[-1] not in available:
        missing = [n for n in names if n not in available]
        raise ProviderError(
            f"execution provider {', '.join(missing)} is not available in this onnxruntime (it has "
            f"{', '.join(available)}); install the matching onnxruntime package (onnxruntime-gpu for CUDA and "
            "TensorRT, onnxruntime-openvino for OpenVINO), or list a provider to fall back to last, e.g. cuda,cpu"
        )
    return tuple(usable)


@dataclasses.dataclass(frozen=True)
class ModelInfo:
    """One servable model: its files, its metadata and its encoder's (None for HMD-only models)."""

    path: Path
    metadata: ModelMetadata
    visual_path: Path | None
    encoder: EncoderMetadata | None
    body_regressor: BodyRegressor | None = None  # fitted on the visual encoder's keypoints (body.py)

    @property
    def name(self) -> str:
        return self.metadata.name

    @property
    def description(self) -> str:
        return self.metadata.description

    @property
    def inputs(self) -> tuple[str, ...]:
        return self.metadata.inputs

    @property
    def kpo(self) -> bool:
        return self.metadata.kpo

    @property
    def lean_gate(self) -> bool:
        """Whether the file asks for the lean gate (runtime/stance.py); a pipeline may override it."""
        return self.metadata.lean_gate

    @property
    def quiet_lift(self) -> bool:
        """Whether the file asks for the body estimate's quiet-head lift (runtime/body.py); a pipeline may
        override it."""
        return self.metadata.quiet_lift

    @property
    def config(self) -> FusionConfig:
        return self.metadata.config

    @property
    def visual_config(self) -> VisualConfig | None:
        return self.encoder.config if self.encoder else None

    @property
    def camera(self) -> CameraInfo | None:
        """The camera the encoder was trained with."""
        return self.encoder.camera if self.encoder else None

    @functools.cached_property
    def rig_offsets_m(self) -> np.ndarray:
        """(3, 3) device -> joint offsets, rows head / left / right; read-only (the pipeline reads it every
        sample, so it is made once)."""
        offsets = np.array(self.metadata.rig_offsets_m, dtype=np.float64)
        offsets.flags.writeable = False
        return offsets


def load_encoder(
    path: str | Path, threads: int = 1, providers: tuple[str, ...] = DEFAULT_PROVIDERS
) -> tuple[ort.InferenceSession, EncoderMetadata]:
    """An exported visual encoder alone (``visual-<kind>.onnx``): its session and metadata; ModelError if
    the file is not one."""
    session = _session(Path(path), threads, providers)
    return session, _metadata(Path(path), session, EncoderMetadata, "visual")


def _properties(session: ort.InferenceSession) -> dict[str, str]:
    meta = session.get_modelmeta().custom_metadata_map
    return {k.removeprefix("egoposevr."): v for k, v in meta.items() if k.startswith("egoposevr.")}


@functools.cache
def _preload_cuda_libraries() -> None:
    """Load the CUDA / cuDNN libraries of the nvidia-* wheels, once, before a CUDA session is made.

    Without this the CUDA provider finds them only on LD_LIBRARY_PATH. A failure is logged, not raised: a
    system-wide CUDA may still serve, and session creation reports what is really missing."""
    preload = getattr(ort, "preload_dlls", None)  # onnxruntime-gpu >= 1.21
    if preload is None:
        return
    try:
        preload()
    except Exception as exc:  # what is missing is the provider's to report
        _log.warning("onnxruntime.preload_dlls failed (%s); relying on the system's CUDA libraries", exc)


def _session(
    path: Path, threads: int, providers: tuple[str, ...] = DEFAULT_PROVIDERS
) -> ort.InferenceSession:
    if _CUDA_PROVIDERS.intersection(providers):
        _preload_cuda_libraries()
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")  # do not burn idle cores
    try:
        return ort.InferenceSession(str(path), options, providers=list(providers))
    except Exception as exc:  # onnxruntime raises its own exception types for bad files
        raise ModelError(f"{path}: cannot load ({exc})") from exc


def _metadata(path: Path, session: ort.InferenceSession, cls: type, kind: str) -> Any:
    properties = _properties(session)
    if properties.get("kind") != kind:
        raise ModelError(f"{path}: not an EgoPoseVR {kind} (metadata kind {properties.get('kind')!r})")
    try:
        return from_properties(cls, properties)
    except ValueError as exc:
        raise ModelError(f"{path}: unusable EgoPoseVR metadata ({exc})") from exc


class LoadedModel:
    """ONNX sessions of one servable model; visual encoders are shared between models via ``shared``."""

    def __init__(self, info: ModelInfo, fusion: ort.InferenceSession, visual: ort.InferenceSession | None):
        self.info, self.fusion, self.visual = info, fusion, visual
        # A graph exported with a symbolic batch axis runs several sessions' windows in one call (the
        # server's cross-session batching); one exported for batch 1 runs them one by one.
        self.batchable = not isinstance(fusion.get_inputs()[0].shape[0], int)

    @classmethod
    def load(
        cls,
        path: str | Path,
        threads: int = 1,
        shared: dict[Path, Any] | None = None,
        providers: tuple[str, ...] = DEFAULT_PROVIDERS,
    ) -> LoadedModel:
        """Load a model file (and its encoder, shared through ``shared``) on the given onnxruntime execution
        providers (:func:`resolve_providers`)."""
        path = Path(path)
        kernels.warm_up()  # compiled (or loaded from numba's cache) before the first pose, not during it
        fusion = _session(path, threads, providers)
        metadata = _metadata(path, fusion, ModelMetadata, "model")
        visual_path = path.parent / metadata.visual_encoder if metadata.visual_encoder else None
        visual, encoder, regressor = None, None, None
        if visual_path is not None:
            shared = {} if shared is None else shared
            if visual_path not in shared:
                if not visual_path.exists():
                    raise ModelError(f"{path}: its visual encoder {visual_path.name} is missing")
                shared[visual_path] = _session(visual_path, threads, providers)
            visual = shared[visual_path]
            encoder = _metadata(visual_path, visual, EncoderMetadata, "visual")
            try:
                regressor = load_regressor_for(visual_path)
            except ValueError as exc:
                raise ModelError(f"{path}: {exc}") from exc
        info = ModelInfo(path, metadata, visual_path, encoder, regressor)
        return cls(info, fusion, visual)

    @property
    def provider(self) -> str:
        """The execution provider that runs the fusion net (the first onnxruntime actually gave it)."""
        return self.fusion.get_providers()[0]

    @property
    def measures_body(self) -> bool:
        """Whether its visual encoder sees depth, so that its keypoints measure bone lengths (body.py).
        RGB-only keypoints guess their depth, so RGB models keep the height-scaled body (MODEL_CARD.md, the
        body regressor, has the measurement)."""
        vc = self.info.visual_config
        return self.visual is not None and vc is not None and vc.channels == RGBD_CHANNELS

    def encode_frames(self, images: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(B, C, h, w) -> uv (B, J, 2), depth_m (B, J), zeta (B, J)."""
        uv, depth_m, zeta = self.visual.run(None, {"image": images})
        return uv, depth_m, zeta
