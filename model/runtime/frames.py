"""Camera frames on the serving side: the visual encoder on one frame (stateless, so the server runs it off
the headset's path) and the per-session keypoint cache that turns encoded frames into the fusion net's
visual tokens (paper Alg. 1 and the incremental feature cache).

The cache keeps, per frame, camera-frame keypoints and Alg. 1's filtered confidence; a frame's world
keypoints are placed with the headset sample nearest its capture time and kept once that sample is settled.
``naive=True`` keeps each frame's encoder input instead and re-encodes the whole window on every request:
the paper's baseline, kept for the benchmark; both give the same tokens.

Shape legend: ``Tv`` visual window, ``J`` = 22 joints, ``C`` channels, ``h``×``w`` encoder input.
"""

from __future__ import annotations

import copy
import dataclasses
import time
from collections import deque
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ...protocol.errors import InputError
from ..inputs import (
    DEPTH_SCALE_M,
    VisibilityFilter,
    camera_to_world,
    lift_keypoints,
    nearest_sample,
    resize_frame,
    visual_tokens,
    visual_window,
)
from ..skeleton import NUM_JOINTS
from . import kernels
from .loading import LoadedModel

HEAD_HISTORY_S = 1.0  # headset poses kept to place frames that arrive late
# A stream's first headset samples, for a model that reads the camera, wait at most this long for its first frame
# (the server's --first-frame-wait-ms; PROTOCOL.md §first-frame; MODEL_CARD.md, rules 68 and 69), so that the first
# answer, which the leg hold keeps, has the camera's measure of the legs.
FIRST_FRAME_WAIT_US = 150_000
# A stream whose first headset sample holds the head lower than this above the floor (stage space: PROTOCOL.md §3)
# begins seated or crouched (the training bodies' standing eyes are 1.45-1.80 m up, seated ones 1.0-1.25); a
# seated stream's first answer made with one frame in its visual window folds its legs wrongly and is then
# re-seated, a move of still legs (MODEL_CARD.md, "Waiting for more than the first frame").
LOW_HEAD_M = 1.35
# ... so, where the low head's wait is on, such a stream's first answer waits for the net's visual window of
# frames, at most this long after its first sample (MODEL_CARD.md, rule 71; rule 70's wait for the headset window
# too cost a late first pose's upper body). LOW_HEAD_WAIT_ON says whether it is by default, in the server and in
# eval: off, since rules 70 and 71 failed (the server's --low-head-wait-ms and eval's @low-head-wait turn it on).
LOW_HEAD_WAIT_US = 1_000_000
LOW_HEAD_WAIT_ON = False
DEFAULT_LOW_HEAD_WAIT_US = LOW_HEAD_WAIT_US if LOW_HEAD_WAIT_ON else 0  # the server's wait unless configured


@dataclasses.dataclass(frozen=True)
class FirstAnswerWait:
    """What a stream's first answer waits for: ``frames`` camera frames since the stream began, at most
    ``wait_us`` after its first sample."""

    frames: int
    wait_us: int

    def met(self, frames: int, waited_us: int) -> bool:
        """Whether the first answer is due, ``waited_us`` after the stream's first sample."""
        return waited_us >= self.wait_us or frames >= self.frames


def first_answer_wait(
    head_pose: Sequence[float],
    head_tracked: bool,
    visual_window: int,
    first_frame_wait_us: int,
    low_head_wait_us: int,
) -> FirstAnswerWait:
    """The wait of a stream (of a model that reads the camera) whose first headset sample has the head at
    ``head_pose`` ([px, py, pz, ...], stage space: y metres above the floor) and ``head_tracked``: its net's visual
    window of frames where the tracked head is low and ``low_head_wait_us`` > 0, else its first frame
    (``first_frame_wait_us`` 0: none)."""
    if low_head_wait_us > 0 and head_tracked and head_pose[1] < LOW_HEAD_M:
        return FirstAnswerWait(visual_window, max(low_head_wait_us, first_frame_wait_us))
    return FirstAnswerWait(1, first_frame_wait_us)


@dataclasses.dataclass(frozen=True)
class EncodedFrame:
    """A camera frame through the visual encoder, ready for a pipeline's cache (``Pipeline.add_frame``)."""

    t_us: int
    size_wh: tuple[int, int]
    intrinsics: np.ndarray  # (4,) fx, fy, cx, cy of the W×H image
    head_from_cam: np.ndarray  # (4, 4)
    kp_cam: np.ndarray  # (J, 3) camera-frame keypoints, m
    zeta: np.ndarray  # (J,) visibility before Alg. 1's filter
    encoder: Path  # the visual encoder that made it
    encode_us: int  # resize + encoder + lifting time


@dataclasses.dataclass
class CachedFrame:
    """One frame in the cache: incremental mode keeps keypoints, naive mode the encoder input as well."""

    t_us: int
    size_wh: tuple[int, int]
    intrinsics: np.ndarray
    head_from_cam: np.ndarray  # (4, 4)
    kp_cam: np.ndarray | None = None  # (J, 3)
    kp_world: np.ndarray | None = None  # (J, 3), kept once the headset pose at capture is settled
    confidence: np.ndarray | None = None  # (J,)
    image: np.ndarray | None = None  # (C, h, w), naive only
    filter_before: VisibilityFilter | None = None  # naive only: Alg. 1 state before this frame


def check_frame(rgb: np.ndarray, depth_mm: np.ndarray, intrinsics: Any, cam_from_head: Any) -> None:
    """Raise ValueError unless the frame is usable: shapes, dtypes, finite positive intrinsics."""
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise InputError(f"rgb must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    if depth_mm.shape != rgb.shape[:2] or depth_mm.dtype != np.uint16:
        raise InputError(f"depth must be {rgb.shape[:2]} uint16, got {depth_mm.shape} {depth_mm.dtype}")
    k = np.asarray(intrinsics, dtype=np.float64)
    if k.shape != (4,) or not np.isfinite(k).all() or k[0] <= 0 or k[1] <= 0:
        raise InputError(f"intrinsics must be 4 finite numbers (fx, fy > 0, cx, cy), got {intrinsics}")
    if cam_from_head is not None:
        m = np.asarray(cam_from_head, dtype=np.float64)
        if m.shape != (4, 4) or not np.isfinite(m).all() or abs(np.linalg.det(m[:3, :3]) - 1.0) > 1e-3:
            raise InputError("cam_from_head must be a finite (4, 4) rigid transform")


def head_from_cam(model: LoadedModel, cam_from_head: np.ndarray | None) -> np.ndarray:
    """(4, 4) the frame's mount, or the training camera's when the frame names none."""
    camera = model.info.camera
    default = camera.cam_from_head if camera else np.eye(4).ravel()
    cam = np.asarray(default, dtype=np.float64).reshape(4, 4) if cam_from_head is None else cam_from_head
    return np.linalg.inv(cam)


def _input_shape(model: LoadedModel) -> tuple[int, int, int]:
    """The encoder's input (C, h, w)."""
    vc = model.info.visual_config
    return vc.channels, vc.input_wh[1], vc.input_wh[0]


def encoder_input(
    model: LoadedModel, rgb: np.ndarray, depth_mm: np.ndarray, out: np.ndarray | None = None
) -> np.ndarray:
    """A decoded frame -> the encoder's input (C, h, w) float32 (``inputs.network_input``'s numbers),
    written into ``out`` when given."""
    vc = model.info.visual_config
    if out is None:
        out = np.empty(_input_shape(model), np.float32)
    rgb_small, depth_small = resize_frame(rgb, depth_mm, vc.input_wh)
    kernels.fill_network_input(rgb_small, depth_small, 1000.0 * DEPTH_SCALE_M, out)
    return out


def encode_frame(
    model: LoadedModel,
    t_us: int,
    rgb: np.ndarray,
    depth_mm: np.ndarray,
    intrinsics: np.ndarray,
    cam_from_head: np.ndarray | None = None,
) -> EncodedFrame:
    """The visual encoder on one decoded frame (arguments as ``Pipeline.push_rgbd``). Stateless, so the
    server runs it beside the session's headset inference; the pipeline takes the result with ``add_frame``.
    Raises InputError for malformed frames, ValueError for a model that reads no camera."""
    check_frame(rgb, depth_mm, intrinsics, cam_from_head)
    return encode_frames(model, [(t_us, rgb, depth_mm, intrinsics, cam_from_head)])[0]


def encode_frames(model: LoadedModel, frames: list[tuple[Any, ...]]) -> list[EncodedFrame]:
    """:func:`encode_frame` on several frames (each its argument tuple after ``model``) in one encoder
    call: the server's frame lane batches the new frames of several sessions that share an encoder.
    The frames must have passed :func:`check_frame` (the caller checks each, so that one malformed frame
    is refused alone). Each frame's ``encode_us`` is the whole call's time."""
    if model.visual is None:
        raise ValueError(f"model {model.info.name} reads no camera")
    started = time.perf_counter()
    images = np.empty((len(frames), *_input_shape(model)), np.float32)
    for image, (_, rgb, depth_mm, _, _) in zip(images, frames, strict=True):
        encoder_input(model, rgb, depth_mm, out=image)
    uv, depth_m, zeta = model.encode_frames(images)
    encoded = []
    for i, (t_us, rgb, _, intrinsics, cam_from_head) in enumerate(frames):
        size_wh = (rgb.shape[1], rgb.shape[0])
        intrinsics = np.asarray(intrinsics, dtype=np.float64)
        encoded.append((int(t_us), size_wh, intrinsics, head_from_cam(model, cam_from_head),
                        lift_keypoints(uv[i], depth_m[i], intrinsics, size_wh), zeta[i]))  # fmt: skip
    encode_us = int((time.perf_counter() - started) * 1e6)
    return [EncodedFrame(*fields, encoder=model.info.visual_path, encode_us=encode_us) for fields in encoded]


class KeypointCache:
    """The last ``visual_window`` frames of one session and the headset poses that place them. Not
    thread-safe: the pipeline that owns it is called by one thread at a time."""

    def __init__(self, visual_window: int, naive: bool = False) -> None:
        self.visual_window, self.naive = visual_window, naive
        self.frames_encoded = 0
        self.forget()

    def forget(self) -> None:
        """Drop the frames, the visibility filter's state and the remembered headset poses (the count of
        encoder runs stays)."""
        self.frames: deque[CachedFrame] = deque(maxlen=max(self.visual_window, 1))
        self.visibility = VisibilityFilter()
        self.head_t_us: deque[int] = deque()
        self.head_poses: deque[np.ndarray] = deque()

    def takes(self, t_us: int) -> bool:
        """Whether a frame captured at t_us is newer than every cached one (the cache is ordered)."""
        return not self.frames or t_us > self.frames[-1].t_us

    def add(self, frame: EncodedFrame) -> np.ndarray:
        """An encoded frame -> Alg. 1's confidence (J,) for it; the frame is cached."""
        cached = CachedFrame(frame.t_us, frame.size_wh, frame.intrinsics, frame.head_from_cam, frame.kp_cam)
        cached.confidence = self.visibility(frame.t_us, frame.zeta)
        self.frames.append(cached)
        self.frames_encoded += 1
        return cached.confidence

    def add_raw(self, model: LoadedModel, frame: CachedFrame, image: np.ndarray) -> tuple[np.ndarray, ...]:
        """Naive mode: a frame with its encoder input (C, h, w), encoded once now for its keypoints;
        -> kp_cam (J, 3) and Alg. 1's confidence (J,)."""
        frame.image, frame.filter_before = image, copy.deepcopy(self.visibility)
        uv, depth_m, zeta = model.encode_frames(image[None])
        self.frames_encoded += 1
        kp_cam = lift_keypoints(uv[0], depth_m[0], frame.intrinsics, frame.size_wh)
        confidence = self.visibility(frame.t_us, zeta[0])  # keeps Alg. 1's state going
        self.frames.append(frame)
        return kp_cam, confidence

    def reencode(self, model: LoadedModel) -> None:
        """Naive mode: run the encoder on every frame of the window again and redo Alg. 1 over it."""
        frames = list(self.frames)
        if not frames:
            return
        uv, depth_m, zeta = model.encode_frames(np.stack([f.image for f in frames]))
        self.frames_encoded += len(frames)
        vis_filter = copy.deepcopy(frames[0].filter_before)
        for k, f in enumerate(frames):
            f.kp_cam = lift_keypoints(uv[k], depth_m[k], f.intrinsics, f.size_wh)
            f.confidence = vis_filter(f.t_us, zeta[k])

    def remember_head(self, t_us: int, head_pose: np.ndarray) -> None:
        """A tracked headset pose (7,), kept for ``HEAD_HISTORY_S`` to place frames."""
        self.head_t_us.append(t_us)
        self.head_poses.append(head_pose)
        while self.head_t_us and (t_us - self.head_t_us[0]) * 1e-6 > HEAD_HISTORY_S:
            self.head_t_us.popleft()
            self.head_poses.popleft()

    def tokens(self, now_us: int, rot: np.ndarray, origin: np.ndarray) -> tuple[np.ndarray, bool]:
        """Visual tokens (Tv, 90) in the heading frame (rot (3, 3), origin (3,)) for a request at now_us,
        and whether any frame was usable."""
        frames = list(self.frames)
        t = np.array([f.t_us for f in frames], dtype=np.int64)
        picked = [frames[i] for i in visual_window(t, now_us, self.visual_window)] if frames else []
        if not picked or not self.head_t_us:
            empty = np.zeros((0, NUM_JOINTS, 3)), np.zeros((0, NUM_JOINTS)), np.zeros(0)
            return visual_tokens(*empty, self.visual_window, rot, origin), False
        kp_world = np.stack([self._world_keypoints(f) for f in picked])
        confidence = np.stack([f.confidence for f in picked])
        age_s = np.array([(now_us - f.t_us) * 1e-6 for f in picked])
        return visual_tokens(kp_world, confidence, age_s, self.visual_window, rot, origin), True

    def _world_keypoints(self, frame: CachedFrame) -> np.ndarray:
        """(J, 3) world keypoints of a frame, placed with the headset sample nearest its capture time.

        Kept once a headset sample at or after the capture exists (later samples are farther away, so the
        nearest one cannot change); the naive baseline recomputes, as it re-encodes everything."""
        if frame.kp_world is not None and not self.naive:
            return frame.kp_world
        head_t = np.fromiter(self.head_t_us, dtype=np.int64)
        head = self.head_poses[int(nearest_sample(frame.t_us, head_t))]
        kp_world = camera_to_world(frame.kp_cam, head, None, frame.head_from_cam)
        if head_t[-1] >= frame.t_us:
            frame.kp_world = kp_world
        return kp_world
