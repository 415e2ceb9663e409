"""The SMPL-22 body skeleton (SMPL's first 22 joints) and batched forward kinematics in numpy.

Frames and units: metres; the rest skeleton stands at the origin with the pelvis at (0, 0, 0), y up, facing
+z, x towards the subject's left (SMPL's canonical frame). Rotations are local: ``local[j]`` rotates joint j's
children relative to its parent, so ``global[j] = global[parent[j]] @ local[j]`` and
``pos[j] = pos[parent[j]] + global[parent[j]] @ offset[j]``.

Shape legend: ``J`` = 22 joints, ``...`` = any batch shape (frames, bodies, ...).
"""

from __future__ import annotations

from typing import Final

import numpy as np

from .rotations import axis_angle_to_matrix, matrix_to_axis_angle

JOINT_NAMES: Final = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2", "left_ankle",
    "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar", "right_collar", "head",
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
)  # fmt: skip
NUM_JOINTS: Final = 22
PARENTS: Final = np.array([-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19])
JOINT_INDEX: Final = {name: i for i, name in enumerate(JOINT_NAMES)}
PELVIS, HEAD, LEFT_WRIST, RIGHT_WRIST = 0, 15, 20, 21
FOOT_JOINT_HEIGHT_M: Final = 0.035  # the foot joint (ball of the foot) above the floor when flat
UPPER_BODY: Final = np.array([3, 6, 9, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21])
LOWER_BODY: Final = np.array([0, 1, 2, 4, 5, 7, 8, 10, 11])
# Collars, shoulders, elbows, wrists: the joints whose local rotations make the arms' motion.
ARM_JOINTS: Final = np.array([13, 14, 16, 17, 18, 19, 20, 21])
SHOULDERS: Final = (16, 17)  # left, right
# SMPL-22 with left and right swapped: hips, knees, ankles, feet, collars, shoulders, elbows, wrists.
MIRROR_JOINTS: Final = np.array(
    [0, 2, 1, 3, 5, 4, 6, 8, 7, 9, 11, 10, 12, 14, 13, 15, 17, 16, 19, 18, 21, 20]
)


def _depth_levels(parents: np.ndarray) -> tuple[np.ndarray, ...]:
    """Joint indices grouped by depth below the root (the root excluded): FK handles one level at a time."""
    depth = np.zeros(len(parents), dtype=int)
    for j in range(1, len(parents)):
        depth[j] = depth[parents[j]] + 1
    return tuple(np.flatnonzero(depth == d) for d in range(1, depth.max() + 1))


# 8 levels instead of 21 joints: fewer small numpy calls per pose (FK of one pose: 112 -> 76 µs measured).
DEPTH_LEVELS: Final = _depth_levels(PARENTS)

# Rest joint positions relative to the pelvis (DESIGN §4), metres, (J, 3).
REST_JOINTS_M: Final = np.array(
    [
        [0.0, 0.0, 0.0],  # pelvis
        [0.0586, -0.0823, -0.0177],  # left_hip
        [-0.0603, -0.0905, -0.0135],  # right_hip
        [0.0044, 0.1244, -0.0384],  # spine1
        [0.1020, -0.4687, -0.0096],  # left_knee
        [-0.1036, -0.4742, -0.0184],  # right_knee
        [0.0089, 0.2624, -0.0116],  # spine2
        [0.0872, -0.8956, -0.0471],  # left_ankle
        [-0.0845, -0.8942, -0.0529],  # right_ankle
        [0.0067, 0.3184, -0.0087],  # spine3
        [0.1283, -0.9559, 0.0750],  # left_foot
        [-0.1194, -0.9564, 0.0774],  # right_foot
        [-0.0067, 0.5300, -0.0422],  # neck
        [0.0784, 0.4324, -0.0276],  # left_collar
        [-0.0763, 0.4309, -0.0324],  # right_collar
        [0.0034, 0.6190, 0.0082],  # head
        [0.2013, 0.4776, -0.0467],  # left_shoulder
        [-0.1895, 0.4777, -0.0409],  # right_shoulder
        [0.4566, 0.4619, -0.0696],  # left_elbow
        [-0.4496, 0.4633, -0.0722],  # right_elbow
        [0.7223, 0.4746, -0.0770],  # left_wrist
        [-0.7188, 0.4701, -0.0782],  # right_wrist
    ]
)
REST_JOINTS_M.flags.writeable = False


def pelvis_over_legs(joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """joints (..., J, 3) m -> the pelvis's height above the ankles' mean (...,) m and each leg's length,
    thigh + shin, (..., 2) m (left, right): how far the legs are folded (a seated person's pelvis is about half
    a leg's length above the ankles, a standing one's about 0.95)."""
    hips, knees, ankles = joints[..., [1, 2], :], joints[..., [4, 5], :], joints[..., [7, 8], :]
    legs_m = np.linalg.norm(knees - hips, axis=-1) + np.linalg.norm(ankles - knees, axis=-1)
    return joints[..., 0, 1] - ankles[..., 1].mean(-1), legs_m


def rest_offsets(bone_scale: np.ndarray | None = None) -> np.ndarray:
    """Offsets of each joint from its parent in the rest pose, (..., J, 3); the pelvis row is zero.

    ``bone_scale`` (..., J) scales each joint's bone (the segment from its parent to it); None = 1.
    """
    offsets = REST_JOINTS_M.copy()
    offsets[1:] -= REST_JOINTS_M[PARENTS[1:]]
    if bone_scale is None:
        return offsets
    scale = np.asarray(bone_scale, dtype=np.float64)
    if scale.shape[-1:] != (NUM_JOINTS,):
        raise ValueError(f"bone_scale must be (..., {NUM_JOINTS}), got {scale.shape}")
    return offsets * scale[..., None]


def bone_lengths(offsets: np.ndarray) -> np.ndarray:
    """(..., J, 3) offsets -> (..., J) bone lengths (pelvis: 0)."""
    return np.linalg.norm(offsets, axis=-1)


def joint_bone_lengths(joints: np.ndarray) -> np.ndarray:
    """(..., J, 3) joint positions -> (..., J - 1) lengths of bones 1..21 (each joint from its parent)."""
    return np.linalg.norm(joints[..., 1:, :] - joints[..., PARENTS[1:], :], axis=-1)


def bone_scale_of(lengths_m: np.ndarray) -> np.ndarray:
    """(..., J - 1) lengths of bones 1..21, m -> (..., J) bone scale against the mean body's (pelvis: 1)."""
    lengths_m = np.asarray(lengths_m, dtype=np.float64)
    scale = np.ones((*lengths_m.shape[:-1], NUM_JOINTS))
    scale[..., 1:] = lengths_m / bone_lengths(rest_offsets())[1:]
    return scale


def forward_kinematics(
    local_rot: np.ndarray, root_pos_m: np.ndarray, offsets_m: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Joint positions and global rotations from local rotations.

    local_rot:  (..., J, 3, 3) local rotation matrices; local_rot[..., 0] is the pelvis's global rotation.
    root_pos_m: (..., 3) world position of the pelvis.
    offsets_m:  (J, 3) or (..., J, 3) rest offsets from each joint's parent; default :func:`rest_offsets`.
    Returns (pos_m (..., J, 3), global_rot (..., J, 3, 3)).
    """
    local_rot = np.asarray(local_rot, dtype=np.float64)
    if local_rot.shape[-3:] != (NUM_JOINTS, 3, 3):
        raise ValueError(f"local_rot must be (..., {NUM_JOINTS}, 3, 3), got {local_rot.shape}")
    batch = local_rot.shape[:-3]
    root_pos_m = np.broadcast_to(np.asarray(root_pos_m, dtype=np.float64), (*batch, 3))
    offsets_m = rest_offsets() if offsets_m is None else np.asarray(offsets_m, dtype=np.float64)
    offsets_m = np.broadcast_to(offsets_m, (*batch, NUM_JOINTS, 3))
    global_rot = np.empty_like(local_rot)
    pos_m = np.empty((*batch, NUM_JOINTS, 3))
    global_rot[..., 0, :, :] = local_rot[..., 0, :, :]
    pos_m[..., 0, :] = root_pos_m
    for joints in DEPTH_LEVELS:  # every parent is one level up, so it is already done
        parent_rot = global_rot[..., PARENTS[joints], :, :]
        global_rot[..., joints, :, :] = parent_rot @ local_rot[..., joints, :, :]
        pos_m[..., joints, :] = (
            pos_m[..., PARENTS[joints], :] + (parent_rot @ offsets_m[..., joints, :, None])[..., 0]
        )
    return pos_m, global_rot


def global_to_local(global_rot: np.ndarray) -> np.ndarray:
    """(..., J, 3, 3) global rotations -> (..., J, 3, 3) local rotations (inverse of the FK recursion)."""
    global_rot = np.asarray(global_rot, dtype=np.float64)
    local_rot = global_rot.copy()
    parent_rot = global_rot[..., PARENTS[1:], :, :]
    local_rot[..., 1:, :, :] = np.swapaxes(parent_rot, -1, -2) @ global_rot[..., 1:, :, :]
    return local_rot


def local_rot_to_smpl(local_rot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., J, 3, 3) local rotations -> (global_orient (..., 3), body_pose (..., 63)) axis-angle, as SMPL takes."""
    axis_angle = matrix_to_axis_angle(local_rot)
    return axis_angle[..., 0, :], axis_angle[..., 1:, :].reshape(*axis_angle.shape[:-2], 63)


def smpl_to_local_rot(global_orient: np.ndarray, body_pose: np.ndarray) -> np.ndarray:
    """(global_orient (..., 3), body_pose (..., 63)) -> (..., J, 3, 3) local rotations."""
    body_pose = np.asarray(body_pose, dtype=np.float64)
    axis_angle = np.concatenate(
        [
            np.asarray(global_orient, dtype=np.float64)[..., None, :],
            body_pose.reshape(*body_pose.shape[:-1], 21, 3),
        ],
        axis=-2,
    )
    return axis_angle_to_matrix(axis_angle)
