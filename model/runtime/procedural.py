"""The ``procedural`` model: a body from the headset and controllers alone, with no network and no weights.

The baseline every learned model is compared with, and a fallback that never wanders (the VRIK style of
avatar legs that VR users know):

- the body's size is the session's height estimate (:class:`~.body.BodyCalibrator`, from the headset);
- the neck hangs under the head joint; standing, the pelvis stays over the planted feet (bending over
  tilts the spine with straight legs, a squat bends the knees), walking it goes along under the head; the
  spine is the rest spine turned onto the pelvis-to-neck line, its bones at their lengths, so a still wearer's
  served head joint is the tracked one (the model's ``head_joint_m``, PROTOCOL.md §model-head-joint);
- with ``seat``, a stream that begins seated (the head lower than this body's stands) plants the feet in
  front of the pelvis, ``SEAT_BACK_PER_DROP`` times that drop (the pelvis hanging upright from the head: a
  chair's sitter has the feet in front of the seat, the seat under the trunk); the seat stays while the sitter
  leans (a lean steps no foot) and turns (the hips turn only past ``SEATED_DEAD_ZONE_DEG``), and comes forward
  over the feet as the head rises to stand (then the stream stands like any other);
- the chest turns with the head, lagging by ``TURN_TIME_S``; the hips turn after it only by as much as the
  head is turned more than ``TURN_DEAD_ZONE_DEG`` from them (a glance, a torso twist or a reach to the side
  turns the shoulders, not the hips or the feet); walking, the dead zone shrinks with speed to none at
  ``WALKING_M_S``, so the hips face the way the walker goes; the twist between them is shared by the three
  spine joints;
- each foot stays planted where it was put. When a foot is more than ``STEP_TRIGGER_M`` (scaled by the
  body) from where it would stand under its hip, or the body turned more than ``STEP_TURN_DEG`` since it
  stood, it steps in ``STEP_S`` along a low arc to where its hip will be when the step ends (the pelvis's
  smoothed velocity ahead); one foot at a time;
- the devices get the network pipeline's smoothing, and the joints its One Euro filter, except the feet and
  tracked wrists (exact);
- knees and elbows by two-bone IK (knees forward, elbows down and back); a wrist goes to its controller, or
  hangs when the controller is lost and comes back to it over ``hands.REACQUIRE_S`` when it is found;
  crouching bends the knees, never sinks the feet;
- the served rotations are re-derived from the joints (:func:`.kpo.rederive_rotations`), as for every model,
  and the head and hands face as their devices do (:meth:`.hands.LostHandPolicy.orientations`).

Shape legend: ``J`` = 22 joints; device order head, left, right.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Final

import numpy as np

from ..config import FusionConfig, ModelMetadata
from ..hmd import check_poses, ignore_untracked
from ..inputs import heading_frame
from ..rig import DEFAULT_OFFSETS_M, TRACKED_JOINTS, joints_from_devices
from ..rotations import about_vertical, wrap_angle
from ..skeleton import (
    ARM_JOINTS,
    FOOT_JOINT_HEIGHT_M,
    JOINT_NAMES,
    NUM_JOINTS,
    PARENTS,
    forward_kinematics,
    rest_offsets,
)
from . import kernels
from .body import BodyCalibrator, GivenBody
from .calibration import Calibration, body_measurements, canonical_poses
from .filters import DevicePoseFilter, OneEuroCascade
from .hands import LostHandPolicy
from .kpo import orient_leaves, rederive_rotations
from .loading import ModelInfo
from .pipeline import (
    DEVICE_POSITION,
    DEVICE_ROTATION,
    POSITION_BETA,
    POSITION_MIN_CUTOFF_HZ,
    PendingPose,
    PoseResult,
)
from .seated_yaw import DEAD_ZONE_DEG

NAME: Final = "procedural"
DESCRIPTION: Final = "no network: pelvis under the head, planted feet that step, IK knees and arms (baseline)"
TURN_TIME_S: Final = 0.4
# Standing, the head turns this far from the hips before they follow: without it a glance or a reach turned the
# served hips and stepped the feet (chosen on the training split's still streams; MODEL_CARD.md, "The procedural
# baseline: hips that turn only past a dead zone").
TURN_DEAD_ZONE_DEG: Final = 30.0
# Seated, the trunk twists further before the chair turns (seated_yaw.DEAD_ZONE_DEG, which the network
# pipeline's seated yaw shares; MODEL_CARD.md, rule 63).
SEATED_DEAD_ZONE_DEG: Final = DEAD_ZONE_DEG
STEP_TRIGGER_M: Final = 0.14  # for a body of SMPL's size
STEP_TURN_DEG: Final = 35.0
STEP_S: Final = 0.28
STEP_LEAN: Final = 0.5  # standing, the feet step after the head once the neck leans this share of the torso
WALKING_M_S: Final = 0.5  # from this head speed on, the pelvis follows the head all the way
MAX_LEAN: Final = 0.95  # the neck at most this fraction of the torso's length ahead of the pelvis
VELOCITY_TIME_S: Final = 0.15  # smoothing of the pelvis's velocity, which steps lead by STEP_S
STEP_HEIGHT_M: Final = 0.06
FOOT_SPREAD_M: Final = 0.02  # feet this much wider than the hips
# A stream that begins seated: the feet this many metres in front of the pelvis per metre the head hangs the
# pelvis lower than it stands (MODEL_CARD.md, rule 63).
SEAT_BACK_PER_DROP: Final = 0.6
SEAT_STOOD_M: Final = 0.02  # a seat this close over the feet is left: the sitter stood up
# ... only where that pelvis is lower than this share of its standing height (eval's seated category's 0.7: a
# short stander's first head is no seat)
SEATED_SHARE: Final = 0.7
LEG_CHAINS: Final = ((1, 4, 7, 10), (2, 5, 8, 11))  # hip, knee, ankle, foot
ARM_CHAINS: Final = ((16, 18, 20), (17, 19, 21))  # shoulder, elbow, wrist
FEET_AND_ANKLES: Final = [7, 8, 10, 11]


# the joints that turn with the chest: neck, collars, head, arms
_CHEST: Final = [12, 13, 14, 15, *ARM_CHAINS[0], *ARM_CHAINS[1]]
_SPINE: Final = [3, 6, 9]  # spine1-3, between the pelvis and the neck


_HALF_TURN: Final = np.diag([-1.0, 1.0, -1.0])  # devices look along -z, SMPL faces +z
_PARENTS: Final = PARENTS.astype(np.int64)  # the compiled kernels' index type, converted once


def _yaw_rotation(yaw: float) -> np.ndarray:
    """(3, 3) the body turned to a headset yaw, with the half turn between them."""
    return about_vertical(yaw) @ _HALF_TURN


class ProceduralModel:
    """The servable face of the procedural baseline: what the registry lists and sessions select."""

    visual = None
    batchable = False  # no net: the scheduler never batches it
    provider = "none"  # runs no network

    def __init__(self) -> None:
        metadata = ModelMetadata(
            format="1", kind="model", name=NAME, description=DESCRIPTION, inputs=("hmd",),
            config=FusionConfig(window=1, fusion="none"), kpo=False, visual_encoder="",
            joint_names=JOINT_NAMES, rig_offsets_m=tuple(map(tuple, DEFAULT_OFFSETS_M.tolist())),
            training={}, units="",
        )  # fmt: skip
        self.info = ModelInfo(path=None, metadata=metadata, visual_path=None, encoder=None)  # type: ignore[arg-type]
        self.measures_body = False
        kernels.warm_up()


@dataclasses.dataclass
class _Foot:
    planted: np.ndarray  # (3,) world position of the foot joint
    step_from: np.ndarray | None = None
    step_to: np.ndarray | None = None
    step_t0_s: float = 0.0


def _two_bone(
    root: np.ndarray, target: np.ndarray, upper: float, lower: float, pole: np.ndarray
) -> np.ndarray:
    """The middle joint of a two-bone chain from root (3,) reaching towards target (3,), bending towards pole
    (3,); an out-of-reach target straightens the chain towards it."""
    axis = target - root
    dist = float(np.linalg.norm(axis))
    if dist < 1e-9:
        return root + pole / max(np.linalg.norm(pole), 1e-9) * upper
    axis = axis / dist
    dist = min(max(dist, abs(upper - lower) + 1e-6), upper + lower - 1e-6)
    along = (upper**2 - lower**2 + dist**2) / (2 * dist)
    height = math.sqrt(max(upper**2 - along**2, 0.0))
    bend = pole - (pole @ axis) * axis
    norm = np.linalg.norm(bend)
    bend = bend / norm if norm > 1e-9 else np.cross(axis, [0.0, 1.0, 0.0])
    return root + along * axis + height * bend


def _reach(root: np.ndarray, target: np.ndarray, length: float) -> np.ndarray:
    """target, or the point towards it at ``length`` from root when it is farther."""
    axis = target - root
    dist = float(np.linalg.norm(axis))
    return target if dist <= length else root + axis * (length / dist)


class ProceduralPipeline(GivenBody):
    """The Pipeline interface (push_hmd, observe_hmd, push_rgbd, add_frame, reset) for the procedural model.
    Not thread-safe: one caller at a time."""

    def __init__(
        self, model: ProceduralModel, bone_scale: np.ndarray | None = None, seat: bool = False
    ) -> None:
        self.model = model
        # a stream that begins seated gets a seat (_update_seat; MODEL_CARD.md, rule 63); False: it stands
        self.seat = seat
        self.fixed_body = bone_scale is not None
        self.bone_scale = (
            np.ones(NUM_JOINTS) if bone_scale is None else np.asarray(bone_scale, dtype=np.float64)
        )
        self.calibration: Calibration | None = None  # the wearer's; kept across reset()
        self.reset()

    def calibrate(self, calibration: Calibration | None) -> None:
        """As :meth:`Pipeline.calibrate <egoposevr.model.runtime.pipeline.Pipeline.calibrate>`."""
        self.calibration = calibration
        self.body.calibrate(*body_measurements(calibration, self.model.info.rig_offsets_m[0]))
        self._body_changed()

    def _body_changed(self) -> None:
        """As :meth:`Pipeline._body_changed <egoposevr.model.runtime.pipeline.Pipeline._body_changed>`."""
        self._set_offsets(rest_offsets(self.bone_scale if self.fixed_body else self.body.bone_scale))

    def _estimated_scale(self) -> np.ndarray:
        return self.body.bone_scale

    def reset(self) -> None:
        self.body = BodyCalibrator()
        self._set_offsets(rest_offsets(self.bone_scale))
        self.device_filter = DevicePoseFilter(DEVICE_POSITION, DEVICE_ROTATION)
        self._restart_stream()
        if self.calibration is not None:
            self.calibrate(self.calibration)

    def _restart_stream(self) -> None:
        """A new session, or the headset jumped (a recentred space, as in :meth:`Pipeline._restart_stream
        <egoposevr.model.runtime.pipeline.Pipeline._restart_stream>`): the stream starts again from the next
        sample; the body's size and the device filter (which already restarted the jumped devices) stay."""
        self.feet: list[_Foot] | None = None
        self.yaw: float | None = None  # the hips'
        self.chest_yaw = 0.0
        self.stood_yaw = 0.0
        self.last_t_us: int | None = None
        self.last_head = np.array([0.0, 1.6, 0.0, 0.0, 0.0, 0.0, 1.0])
        self.frames_encoded = 0
        self.velocity = np.zeros(3)
        self.last_pelvis: np.ndarray | None = None
        self.hands = LostHandPolicy()  # the head's and hands' orientations from their devices
        self.position_filter = OneEuroCascade(POSITION_MIN_CUTOFF_HZ, POSITION_BETA)
        self.standing_pelvis_y = 0.0  # the highest an upright pelvis under the head has been
        self.support_shift = np.zeros(3)
        self.seat_back_m = 0.0  # how far behind the planted feet a seated stream's pelvis is (_update_seat)
        self._seat_m = 0.0  # the seat's distance behind the feet as the stream began (0: it began standing)
        self._seat_xz = np.zeros(3)  # where that seat is, on the floor plane

    # The camera is not read.
    def push_rgbd(self, *args, **kwargs) -> bool:
        return False

    def add_frame(self, frame) -> bool:
        return False

    def observe_hmd(self, t_us: int, poses: np.ndarray, valid: np.ndarray) -> None:
        self.push_hmd(t_us, poses, valid)

    def begin_hmd(self, t_us: int, poses: np.ndarray, valid: np.ndarray) -> PendingPose:
        """As :meth:`Pipeline.begin_hmd`: no net runs, so the pose is done here."""
        pose = self.push_hmd(t_us, poses, valid)
        return PendingPose(pose.t_us, np.asarray(valid, dtype=bool), pose.joints[:0], np.eye(3), None,
                           pose.timing_us, self.model, {}, done=pose)  # fmt: skip

    def finish_hmd(self, pending: PendingPose, sixd: None) -> PoseResult:
        return pending.done

    def push_hmd(self, t_us: int, poses: np.ndarray, valid: np.ndarray) -> PoseResult:
        started = time.perf_counter()
        t_us = int(t_us)
        valid = np.asarray(valid, dtype=bool)
        poses = ignore_untracked(poses, valid)
        check_poses(poses, valid)
        poses = self.device_filter(t_us, canonical_poses(poses, self.calibration), valid)
        if self.device_filter.jumped[0]:
            self._restart_stream()
        if valid[0]:
            self.last_head = poses[0].copy()
        device_poses = poses.copy()
        device_poses[0] = self.last_head
        tracked, tracked_rot = joints_from_devices(device_poses, self.model.info.rig_offsets_m)
        if not self.fixed_body and self.body.push(tracked, valid):
            self._set_offsets(rest_offsets(self.body.bone_scale))
        dt_s = 0.0 if self.last_t_us is None else max(t_us - self.last_t_us, 0) * 1e-6
        self.last_t_us = t_us
        joints, body_rot = self._solve(t_us, dt_s, tracked, valid)
        exact = FEET_AND_ANKLES + [20 + k for k in range(2) if valid[k + 1]]  # planted feet, tracked wrists
        kept = joints[exact].copy()
        joints = self.position_filter(t_us, joints)
        joints[exact] = kept
        for device in np.flatnonzero(~valid[1:]) + 1:
            self.hands.lost_wrist(int(device), joints[TRACKED_JOINTS[device]])
        local = np.broadcast_to(np.eye(3), (NUM_JOINTS, 3, 3)).copy()
        local[0] = body_rot
        local[[3, 6, 9]] = about_vertical(wrap_angle(self.chest_yaw - self.yaw) / 3)  # the chest's twist
        _, glob = kernels.forward_kinematics_one(local, np.zeros(3), self.offsets, _PARENTS)
        local = rederive_rotations(local, joints, self.offsets, glob)
        joints, glob = kernels.forward_kinematics_one(local, joints[0].copy(), self.offsets, _PARENTS)
        orient_leaves(local, glob, *self.hands.orientations(t_us, valid, tracked_rot, glob))
        axis_angle = kernels.matrices_to_rotvecs(local)
        return PoseResult(
            t_us=t_us, model=NAME, global_orient=axis_angle[0], body_pose=axis_angle[1:].reshape(-1),
            transl=joints[0].copy(), joints=joints, local_rot=local, camera=None,
            timing_us={"procedural": int((time.perf_counter() - started) * 1e6)},
            planted=self._planted(), floor_y_m=0.0,
        )  # fmt: skip

    def _planted(self) -> tuple[bool, bool]:
        """(left, right): each foot standing where it was put, not in a step."""
        if self.feet is None:
            return False, False
        return self.feet[0].step_to is None, self.feet[1].step_to is None

    def _set_offsets(self, offsets: np.ndarray) -> None:
        """The body's bone offsets (J, 3) and its upright rest pose (J, 3) at the pelvis, kept together."""
        self.offsets = offsets
        self._rest = forward_kinematics(np.broadcast_to(np.eye(3), (NUM_JOINTS, 3, 3)), np.zeros(3), offsets)[
            0
        ]

    def _over_feet(self, rest_world: np.ndarray) -> np.ndarray:
        """(3,) on the floor plane: where an upright pelvis stands over the planted feet."""
        feet_mid = (self.feet[0].planted + self.feet[1].planted) / 2
        stance = rest_world[[10, 11]].mean(axis=0) - rest_world[0]  # feet below an upright pelvis
        return (feet_mid - stance) * [1.0, 0.0, 1.0]

    def _update_seat(self, hanging_m: np.ndarray) -> None:
        """``seat_back_m`` for this sample, the pelvis hanging upright from the head at hanging_m (3,). The
        stream's first sample sets the seat there (its distance behind the feet SEAT_BACK_PER_DROP times how
        much lower than this body's standing pelvis that is, where it is under SEATED_SHARE of it and
        ``seat`` is on; else no seat). Later the seat keeps its place while the head drops (a sitter leaning
        forward) and comes forward over the feet with the drop as the head rises; once it is within
        SEAT_STOOD_M of them the stream stands for good."""
        standing_y_m = FOOT_JOINT_HEIGHT_M - float(self._rest[[10, 11], 1].mean())
        back_m = SEAT_BACK_PER_DROP * max(standing_y_m - float(hanging_m[1]), 0.0)
        if self.feet is None:
            seated = self.seat and hanging_m[1] < SEATED_SHARE * standing_y_m
            self._seat_m = back_m if seated else 0.0
            self._seat_xz = hanging_m * [1.0, 0.0, 1.0]
        self.seat_back_m = min(self._seat_m, back_m)
        if self.seat_back_m < SEAT_STOOD_M:
            self._seat_m = self.seat_back_m = 0.0

    def _seat(self, rest_world: np.ndarray) -> np.ndarray:
        """(3,) on the floor plane: where the pelvis stands over the planted feet, or in a stream that began
        seated sits: at the seat, coming forward over the feet as ``seat_back_m`` shrinks."""
        over_feet = self._over_feet(rest_world)
        if self._seat_m <= 0.0:
            return over_feet
        return over_feet + (self._seat_xz - over_feet) * (self.seat_back_m / self._seat_m)

    def _walking(self) -> float:
        """How far the body is walking, 0 (standing) to 1 (from WALKING_M_S): the pelvis's smoothed speed."""
        return min(float(np.linalg.norm(self.velocity[[0, 2]])) / WALKING_M_S, 1.0)

    def _turn(self, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """The hips' and the chest's yaw rotations (3, 3) each: the chest follows the head's yaw with a lag,
        the hips only beyond a dead zone (TURN_DEAD_ZONE_DEG, none at walking speed)."""
        head_rot, _ = heading_frame(self.last_head)
        head_yaw = math.atan2(head_rot[0, 2], head_rot[0, 0])
        if self.yaw is None:
            self.yaw = self.stood_yaw = self.chest_yaw = head_yaw
        follow = 1.0 - math.exp(-dt_s / TURN_TIME_S)
        self.chest_yaw += wrap_angle(head_yaw - self.chest_yaw) * follow
        gap = wrap_angle(head_yaw - self.yaw)
        seated = self.seat_back_m > 0.0
        dead_zone = math.radians(SEATED_DEAD_ZONE_DEG if seated else TURN_DEAD_ZONE_DEG) * (
            1.0 - self._walking()
        )
        self.yaw += math.copysign(max(abs(gap) - dead_zone, 0.0), gap) * follow
        return _yaw_rotation(self.yaw), _yaw_rotation(self.chest_yaw)

    def _solve(
        self, t_us: int, dt_s: float, tracked: np.ndarray, valid: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        now_s = t_us * 1e-6
        body_rot, chest_rot = self._turn(dt_s)
        offsets, rest = self.offsets, self._rest
        rest_world = rest @ body_rot.T  # upright, at the pelvis
        # the neck, collars and arms twisted about spine3 with the chest; the spine and legs with the hips
        rest_world[_CHEST] = (rest[_CHEST] - rest[9]) @ chest_rot.T + rest_world[9]
        upright = rest_world + (tracked[0] - rest_world[15])  # hanging from the head joint
        if self.last_pelvis is not None and dt_s > 0:
            blend = 1.0 - math.exp(-dt_s / VELOCITY_TIME_S)
            self.velocity += blend * ((upright[0] - self.last_pelvis) / dt_s - self.velocity)
        self.last_pelvis = upright[0].copy()
        scale = float(np.mean((self.bone_scale if self.fixed_body else self.body.bone_scale)[1:]))
        joints = self._torso(upright, rest_world, tracked[0])
        support = upright.copy()  # the hips where the feet belong (see _torso)
        if self.feet is not None:
            support[[0, 1, 2]] += self._seat(rest_world) - upright[0] * [1.0, 0.0, 1.0] + self.support_shift
        self._update_seat(upright[0])
        self._place_feet(now_s, support, body_rot, scale)
        for side, (hip, knee, ankle, foot) in enumerate(LEG_CHAINS):
            foot_pos = self._foot_position(side, now_s)
            ankle_target = foot_pos - body_rot @ (rest[foot] - rest[ankle])
            thigh, shin = np.linalg.norm(offsets[knee]), np.linalg.norm(offsets[ankle])
            ankle_pos = _reach(joints[hip], ankle_target, thigh + shin - 1e-6)
            forward = body_rot @ np.array([0.0, 0.0, 1.0])
            joints[knee] = _two_bone(joints[hip], ankle_pos, thigh, shin, forward)
            joints[ankle] = ankle_pos
            joints[foot] = ankle_pos + body_rot @ (rest[foot] - rest[ankle])
        for side, (shoulder, elbow, wrist) in enumerate(ARM_CHAINS):
            upper, lower = np.linalg.norm(offsets[elbow]), np.linalg.norm(offsets[wrist])
            if valid[side + 1]:  # a controller found again: from where its wrist was while lost
                target = tracked[side + 1] + self.hands.found_gap(t_us, side + 1, tracked[side + 1])
            else:  # hanging by the side
                target = joints[shoulder] + np.array([0.0, -(upper + lower) * 0.98, 0.0])
            target = _reach(joints[shoulder], target, upper + lower - 1e-6)
            pole = chest_rot @ np.array([0.0, -1.0, -0.5])
            joints[elbow] = _two_bone(joints[shoulder], target, upper, lower, pole)
            joints[wrist] = target
        return joints, body_rot

    def _torso(self, upright: np.ndarray, rest_world: np.ndarray, head: np.ndarray) -> np.ndarray:
        """The upper body (J, 3). The neck hangs under the head joint. While the body stands, the pelvis stays
        over the planted feet (in a stream that began seated, on its seat: :meth:`_seat`), at most at its
        standing height and at the torso's length from the neck: bending over tilts the spine with straight
        legs, a squat (the head going straight down) bends the knees.
        Walking (from WALKING_M_S) the pelvis goes along under the head. The spine lies on the line from the
        pelvis to the neck."""
        joints = upright.copy()
        self.standing_pelvis_y = max(self.standing_pelvis_y, float(upright[0, 1]))
        if self.feet is None:
            return joints
        neck, pelvis_upright = upright[12], upright[0]
        flat = np.array([1.0, 0.0, 1.0])
        over_feet = self._seat(rest_world)
        walking = self._walking()
        pelvis = over_feet + walking * (pelvis_upright * flat - over_feet)
        torso = float(np.linalg.norm(rest_world[12] - rest_world[0]))
        # Where the feet should be: under the hips when walking, or once the neck leans so far (more than
        # STEP_LEAN of the torso's length) that standing there would topple; otherwise where they are.
        # (seated, a lean is a sitter reaching: nothing topples, so it steps nothing)
        leaning = 0.0 if self.seat_back_m > 0.0 else float(np.linalg.norm((neck - over_feet) * flat)) / torso
        moving = max(walking, min(max((leaning - STEP_LEAN) / STEP_LEAN, 0.0), 1.0))
        self.support_shift = moving * (pelvis_upright - over_feet) * flat
        lean = (neck - pelvis) * flat
        reach = float(np.linalg.norm(lean))
        if reach > MAX_LEAN * torso:  # the neck is too far ahead: the pelvis follows it
            pelvis += lean * (1.0 - MAX_LEAN * torso / reach)
            reach = MAX_LEAN * torso
        pelvis[1] = min(neck[1] - math.sqrt(torso**2 - reach**2), self.standing_pelvis_y)
        shift = pelvis - pelvis_upright
        for joint in (0, 1, 2):  # pelvis and hips
            joints[joint] = upright[joint] + shift
        # The rest spine turned onto the pelvis-to-neck line: its bones keep their lengths, so the forward
        # kinematics that serves the pose puts the head joint on the tracked one (joints on the straight line
        # at their rest heights served it 1.8 cm behind: MODEL_CARD.md, rule 88).
        turn = kernels.swing(rest_world[12] - rest_world[0], neck - pelvis)
        joints[_SPINE] = pelvis + (rest_world[_SPINE] - rest_world[0]) @ turn.T
        joints[ARM_JOINTS] = upright[ARM_JOINTS] + (joints[9] - upright[9])  # collars and arms ride on spine3
        joints[15] = head
        return joints

    def _ideal_feet(self, joints: np.ndarray, body_rot: np.ndarray) -> np.ndarray:
        """(2, 3) where the foot joints would stand: under the hips (``seat_back_m`` in front of them in a
        stream that began seated), a little apart, on the floor."""
        out = np.empty((2, 3))
        rest = self._rest
        ahead = body_rot @ np.array([0.0, 0.0, self.seat_back_m])
        for side, (hip, _, _, foot) in enumerate(LEG_CHAINS):
            outward = body_rot @ np.array([FOOT_SPREAD_M if side == 0 else -FOOT_SPREAD_M, 0.0, 0.0])
            out[side] = joints[hip] + outward + ahead + body_rot @ (rest[foot] - rest[hip]) * [1.0, 0.0, 1.0]
        out[:, 1] = FOOT_JOINT_HEIGHT_M
        return out

    def _place_feet(self, now_s: float, joints: np.ndarray, body_rot: np.ndarray, scale: float) -> None:
        """Finish steps that are done; start one when a foot is far from where it would stand, or the body
        has turned since the feet were last both in place."""
        ideal = self._ideal_feet(joints, body_rot)
        if self.feet is None:
            self.feet = [_Foot(planted=ideal[k].copy()) for k in range(2)]
            return
        for foot in self.feet:
            if foot.step_to is not None and now_s - foot.step_t0_s >= STEP_S:
                foot.planted, foot.step_from, foot.step_to = foot.step_to, None, None
        if any(f.step_to is not None for f in self.feet):
            return
        distance = [float(np.linalg.norm((self.feet[k].planted - ideal[k])[[0, 2]])) for k in range(2)]
        trigger = STEP_TRIGGER_M * scale
        turned = abs((self.yaw - self.stood_yaw + math.pi) % (2 * math.pi) - math.pi) > math.radians(
            STEP_TURN_DEG
        )
        if max(distance) <= trigger and not turned:
            return
        worst = int(np.argmax(distance))
        foot = self.feet[worst]
        ahead = self.velocity * STEP_S * [1.0, 0.0, 1.0]
        foot.step_from, foot.step_to, foot.step_t0_s = foot.planted.copy(), ideal[worst] + ahead, now_s
        if distance[1 - worst] <= trigger:
            self.stood_yaw = self.yaw  # the other foot is in place: this step completes the turn

    def _foot_position(self, side: int, now_s: float) -> np.ndarray:
        foot = self.feet[side]
        if foot.step_to is None:
            return foot.planted
        phase = min(max((now_s - foot.step_t0_s) / STEP_S, 0.0), 1.0)
        smooth = phase * phase * (3 - 2 * phase)
        position = foot.step_from + smooth * (foot.step_to - foot.step_from)
        position[1] += STEP_HEIGHT_M * math.sin(math.pi * phase)
        return position


# The network pipeline's options that the procedural one has no stage for (it plants its own feet, has no
# KPO, no leg hold and no estimated body to keep).
NETWORK_PIPELINE_OPTIONS: Final = (
    "naive", "kpo_weights", "contacts", "steady_stance", "leg_hold", "lean_gate", "reseat", "body_hold",
    "sure_plant", "warm_reseat", "seated_yaw", "quiet_lift", "early_body", "head_relative_filter",
)  # fmt: skip
# ... and the procedural pipeline's that the network one has no stage for (its net says where seated feet are)
PROCEDURAL_PIPELINE_OPTIONS: Final = ("seat",)


def pipeline_for(model, **kwargs):
    """A session's pipeline for any servable model: the procedural one's, or the network pipeline; each
    drops the other's options."""
    from .pipeline import Pipeline

    theirs = NETWORK_PIPELINE_OPTIONS if isinstance(model, ProceduralModel) else PROCEDURAL_PIPELINE_OPTIONS
    for option in theirs:
        kwargs.pop(option, None)
    if isinstance(model, ProceduralModel):
        return ProceduralPipeline(model, **kwargs)
    return Pipeline(model, **kwargs)
