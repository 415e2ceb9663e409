"""The one motion representation every source is retargeted to: SMPL-22 local rotations + pelvis positions.

The model learns rotations, so a motion carries local rotations (not only positions) plus the body's per-bone
length scales; ``joints()`` runs forward kinematics to get positions. World frame: y up, metres, floor at
y = 0 after :func:`ground`.

Shape legend: ``F`` frames, ``J`` = 22 joints.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from ..skeleton import FOOT_JOINT_HEIGHT_M, NUM_JOINTS, forward_kinematics, rest_offsets

# Height of the SMPL foot (toe-base) and ankle joints above the sole when standing flat, metres. Used to put
# the floor under a motion; the renderer's shoe capsules are sized to match.
ANKLE_JOINT_HEIGHT_M = 0.08
FEET = (7, 8, 10, 11)  # left/right ankle, left/right foot


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


def ground(motion: Motion, percentile: float = 1.0) -> Motion:
    """Put the floor at y = 0 under the feet and the first frame's pelvis above the origin.

    The floor is a low percentile over all frames of the lowest foot point (foot and ankle joints minus their
    height above the sole), so a jump or a noisy frame does not lift it.
    """
    joints = motion.joints()
    sole_y = np.minimum(
        joints[:, [10, 11], 1].min(axis=1) - FOOT_JOINT_HEIGHT_M,
        joints[:, [7, 8], 1].min(axis=1) - ANKLE_JOINT_HEIGHT_M,
    )
    floor_y = np.percentile(sole_y, percentile)
    shift = np.array([-motion.root_pos_m[0, 0], -floor_y, -motion.root_pos_m[0, 2]])
    return motion.replace(root_pos_m=motion.root_pos_m + shift)
