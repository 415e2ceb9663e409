"""Where the tracked devices sit on the body: headset and controller grips relative to SMPL joints.

Devices are not joints. A device pose is its joint's pose moved by a fixed offset (in the joint's frame) and
turned half a turn about y (SMPL frames face +z, OpenXR devices look along -z):

    R_device = R_joint @ DEVICE_FROM_JOINT,      p_device = p_joint + R_joint @ offset

The synthesis engine uses these defaults to make headset tracks; the runtime inverts them to find where the
head and wrist joints are, which anchors forward kinematics and drives KPO's alignment term.

Shape legend: device order head, left controller, right controller; poses ``[px, py, pz, qx, qy, qz, qw]``.
"""

from __future__ import annotations

from typing import Final

import numpy as np

from .rotations import quat_xyzw_to_matrix
from .skeleton import HEAD, LEFT_WRIST, RIGHT_WRIST

# Device frame (x right, y up, -z forward) from the SMPL joint frame (x left, y up, +z forward): Ry(180°).
DEVICE_FROM_JOINT: Final = np.diag([-1.0, 1.0, -1.0])
TRACKED_JOINTS: Final = (HEAD, LEFT_WRIST, RIGHT_WRIST)
# Offsets in the joint's frame, metres: the headset's view pose (between the eyes) ahead of and above the head
# joint, grips in the palms. The head's is where the eyes of the synthesis engine's mesh bodies are (the mean
# over data/bodies.npz's 64: 0.6 / 2.4 / 8.3 cm, sd 0.1 / 0.7 / 0.5 cm; x left out, as a mirrored body has
# it on the other side). Until 2026-11-27 it was (0, 6, 11) cm, 4.6 cm from any of those bodies' eyes: every
# served body hung that far from its head (MODEL_CARD.md). A model file carries the offsets it was trained
# with (ModelMetadata.rig_offsets_m); the runtime reads those.
HEAD_OFFSET_M: Final = (0.0, 0.024, 0.083)
LEFT_GRIP_OFFSET_M: Final = (0.085, -0.015, 0.015)
RIGHT_GRIP_OFFSET_M: Final = (-0.085, -0.015, 0.015)
DEFAULT_OFFSETS_M: Final = np.array([HEAD_OFFSET_M, LEFT_GRIP_OFFSET_M, RIGHT_GRIP_OFFSET_M])
# The point the runtime's stillness gates watch (runtime.stance: the steady stance and the leg hold), as an
# offset like HEAD_OFFSET_M: 6 cm under and 11 cm behind the view pose, 2.7 cm behind and 3.6 cm under the
# head joint, towards the top of the neck, where nodding and turning the head move it less than the head
# joint. It is where the head joint was taken to be until 2026-11-27, and the gates' thresholds were chosen
# watching it; watching the head joint instead made still legs step (MODEL_CARD.md, rule 8).
STILLNESS_OFFSET_M: Final = (0.0, 0.06, 0.11)
_STILLNESS_OFFSET: Final = np.array(STILLNESS_OFFSET_M)  # stillness_point runs every sample


def joints_from_devices(
    poses: np.ndarray, offsets_m: np.ndarray = DEFAULT_OFFSETS_M
) -> tuple[np.ndarray, np.ndarray]:
    """Device poses (..., 3, 7) -> tracked joints' positions (..., 3, 3) m and global rotations (..., 3, 3, 3).

    Rows follow TRACKED_JOINTS (head, left wrist, right wrist).
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.shape[-2:] != (3, 7):
        raise ValueError(f"poses must be (..., 3, 7), got {poses.shape}")
    joint_rot = quat_xyzw_to_matrix(poses[..., 3:]) @ DEVICE_FROM_JOINT.T
    joint_pos = poses[..., :3] - np.einsum("...ij,...j->...i", joint_rot, offsets_m)
    return joint_pos, joint_rot


def head_joint_in_view_m(head_offset_m: np.ndarray) -> np.ndarray:
    """Where a head offset (3,) like HEAD_OFFSET_M (in the joint's frame: the view pose ahead of and above the head
    joint) puts the head joint in the view pose's own frame (x right, y up, z back; PROTOCOL.md's ``head``
    space), m (3,): (0, -0.024, 0.083) for HEAD_OFFSET_M, 2.4 cm below and 8.3 cm behind the eyes."""
    return -DEVICE_FROM_JOINT @ np.asarray(head_offset_m, dtype=np.float64)


def stillness_point(head_m: np.ndarray, head_rot: np.ndarray, head_offset_m: np.ndarray) -> np.ndarray:
    """The point the stillness gates watch (3,), from the head joint head_m (3,) and its global rotation
    head_rot (3, 3) that :func:`joints_from_devices` found with the head offset head_offset_m (3,)."""
    return head_m + head_rot @ (head_offset_m - _STILLNESS_OFFSET)
