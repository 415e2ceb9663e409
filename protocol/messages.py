"""Pydantic v2 models of every protocol-v1 message (PROTOCOL.md is the contract; this is its code).

Conventions shared by all messages:
- right-handed world, Y up, -Z forward, metres; quaternions are (x, y, z, w); times are integer microseconds
  (``t_us``) on the sender's monotonic clock.
- floats must be finite; integers in float fields are accepted (JavaScript encoders write 1.0 as 1); bools,
  strings and nil are not.
- unknown fields are ignored (forward compatibility); optional fields may be absent or nil.

Messages are frozen: build a new one rather than mutating a decoded one.
"""

from __future__ import annotations

import math
from typing import Annotated, ClassVar, Literal

from annotated_types import Len
from pydantic import BaseModel, ConfigDict, Field, Strict, model_validator
from pydantic.types import AllowInfNan
from pydantic_core import PydanticCustomError

PROTOCOL_VERSION = 1

# --- field types -------------------------------------------------------------------------------------------
Float = Annotated[float, Strict(), AllowInfNan(False)]
Int = Annotated[int, Strict()]
Bool = Annotated[bool, Strict()]
Seq = Annotated[int, Strict(), Field(ge=0, lt=2**63)]
TimeUs = Annotated[int, Strict(), Field(ge=0, lt=2**63)]
Coord = Annotated[float, Strict(), AllowInfNan(False), Field(ge=-1e4, le=1e4)]  # metres or unit-less
Name = Annotated[str, Strict(), Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.:\-]+$")]
Text = Annotated[str, Strict(), Field(max_length=1024)]
Digest = Annotated[str, Strict(), Field(pattern=r"^[0-9a-f]{64}$")]  # sha256, lowercase hex
Blob = Annotated[bytes, Strict(), Field(min_length=1)]


def vec(n: int, item: object = Float) -> object:
    """A fixed-length array of ``n`` items."""
    return Annotated[list[item], Len(n, n)]  # type: ignore[valid-type]


# [px, py, pz, qx, qy, qz, qw]. Any number at all for an untracked device (zeros, NaN, a stale pose): its seven
# numbers are ignored. A tracked device's are checked by Hmd (finite, |coordinate| <= 10 km, unit quaternion).
AnyFloat = Annotated[float, Strict()]
DevicePose = vec(7, AnyFloat)
COORD_LIMIT = 1e4
IMAGE_MAX_SIDE_PX = 4096
QUAT_NORM_TOLERANCE = 0.1  # |‖q‖ - 1| allowed for a tracked device; consumers normalise
JPEG_SIGNATURE = b"\xff\xd8\xff"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


class Message(BaseModel):
    """Base of every v1 message: a msgpack map with ``type`` and ``v``."""

    model_config = ConfigDict(extra="ignore", frozen=True)
    TYPE: ClassVar[str]
    type: (
        str  # each message narrows this to its Literal; declared here so that it is the first key on the wire
    )
    v: Literal[1] = 1


# --- client -> server --------------------------------------------------------------------------------------
class Hello(Message):
    """First message on every connection; the server answers ``welcome`` or a fatal ``error``."""

    TYPE: ClassVar[str] = "hello"
    type: Literal["hello"] = "hello"
    role: Literal["input", "render"]
    session: Name
    model: Name | None = None
    token: Annotated[str, Strict(), Field(max_length=256)] | None = None
    client: Annotated[str, Strict(), Field(max_length=128)] | None = None


class Hmd(Message):
    """One headset sample: head and controller poses at ``t_us``; ``valid`` = (head, left, right) tracked.

    ``truth`` (optional, replayed recordings only): the true 22 joints (66 floats, m), passed through to the
    pose so that viewers can show the ground truth; the model never sees it."""

    TYPE: ClassVar[str] = "hmd"
    type: Literal["hmd"] = "hmd"
    seq: Seq
    t_us: TimeUs
    head: DevicePose
    left: DevicePose
    right: DevicePose
    valid: vec(3, Bool)
    truth: vec(66, Coord) | None = None  # ground-truth joints (recorded sessions): echoed in the pose

    @model_validator(mode="after")
    def _tracked_devices_are_usable(self) -> Hmd:
        for name, pose, tracked in zip(("head", "left", "right"), self.poses(), self.valid, strict=True):
            if tracked:
                _check_tracked_pose(name, pose)
        return self

    def poses(self) -> tuple[list[float], list[float], list[float]]:
        """(head, left, right) device poses, each [px, py, pz, qx, qy, qz, qw]."""
        return self.head, self.left, self.right


def _check_tracked_pose(name: str, pose: list[float]) -> None:
    """A tracked device's seven numbers: finite, coordinates within ±10 km, a unit quaternion (±0.1)."""
    for k, value in enumerate(pose):
        if not math.isfinite(value):
            raise PydanticCustomError(
                "finite_number",
                f"{name}[{k}]: expected a finite number for a tracked device (valid is true), got {value}",
            )
        if abs(value) > COORD_LIMIT:
            raise PydanticCustomError(
                "out_of_range", f"{name}[{k}]: expected a value within ±{COORD_LIMIT:g}, got {value:g}"
            )
    norm = math.sqrt(sum(q * q for q in pose[3:]))
    if abs(norm - 1.0) > QUAT_NORM_TOLERANCE:
        raise PydanticCustomError(
            "bad_quaternion",
            f"{name}: expected a unit quaternion (norm 1 ± {QUAT_NORM_TOLERANCE}) for a tracked device, "
            f"got norm {norm:.4g}",
        )


class Rgbd(Message):
    """One egocentric RGB-D frame: JPEG colour and 16-bit PNG depth (millimetres, 0 = no reading)."""

    TYPE: ClassVar[str] = "rgbd"
    type: Literal["rgbd"] = "rgbd"
    seq: Seq
    t_us: TimeUs
    width: Annotated[int, Strict(), Field(ge=1, le=IMAGE_MAX_SIDE_PX)]
    height: Annotated[int, Strict(), Field(ge=1, le=IMAGE_MAX_SIDE_PX)]
    intrinsics: vec(4)  # fx, fy, cx, cy in pixels
    rgb: Blob
    depth: Blob
    cam_from_head: vec(16) | None = None  # row-major 4x4, metres

    @model_validator(mode="after")
    def _check_images_and_camera(self) -> Rgbd:
        fx, fy, _, _ = self.intrinsics
        if fx <= 0 or fy <= 0:
            raise PydanticCustomError("out_of_range", f"intrinsics: expected fx, fy > 0, got {fx} and {fy}")
        if not self.rgb.startswith(JPEG_SIGNATURE):
            raise PydanticCustomError(
                "bad_image",
                f"rgb: expected a JPEG (starts {JPEG_SIGNATURE.hex()}), got {self.rgb[:4].hex()}...",
            )
        if not self.depth.startswith(PNG_SIGNATURE):
            raise PydanticCustomError(
                "bad_image",
                f"depth: expected a PNG (starts {PNG_SIGNATURE[:4].hex()}), got {self.depth[:4].hex()}...",
            )
        if self.cam_from_head is not None:
            _check_rigid(self.cam_from_head)
        return self


def _check_rigid(m: list[float]) -> None:
    """Raise unless the row-major 4x4 ``m`` is a rotation + translation with last row (0, 0, 0, 1)."""
    if any(abs(a - b) > 1e-6 for a, b in zip(m[12:], (0.0, 0.0, 0.0, 1.0), strict=True)):
        raise PydanticCustomError(
            "bad_transform", f"cam_from_head: expected the last row 0 0 0 1, got {m[12:]}"
        )
    rows = (m[0:3], m[4:7], m[8:11])
    for i in range(3):
        for j in range(3):
            dot = sum(a * b for a, b in zip(rows[i], rows[j], strict=True))
            if abs(dot - (1.0 if i == j else 0.0)) > 1e-3:
                raise PydanticCustomError(
                    "bad_transform",
                    "cam_from_head: expected a rotation (orthonormal rows) in the upper 3x3 block",
                )


class SelectModel(Message):
    """Swap the session's model without reconnecting; answered by ``models`` (or ``error``)."""

    TYPE: ClassVar[str] = "select_model"
    type: Literal["select_model"] = "select_model"
    model: Name


class Calibrate(Message):
    """Ask the server to measure the wearer: hold ``pose`` still for ``seconds`` (PROTOCOL.md §4.1); answered
    by ``calibration`` messages. ``clear`` forgets the session's calibration instead."""

    TYPE: ClassVar[str] = "calibrate"
    type: Literal["calibrate"] = "calibrate"
    pose: Literal["tpose", "stand"] = "tpose"
    seconds: Annotated[float, Strict(), AllowInfNan(False), Field(ge=0.5, le=10.0)] = 2.0
    clear: Bool = False


# A bone's length, m: the SMPL mean body's shortest is 5.6 cm (spine2 to spine3), its longest 43 cm (knee to
# ankle); the server also holds each to 0.5-2 times the mean body's (PROTOCOL.md §4.2).
BoneLength = Annotated[float, Strict(), AllowInfNan(False), Field(ge=0.01, le=1.0)]


class SetBody(Message):
    """Serve a known wearer's body from now on (PROTOCOL.md §4.2): ``bone_lengths_m`` as a ``body`` message
    gave them (joints 1..21, each from its parent), or ``clear`` to estimate the body again. Answered by
    ``body``."""

    TYPE: ClassVar[str] = "set_body"
    type: Literal["set_body"] = "set_body"
    bone_lengths_m: vec(21, BoneLength) | None = None
    clear: Bool = False

    @model_validator(mode="after")
    def _one_of(self) -> SetBody:
        if (self.bone_lengths_m is None) == (not self.clear):
            raise PydanticCustomError(
                "bad_set_body", "set_body: give bone_lengths_m or clear: true, not both and not neither"
            )
        return self


class GetBody(Message):
    """Ask for the wearer's body as the session knows it; answered by ``body`` (PROTOCOL.md §4.2)."""

    TYPE: ClassVar[str] = "get_body"
    type: Literal["get_body"] = "get_body"


class ListModels(Message):
    """Ask for the ``models`` list."""

    TYPE: ClassVar[str] = "list_models"
    type: Literal["list_models"] = "list_models"


class Ping(Message):
    """Liveness/latency probe; ``nonce`` and ``t_us`` are echoed in ``pong``."""

    TYPE: ClassVar[str] = "ping"
    type: Literal["ping"] = "ping"
    nonce: Seq | None = None
    t_us: TimeUs | None = None


# --- server -> client --------------------------------------------------------------------------------------
class Welcome(Message):
    """Answer to ``hello``: the session joined, the role granted, the active model and all models."""

    TYPE: ClassVar[str] = "welcome"
    type: Literal["welcome"] = "welcome"
    session: Name
    role: Literal["input", "render"]
    server: Text  # "egoposevr/<version>"
    model: Name
    models: Annotated[list[Name], Len(0, 256)]
    provider: Text | None = (
        None  # the onnxruntime execution provider running the active model ("none": no net)
    )


class Pose(Message):
    """The full-body pose answering headset sample ``seq``/``t_us``.

    ``global_orient`` (3) and ``body_pose`` (21×3) are SMPL axis-angle vectors (radians, local rotations in
    SMPL joint order 1..21); ``transl`` (3) is the pelvis joint's world position; ``joints`` (22×3) are world
    joint positions, flattened row-major; ``timing_us`` maps pipeline stage names to microseconds.
    ``camera`` (optional): absent for models that read no camera; ``true`` if an RGB-D frame contributed,
    ``false`` if the model had to run on the headset stream alone (no frame yet, or the camera went quiet).
    ``skipped`` (optional): headset samples of this session that got no pose since the previous pose, because
    the server was behind and the newest sample won. ``truth`` (optional): the ground-truth joints the
    answered ``hmd`` sample carried (recorded sessions), so that viewers can draw them beside the pose.
    ``planted`` (optional): (left, right), whether the server holds each foot planted on the floor (it does not
    slide while true), for models that plant feet; ``floor_y_m`` (optional): the height of the floor the served
    soles were held to, where there was one (0 in a floor-level space, the session's estimate in a LOCAL one).
    """

    TYPE: ClassVar[str] = "pose"
    type: Literal["pose"] = "pose"
    seq: Seq
    t_us: TimeUs
    model: Name
    global_orient: vec(3)
    body_pose: vec(63)
    transl: vec(3)
    joints: vec(66)
    timing_us: Annotated[dict[Annotated[str, Strict(), Field(max_length=32)], TimeUs], Len(0, 32)]
    camera: Annotated[bool, Strict()] | None = None
    skipped: Seq | None = None
    truth: vec(66) | None = None  # the answered hmd sample's ground-truth joints, when it carried them
    planted: vec(2, Bool) | None = None  # (left, right) feet held planted; absent: the model plants none
    floor_y_m: Coord | None = None  # the floor's height the served soles were held to (m), when one was


class ModelInfo(BaseModel):
    """One servable model in a ``models`` list."""

    model_config = ConfigDict(extra="ignore", frozen=True)
    name: Name
    inputs: Annotated[list[Literal["hmd", "rgb", "depth"]], Len(1, 3)]
    description: Text = ""
    sha256: Digest | None = None  # the model file served; absent for a model that is code (procedural)
    encoder_sha256: Digest | None = None  # its visual encoder's file, for models that read a camera
    # Where the model hangs the body's head joint: in the ``head`` device's frame (x right, y up, z back), m
    head_joint_m: vec(3, Coord) | None = None


class Models(Message):
    """The models a session may select, and the one it uses now."""

    TYPE: ClassVar[str] = "models"
    type: Literal["models"] = "models"
    active: Name
    models: Annotated[list[ModelInfo], Len(0, 256)]


class Ref(BaseModel):
    """Which client message an ``error`` is about: its ``type`` and, when it had a readable one, its ``seq``
    (``hmd`` and ``rgbd`` count separately, so the type says which counter)."""

    model_config = ConfigDict(extra="ignore", frozen=True)
    type: Annotated[str, Strict(), Field(min_length=1, max_length=64)]
    seq: Seq | None = None


class Error(Message):
    """Something the peer sent was refused; ``fatal`` means the server closes the connection next.

    ``ref`` names the message that caused it (type and seq) whenever one did and could be read; ``seq``
    repeats ``ref.seq`` for clients written before ``ref`` existed."""

    TYPE: ClassVar[str] = "error"
    type: Literal["error"] = "error"
    code: Annotated[str, Strict(), Field(min_length=1, max_length=64)]
    message: Text
    fatal: Bool = False
    seq: Seq | None = None  # seq of the offending message, when it had one
    ref: Ref | None = None


class SessionStatus(Message):
    """Who is in a session, sent to its render clients: when one joins (``event`` 'joined') and whenever the
    input client joins or leaves ('input_joined', 'input_left'). ``input``: an input client is connected."""

    TYPE: ClassVar[str] = "session"
    type: Literal["session"] = "session"
    session: Name
    event: Literal["joined", "input_joined", "input_left"]
    input: Bool
    model: Name
    renders: Annotated[int, Strict(), Field(ge=0, le=1_000_000)]


class Calibration(Message):
    """Where a session's calibration stands, sent to every client of the session: ``started`` (hold the
    pose now), ``done`` (with what was measured), ``failed`` (``message`` says why), ``cleared``.

    ``corrections`` (12): the rotation the server applies to each device from now on (head, left, right;
    xyzw quaternions, ``R_device @ c``)."""

    TYPE: ClassVar[str] = "calibration"
    type: Literal["calibration"] = "calibration"
    status: Literal["started", "done", "failed", "cleared"]
    pose: Literal["tpose", "stand"]
    message: Text = ""
    head_height_m: Float | None = None
    arm_span_m: Float | None = None
    corrections: vec(12) | None = None


class Body(Message):
    """The wearer's body as the session knows it, sent to every client of the session after ``get_body`` and
    ``set_body``: ``bone_lengths_m`` (joints 1..21, each from its parent, m); ``given`` whether a client gave it
    (``set_body``) or the server estimates it; ``measured`` whether the camera has measured some of the wearer's
    bones and they have stood (or calibrated): a body worth keeping for their next session."""

    TYPE: ClassVar[str] = "body"
    type: Literal["body"] = "body"
    bone_lengths_m: vec(21)
    given: Bool
    measured: Bool


class Pong(Message):
    """Answer to ``ping``: echoes ``nonce``/``t_us`` and adds the server's clock."""

    TYPE: ClassVar[str] = "pong"
    type: Literal["pong"] = "pong"
    nonce: Seq | None = None
    t_us: TimeUs | None = None
    server_t_us: TimeUs


CLIENT_MESSAGES: tuple[type[Message], ...] = (
    Hello,
    Hmd,
    Rgbd,
    SelectModel,
    ListModels,
    Ping,
    Calibrate,
    SetBody,
    GetBody,
)
SERVER_MESSAGES: tuple[type[Message], ...] = (
    Welcome,
    Pose,
    Models,
    Error,
    Pong,
    SessionStatus,
    Calibration,
    Body,
)
MESSAGE_TYPES: dict[str, type[Message]] = {m.TYPE: m for m in CLIENT_MESSAGES + SERVER_MESSAGES}
