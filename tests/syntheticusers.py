"""Synthetic headset users for calibration tests: a body of given proportions holding a pose, wearing the
headset and holding the controllers their own way (device-from-joint turns other than the rig's default).

Shape legend: ``N`` samples; devices (head, left, right); poses ``[px, py, pz, qx, qy, qz, qw]``.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation

from egoposevr.model.rig import DEFAULT_OFFSETS_M, DEVICE_FROM_JOINT, TRACKED_JOINTS
from egoposevr.model.skeleton import FOOT_JOINT_HEIGHT_M, NUM_JOINTS, forward_kinematics, rest_offsets


@dataclasses.dataclass(frozen=True)
class User:
    """How one person differs from the rig's defaults (angles in degrees)."""

    height_scale: float = 1.0
    arm_scale: float = 1.0  # upper arms and forearms against the height scale's
    head_tilt_deg: float = 0.0  # headset pitched on the face (+ = looking down when the gaze is level)
    grip_pitch_deg: tuple[float, float] = (
        0.0,
        0.0,
    )  # the grip tipped about the wrist frame's z, left and right
    grip_roll_deg: tuple[float, float] = (0.0, 0.0)  # turned about the forearm

    @property
    def bone_scale(self) -> np.ndarray:
        scale = np.full(NUM_JOINTS, self.height_scale)
        scale[[18, 19, 20, 21]] = self.height_scale * self.arm_scale
        return scale

    def device_turns(self) -> np.ndarray:
        """(3, 3, 3) device-from-joint rotations: R_device = R_joint @ turn."""
        head = Rotation.from_euler("x", self.head_tilt_deg, degrees=True).as_matrix() @ DEVICE_FROM_JOINT
        grips = [
            Rotation.from_euler("xz", [roll, pitch], degrees=True).as_matrix() @ DEVICE_FROM_JOINT
            for pitch, roll in zip(self.grip_pitch_deg, self.grip_roll_deg, strict=True)
        ]
        return np.stack([head, *grips])


def posed_joints(user: User, yaw_deg: float, arm_raise_deg: float, arms_down: bool = False):
    """(J, 3) joints and (J, 3, 3) global rotations of ``user`` standing on the floor (y = 0) facing
    ``yaw_deg`` about y, arms out (raised by ``arm_raise_deg``) or hanging."""
    local = np.broadcast_to(np.eye(3), (NUM_JOINTS, 3, 3)).copy()
    local[0] = Rotation.from_euler("y", yaw_deg, degrees=True).as_matrix()
    raise_deg = -80.0 if arms_down else arm_raise_deg
    local[16] = Rotation.from_euler("z", raise_deg, degrees=True).as_matrix()  # left arm: +x toward +y
    local[17] = Rotation.from_euler("z", -raise_deg, degrees=True).as_matrix()
    joints, glob = forward_kinematics(local, np.zeros(3), rest_offsets(user.bone_scale))
    joints = joints - [0.0, joints[[10, 11], 1].min() - FOOT_JOINT_HEIGHT_M, 0.0]
    return joints, glob


def device_poses(user: User, joints: np.ndarray, glob: np.ndarray) -> np.ndarray:
    """(3, 7) the devices a pose puts where the user wears and holds them."""
    poses = np.zeros((3, 7))
    for d, (joint, turn) in enumerate(zip(TRACKED_JOINTS, user.device_turns(), strict=True)):
        poses[d, :3] = joints[joint] + glob[joint] @ DEFAULT_OFFSETS_M[d]
        poses[d, 3:] = Rotation.from_matrix(glob[joint] @ turn).as_quat()
    return poses


def holding(
    user: User,
    seconds: float = 2.5,
    rate_hz: float = 90.0,
    yaw_deg: float = 30.0,
    arm_raise_deg: float = 0.0,
    arms_down: bool = False,
    sway_m: float = 0.005,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A user holding a pose: t_us (N,), poses (N, 3, 7), valid (N, 3), with a little sway and jitter."""
    rng = np.random.default_rng(seed)
    joints, glob = posed_joints(user, yaw_deg, arm_raise_deg, arms_down)
    base = device_poses(user, joints, glob)
    n = int(seconds * rate_hz)
    t_us = (np.arange(n) * 1e6 / rate_hz).astype(np.int64) + 1_000_000
    poses = np.repeat(base[None], n, axis=0)
    phase = np.linspace(0.0, 2 * np.pi, n)[:, None, None]
    poses[:, :, :3] += sway_m * np.sin(phase) * np.array([1.0, 0.3, 0.6]) + rng.normal(0, 0.001, (n, 3, 3))
    return t_us, poses, np.ones((n, 3), dtype=bool)
