"""Headset device stream -> the paper's 72-d per-sample feature x_t (Eq. 1), streaming and batched.

For each device i in (head, left controller, right controller) the global descriptor g_i (18) is
``[position 3 (m), rotation 6D 6, linear velocity 3 (m/s), angular velocity 6D 6]``, and for each controller
c the local descriptor r_c (9) is ``[position in the head frame 3 (m), rotation in the head frame 6D 6]``:

    x_t = [g_head, g_left, g_right, r_left, r_right]        (72,)   — see FEATURE_SLICES

Velocities come from the samples' own timestamps, so features do not depend on the headset's rate:
- linear velocity = (p_t - p_ref) / dt, world frame, m/s;
- angular velocity ω = log(R_ref^T R_t) / dt (body frame, rad/s), encoded rate-independently as the 6D of the
  rotation it would turn through in ``DT_REF_S`` (= one frame at the paper's 60 Hz): 6D(exp(ω · DT_REF_S)).

Robustness (real headsets jitter, drop and repeat samples):
- the reference is the newest earlier *tracked* sample at least ``MIN_DT_S`` older (near-coincident
  timestamps would blow up jitter) and at most ``MAX_GAP_S`` older (beyond that the motion in between is
  unknown: velocity 0). Dropped samples just lengthen dt;
- a sample whose timestamp does not advance keeps the previous velocities and does not enter the history;
- an untracked device (valid = False) holds its last tracked pose — a controller relative to the head, so a
  lost controller moves with the body — with zero velocity; a device never yet tracked sits at a default pose.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Final

import numpy as np
from scipy.spatial.transform import Rotation

from .rotations import (
    matrix_to_sixd,
    normalize_quat,
    quat_xyzw_conjugate,
    quat_xyzw_multiply,
    quat_xyzw_to_matrix,
)

DEVICES: Final = ("head", "left", "right")
FEATURE_DIM: Final = 72
FEATURE_SLICES: Final = {
    **{f"{d}_{part}": slice(18 * i + a, 18 * i + b) for i, d in enumerate(DEVICES)
       for part, a, b in (("pos", 0, 3), ("rot6d", 3, 9), ("vel", 9, 12), ("angvel6d", 12, 18))},
    "left_in_head_pos": slice(54, 57), "left_in_head_rot6d": slice(57, 63),
    "right_in_head_pos": slice(63, 66), "right_in_head_rot6d": slice(66, 72),
}  # fmt: skip
DT_REF_S: Final = 1.0 / 60.0
MIN_DT_S: Final = 0.004
MAX_GAP_S: Final = 0.25
HISTORY_LEN: Final = 16

# Where devices sit before they were ever tracked. Head: standing height, looking down -Z. Controllers, in the
# head device's frame (x right, y up, -z forward): hands hanging by the hips, slightly forward.
DEFAULT_HEAD_POS_M: Final = np.array([0.0, 1.6, 0.0])
DEFAULT_CONTROLLER_IN_HEAD_POS_M: Final = np.array([[-0.2, -0.7, -0.1], [0.2, -0.7, -0.1]])


@dataclass
class _DeviceTrack:
    """Per-device memory: recent tracked samples (t_us, pos (3,), quat_xyzw (4,)) and the last velocities."""

    history: deque[tuple[int, np.ndarray, np.ndarray]] = field(
        default_factory=lambda: deque(maxlen=HISTORY_LEN)
    )
    vel_m_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    angvel_rad_s: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def stop(self) -> None:
        """Motion unknown or absent: zero linear and angular velocity."""
        self.vel_m_s, self.angvel_rad_s = np.zeros(3), np.zeros(3)

    def reference(self, t_us: int) -> tuple[int, np.ndarray, np.ndarray] | None:
        """Newest (t_us, pos, quat_xyzw) with MIN_DT_S <= age <= MAX_GAP_S, or None."""
        for ref in reversed(self.history):
            age_s = (t_us - ref[0]) * 1e-6
            if age_s > MAX_GAP_S:
                return None
            if age_s >= MIN_DT_S:
                return ref
        return None


class HmdFeatureExtractor:
    """Stateful: feed samples in arrival order with :meth:`push`, get x_t (72,) for each.

    One instance per session; :meth:`reset` forgets everything (e.g. after a long pause).
    """

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self._tracks = [_DeviceTrack() for _ in DEVICES]
        self._last_t_us: int | None = None
        self._held_head = (DEFAULT_HEAD_POS_M.copy(), np.eye(3))
        self._held_in_head = [(p.copy(), np.eye(3)) for p in DEFAULT_CONTROLLER_IN_HEAD_POS_M]

    def push(self, t_us: int, poses: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """t_us: sample time (µs); poses (3, 7) [px, py, pz, qx, qy, qz, qw] for head, left, right;
        valid (3,) bool. Returns x_t (72,) float64."""
        poses = np.asarray(poses, dtype=np.float64)
        valid = np.asarray(valid, dtype=bool)
        if poses.shape != (3, 7) or valid.shape != (3,):
            raise ValueError(f"poses must be (3, 7) and valid (3,), got {poses.shape} and {valid.shape}")
        if not np.isfinite(poses).all():
            raise ValueError("poses must be finite")
        t_us = int(t_us)
        advancing = self._last_t_us is None or t_us > self._last_t_us
        # An untracked device's pose is meaningless (the protocol lets it be all zeros): never convert it.
        quat_xyzw = normalize_quat(np.where(valid[:, None], poses[:, 3:], [0.0, 0.0, 0.0, 1.0]))
        pos, rot = self._resolve_poses(poses[:, :3], quat_xyzw, valid)
        vel, angvel = self._velocities(t_us, pos, quat_xyzw, valid, advancing)
        if advancing:
            self._last_t_us = t_us
        return _assemble(pos, rot, vel, angvel)

    def _resolve_poses(
        self, pos_m: np.ndarray, quat_xyzw: np.ndarray, valid: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """World poses of all devices, untracked ones replaced by their held pose. -> (3, 3), (3, 3, 3)."""
        pos = pos_m.copy()
        rot = quat_xyzw_to_matrix(quat_xyzw)
        if valid[0]:
            self._held_head = (pos[0].copy(), rot[0].copy())
        else:
            pos[0], rot[0] = self._held_head
        for c in (1, 2):
            if valid[c]:
                self._held_in_head[c - 1] = (rot[0].T @ (pos[c] - pos[0]), rot[0].T @ rot[c])
            else:
                rel_pos, rel_rot = self._held_in_head[c - 1]
                pos[c], rot[c] = pos[0] + rot[0] @ rel_pos, rot[0] @ rel_rot
        return pos, rot

    def _velocities(
        self, t_us: int, pos: np.ndarray, quat_xyzw: np.ndarray, valid: np.ndarray, advancing: bool
    ) -> tuple[np.ndarray, np.ndarray]:
        """Linear (3, 3) m/s and body angular (3, 3) rad/s velocities; updates the device histories."""
        updates = []  # (device, dt_s, ref_pos, ref_quat) of devices with a fresh reference
        for d, track in enumerate(self._tracks):
            if not valid[d]:
                track.stop()
                continue
            if not advancing:
                continue  # keep the previous velocities; a repeated timestamp says nothing about motion
            ref = track.reference(t_us)
            if ref is not None:
                updates.append((d, (t_us - ref[0]) * 1e-6, ref[1], ref[2]))
            elif track.history and (t_us - track.history[-1][0]) * 1e-6 > MAX_GAP_S:
                track.stop()
            track.history.append((t_us, pos[d].copy(), quat_xyzw[d]))
        if updates:
            self._apply_differences(updates, pos, quat_xyzw)
        vel = np.stack([t.vel_m_s for t in self._tracks])
        angvel = np.stack([t.angvel_rad_s for t in self._tracks])
        return vel, angvel

    def _apply_differences(self, updates: list, pos: np.ndarray, quat_xyzw: np.ndarray) -> None:
        """Finite differences against each device's reference; updates are (device, dt_s, ref_pos, ref_quat).

        The relative rotation q_ref* · q is the body-frame turn since the reference; one scipy call for all.
        """
        devices = [u[0] for u in updates]
        ref_quat = np.stack([u[3] for u in updates])
        rel_quat = quat_xyzw_multiply(quat_xyzw_conjugate(ref_quat), quat_xyzw[devices])
        rel_rotvec = Rotation.from_quat(rel_quat).as_rotvec()
        for (d, dt_s, ref_pos, _), rotvec in zip(updates, rel_rotvec, strict=True):
            self._tracks[d].vel_m_s = (pos[d] - ref_pos) / dt_s
            self._tracks[d].angvel_rad_s = rotvec / dt_s


def _assemble(pos: np.ndarray, rot: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> np.ndarray:
    """(3, 3) pos, (3, 3, 3) rot, (3, 3) vel, (3, 3) angvel -> x_t (72,)."""
    step_rot = Rotation.from_rotvec(angvel * DT_REF_S).as_matrix()  # (3, 3, 3)
    global_desc = np.concatenate([pos, matrix_to_sixd(rot), vel, matrix_to_sixd(step_rot)], axis=1)  # (3, 18)
    head_rot_t = rot[0].T
    in_head_pos = (pos[1:] - pos[0]) @ rot[0]  # rows: R_H^T (p_c - p_H)
    in_head_rot = head_rot_t @ rot[1:]  # (2, 3, 3)
    local_desc = np.concatenate([in_head_pos, matrix_to_sixd(in_head_rot)], axis=1)  # (2, 9)
    return np.concatenate([global_desc.ravel(), local_desc.ravel()])


def hmd_features(t_us: np.ndarray, poses: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """Batch version over a recorded sequence, identical to pushing the samples one by one.

    t_us (N,) µs; poses (N, 3, 7); valid (N, 3) bool (default: all tracked). Returns (N, 72) float64.
    """
    t_us = np.asarray(t_us)
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (3, 7) or t_us.shape != poses.shape[:1]:
        raise ValueError(f"t_us must be (N,) and poses (N, 3, 7), got {t_us.shape} and {poses.shape}")
    valid = np.ones((len(t_us), 3), dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    if valid.shape != (len(t_us), 3):
        raise ValueError(f"valid must be ({len(t_us)}, 3), got {valid.shape}")
    extractor = HmdFeatureExtractor()
    out = np.empty((len(t_us), FEATURE_DIM))
    for i in range(len(t_us)):
        out[i] = extractor.push(int(t_us[i]), poses[i], valid[i])
    return out
