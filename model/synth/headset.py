"""Headset and controller tracks from a motion, and the headset-mounted camera model.

Devices are not joints. The headset's origin sits in front of and above the SMPL head joint; a controller's
grip sits in the palm, ahead of the wrist. Both follow the OpenXR convention of PROTOCOL.md (a device at
identity looks along -z with +y up). The SMPL frames face +z, so a device is its joint's frame turned half
a turn about y. Tracks get white noise, slow drift, timestamp jitter, and controller dropouts: random
ones, plus a controller hidden behind the head from the headset's tracking cameras.

Shape legend: ``N`` headset samples, ``J`` = 22 joints; device order head, left, right.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Final

import numpy as np
from scipy.spatial.transform import Rotation

from ..rig import DEVICE_FROM_JOINT, HEAD_OFFSET_M, LEFT_GRIP_OFFSET_M, RIGHT_GRIP_OFFSET_M
from ..skeleton import (
    FOOT_JOINT_HEIGHT_M,
    HEAD,
    LEFT_WRIST,
    NUM_JOINTS,
    RIGHT_WRIST,
    forward_kinematics,
    rest_offsets,
)
from .motion import Motion, sample_at

# Per sequence, the renders draw the controllers' tracking cone (degrees off a controller's forward axis) from
# this range (synth.variation); so does stage 2 for the copies it re-tracks (training.train.arm_swaps).
TRACKING_CONE_DEG: Final = (75.0, 100.0)


@dataclasses.dataclass(frozen=True)
class HeadsetRig:
    """Where the devices sit on the body and how noisy their tracking is. Offsets are in the joint's frame."""

    head_offset_m: tuple[float, float, float] = HEAD_OFFSET_M
    left_grip_offset_m: tuple[float, float, float] = LEFT_GRIP_OFFSET_M
    right_grip_offset_m: tuple[float, float, float] = RIGHT_GRIP_OFFSET_M
    head_noise_m: float = 0.0005
    hand_noise_m: float = 0.0015
    head_noise_deg: float = 0.1
    hand_noise_deg: float = 0.4
    drift_m: float = 0.002
    jitter_us: float = 150.0
    dropouts_per_min: float = 3.0
    dropout_s: tuple[float, float] = (0.1, 1.0)
    behind_head_m: float = 0.05  # a controller this far behind the headset's plane is lost
    view_tilt_deg: tuple[float, float] = (0.0, 0.0)  # pitch, roll of the view pose on the head (the fit)
    grip_tilt_deg: tuple[float, float] = (0.0, 0.0)  # left, right handle angle in the palm (about its normal)
    # Inside-out tracking: a controller further than this from the headset's forward axis is out of its
    # cameras' view, and one hidden behind the other (within occlusion_deg as the headset sees them, farther
    # away) is occluded; either is lost once it lasts longer than tracking_grace_s (the IMU bridges that long).
    tracking_cone_deg: float = 180.0
    occlusion_deg: float = 0.0
    tracking_grace_s: float = 0.25


@dataclasses.dataclass(frozen=True)
class HeadsetTrack:
    """Synthesised headset samples with the ground truth at the same instants.

    t_us (N,) int64 sender clock; poses (N, 3, 7) [px, py, pz, qx, qy, qz, qw] world; valid (N, 3) bool;
    local_rot (N, J, 3, 3), root_pos_m (N, 3), joints_m (N, J, 3): the body at each sample; motion_t_s (N,)
    the motion time of each sample.
    """

    t_us: np.ndarray
    poses: np.ndarray
    valid: np.ndarray
    local_rot: np.ndarray
    root_pos_m: np.ndarray
    joints_m: np.ndarray
    motion_t_s: np.ndarray


def rig_from_fields(fields: dict[str, Any]) -> HeadsetRig:
    """A HeadsetRig from a manifest's per-sequence ``headset`` entry (JSON lists as tuples; unknown keys,
    from a newer engine, ignored)."""
    names = {f.name for f in dataclasses.fields(HeadsetRig)}
    return HeadsetRig(**{k: tuple(v) if isinstance(v, list) else v for k, v in fields.items() if k in names})


def tpose_samples(
    bone_scale: np.ndarray, rig: HeadsetRig, rate_hz: float, seconds: float, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A user with these bones and this rig holding a T-pose on the floor (PROTOCOL.md §4.1's calibration),
    still but for the rig's tracking noise -> t_us (N,), poses (N, 3, 7), valid (N, 3)."""
    local = np.broadcast_to(np.eye(3), (NUM_JOINTS, 3, 3))
    joints, glob = forward_kinematics(local, np.zeros(3), rest_offsets(bone_scale))
    joints = joints - [0.0, joints[[10, 11], 1].min() - FOOT_JOINT_HEIGHT_M, 0.0]
    n = int(seconds * rate_hz)
    poses = np.repeat(device_poses(joints[None], glob[None], rig), n, axis=0)
    rng = np.random.default_rng(seed)
    poses[:, 0, :3] += rng.normal(0.0, rig.head_noise_m, (n, 3))
    poses[:, 1:, :3] += rng.normal(0.0, rig.hand_noise_m, (n, 2, 3))
    t_us = (np.arange(n) * 1e6 / rate_hz).astype(np.int64)
    return t_us, poses, np.ones((n, 3), dtype=bool)


def device_tilts(rig: HeadsetRig) -> np.ndarray:
    """(3, 3, 3) each device's rotation on its joint beyond DEVICE_FROM_JOINT: the headset's fit (pitch about
    the view's X, roll about its Z) and each controller's handle angle (about the palm's normal, which is the
    protocol controller frame's Y)."""
    head = Rotation.from_euler("xz", rig.view_tilt_deg, degrees=True).as_matrix()
    left, right = (Rotation.from_euler("y", a, degrees=True).as_matrix() for a in rig.grip_tilt_deg)
    return np.stack([head, left, right])


def device_poses(joints_m: np.ndarray, global_rot: np.ndarray, rig: HeadsetRig) -> np.ndarray:
    """Noise-free device poses (N, 3, 7) from joint positions (N, J, 3) and global rotations (N, J, 3, 3):
    the head's view pose and the controllers in the protocol's frame (PROTOCOL.md §3.3)."""
    poses = np.empty((len(joints_m), 3, 7))
    tilts = device_tilts(rig)
    for k, (joint, offset) in enumerate(
        (
            (HEAD, rig.head_offset_m),
            (LEFT_WRIST, rig.left_grip_offset_m),
            (RIGHT_WRIST, rig.right_grip_offset_m),
        )
    ):
        rot = global_rot[:, joint]
        poses[:, k, :3] = joints_m[:, joint] + rot @ np.asarray(offset)
        poses[:, k, 3:] = Rotation.from_matrix(rot @ DEVICE_FROM_JOINT @ tilts[k]).as_quat()
    return poses


def held_longer_than(lost: np.ndarray, t_s: np.ndarray, grace_s: float) -> np.ndarray:
    """(N,) bool: True where ``lost`` has lasted longer than grace_s (the runtime's inertial bridge)."""
    out = np.zeros_like(lost)
    start = None
    for i, now in enumerate(lost):
        start = (t_s[i] if start is None else start) if now else None
        out[i] = now and t_s[i] - start > grace_s
    return out


def out_of_view(poses: np.ndarray, t_s: np.ndarray, rig: HeadsetRig) -> np.ndarray:
    """(N, 2) bool: controllers the headset's cameras cannot see (outside the cone, or occluded by the other
    controller), after the grace period. poses (N, 3, 7) noise-free."""
    head_rot = Rotation.from_quat(poses[:, 0, 3:])
    rel = np.stack([head_rot.inv().apply(poses[:, k, :3] - poses[:, 0, :3]) for k in (1, 2)], axis=1)
    dist = np.linalg.norm(rel, axis=-1)
    direction = rel / np.maximum(dist, 1e-9)[..., None]
    off_axis = np.degrees(np.arccos(np.clip(-direction[..., 2], -1.0, 1.0)))  # from the view's -Z
    lost = off_axis > rig.tracking_cone_deg
    if rig.occlusion_deg > 0:
        apart = np.degrees(np.arccos(np.clip((direction[:, 0] * direction[:, 1]).sum(-1), -1.0, 1.0)))
        behind = apart < rig.occlusion_deg
        lost[:, 0] |= behind & (dist[:, 0] > dist[:, 1] + 0.05)
        lost[:, 1] |= behind & (dist[:, 1] > dist[:, 0] + 0.05)
    return np.stack([held_longer_than(lost[:, k], t_s, rig.tracking_grace_s) for k in range(2)], axis=1)


def hold_last_tracked(device_poses: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """One device's poses (N, 7) as it reports them: while lost (valid (N,) False) its last tracked pose, as
    runtimes do (a device lost from the first sample keeps its own first pose)."""
    samples = np.arange(len(valid))
    return device_poses[np.maximum.accumulate(np.where(valid, samples, 0))]


def _drift(rng: np.random.Generator, n: int, rate_hz: float, scale_m: float) -> np.ndarray:
    """(n, 3) slow random offsets: a random walk pulled back to zero (time constant ~2 s)."""
    pull = np.exp(-1.0 / (2.0 * rate_hz))
    steps = rng.normal(0.0, scale_m * np.sqrt(1 - pull**2), size=(n, 3))
    out = np.empty((n, 3))
    acc = np.zeros(3)
    for i in range(n):
        acc = acc * pull + steps[i]
        out[i] = acc
    return out


def _dropouts(rng: np.random.Generator, t_s: np.ndarray, rig: HeadsetRig) -> np.ndarray:
    """(N,) bool: True where a random tracking loss is under way."""
    lost = np.zeros(len(t_s), dtype=bool)
    span = t_s[-1] - t_s[0]
    for _ in range(rng.poisson(rig.dropouts_per_min * span / 60.0)):
        start = rng.uniform(t_s[0], t_s[-1])
        lost |= (t_s >= start) & (t_s < start + rng.uniform(*rig.dropout_s))
    return lost


def simulate_headset(
    motion: Motion,
    rate_hz: float,
    rng: np.random.Generator,
    rig: HeadsetRig | None = None,
    start_us: int | None = None,
) -> HeadsetTrack:
    """Headset + controller samples at ``rate_hz`` over the motion, with noise and dropouts."""
    rig = rig or HeadsetRig()
    count = max(1, int(np.floor(motion.duration_s * rate_hz)))
    motion_t_s = np.arange(count) / rate_hz
    local_rot, root = sample_at(motion, motion_t_s)
    joints, global_rot = forward_kinematics(local_rot, root, motion.offsets_m())
    poses = device_poses(joints, global_rot, rig)
    unseen = out_of_view(poses, motion_t_s, rig)

    noise_m = np.array([rig.head_noise_m, rig.hand_noise_m, rig.hand_noise_m])
    noise_deg = np.array([rig.head_noise_deg, rig.hand_noise_deg, rig.hand_noise_deg])
    for k in range(3):
        poses[:, k, :3] += rng.normal(0.0, noise_m[k], (count, 3)) + _drift(rng, count, rate_hz, rig.drift_m)
        wobble = Rotation.from_rotvec(rng.normal(0.0, np.deg2rad(noise_deg[k]), (count, 3)))
        poses[:, k, 3:] = (wobble * Rotation.from_quat(poses[:, k, 3:])).as_quat()

    valid = np.ones((count, 3), dtype=bool)
    head_rot = Rotation.from_quat(poses[:, 0, 3:])
    for k in (1, 2):
        in_head = head_rot.inv().apply(poses[:, k, :3] - poses[:, 0, :3])
        behind = in_head[:, 2] > rig.behind_head_m  # device +z points backwards
        valid[:, k] = ~(behind | unseen[:, k - 1] | _dropouts(rng, motion_t_s, rig))
        poses[:, k] = hold_last_tracked(poses[:, k], valid[:, k])

    start_us = int(rng.integers(1_000_000, 10_000_000_000)) if start_us is None else start_us
    jitter = np.clip(rng.normal(0.0, rig.jitter_us, count), -3 * rig.jitter_us, 3 * rig.jitter_us)
    t_us = start_us + np.round(motion_t_s * 1e6 + jitter).astype(np.int64)
    t_us = np.maximum.accumulate(t_us)  # jitter never makes the clock run backwards
    return HeadsetTrack(t_us, poses, valid, local_rot, root, joints, motion_t_s)


# ------------------------------------------------------------------------------------------- camera
@dataclasses.dataclass(frozen=True)
class CameraModel:
    """A pinhole RGB-D camera rigidly mounted on the headset, pitched down at the body.

    ``position_m`` is in the headset device frame (x right, y up, -z forward); ``pitch_down_deg`` tilts the
    optical axis from the headset's forward towards its -y. Camera axes are OpenCV's (x right, y down, z
    optical axis), as in PROTOCOL.md.
    """

    width: int = 320
    height: int = 256
    hfov_deg: float = 90.0
    pitch_down_deg: float = 78.0
    yaw_deg: float = 0.0  # turned about the headset's up axis, towards its -x for positive angles
    roll_deg: float = 0.0  # about the optical axis
    # Radial lens distortion (OpenCV's k1, k2) that the image has but the reported pinhole intrinsics do not
    # describe: the protocol has no distortion, so a real camera's leftover distortion is a nuisance to learn.
    k1: float = 0.0
    k2: float = 0.0
    position_m: tuple[float, float, float] = (0.0, -0.05, -0.07)
    min_depth_m: float = 0.1
    max_depth_m: float = 6.0

    @property
    def fx(self) -> float:
        return self.width / 2 / np.tan(np.deg2rad(self.hfov_deg) / 2)

    @property
    def width_height(self) -> tuple[int, int]:
        return self.width, self.height

    def intrinsics(self) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) in pixels, square pixels, centre of the top-left pixel at (0, 0)."""
        return self.fx, self.fx, (self.width - 1) / 2, (self.height - 1) / 2

    def device_from_camera(self) -> np.ndarray:
        """(4, 4): camera coordinates -> headset device coordinates."""
        axes = np.diag([1.0, -1.0, -1.0])  # OpenCV axes looking along the headset's forward
        tilt = Rotation.from_euler("x", -self.pitch_down_deg, degrees=True).as_matrix()
        yaw = Rotation.from_euler("y", self.yaw_deg, degrees=True).as_matrix()
        roll = Rotation.from_euler("z", self.roll_deg, degrees=True).as_matrix()
        out = np.eye(4)
        out[:3, :3] = yaw @ tilt @ axes @ roll
        out[:3, 3] = self.position_m
        return out

    def cam_from_head(self) -> np.ndarray:
        """(4, 4) headset device -> camera (the ``rgbd.cam_from_head`` of the wire protocol)."""
        return np.linalg.inv(self.device_from_camera())

    def world_from_camera(self, head_pose: np.ndarray) -> np.ndarray:
        """(..., 4, 4) camera -> world for head device poses (..., 7)."""
        head_pose = np.asarray(head_pose, dtype=np.float64)
        world_from_device = np.broadcast_to(np.eye(4), (*head_pose.shape[:-1], 4, 4)).copy()
        world_from_device[..., :3, :3] = (
            Rotation.from_quat(head_pose[..., 3:].reshape(-1, 4))
            .as_matrix()
            .reshape(*head_pose.shape[:-1], 3, 3)
        )
        world_from_device[..., :3, 3] = head_pose[..., :3]
        return world_from_device @ self.device_from_camera()

    @property
    def distorted(self) -> bool:
        return self.k1 != 0.0 or self.k2 != 0.0

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """(..., 3) camera-frame points -> (..., 2) pixel coordinates (u, v), lens distortion included."""
        fx, fy, cx, cy = self.intrinsics()
        z = points_cam[..., 2]
        safe = np.where(np.abs(z) < 1e-9, 1e-9, z)
        x, y = points_cam[..., 0] / safe, points_cam[..., 1] / safe
        r2 = x * x + y * y
        factor = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
        return np.stack([fx * x * factor + cx, fy * y * factor + cy], axis=-1)

    def in_view(self, points_cam: np.ndarray) -> np.ndarray:
        """(...,) bool: in front of the camera (beyond the minimum depth) and inside the image."""
        uv = self.project(points_cam)
        return (
            (points_cam[..., 2] > self.min_depth_m)
            & (uv[..., 0] >= -0.5)
            & (uv[..., 0] <= self.width - 0.5)
            & (uv[..., 1] >= -0.5)
            & (uv[..., 1] <= self.height - 0.5)
        )
