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
  Its own seven numbers are never read: zeros, NaN or a stale pose all give the same features
  (:func:`ignore_untracked` makes them harmless for code that converts every row).
"""

from __future__ import annotations

from typing import Final

import numpy as np

from ..protocol.errors import InputError
from .runtime import kernels

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


class HmdFeatureExtractor:
    """Stateful: feed samples in arrival order with :meth:`push`, get x_t (72,) for each.

    One instance per session; :meth:`reset` forgets everything (e.g. after a long pause). The per-sample
    arithmetic is one compiled call (:func:`.kernels.hmd_feature_step`); this class holds its state as
    arrays and checks the input.
    """

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self._history_t_us = np.zeros((3, HISTORY_LEN), dtype=np.int64)  # per device, oldest first
        self._history_pose = np.zeros((3, HISTORY_LEN, 7))  # [p xyz, q xyzw] of tracked samples
        self._history_len = np.zeros(3, dtype=np.int64)
        self._velocity = np.zeros((3, 6))  # [linear m/s, body angular rad/s]
        self._last_t_us = np.zeros(2, dtype=np.int64)  # [time, set?]
        # Held poses: the head's [pos, rotation rows]; each controller's [pos, rotation rows] in the head frame.
        self._held = np.zeros((3, 4, 3))
        self._held[:, 1:] = np.eye(3)
        self._held[0, 0] = DEFAULT_HEAD_POS_M
        self._held[1:, 0] = DEFAULT_CONTROLLER_IN_HEAD_POS_M

    def push(self, t_us: int, poses: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """t_us: sample time (µs); poses (3, 7) [px, py, pz, qx, qy, qz, qw] for head, left, right;
        valid (3,) bool. Returns x_t (72,) float64."""
        poses = np.ascontiguousarray(poses, dtype=np.float64)
        valid = np.ascontiguousarray(valid, dtype=np.bool_)
        check_poses(poses, valid)
        return kernels.hmd_feature_step(
            int(t_us), poses, valid, self._history_t_us, self._history_pose, self._history_len,
            self._velocity, self._last_t_us, self._held, _TIMING,
        )  # fmt: skip


_TIMING: Final = np.array([MIN_DT_S, MAX_GAP_S, DT_REF_S])
PLACEHOLDER_POSE: Final = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])  # origin, identity rotation


def check_poses(poses: np.ndarray, valid: np.ndarray) -> None:
    """Raise InputError unless poses is (3, 7), valid (3,), and every tracked pose finite with a quaternion
    of non-zero length (an untracked device's numbers are not read)."""
    poses, valid = np.asarray(poses), np.asarray(valid, dtype=bool)
    if poses.shape != (3, 7) or valid.shape != (3,):
        raise InputError(f"poses must be (3, 7) and valid (3,), got {poses.shape} and {valid.shape}")
    if not np.isfinite(poses[valid]).all():
        raise InputError("tracked poses must be finite")
    if ((poses[:, 3:] ** 2).sum(-1)[valid] < 1e-12).any():
        raise InputError("quaternion of zero length")


def ignore_untracked(poses: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(3, 7) poses with every untracked device's row replaced by :data:`PLACEHOLDER_POSE` (a copy).

    A client may send anything for a device it does not track (PROTOCOL.md §5: zeros, NaN, its last pose);
    nothing downstream may read those numbers, and this keeps code that converts every row from failing.
    """
    poses, valid = np.array(poses, dtype=np.float64), np.asarray(valid, dtype=bool)
    if poses.shape != (3, 7) or valid.shape != (3,):
        raise InputError(f"poses must be (3, 7) and valid (3,), got {poses.shape} and {valid.shape}")
    poses[~valid] = PLACEHOLDER_POSE
    return poses


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


# ------------------------------------------------------------------------------------ tracking state
# The paper's x_t has no tracking state: a network reading it cannot tell a controller standing still from one
# that was lost (a third of real samples have one lost). Models with ``FusionConfig.device_validity`` read,
# after x_t, per device: valid (0/1) and the time since it was last tracked, capped and scaled to 0..1.
VALIDITY_DIM: Final = 6  # [valid head, valid left, valid right, age head, age left, age right]
AGE_CAP_S: Final = 2.0


def hmd_input_dim(device_validity: bool) -> int:
    """The width of the HMD stream's per-sample input."""
    return FEATURE_DIM + (VALIDITY_DIM if device_validity else 0)


class TrackingState:
    """Stateful: per sample, each device's valid flag and the time since it was last tracked (VALIDITY_DIM,).
    A device never tracked counts as lost for AGE_CAP_S."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self._last_tracked_us: list[int | None] = [None, None, None]

    def push(self, t_us: int, valid: np.ndarray) -> np.ndarray:
        out = np.empty(VALIDITY_DIM)
        for k in range(3):
            if valid[k]:
                self._last_tracked_us[k] = int(t_us)
            last = self._last_tracked_us[k]
            age_s = AGE_CAP_S if last is None else min(max(t_us - last, 0) * 1e-6, AGE_CAP_S)
            out[k], out[3 + k] = float(bool(valid[k])), age_s / AGE_CAP_S
        return out


def tracking_features(t_us: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Batch :class:`TrackingState` over a sequence: t_us (N,), valid (N, 3) -> (N, VALIDITY_DIM)."""
    state = TrackingState()
    return np.stack([state.push(int(t), v) for t, v in zip(t_us, np.asarray(valid, dtype=bool), strict=True)])
