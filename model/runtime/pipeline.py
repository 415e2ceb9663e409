"""The serving pipeline: one :class:`Pipeline` per session, numpy + onnxruntime, no torch.

    push_rgbd(frame)   visual encoder once per NEW frame -> keypoint cache (frames.KeypointCache)
    push_hmd(sample)   devices smoothed (filters.DevicePoseFilter) -> x_t into the HMD window -> heading frame
                       -> visual tokens from the cache (Alg. 1) -> fusion net -> FK anchored at the headset's
                       head joint -> One Euro on positions (two stages)
                       -> KPO (if the model has it; lost controllers: hands.LostHandPolicy; planted feet:
                          contact.FootContacts; still legs: stance.LegHold)
                       -> rotations re-derived from the positions -> PoseResult

When the camera is missing (no frame yet, or none newer than ``MAX_FRAME_AGE_S``) the model runs with an
empty visual window — trained for with camera dropout — and the result says ``camera = False``.

Shape legend: ``T`` HMD window, ``Tv`` visual window, ``J`` = 22 joints.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np

from ..hmd import HmdFeatureExtractor, TrackingState, check_poses, ignore_untracked
from ..inputs import canonicalize_hmd, heading_frame
from ..rig import TRACKED_JOINTS, joints_from_devices, stillness_point
from ..rotations import heading_of
from ..skeleton import HEAD, NUM_JOINTS, PARENTS, rest_offsets
from . import kernels, stance
from .body import (
    EARLY_BODY_SIGHTINGS,
    MIN_VISUAL_SAMPLES,
    BodyCalibrator,
    GivenBody,
    ServedScale,
    held_target,
)
from .calibration import Calibration, body_measurements, canonical_poses
from .contact import FootContacts
from .filters import DevicePoseFilter, OneEuroCascade
from .frames import (
    CachedFrame,
    EncodedFrame,
    KeypointCache,
    check_frame,
    encode_frame,
    encoder_input,
    head_from_cam,
)
from .hands import LostHandPolicy
from .kpo import KpoWeights, orient_leaves, rederive_rotations, solve_kpo
from .loading import LoadedModel
from .seated_yaw import FOLDED_SHARE, SeatedYaw, turn_pelvis
from .stance import LegHold, SteadyStance

# One Euro on joint positions (paper Eq. 8), two stages (filters.OneEuroCascade), and on the devices' poses
# before anything reads them (filters.DevicePoseFilter): the jitter/lag trade chosen on the training split
# (MODEL_CARD.md, "Jitter").
POSITION_MIN_CUTOFF_HZ = 6.0
POSITION_BETA = 4.0  # Hz per m/s
DEVICE_POSITION = (12.0, 40.0)  # (min cutoff Hz, beta Hz per m/s)
DEVICE_ROTATION = (12.0, 10.0)  # (min cutoff Hz, beta Hz per quaternion unit/s)
_PARENTS = PARENTS.astype(np.int64)
_TRACKED = np.array(TRACKED_JOINTS)
_LEG_BONES = np.array([4, 5, 7, 8])  # thighs and shins: the scale that a foot's step is measured in
_ORIGIN = np.zeros(3)


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
    # (left, right): each foot held planted on the floor by the runtime; None: the model plants no feet
    planted: tuple[bool, bool] | None = None
    floor_y_m: float | None = None  # the floor the soles were held to; None: none (no planted feet, no floor)


class Pipeline(GivenBody):
    """Per-session state machine around one :class:`LoadedModel`. Not thread-safe: one caller at a time.

    Body size: with ``bone_scale`` (J,) given, the skeleton is that body's. Otherwise a
    :class:`~egoposevr.model.runtime.body.BodyCalibrator` estimates it from the session's headset (height) and, for
    RGB-D models, the camera (measured hip, spine and leg lengths, through the encoder's body regressor),
    assuming a stage reference space (floor at y = 0).
    """

    def __init__(
        self,
        model: LoadedModel,
        naive: bool = False,
        bone_scale: np.ndarray | None = None,
        kpo_weights: KpoWeights | None = None,
        contacts: bool = True,
        steady_stance: bool = True,
        leg_hold: bool = True,
        lean_gate: bool | None = None,
        reseat: bool = False,
        body_hold: bool = True,
        sure_plant: bool = False,
        warm_reseat: bool = True,
        seated_yaw: bool = False,
        quiet_lift: bool | None = None,
        early_body: bool = True,
        head_relative_filter: bool = False,
    ) -> None:
        self.model, self.naive, self.kpo_weights = model, naive, kpo_weights or KpoWeights()
        self.contacts = contacts  # planted feet and the floor (contact.py), with KPO
        self.steady_stance = steady_stance  # with contacts: feet stay down while the head is still
        self.leg_hold = leg_hold  # with contacts: pelvis, hips and knees stay while both feet are down
        # with the leg hold: a head that leans about the served pelvis is quiet for both gates (stance.py).
        # None: as the model file says (ModelMetadata.lean_gate). A file asks for it only when its nets were
        # chosen with it: under the gate, nets that were not froze wrong early guesses of seated legs
        # (MODEL_CARD.md, rule 37).
        self.lean_gate = model.info.lean_gate if lean_gate is None else lean_gate
        # a held leg or a steady foot's anchor far from the network's mean placement moves to it faster
        # (stance.RESEAT_SLACK_M); off by default: it failed MODEL_CARD.md rules 38 and 39
        self.reseat = reseat
        # with the leg hold: while it holds, the hips, thighs, shins and feet keep their served size once the
        # body's first measurement (or the last calibration) is BODY_HOLD_AFTER_S old (body.held_target):
        # still people's feet skate about 20 % less and settle about 20 % stiller (MODEL_CARD.md, rule 57)
        self.body_hold = body_hold
        # a planted foot the contact head is sure of is not let go by the network lifting it (contact.SURE_P)
        self.sure_plant = sure_plant
        # once the net's input windows have filled (a stream's first answers read a padded headset window and
        # few camera frames), held legs and a steady stance's planted feet re-seat at its answers where it
        # folds the legs then (stance.REBASE_S, REBASE_FOLDED_SHARE): a seated session's cold first guess of
        # the legs is not what stays (MODEL_CARD.md, rules 59-62; on by default since rule 62)
        self.warm_reseat = warm_reseat
        # while the net's legs are folded and no camera frame is in its window, the pelvis keeps its yaw in the
        # world inside a dead zone (seated_yaw.py): without the camera the nets turn a seated person's legs
        # with the head; off by default (MODEL_CARD.md, rule 65)
        self.seated_yaw = seated_yaw
        # the body estimate is never shorter than the highest quiet head says (body.QuietHead): a body the
        # camera measured short floats its planted feet; None: as the model file says (ModelMetadata.quiet_lift;
        # MODEL_CARD.md, rules 77 and 78)
        self.quiet_lift = model.info.quiet_lift if quiet_lift is None else quiet_lift
        # the body estimate takes the camera's first sighting of a bone as its first measurement
        # (body.EARLY_BODY_SIGHTINGS), not the median of MIN_VISUAL_SAMPLES: a still person's first answers then
        # have the camera's legs, not the height's, and held legs do not lengthen under them a quarter second in
        # (still people's leakage 28-39 % lower; on by default since MODEL_CARD.md's rule 86)
        self.early_body = early_body
        # the joints' One Euro filter smooths the pose relative to the head joint, which is then put where the
        # (already smoothed) headset puts it: filtering the head-anchored pose made the whole body trail a moving
        # head by its lag, 2-3 cm at walking speed (MODEL_CARD.md, rule 90); off by default
        self.head_relative_filter = head_relative_filter
        info = model.info
        self.window = info.config.window
        self.visual_window = info.config.visual_window if model.visual is not None else 0
        self.fixed_body = bone_scale is not None
        self.bone_scale = (
            np.ones(NUM_JOINTS) if bone_scale is None else np.asarray(bone_scale, dtype=np.float64)
        )
        self.calibration: Calibration | None = None  # the wearer's; kept across reset()
        self.reset()

    def calibrate(self, calibration: Calibration | None) -> None:
        """Apply a per-session calibration (runtime/calibration.py), or drop it with None: device rotations
        are read as the training rig's from the next sample on, and the body takes its height and arms."""
        self.calibration = calibration
        self._apply_calibration()
        self._hold_clock_us = None  # a calibration resizes held legs too: the body_hold waits again

    def _body_changed(self) -> None:
        """A body given or taken back (GivenBody.give_body): the skeleton is resized from the next sample on."""
        served = self.served_scale.scale if self.served_scale.scale is not None else self.body.bone_scale
        self.offsets = rest_offsets(self.bone_scale if self.fixed_body else served)

    def _estimated_scale(self) -> np.ndarray:
        """The running estimate of the wearer's body (the served skeleton follows it over a few samples, and
        keeps still legs' size while they are held: body.held_target)."""
        return self.body.bone_scale

    def _apply_calibration(self) -> None:
        """The body takes the calibration's measures; the served skeleton follows from the next sample."""
        self.body.calibrate(*body_measurements(self.calibration, self.model.info.rig_offsets_m[0]))

    def reset(self) -> None:
        """Forget the stream (a new session, a model switch, a long pause); a calibration stays."""
        self.tracking = TrackingState()
        self.offsets = rest_offsets(self.bone_scale)
        self.body = BodyCalibrator(
            self.model.info.body_regressor,
            float(self.model.info.rig_offsets_m[0, 1]),
            self.quiet_lift,
            first_measure_sightings=EARLY_BODY_SIGHTINGS if self.early_body else MIN_VISUAL_SAMPLES,
        )
        self.served_scale = ServedScale()
        # body_hold's clock: the sample when the camera first measured a bone this session, or the first after
        # the last calibration (None until then)
        self._hold_clock_us: int | None = None
        self.last_head_pose = np.array([0.0, 1.6, 0.0, 0.0, 0.0, 0.0, 1.0])
        self.cache = KeypointCache(self.visual_window, self.naive)
        self.device_filter = DevicePoseFilter(DEVICE_POSITION, DEVICE_ROTATION)
        self.position_filter = OneEuroCascade(POSITION_MIN_CUTOFF_HZ, POSITION_BETA)
        self._pending_visual_us = 0
        self._restart_stream()
        if self.calibration is not None:
            self._apply_calibration()

    def _restart_stream(self) -> None:
        """What a new session starts with and a headset that jumped (filters.DevicePoseFilter.jump_m: a
        recentred reference space, a replay that starts over) starts again with, since the stream before the
        jump would read as a flight across the room: the HMD window, the frames, the joints' filter, and no
        foot planted where the body was. The body's size, the calibration and the tracking state stay."""
        self.features = HmdFeatureExtractor()
        self.hmd_window: np.ndarray | None = None  # (T, 72 [+ 6 tracking state])
        self.cache.forget()
        self.position_filter.reset()
        self.feet = FootContacts(reseat=self.reseat, sure_plant=self.sure_plant)
        self.stance = SteadyStance()
        self.hands = LostHandPolicy()
        self.legs = LegHold(lean=self.lean_gate, reseat=self.reseat)
        self._stream_samples = 0  # headset samples since the stream (re)started
        self._rebased = False  # warm_reseat's re-seat done this stream
        self._seated_heading = SeatedYaw()  # seated_yaw's held heading

    @property
    def frames_encoded(self) -> int:
        """Encoder runs so far (the naive baseline counts every re-encoded frame)."""
        return self.cache.frames_encoded

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
        check_frame(rgb, depth_mm, intrinsics, cam_from_head)
        if self.model.visual is None or not self.cache.takes(t_us):
            return False
        if not self.naive:
            return self.add_frame(encode_frame(self.model, t_us, rgb, depth_mm, intrinsics, cam_from_head))
        started = time.perf_counter()
        frame = CachedFrame(
            t_us=int(t_us),
            size_wh=(rgb.shape[1], rgb.shape[0]),
            intrinsics=np.asarray(intrinsics, dtype=np.float64),
            head_from_cam=head_from_cam(self.model, cam_from_head),
        )
        kp_cam, confidence = self.cache.add_raw(self.model, frame, encoder_input(self.model, rgb, depth_mm))
        self._measure_body(kp_cam, confidence)
        self._pending_visual_us += int((time.perf_counter() - started) * 1e6)
        return True

    def add_frame(self, frame: EncodedFrame) -> bool:
        """An already encoded frame (:func:`~egoposevr.model.runtime.frames.encode_frame`, possibly run in
        another thread) into the cache: Alg. 1's filter, then the keypoint cache. Returns False, doing
        nothing, for a model without a camera, a frame from another model's encoder (a model switch happened
        meanwhile) or a frame not newer than the newest cached one."""
        if self.model.visual is None or frame.encoder != self.model.info.visual_path:
            return False
        if not self.cache.takes(frame.t_us):
            return False
        self._measure_body(frame.kp_cam, self.cache.add(frame))
        self._pending_visual_us += frame.encode_us
        return True

    def _measure_body(self, kp_cam: np.ndarray, confidence: np.ndarray) -> None:
        """Bone lengths from a new frame's keypoints where Alg. 1 keeps both ends (body.py), through the
        encoder's body regressor when it has one. Only with a depth channel (LoadedModel.measures_body)."""
        if self.fixed_body or not self.model.measures_body:
            return
        self.body.push_visual(kp_cam, confidence > 0.0)  # the served skeleton follows it in _ingest

    # ------------------------------------------------------------------------------------------ headset
    def observe_hmd(self, t_us: int, poses: np.ndarray, valid: np.ndarray) -> None:
        """A sample that gets no pose (the server skipped it to catch up): it still feeds the HMD window,
        the velocities and the body estimate, so the next answered sample sees an unbroken stream."""
        self._ingest(int(t_us), poses, valid)

    def _ingest(
        self, t_us: int, poses: np.ndarray, valid: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Update the stream state -> poses (3, 7), valid (3,), tracked joints' positions (3, 3) and global
        rotations (3, 3, 3)."""
        valid = np.asarray(valid, dtype=bool)
        poses = ignore_untracked(poses, valid)  # an untracked device's numbers are never read
        check_poses(poses, valid)  # before any state changes: a bad sample leaves the session as it was
        poses = self.device_filter(t_us, canonical_poses(poses, self.calibration), valid)
        if self.device_filter.jumped[0]:
            self._restart_stream()
        x = self.features.push(t_us, poses, valid)
        self._stream_samples += 1
        if self.model.info.config.device_validity:
            x = np.concatenate([x, self.tracking.push(t_us, valid)])
        if valid[0]:
            self.last_head_pose = poses[0].copy()
            self.cache.remember_head(t_us, self.last_head_pose)
        self.hmd_window = (
            np.tile(x, (self.window, 1)) if self.hmd_window is None else np.roll(self.hmd_window, -1, 0)
        )
        self.hmd_window[-1] = x
        device_poses = poses.copy()
        device_poses[0] = self.last_head_pose  # the newest tracked headset pose
        tracked_pos, tracked_rot = joints_from_devices(device_poses, self.model.info.rig_offsets_m)
        if not self.fixed_body:
            self.body.push(tracked_pos, valid, t_us)
            if self.served_scale.follow(t_us, self._body_target(t_us)):
                self.offsets = rest_offsets(self.served_scale.scale)
        return poses, valid, tracked_pos, tracked_rot

    def _body_target(self, t_us: int) -> np.ndarray:
        """The bone scale (J,) the served skeleton follows: the running estimate, or with ``body_hold``
        (body.held_target) its leg bones kept while the legs are held. Starts the hold's clock at the first
        sample that has a measured body (after the session's start or a calibration)."""
        if self._hold_clock_us is None and self.body.measured:
            self._hold_clock_us = t_us
        if not (self.body_hold and self.leg_hold and self.legs.holding):
            return self.body.bone_scale
        return held_target(self.body.bone_scale, self.served_scale.scale, t_us, self._hold_clock_us)

    def _inputs_filled(self) -> bool:
        """Whether the net's windows hold no padding now: ``window`` headset samples since the stream began
        and, for a net that reads the camera, ``visual_window`` frames (or twice ``window`` samples without
        them: a headset whose camera does not send)."""
        if self._stream_samples < self.window:
            return False
        return (
            self.visual_window == 0
            or len(self.cache.frames) >= self.visual_window
            or self._stream_samples >= 2 * self.window
        )

    def _rebase_when_warm(self, t_us: int, joints: np.ndarray) -> None:
        """With warm_reseat: at the first sample whose windows are filled, the hold and the feet re-seat (with
        stance.REBASE_FOLDED_SHARE, only if the network's joints (J, 3) fold the legs then)."""
        if self.warm_reseat and not self._rebased and self._inputs_filled():
            self._rebased = True
            share = stance.REBASE_FOLDED_SHARE
            if share is None or stance.legs_folded(joints, share):
                self.feet.rebase(t_us)
                self.legs.rebase(t_us)

    def _keep_seated_yaw(
        self, local: np.ndarray, joints: np.ndarray, glob: np.ndarray, camera: bool
    ) -> tuple[np.ndarray, np.ndarray]:
        """With seated_yaw: the net's rotations local (J, 3, 3) turned in place to keep a seated pelvis's yaw
        (seated_yaw.SeatedYaw), and the joints (J, 3) and global rotations (J, 3, 3) of FK again; as given where
        nothing turns."""
        holds = not camera and stance.legs_folded(joints, FOLDED_SHARE)
        turn = self._seated_heading.correction(heading_of(glob[0]), holds)
        if turn == 0.0:
            return joints, glob
        turn_pelvis(local, turn)
        return kernels.forward_kinematics_one(local, _ORIGIN, self.offsets, _PARENTS)

    def push_hmd(self, t_us: int, poses: np.ndarray, valid: np.ndarray) -> PoseResult:
        """poses (3, 7) head/left/right [p xyz m, q xyzw], valid (3,) -> the pose for this sample."""
        pending = self.begin_hmd(t_us, poses, valid)
        return self.finish_hmd(pending, run_fusion([pending])[0])

    def begin_hmd(self, t_us: int, poses: np.ndarray, valid: np.ndarray) -> PendingPose:
        """:meth:`push_hmd` up to the fusion net: the sample enters the stream and the net's inputs are
        built. The server runs the nets of several sessions' pending poses as one batch (:func:`run_fusion`)
        and then :meth:`finish_hmd` each; nothing else may touch this pipeline in between."""
        started = time.perf_counter()
        t_us = int(t_us)
        _, valid, tracked_pos, tracked_rot = self._ingest(t_us, poses, valid)
        rot, origin = heading_frame(self.last_head_pose)
        inputs = {"hmd": canonicalize_hmd(self.hmd_window, rot, origin)[None]}  # float32
        features_done = time.perf_counter()
        timing = {"features": int((features_done - started) * 1e6)}
        camera: bool | None = None
        if self.model.visual is not None:
            if self.naive:
                self.cache.reencode(self.model)
            tokens, camera = self.cache.tokens(t_us, rot, origin)
            inputs["visual"] = tokens[None]
            timing["visual"] = self._pending_visual_us + int((time.perf_counter() - features_done) * 1e6)
            self._pending_visual_us = 0
        return PendingPose(
            t_us, valid, tracked_pos, rot, camera, timing, self.model, inputs, tracked_rot=tracked_rot
        )

    def _feet_state(self) -> dict[str, Any]:
        """The answer's ``planted`` and ``floor_y_m`` (PoseResult's): only where the runtime plants feet."""
        if not (self.model.info.kpo and self.contacts):
            return {}
        return {"planted": self.feet.planted, "floor_y_m": self.feet.floor_held_m}

    def _stillness_point(self, pending: PendingPose) -> np.ndarray:
        """Where the stillness gates watch the head (rig.STILLNESS_OFFSET_M), (3,)."""
        if pending.tracked_rot is None:
            return pending.tracked_pos[0]
        return stillness_point(
            pending.tracked_pos[0], pending.tracked_rot[0], self.model.info.rig_offsets_m[0]
        )

    def finish_hmd(self, pending: PendingPose, sixd: np.ndarray) -> PoseResult:
        """The rest of :meth:`push_hmd` from the fusion net's output sixd (J, 6): FK, filter, KPO,
        rotations."""
        timing = dict(pending.timing_us)
        clock = time.perf_counter()

        def lap(stage: str) -> None:
            nonlocal clock
            now = time.perf_counter()
            timing[stage] = int((now - clock) * 1e6)
            clock = now

        t_us, valid, tracked_pos = pending.t_us, pending.valid, pending.tracked_pos
        local = kernels.sixd_to_matrices(sixd.astype(np.float64))
        local[0] = pending.heading_rot @ local[0]  # pelvis: heading frame -> world
        joints, glob_pred = kernels.forward_kinematics_one(local, _ORIGIN, self.offsets, _PARENTS)
        if self.seated_yaw:
            joints, glob_pred = self._keep_seated_yaw(local, joints, glob_pred, pending.camera is True)
        if self.head_relative_filter:  # the shape filtered, the head where the headset is
            joints = self.position_filter(t_us, joints - joints[HEAD]) + tracked_pos[0]
        else:  # anchored at the head, then filtered
            joints = self.position_filter(t_us, joints + (tracked_pos[0] - joints[HEAD]))
        lap("fk_filter")
        if self.model.info.kpo:
            targets = np.zeros((NUM_JOINTS, 3))
            observed = np.zeros(NUM_JOINTS, dtype=bool)
            targets[_TRACKED] = tracked_pos
            observed[_TRACKED] = valid
            self.hands.targets(t_us, joints, valid, tracked_pos, targets, observed)
            if self.contacts:
                self._rebase_when_warm(t_us, joints)
                bones = self.bone_scale if self.fixed_body else self.served_scale.scale
                leg_scale = float(bones[_LEG_BONES].mean())
                still_m = self._stillness_point(pending)
                pivot_m = self.legs.pivot_m if self.leg_hold else None  # the hold's served pelvis, or None
                steady = self.steady_stance and self.stance.observe_head(
                    t_us, still_m, bool(valid[0]), pivot_m
                )
                self.feet.targets(t_us, joints, leg_scale, targets, observed, pending.contact_p, steady)
                self.stance.observe_feet(self.feet.planted)
                if self.leg_hold:
                    network = joints  # the lambda's, bound now: `joints` becomes KPO's result below
                    self.legs.targets(
                        t_us, joints, still_m, bool(valid[0]), self.feet.planted, targets, observed,
                        unheld=lambda: solve_kpo(network, targets, observed, self.kpo_weights),
                    )  # fmt: skip
            joints = solve_kpo(joints, targets, observed, self.kpo_weights)
            if self.contacts and self.leg_hold:
                self.legs.served(joints)
            lap("kpo")
        local = rederive_rotations(local, joints, self.offsets, glob_pred)
        # The served joints are FK of the served rotations, so the two always agree exactly.
        joints, glob = kernels.forward_kinematics_one(local, joints[0].copy(), self.offsets, _PARENTS)
        if pending.tracked_rot is not None:  # head and hands face as their devices do (no joint moves)
            leaves, leaf_rot = self.hands.orientations(t_us, valid, pending.tracked_rot, glob)
            orient_leaves(local, glob, leaves, leaf_rot)
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
            camera=pending.camera,
            timing_us=timing,
            **self._feet_state(),
        )


@dataclasses.dataclass
class PendingPose:
    """A headset sample's pose up to the fusion net (:meth:`Pipeline.begin_hmd`): the net's inputs
    (each with a leading batch axis of 1) and what :meth:`Pipeline.finish_hmd` needs afterwards."""

    t_us: int
    valid: np.ndarray  # (3,) bool
    tracked_pos: np.ndarray  # (3, 3) head and wrist joints from the devices, m
    heading_rot: np.ndarray  # (3, 3) heading frame -> world
    camera: bool | None
    timing_us: dict[str, int]  # stages so far; run_fusion adds "fusion"
    model: Any  # LoadedModel
    inputs: dict[str, np.ndarray]  # hmd (1, T, D) [, visual (1, Tv, 90)] float32; {} runs no net
    done: PoseResult | None = None  # a pipeline without a net (procedural) answers in begin_hmd
    contact_p: np.ndarray | None = None  # (2,) left / right foot on the floor, from a net with a contact head
    # (3, 3, 3) the head's and wrists' global rotations from the devices
    tracked_rot: np.ndarray | None = None


def run_fusion(pending: list[PendingPose]) -> list[np.ndarray | None]:
    """The fusion nets of several pending poses -> each one's sixd (J, 6), in order. Poses of one model
    whose graph has a batch axis (:attr:`LoadedModel.batchable`) run as one call; the call's time is every
    one of its poses' ``fusion`` stage, and a graph's contact output each pose's ``contact_p``."""
    out: list[np.ndarray | None] = [None] * len(pending)  # None where no net runs
    for indices in _fusion_groups(pending):
        started = time.perf_counter()
        names = pending[indices[0]].inputs
        feed = {name: np.concatenate([pending[i].inputs[name] for i in indices]) for name in names}
        outputs = pending[indices[0]].model.fusion.run(None, feed)  # rot6d (B, J, 6) [, contact (B, 2)]
        fusion_us = int((time.perf_counter() - started) * 1e6)
        for row, i in enumerate(indices):
            out[i] = outputs[0][row]
            pending[i].timing_us["fusion"] = fusion_us
            if len(outputs) > 1:
                pending[i].contact_p = outputs[1][row]
    return out


def _fusion_groups(pending: list[PendingPose]) -> list[list[int]]:
    """Indices of ``pending`` that can share one fusion call: same model and a batch axis; else alone."""
    groups: dict[int, list[int]] = {}
    alone: list[list[int]] = []
    for i, p in enumerate(pending):
        if not p.inputs:
            continue
        if p.model.batchable:
            groups.setdefault(id(p.model.fusion), []).append(i)
        else:
            alone.append([i])
    return [*groups.values(), *alone]
