"""The serving pipeline: numpy + onnxruntime, no torch. One :class:`Pipeline` per session.

    push_rgbd(frame)   visual encoder once per NEW frame -> keypoint cache (ring buffer of Tv frames)
    push_hmd(sample)   -> x_t into the HMD window -> heading frame -> visual tokens from the cache (Alg. 1)
                       -> fusion net -> FK anchored at the headset's head joint -> One Euro on positions
                       -> KPO (if the model has it) -> rotations re-derived from the positions -> PoseResult

A model is a folder's ``<name>.onnx`` (fusion net) plus the ``visual-*.onnx`` it names in its metadata; the
metadata carries everything else (:mod:`egoposevr.model.export`). ``naive=True`` keeps raw frames instead
and re-encodes the whole visual window on every request — the paper's baseline for the incremental cache,
kept for the benchmark; both modes give the same poses.

When the camera is missing (no frame yet, or none newer than ``MAX_FRAME_AGE_S``) the model runs with an
empty visual window — trained for with camera dropout — and the result says ``camera = False``.

Shape legend: ``T`` HMD window, ``Tv`` visual window, ``J`` = 22 joints.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort

from . import kernels
from .body import BodyCalibrator, BodyRegressor, load_regressor_for
from .filters import OneEuroFilter
from .hmd import HmdFeatureExtractor, ignore_untracked
from .inputs import (
    VisibilityFilter,
    camera_to_world,
    canonicalize_hmd,
    heading_frame,
    lift_keypoints,
    nearest_sample,
    network_input,
    resize_frame,
    visual_tokens,
    visual_window,
)
from .kpo import KpoWeights, rederive_rotations, solve_kpo
from .rig import TRACKED_JOINTS, joints_from_devices
from .skeleton import HEAD, NUM_JOINTS, PARENTS, rest_offsets

HEAD_HISTORY_S = 1.0
# One Euro on joint positions (paper Eq. 8). Chosen on 4 val clips: (4 Hz, 2) costs 0.2-0.3 cm MPJPE against no
# filter and cuts jitter 4.5x; (2 Hz, 1) halves jitter again but lags by 0.6 cm upper body.
POSITION_MIN_CUTOFF_HZ = 4.0
POSITION_BETA = 2.0
_PARENTS = PARENTS.astype(np.int64)
_TRACKED = np.array(TRACKED_JOINTS)
# A lost controller (it reports its last pose, valid = False) hands its wrist back to the network gradually:
# KPO holds the wrist at the network's position plus the correction tracking last gave it, fading with this
# time constant, for LOST_HAND_HOLD_S; then the wrist is free like any untracked joint. The network alone is
# 6-8 cm off at the moment of loss (the avatar's hand jumped that far); on the validation split, with the
# controllers lost 16-20 % of the time, the lost wrists' error in their first 0.1 s falls 8.0 -> 5.5 cm and
# upper-body MPJPE 2.49 -> 2.46 cm (with the single-map body regressor of the time; fade 0.25 s: 2.46, 1 s:
# 2.47). A frozen wrist or one held in the head's frame does worse than the network after 0.1-0.25 s; the
# camera's wrist keypoints are 11 cm off when lost.
LOST_HAND_FADE_S = 0.5
LOST_HAND_HOLD_S = 1.5
_ORIGIN = np.zeros(3)
RGBD_CHANNELS = 4  # RGB + depth: the encoder input that measures bone lengths


class ModelError(Exception):
    """A model file that cannot be served: unreadable, not an EgoPoseVR graph, or missing its encoder."""


@dataclasses.dataclass(frozen=True)
class ModelInfo:
    name: str
    description: str
    inputs: tuple[str, ...]
    kpo: bool
    path: Path
    visual_path: Path | None
    config: dict[str, Any]  # FusionConfig fields
    visual_config: dict[str, Any] | None  # VisualConfig fields
    camera: dict[str, Any] | None  # the training camera (default cam_from_head)
    rig_offsets_m: np.ndarray
    body_regressor: BodyRegressor | None = None  # fitted on the visual encoder's keypoints (body.py)


def _metadata(session: ort.InferenceSession) -> dict[str, str]:
    meta = session.get_modelmeta().custom_metadata_map
    return {k.removeprefix("egoposevr."): v for k, v in meta.items() if k.startswith("egoposevr.")}


def _session(path: Path, threads: int) -> ort.InferenceSession:
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")  # do not burn idle cores
    try:
        return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own exception types for bad files
        raise ModelError(f"{path}: cannot load ({exc})") from exc


class LoadedModel:
    """ONNX sessions of one servable model; visual encoders are shared between models via ``shared``."""

    def __init__(self, info: ModelInfo, fusion: ort.InferenceSession, visual: ort.InferenceSession | None):
        self.info, self.fusion, self.visual = info, fusion, visual

    @classmethod
    def load(cls, path: str | Path, threads: int = 1, shared: dict[Path, Any] | None = None) -> LoadedModel:
        path = Path(path)
        kernels.warm_up()  # compiled (or loaded from numba's cache) before the first pose, not during it
        fusion = _session(path, threads)
        meta = _metadata(fusion)
        if meta.get("kind") != "model":
            raise ModelError(f"{path}: not an EgoPoseVR model (metadata kind {meta.get('kind')!r})")
        try:
            visual_path = path.parent / meta["visual_encoder"] if meta["visual_encoder"] else None
            visual, visual_meta, regressor = None, {}, None
            if visual_path is not None:
                shared = {} if shared is None else shared
                if visual_path not in shared:
                    if not visual_path.exists():
                        raise ModelError(f"{path}: its visual encoder {visual_path.name} is missing")
                    shared[visual_path] = _session(visual_path, threads)
                visual = shared[visual_path]
                visual_meta = _metadata(visual)
                try:
                    regressor = load_regressor_for(visual_path)
                except ValueError as exc:
                    raise ModelError(f"{path}: {exc}") from exc
            info = ModelInfo(
                name=meta["name"],
                description=meta.get("description", ""),
                inputs=tuple(json.loads(meta["inputs"])),
                kpo=meta.get("kpo") == "true",
                path=path,
                visual_path=visual_path,
                config=json.loads(meta["config"]),
                visual_config=json.loads(visual_meta["config"]) if visual_meta else None,
                camera=json.loads(visual_meta["camera"]) if visual_meta else None,
                rig_offsets_m=np.asarray(json.loads(meta["rig_offsets_m"])),
                body_regressor=regressor,
            )
        except (KeyError, ValueError) as exc:
            raise ModelError(f"{path}: incomplete EgoPoseVR metadata ({exc})") from exc
        return cls(info, fusion, visual)

    @property
    def measures_body(self) -> bool:
        """Whether its visual encoder sees depth, so that its keypoints measure bone lengths (body.py).
        RGB-only keypoints guess their depth: a body regressor fitted on visual-rgb's lengths made validation
        worse (hmd-rgb upper body 3.70 -> 4.68 cm, lower 9.61 -> 11.74 cm) although its summed bone error
        was lower (34 against 41 cm), so RGB models keep the height-scaled body."""
        return self.visual is not None and self.info.visual_config.get("channels") == RGBD_CHANNELS

    def encode_frames(self, images: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(B, C, h, w) -> uv (B, J, 2), depth_m (B, J), zeta (B, J)."""
        uv, depth_m, zeta = self.visual.run(None, {"image": images})
        return uv, depth_m, zeta


@dataclasses.dataclass
class PoseResult:
    """One answer. Positions in metres (world), rotations local (row 0: pelvis global)."""

    t_us: int
    model: str
    global_orient: np.ndarray  # (3,) axis-angle
    body_pose: np.ndarray  # (63,)
    transl: np.ndarray  # (3,) pelvis position
    joints: np.ndarray  # (J, 3)
    local_rot: np.ndarray  # (J, 3, 3)
    camera: bool | None  # None: the model reads no camera; False: it had no usable frame
    timing_us: dict[str, int]


@dataclasses.dataclass
class _Frame:
    """One cached camera frame: incremental mode keeps keypoints, naive mode the encoder input."""

    t_us: int
    size_wh: tuple[int, int]
    intrinsics: np.ndarray
    head_from_cam: np.ndarray  # (4, 4)
    kp_cam: np.ndarray | None = None  # (J, 3)
    kp_world: np.ndarray | None = None  # (J, 3), kept once the headset pose at capture is settled
    confidence: np.ndarray | None = None  # (J,)
    image: np.ndarray | None = None  # (C, h, w), naive only
    filter_before: VisibilityFilter | None = None  # naive only: Alg. 1 state before this frame


@dataclasses.dataclass(frozen=True)
class EncodedFrame:
    """A camera frame through the visual encoder, ready for a pipeline's cache (:meth:`Pipeline.add_frame`)."""

    t_us: int
    size_wh: tuple[int, int]
    intrinsics: np.ndarray  # (4,) fx, fy, cx, cy of the W×H image
    head_from_cam: np.ndarray  # (4, 4)
    kp_cam: np.ndarray  # (J, 3) camera-frame keypoints, m
    zeta: np.ndarray  # (J,) visibility before Alg. 1's filter
    encoder: Path  # the visual encoder that made it
    encode_us: int  # resize + encoder + lifting time


def _head_from_cam(model: LoadedModel, cam_from_head: np.ndarray | None) -> np.ndarray:
    default = model.info.camera["cam_from_head"] if model.info.camera else np.eye(4).ravel()
    cam = np.asarray(default, dtype=np.float64).reshape(4, 4) if cam_from_head is None else cam_from_head
    return np.linalg.inv(cam)


def encode_frame(
    model: LoadedModel,
    t_us: int,
    rgb: np.ndarray,
    depth_mm: np.ndarray,
    intrinsics: np.ndarray,
    cam_from_head: np.ndarray | None = None,
) -> EncodedFrame:
    """The visual encoder on one decoded frame (arguments as :meth:`Pipeline.push_rgbd`). Stateless, so the
    server runs it beside the session's headset inference; the pipeline takes the result with ``add_frame``.
    Raises ValueError for malformed frames or a model that reads no camera."""
    _check_frame(rgb, depth_mm, intrinsics, cam_from_head)
    if model.visual is None:
        raise ValueError(f"model {model.info.name} reads no camera")
    started = time.perf_counter()
    vc = model.info.visual_config
    image = network_input(*resize_frame(rgb, depth_mm, (vc["width"], vc["height"])), vc["channels"])
    uv, depth_m, zeta = model.encode_frames(image[None])
    size_wh = (rgb.shape[1], rgb.shape[0])
    intrinsics = np.asarray(intrinsics, dtype=np.float64)
    return EncodedFrame(
        t_us=int(t_us),
        size_wh=size_wh,
        intrinsics=intrinsics,
        head_from_cam=_head_from_cam(model, cam_from_head),
        kp_cam=lift_keypoints(uv[0], depth_m[0], intrinsics, size_wh),
        zeta=zeta[0],
        encoder=model.info.visual_path,
        encode_us=int((time.perf_counter() - started) * 1e6),
    )


def _check_frame(rgb: np.ndarray, depth_mm: np.ndarray, intrinsics: Any, cam_from_head: Any) -> None:
    """Raise ValueError unless the frame is usable: shapes, dtypes, finite positive intrinsics."""
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    if depth_mm.shape != rgb.shape[:2] or depth_mm.dtype != np.uint16:
        raise ValueError(f"depth must be {rgb.shape[:2]} uint16, got {depth_mm.shape} {depth_mm.dtype}")
    k = np.asarray(intrinsics, dtype=np.float64)
    if k.shape != (4,) or not np.isfinite(k).all() or k[0] <= 0 or k[1] <= 0:
        raise ValueError(f"intrinsics must be 4 finite numbers (fx, fy > 0, cx, cy), got {intrinsics}")
    if cam_from_head is not None:
        m = np.asarray(cam_from_head, dtype=np.float64)
        if m.shape != (4, 4) or not np.isfinite(m).all() or abs(np.linalg.det(m[:3, :3]) - 1.0) > 1e-3:
            raise ValueError("cam_from_head must be a finite (4, 4) rigid transform")


class Pipeline:
    """Per-session state machine around one :class:`LoadedModel`. Not thread-safe: one caller at a time.

    Body size: with ``bone_scale`` (J,) given, the skeleton is that body's. Otherwise a
    :class:`~egoposevr.model.body.BodyCalibrator` estimates it from the session's headset (height) and, for
    RGB-D models, the camera (measured hip, spine and leg lengths, through the encoder's body regressor),
    assuming a stage reference space (floor at y = 0).
    """

    def __init__(
        self,
        model: LoadedModel,
        naive: bool = False,
        bone_scale: np.ndarray | None = None,
        kpo_weights: KpoWeights | None = None,
    ) -> None:
        self.model, self.naive, self.kpo_weights = model, naive, kpo_weights or KpoWeights()
        info = model.info
        self.window = int(info.config["window"])
        self.visual_window = int(info.config["visual_window"]) if model.visual is not None else 0
        self.fixed_body = bone_scale is not None
        self.bone_scale = (
            np.ones(NUM_JOINTS) if bone_scale is None else np.asarray(bone_scale, dtype=np.float64)
        )
        self.reset()

    def reset(self) -> None:
        """Forget everything (a new session, a model switch, a long pause)."""
        self.features = HmdFeatureExtractor()
        self.offsets = rest_offsets(self.bone_scale)
        self.body = BodyCalibrator(self.model.info.body_regressor)
        self.hmd_window: np.ndarray | None = None  # (T, 72)
        self.head_t_us: deque[int] = deque()
        self.head_poses: deque[np.ndarray] = deque()
        self.last_head_pose = np.array([0.0, 1.6, 0.0, 0.0, 0.0, 0.0, 1.0])
        self.frames: deque[_Frame] = deque(maxlen=max(self.visual_window, 1))
        self.visibility = VisibilityFilter()
        self.position_filter = OneEuroFilter(POSITION_MIN_CUTOFF_HZ, POSITION_BETA)
        self._pending_visual_us = 0
        self.frames_encoded = 0
        # controller -> (wrist m, t_us) when it was last valid
        self._last_tracked: dict[int, tuple[np.ndarray, int]] = {}
        self._hand_correction: dict[int, np.ndarray] = {}  # lost controller -> last tracked - network, m

    # ------------------------------------------------------------------------------------------ camera
    def push_rgbd(
        self,
        t_us: int,
        rgb: np.ndarray,
        depth_mm: np.ndarray,
        intrinsics: np.ndarray,
        cam_from_head: np.ndarray | None = None,
    ) -> bool:
        """A decoded frame: rgb (H, W, 3) uint8, depth (H, W) uint16 mm, intrinsics (fx, fy, cx, cy) of
        that W×H image, cam_from_head (4, 4) or None for the training camera's.

        Returns False, doing nothing, when the model reads no camera or the frame is not newer than the
        newest cached one (the cache is ordered by capture time); the caller counts those. Raises
        ValueError for malformed frames.
        """
        _check_frame(rgb, depth_mm, intrinsics, cam_from_head)
        if self.model.visual is None or (self.frames and t_us <= self.frames[-1].t_us):
            return False
        if not self.naive:
            return self.add_frame(encode_frame(self.model, t_us, rgb, depth_mm, intrinsics, cam_from_head))
        started = time.perf_counter()
        vc = self.model.info.visual_config
        image = network_input(*resize_frame(rgb, depth_mm, (vc["width"], vc["height"])), vc["channels"])
        frame = _Frame(
            t_us=int(t_us),
            size_wh=(rgb.shape[1], rgb.shape[0]),
            intrinsics=np.asarray(intrinsics, dtype=np.float64),
            head_from_cam=_head_from_cam(self.model, cam_from_head),
        )
        frame.image, frame.filter_before = image, copy.deepcopy(self.visibility)
        kp_cam, zeta = self._encode(frame, image[None])
        self._measure_body(kp_cam, self.visibility(frame.t_us, zeta))  # keep Alg. 1's state going
        self.frames.append(frame)
        self._pending_visual_us += int((time.perf_counter() - started) * 1e6)
        return True

    def add_frame(self, frame: EncodedFrame) -> bool:
        """An already encoded frame (:func:`encode_frame`, possibly run in another thread) into the cache:
        Alg. 1's filter, then the keypoint cache. Returns False, doing nothing, for a model without a camera,
        a frame from another model's encoder (a model switch happened meanwhile) or a frame not newer than
        the newest cached one."""
        if self.model.visual is None or frame.encoder != self.model.info.visual_path:
            return False
        if self.frames and frame.t_us <= self.frames[-1].t_us:
            return False
        cached = _Frame(frame.t_us, frame.size_wh, frame.intrinsics, frame.head_from_cam, kp_cam=frame.kp_cam)
        cached.confidence = self.visibility(frame.t_us, frame.zeta)
        self._measure_body(frame.kp_cam, cached.confidence)
        self.frames.append(cached)
        self.frames_encoded += 1
        self._pending_visual_us += frame.encode_us
        return True

    def _measure_body(self, kp_cam: np.ndarray, confidence: np.ndarray) -> None:
        """Bone lengths from a new frame's keypoints where Alg. 1 keeps both ends (body.py), through the
        encoder's body regressor when it has one. Only with a depth channel: RGB-only keypoints guess their
        depth; raw lengths from them made hmd-rgb's lower-body MPJPE worse (9.61 -> 9.81 cm), and so did a
        regressor fitted on them (LoadedModel.measures_body)."""
        if self.fixed_body or not self.model.measures_body:
            return
        if self.body.push_visual(kp_cam, confidence > 0.0):
            self.offsets = rest_offsets(self.body.bone_scale)

    def _encode(self, frame: _Frame, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Encoder on (1, C, h, w) -> camera-frame keypoints (J, 3) and ζ (J,)."""
        uv, depth_m, zeta = self.model.encode_frames(images)
        self.frames_encoded += len(images)
        return lift_keypoints(uv[0], depth_m[0], frame.intrinsics, frame.size_wh), zeta[0]

    def _naive_reencode(self) -> None:
        """The baseline: run the encoder on every frame of the window again and redo Alg. 1 over it."""
        frames = list(self.frames)
        if not frames:
            return
        uv, depth_m, zeta = self.model.encode_frames(np.stack([f.image for f in frames]))
        self.frames_encoded += len(frames)
        vis_filter = copy.deepcopy(frames[0].filter_before)
        for k, f in enumerate(frames):
            f.kp_cam = lift_keypoints(uv[k], depth_m[k], f.intrinsics, f.size_wh)
            f.confidence = vis_filter(f.t_us, zeta[k])

    # ------------------------------------------------------------------------------------------ headset
    def observe_hmd(self, t_us: int, poses: np.ndarray, valid: np.ndarray) -> None:
        """A sample that gets no pose (the server skipped it to catch up): it still feeds the HMD window,
        the velocities and the body estimate, so the next answered sample sees an unbroken stream."""
        self._ingest(int(t_us), poses, valid)

    def _ingest(
        self, t_us: int, poses: np.ndarray, valid: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Update the stream state -> poses (3, 7), valid (3,), tracked joint positions (3, 3)."""
        valid = np.asarray(valid, dtype=bool)
        poses = ignore_untracked(
            poses, valid
        )  # checks the shapes; an untracked device's numbers are never read
        x = self.features.push(t_us, poses, valid)  # validates finiteness
        self._remember_head(t_us, poses[0], bool(valid[0]))
        self.hmd_window = (
            np.tile(x, (self.window, 1)) if self.hmd_window is None else np.roll(self.hmd_window, -1, 0)
        )
        self.hmd_window[-1] = x
        device_poses = poses.copy()
        device_poses[0] = self.last_head_pose  # the newest tracked headset pose
        tracked_pos, _ = joints_from_devices(device_poses, self.model.info.rig_offsets_m)
        if not self.fixed_body and self.body.push(tracked_pos, valid):
            self.offsets = rest_offsets(self.body.bone_scale)
        return poses, valid, tracked_pos

    def push_hmd(self, t_us: int, poses: np.ndarray, valid: np.ndarray) -> PoseResult:
        """poses (3, 7) head/left/right [p xyz m, q xyzw], valid (3,) -> the pose for this sample."""
        timing: dict[str, int] = {}
        clock = time.perf_counter()

        def lap(stage: str) -> None:
            nonlocal clock
            now = time.perf_counter()
            timing[stage] = int((now - clock) * 1e6)
            clock = now

        t_us = int(t_us)
        poses, valid, tracked_pos = self._ingest(t_us, poses, valid)
        rot, origin = heading_frame(self.last_head_pose)
        inputs = {"hmd": canonicalize_hmd(self.hmd_window, rot, origin)[None]}
        lap("features")
        camera: bool | None = None
        if self.model.visual is not None:
            if self.naive:
                self._naive_reencode()
            tokens, camera = self._visual_tokens(t_us, rot, origin)
            inputs["visual"] = tokens[None]
            timing["visual"] = self._pending_visual_us + int((time.perf_counter() - clock) * 1e6)
            self._pending_visual_us = 0
            clock = time.perf_counter()
        sixd = self.model.fusion.run(None, inputs)[0][0]  # (J, 6)
        lap("fusion")
        local = kernels.sixd_to_matrices(sixd.astype(np.float64))
        local[0] = rot @ local[0]  # pelvis: heading frame -> world
        joints, glob_pred = kernels.forward_kinematics_one(local, _ORIGIN, self.offsets, _PARENTS)
        joints = self.position_filter(t_us, joints + (tracked_pos[0] - joints[HEAD]))  # anchored at the head
        lap("fk_filter")
        if self.model.info.kpo:
            targets = np.zeros((NUM_JOINTS, 3))
            observed = np.zeros(NUM_JOINTS, dtype=bool)
            targets[_TRACKED] = tracked_pos
            observed[_TRACKED] = valid
            self._hand_over_lost_controllers(t_us, joints, valid, tracked_pos, targets, observed)
            joints = solve_kpo(joints, targets, observed, self.kpo_weights)
            lap("kpo")
        local = rederive_rotations(local, joints, self.offsets, glob_pred)
        # The served joints are FK of the served rotations, so the two always agree exactly.
        joints, _ = kernels.forward_kinematics_one(local, joints[0].copy(), self.offsets, _PARENTS)
        axis_angle = kernels.matrices_to_rotvecs(local)
        global_orient, body_pose = axis_angle[0], axis_angle[1:].reshape(-1)
        lap("rotations")
        return PoseResult(
            t_us=t_us,
            model=self.model.info.name,
            global_orient=global_orient,
            body_pose=body_pose,
            transl=joints[0].copy(),
            joints=joints,
            local_rot=local,
            camera=camera,
            timing_us=timing,
        )

    def _hand_over_lost_controllers(
        self,
        t_us: int,
        joints: np.ndarray,
        valid: np.ndarray,
        tracked_pos: np.ndarray,
        targets: np.ndarray,
        observed: np.ndarray,
    ) -> None:
        """KPO targets for the wrists of lost controllers (see ``LOST_HAND_FADE_S``). joints (J, 3) the
        network's (filtered, anchored) joints; targets, observed (J,) are filled in.

        At the first lost sample the correction is measured against the network's wrist of that sample, so
        the served wrist starts exactly where tracking left it (the network's answer itself moves when a
        controller's valid flag drops) and then follows the network's motion while the correction fades."""
        for device in (1, 2):
            wrist = int(_TRACKED[device])
            if valid[device]:
                self._last_tracked[device] = (tracked_pos[device].copy(), t_us)
                self._hand_correction.pop(device, None)
                continue
            if device not in self._last_tracked:
                continue
            last_pos, since_us = self._last_tracked[device]
            age_s = max(t_us - since_us, 0) * 1e-6
            if age_s > LOST_HAND_HOLD_S:
                continue
            correction = self._hand_correction.setdefault(device, last_pos - joints[wrist])
            targets[wrist] = joints[wrist] + np.exp(-age_s / LOST_HAND_FADE_S) * correction
            observed[wrist] = True

    def _remember_head(self, t_us: int, head_pose: np.ndarray, head_valid: bool) -> None:
        if not head_valid:
            return
        self.last_head_pose = head_pose.copy()
        self.head_t_us.append(t_us)
        self.head_poses.append(self.last_head_pose)
        while self.head_t_us and (t_us - self.head_t_us[0]) * 1e-6 > HEAD_HISTORY_S:
            self.head_t_us.popleft()
            self.head_poses.popleft()

    def _world_keypoints(self, frame: _Frame) -> np.ndarray:
        """(J, 3) world keypoints of a frame, placed with the headset sample nearest its capture time.

        Cached once a headset sample at or after the capture exists (later samples are farther away, so
        the nearest one cannot change); the naive baseline recomputes, as it re-encodes everything."""
        if frame.kp_world is not None and not self.naive:
            return frame.kp_world
        head_t = np.fromiter(self.head_t_us, dtype=np.int64)
        head = self.head_poses[int(nearest_sample(frame.t_us, head_t))]
        kp_world = camera_to_world(frame.kp_cam, head, None, frame.head_from_cam)
        if head_t[-1] >= frame.t_us:
            frame.kp_world = kp_world
        return kp_world

    def _visual_tokens(self, now_us: int, rot: np.ndarray, origin: np.ndarray) -> tuple[np.ndarray, bool]:
        """Tokens (Tv, 90) from the cached frames, and whether any frame was usable."""
        frames = list(self.frames)
        t = np.array([f.t_us for f in frames], dtype=np.int64)
        picked = [frames[i] for i in visual_window(t, now_us, self.visual_window)] if frames else []
        if not picked or not self.head_t_us:
            return visual_tokens(np.zeros((0, NUM_JOINTS, 3)), np.zeros((0, NUM_JOINTS)), np.zeros(0),
                                 self.visual_window, rot, origin), False  # fmt: skip
        kp_world = np.stack([self._world_keypoints(f) for f in picked])
        confidence = np.stack([f.confidence for f in picked])
        age_s = np.array([(now_us - f.t_us) * 1e-6 for f in picked])
        return visual_tokens(kp_world, confidence, age_s, self.visual_window, rot, origin), True
