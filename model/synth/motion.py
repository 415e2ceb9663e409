"""The one motion representation every source is retargeted to: SMPL-22 local rotations + pelvis positions.

The model learns rotations, so a motion carries local rotations (not only positions) plus the body's per-bone
length scales; ``joints()`` runs forward kinematics to get positions. World frame: y up, metres, floor at
y = 0 after :func:`ground`. Also here: feet that stand and grip, for motion retargeted from another skeleton
(:func:`fix_feet`: :func:`level_feet`, :func:`lock_support_feet`) and the measures that say whether they do
(:func:`foot_slide`, :func:`stance_foot_height_m`, :func:`standing_foot_tilt_deg`).

Shape legend: ``F`` frames, ``J`` = 22 joints.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from ..skeleton import FOOT_JOINT_HEIGHT_M, NUM_JOINTS, forward_kinematics, rest_offsets

# Height of the SMPL ankle joint above the sole, metres: the leg's length to the floor (bodies.py); the
# renderer's shoe capsules are sized to match. The floor itself is put under the foot joint (FOOT_JOINT_HEIGHT_M).
ANKLE_JOINT_HEIGHT_M = 0.08
FEET_BONES = ((7, 10), (8, 11))  # (ankle, foot joint): left, right
ANKLES = tuple(ankle for ankle, _ in FEET_BONES)
# A foot is down while its ankle is within this of its lowest (5th percentile) height in the clip.
FOOT_DOWN_M = 0.02
MAX_FOOT_TURN_DEG = 30.0  # a larger measured tilt is a clip whose feet are never flat (tiptoes), not a rig's


@dataclasses.dataclass(frozen=True)
class Motion:
    """One clip on the SMPL-22 skeleton.

    local_rot:  (F, J, 3, 3) local rotations; [:, 0] is the pelvis's global rotation.
    root_pos_m: (F, 3) world position of the pelvis.
    bone_scale: (J,) per-bone length scale of this body against the SMPL rest skeleton.
    source:     where it came from, e.g. ``cmu:01_02`` or ``procedural:squat``.
    licence:    the source's terms, copied into dataset manifests.
    """

    name: str
    fps: float
    local_rot: np.ndarray
    root_pos_m: np.ndarray
    bone_scale: np.ndarray
    source: str
    licence: str

    def __post_init__(self) -> None:
        frames = len(self.local_rot)
        if self.local_rot.shape != (frames, NUM_JOINTS, 3, 3) or self.root_pos_m.shape != (frames, 3):
            raise ValueError(f"bad motion shapes {self.local_rot.shape} / {self.root_pos_m.shape}")
        if self.bone_scale.shape != (NUM_JOINTS,) or self.fps <= 0:
            raise ValueError("bone_scale must be (22,) and fps > 0")

    @property
    def num_frames(self) -> int:
        return len(self.local_rot)

    @property
    def duration_s(self) -> float:
        return self.num_frames / self.fps

    def offsets_m(self) -> np.ndarray:
        """(J, 3) rest offsets of this body."""
        return rest_offsets(self.bone_scale)

    def fk(self) -> tuple[np.ndarray, np.ndarray]:
        """(joints_m (F, J, 3), global_rot (F, J, 3, 3))."""
        return forward_kinematics(self.local_rot, self.root_pos_m, self.offsets_m())

    def joints(self) -> np.ndarray:
        """(F, J, 3) world joint positions, metres."""
        return self.fk()[0]

    def replace(self, **changes) -> Motion:
        return dataclasses.replace(self, **changes)

    def slice(self, start: int, stop: int) -> Motion:
        return self.replace(local_rot=self.local_rot[start:stop], root_pos_m=self.root_pos_m[start:stop])


def sample_at(motion: Motion, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotations slerped and root linearly interpolated at times ``t_s`` (N,) (clamped to the clip).

    Returns (local_rot (N, J, 3, 3), root_pos_m (N, 3)).
    """
    src_t = np.arange(motion.num_frames) / motion.fps
    t_s = np.clip(np.asarray(t_s, dtype=np.float64), 0.0, src_t[-1])
    if motion.num_frames == 1:
        return np.repeat(motion.local_rot, len(t_s), 0), np.repeat(motion.root_pos_m, len(t_s), 0)
    local_rot = np.empty((len(t_s), NUM_JOINTS, 3, 3))
    for j in range(NUM_JOINTS):
        local_rot[:, j] = Slerp(src_t, Rotation.from_matrix(motion.local_rot[:, j]))(t_s).as_matrix()
    root = np.stack([np.interp(t_s, src_t, motion.root_pos_m[:, k]) for k in range(3)], axis=-1)
    return local_rot, root


def resample(motion: Motion, fps: float) -> Motion:
    """The same clip at another frame rate (slerp for rotations, linear for the root)."""
    if fps == motion.fps:
        return motion
    frames = max(1, int(np.floor(motion.duration_s * fps + 1e-9)))
    local_rot, root = sample_at(motion, np.arange(frames) / fps)
    return motion.replace(fps=float(fps), local_rot=local_rot, root_pos_m=root)


def feet_down(joints_m: np.ndarray, margin_m: float) -> np.ndarray:
    """(F, 2) bool: each foot (left, right) down, its ankle within ``margin_m`` of its lowest height in the clip
    (the 5th percentile, so that a noisy frame does not set it). joints_m: (F, J, 3)."""
    ankle_y = joints_m[:, list(ANKLES), 1]
    return ankle_y < np.percentile(ankle_y, 5, axis=0) + margin_m


def ground(motion: Motion) -> Motion:
    """Put the floor at y = 0 under the standing feet and the first frame's pelvis above the origin.

    The floor is where the feet stand: over the frames where a foot is down (its ankle within FOOT_DOWN_M of
    its lowest, the 5th percentile of the clip), the median height of its sole (the foot joint minus
    FOOT_JOINT_HEIGHT_M, a flat foot's). A jump, a noisy frame or a foot that points its toes down in a swing
    moves it little; a foot tilted at every frame (:func:`level_feet` first) would stand on its ball.
    """
    joints = motion.joints()
    down = feet_down(joints, FOOT_DOWN_M)
    soles = [
        joints[down[:, side], ball, 1] - FOOT_JOINT_HEIGHT_M for side, (_, ball) in enumerate(FEET_BONES)
    ]
    floor_y = float(np.median(np.concatenate(soles)))
    shift = np.array([-motion.root_pos_m[0, 0], -floor_y, -motion.root_pos_m[0, 2]])
    return motion.replace(root_pos_m=motion.root_pos_m + shift)


# A body moves when its pelvis crosses the floor faster than this; below it, standing feet may shuffle.
MOVING_M_S = 0.3
STANCE_M_S = 0.1  # a foot slower than this over the floor stands (or is about to)


def _floor_speeds(points_m: np.ndarray, fps: float) -> np.ndarray:
    """(F, ...) speed over the floor (x, z) of points (F, ..., 3), m/s, by central differences."""
    return np.linalg.norm(np.gradient(points_m[..., [0, 2]], 1.0 / fps, axis=0), axis=-1)


def foot_slide(joints_m: np.ndarray, fps: float) -> float | None:
    """How much the feet slide while the body travels: over the frames where the pelvis crosses the floor
    faster than MOVING_M_S, the median of the slower ankle's speed over the floor as a share of the pelvis's.

    Walking or running with feet that grip, one foot stands while the body passes over it: about 0.1 (the
    share of the stride spent switching feet). Feet that slide under a moving body (a root path that does not
    match the legs' strides, as a conversion onto another skeleton can leave) give 0.3 or more, and a body
    gliding with its feet still in the pose gives 1. None when the pelvis never moves that fast.
    joints_m: (F, J, 3) SMPL-22 joints (or any skeleton whose 0 is the pelvis and ANKLES its ankles)."""
    if len(joints_m) < 3:
        return None
    pelvis = _floor_speeds(joints_m[:, 0], fps)
    moving = pelvis > MOVING_M_S
    if not moving.any():
        return None
    slower = _floor_speeds(joints_m[:, list(ANKLES)], fps).min(axis=1)
    return float(np.median(slower[moving] / pelvis[moving]))


def stance_foot_height_m(joints_m: np.ndarray, fps: float) -> float | None:
    """The median height of the lower foot joint (the ball of the foot) over the frames where it stands
    (slower than STANCE_M_S over the floor): FOOT_JOINT_HEIGHT_M on a grounded motion whose feet stand flat;
    higher where a conversion tilts the foot or the floor was put too low. None when no foot stands.
    joints_m: (F, J, 3) grounded SMPL-22 joints."""
    if len(joints_m) < 3:
        return None
    feet = joints_m[:, [10, 11]]
    lower = np.argmin(feet[..., 1], axis=1)
    rows = np.arange(len(feet))
    standing = _floor_speeds(feet, fps)[rows, lower] < STANCE_M_S
    if not standing.any():
        return None
    return float(np.median(feet[rows, lower, 1][standing]))


def level_feet(motion: Motion) -> Motion:
    """Each foot turned at the ankle by one constant pitch so that it stands flat while it is down.

    A conversion onto another skeleton can leave every foot tilted by the same angle: the source rig's foot
    bone at rest is not a flat-standing foot, and the retargeting maps rest onto SMPL's flat rest foot (CMU's
    conversions stand with the ball of the foot ~3 cm high, toes up by ~13°; ``egoposevr motion inspect``
    reports it). Over the frames where a foot is down (its ankle within FOOT_DOWN_M of its lowest), the median
    pitch of the ankle->ball bone against SMPL's rest is that tilt; the ankle's local rotation is turned back
    by it about the foot's own lateral axis, so the rest of the pose is unchanged. At most
    MAX_FOOT_TURN_DEG. The motion is not re-grounded."""
    local = motion.local_rot.copy()
    offsets = motion.offsets_m()
    limit = np.radians(MAX_FOOT_TURN_DEG)
    axes = np.cross([0.0, 1.0, 0.0], offsets[[ball for _, ball in FEET_BONES]])  # (2, 3) each foot's lateral
    lengths = np.linalg.norm(axes, axis=1)
    turned_rad = np.zeros(2)
    for _ in range(2):  # measured in the world, turned in the ankle's frame: a second pass settles it
        steps_rad = np.clip(
            _standing_tilts_rad(motion.replace(local_rot=local)), -limit - turned_rad, limit - turned_rad
        )
        steps_rad[(np.abs(steps_rad) < 1e-4) | (lengths < 1e-9)] = 0.0
        if not steps_rad.any():
            break
        turned_rad += steps_rad
        for side, (ankle, _) in enumerate(FEET_BONES):
            turn = Rotation.from_rotvec(axes[side] / max(lengths[side], 1e-9) * steps_rad[side]).as_matrix()
            local[:, ankle] = local[:, ankle] @ turn
    return motion.replace(local_rot=local)


def standing_foot_tilt_deg(motion: Motion) -> tuple[float, float]:
    """(left, right): how far each standing foot points its toes up against SMPL's flat rest foot, degrees
    (what :func:`level_feet` turns back)."""
    left, right = np.degrees(_standing_tilts_rad(motion))
    return float(left), float(right)


def _standing_tilts_rad(motion: Motion) -> np.ndarray:
    """(2,) left, right: how far each ankle->ball bone points above SMPL's flat rest foot (radians, positive:
    toes up), the median over the frames where that foot is down."""
    joints, global_rot = motion.fk()
    down = feet_down(joints, FOOT_DOWN_M)
    offsets = motion.offsets_m()
    tilts = np.zeros(2)
    for side, (ankle, ball) in enumerate(FEET_BONES):
        foot_m = offsets[ball]
        bone = global_rot[down[:, side], ankle] @ foot_m  # (frames down, 3)
        pitch = np.arcsin(np.clip(bone[:, 1] / np.linalg.norm(bone, axis=1), -1.0, 1.0))
        tilts[side] = np.median(pitch) - np.arcsin(foot_m[1] / np.linalg.norm(foot_m))
    return tilts


def fix_feet(motion: Motion) -> Motion:
    """What synth's import does to a motion retargeted from another skeleton: its feet levelled
    (:func:`level_feet`), its path rebuilt from its strides if its feet slide (:func:`lock_support_feet`), and
    the floor put under the standing feet again (:func:`ground`)."""
    return ground(lock_support_feet(level_feet(motion)))


SLIDE_TO_LOCK = 0.2  # feet that slide more than this (foot_slide) are locked; captures whose feet grip: ~0.1
SUPPORT_SWITCH_M_S = 0.1  # the other foot must be this much slower to take the weight (no flicker)
SUPPORT_DOWN_M = 0.04  # a foot whose ankle is higher than this over its lowest is in the air (jumps, runs)


def lock_support_feet(motion: Motion) -> Motion:
    """The pelvis path re-derived so that the foot bearing the weight stays where it stands, for a motion
    whose feet slide (:func:`foot_slide` over SLIDE_TO_LOCK; others are returned as they are).

    A conversion onto a skeleton other than the actor's can keep the recorded pelvis path while the legs take
    shorter or longer strides: the feet then slide under the body (CMU's Daz-rig conversions, ``egoposevr
    motion inspect``). The pose is kept and the path is rebuilt from the legs (:func:`support_lock_offsets_m`):
    the body travels as far as its strides carry it. Not re-grounded (the path moves over the floor only)."""
    joints = motion.joints()
    slide = foot_slide(joints, motion.fps)
    if slide is None or slide < SLIDE_TO_LOCK:
        return motion
    root = motion.root_pos_m.copy()
    root[:, [0, 2]] += support_lock_offsets_m(joints, motion.fps)
    return motion.replace(root_pos_m=root)


def support_lock_offsets_m(joints_m: np.ndarray, fps: float) -> np.ndarray:
    """(F, 2) x, z shifts that hold the supporting mid-foot (between ankle and ball) still over the floor.

    The support is the slower of the feet that are down (ankle within SUPPORT_DOWN_M of its lowest); the
    other takes over once it is SUPPORT_SWITCH_M_S slower. Each frame's shift cancels the support's move since
    the frame before (a foot that has just come down is held from the frame after); with no foot down (a
    jump, a run's flight) the shift carries on unchanged, so the body flies as recorded.
    joints_m: (F, J, 3) SMPL-22 joints."""
    frames = len(joints_m)
    mid_foot = 0.5 * (joints_m[:, list(ANKLES)] + joints_m[:, [10, 11]])  # (F, 2 feet, 3)
    speed = _floor_speeds(mid_foot, fps)
    down = feet_down(joints_m, SUPPORT_DOWN_M)
    offsets = np.zeros((frames, 2))
    support: int | None = None
    for i in range(1, frames):
        offsets[i] = offsets[i - 1]
        support = _support(support, down[i], speed[i])
        if support is not None and down[i - 1, support]:
            offsets[i] -= (mid_foot[i, support] - mid_foot[i - 1, support])[[0, 2]]
    return offsets


def _support(was: int | None, down: np.ndarray, speed: np.ndarray) -> int | None:
    """Which foot bears the weight now: None with no foot down; the one that did while it stays down unless
    the other is down and SUPPORT_SWITCH_M_S slower; else the slower foot that is down."""
    if not down.any():
        return None
    if was is not None and down[was]:
        other = 1 - was
        return other if down[other] and speed[other] < speed[was] - SUPPORT_SWITCH_M_S else was
    return int(np.argmin(np.where(down, speed, np.inf)))
