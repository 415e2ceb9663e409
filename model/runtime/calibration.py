"""Per-session calibration: the wearer's height, arm length and how they hold the devices, from a few seconds
of standing still.

The running body estimate (:mod:`.body`) needs no help, but it only learns the height once the user stands
up and never learns how they hold the controllers. A ``calibrate`` request (PROTOCOL.md §4.1) asks the user
to hold one of two poses while :class:`CalibrationCollector` gathers the headset samples:

- ``stand``: standing straight, looking ahead. Measures the head joint's standing height and how the
  headset sits on the head (its pitch and roll against a level gaze).
- ``tpose``: the same, with both arms stretched out sideways, palms down. Also measures each arm's length
  (shoulder to wrist, from the shoulders the height places under the head) and how each controller is held:
  its rotation against the wrist's (the handle angle in the palm, the roll of the hand).

Why rotations and not positions: with three tracked points, a grip held a few centimetres off the forearm's
axis and an arm raised a few degrees above the horizontal look the same. A rotation is measured against the
direction from the shoulder to the controller, which such errors move by a degree or two; the along-arm
part of a grip's position offset is absorbed into the arm's length.

A :class:`Calibration` is applied by rewriting each device's rotation into what the training rig's default
grip would have reported (:func:`canonical_poses`): ``R' = R_device @ correction``. Positions do not change,
so everything downstream (the network's inputs, the tracked joints, KPO) sees the rig it was trained on.

Shape legend: devices ``D = 3`` (head, left controller, right controller); poses ``[px, py, pz, qx, qy, qz,
qw]``; ``N`` collected samples. Body frame: x to the body's left, y up, z forward (SMPL's).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Final, Literal

import numpy as np
from scipy.spatial.transform import Rotation

from ..hmd import ignore_untracked
from ..rig import DEFAULT_OFFSETS_M, DEVICE_FROM_JOINT, joints_from_devices
from ..rotations import quat_xyzw_to_matrix
from ..skeleton import HEAD, REST_JOINTS_M
from . import kernels
from .body import SCALE_RANGE, STANDING_HEAD_HEIGHT_M, height_scale

CalibrationPose = Literal["stand", "tpose"]
POSES: Final = ("stand", "tpose")
DEFAULT_SECONDS: Final = 2.0
DEVICE_NAMES: Final = ("headset", "left controller", "right controller")
STILL_POSITION_M: Final = 0.04  # a device may wander this far from its mean while the user holds still
STILL_ANGLE_DEG: Final = 8.0
MIN_SAMPLES: Final = 10
MAX_HEAD_TILT_DEG: Final = 25.0  # a headset pitched or rolled more than this from level: not looking ahead
MAX_GRIP_TURN_DEG: Final = 75.0  # a grip turned more than this from the default one: not a T-pose
MAX_ARM_HEIGHT_M: Final = 0.25  # a controller this far above or below the shoulders: not a T-pose
MAX_FACING_DEG: Final = 35.0  # the arm line's normal against the head's heading
ARM_SCALE_RANGE: Final = (0.75, 1.35)  # arm length against the mean body's, after the height scale
LEFT_SHOULDER, RIGHT_SHOULDER, LEFT_WRIST, RIGHT_WRIST = 16, 17, 20, 21
_UP: Final = np.array([0.0, 1.0, 0.0])


class CalibrationFailed(ValueError):
    """The user did not hold the pose (moved, a device was lost, arms not out): the reason is for the user."""


@dataclasses.dataclass(frozen=True)
class Calibration:
    """What a calibration measured. ``corrections`` (D, 3, 3) right-multiply each device's rotation.

    ``arm_scale`` is the arms' length (shoulder to wrist) against the mean SMPL body's, None after ``stand``.
    """

    pose: CalibrationPose
    head_height_m: float  # the head joint above the floor, standing straight
    corrections: np.ndarray
    arm_scale: float | None = None
    arm_span_m: float | None = None  # wrist to wrist with the arms out, through the shoulders
    # The height of the head offset (rig_offsets_m[0][1]) that head_height_m was measured with: a model whose
    # file puts the head joint elsewhere under the headset takes the head height it would have measured
    # (body_measurements). None: taken to be the applying model's.
    head_offset_y_m: float | None = None

    @property
    def height_scale(self) -> float:
        return height_scale(self.head_height_m)

    @functools.cached_property
    def correction_quats(self) -> np.ndarray:
        """(D, 4) xyzw quaternions of ``corrections``."""
        return Rotation.from_matrix(self.corrections).as_quat()


def canonical_poses(poses: np.ndarray, calibration: Calibration | None) -> np.ndarray:
    """poses (D, 7) as the wearer's devices report them -> as the default rig would (a copy).

    ``R' = R @ C`` is the quaternion product ``q ⊗ c`` (a compiled kernel: no matrix round trip)."""
    if calibration is None:
        return poses
    out = np.array(poses, dtype=np.float64, copy=True)
    out[:, 3:] = kernels.quats_multiply(np.ascontiguousarray(out[:, 3:]), calibration.correction_quats)
    return out


def body_measurements(
    calibration: Calibration | None, head_offset_m: np.ndarray
) -> tuple[float | None, float | None]:
    """(head height m, arm scale) for :meth:`BodyCalibrator.calibrate` of a model whose head offset is
    head_offset_m (3,); (None, None) without a calibration. The calibration outlives a model switch, and
    models differ in where under the headset they put the head joint: measured level, the head joint is the
    offset's height under the view pose, so the head height moves by the two offsets' difference."""
    if calibration is None:
        return None, None
    head_height_m = calibration.head_height_m
    if calibration.head_offset_y_m is not None:
        head_height_m += calibration.head_offset_y_m - float(head_offset_m[1])
    return head_height_m, calibration.arm_scale


class CalibrationCollector:
    """Gathers ``seconds`` of headset samples from the first one pushed, then measures.

    ``push`` returns None while collecting, then the :class:`Calibration`; it raises
    :class:`CalibrationFailed` when the user did not hold the pose.
    """

    def __init__(
        self,
        pose: CalibrationPose = "tpose",
        seconds: float = DEFAULT_SECONDS,
        rig_offsets_m: np.ndarray = DEFAULT_OFFSETS_M,
    ) -> None:
        if pose not in POSES:
            raise ValueError(f"pose must be one of {POSES}, got {pose!r}")
        self.pose, self.seconds = pose, float(seconds)
        self.rig_offsets_m = np.asarray(rig_offsets_m, dtype=np.float64)
        self._start_us: int | None = None
        self._poses: list[np.ndarray] = []

    @property
    def needed(self) -> tuple[int, ...]:
        """Devices that must stay tracked throughout."""
        return (0, 1, 2) if self.pose == "tpose" else (0,)

    def push(self, t_us: int, poses: np.ndarray, valid: np.ndarray) -> Calibration | None:
        """One headset sample: poses (D, 7), valid (D,)."""
        lost = [DEVICE_NAMES[d] for d in self.needed if not valid[d]]
        if lost:
            raise CalibrationFailed(f"the {' and '.join(lost)} lost tracking during calibration")
        if self._start_us is None:
            self._start_us = int(t_us)
        self._poses.append(ignore_untracked(poses, valid))  # a copy; an untracked device's numbers are unread
        if int(t_us) - self._start_us < self.seconds * 1e6 or len(self._poses) < MIN_SAMPLES:
            return None
        return measure(self.pose, np.stack(self._poses), self.rig_offsets_m)


def measure(pose: CalibrationPose, samples: np.ndarray, rig_offsets_m: np.ndarray) -> Calibration:
    """samples (N, D, 7) of a user holding ``pose`` -> the calibration; raises CalibrationFailed."""
    mean = _still_mean(samples, (0, 1, 2) if pose == "tpose" else (0,))
    head_turn, heading = _head_turn(mean[0])
    head_pos, _ = joints_from_devices(_with_rotation(mean, 0, heading @ DEVICE_FROM_JOINT), rig_offsets_m)
    head_height_m = float(head_pos[0, 1])
    _check_height(head_height_m)
    corrections = np.stack([np.eye(3)] * 3)
    corrections[0] = head_turn.T @ DEVICE_FROM_JOINT
    offset_y_m = float(rig_offsets_m[0][1])
    if pose == "stand":
        return Calibration(pose, head_height_m, corrections, head_offset_y_m=offset_y_m)
    arms = _measure_arms(mean, head_pos[0], heading, height_scale(head_height_m), rig_offsets_m)
    corrections[1:] = arms["corrections"]
    return Calibration(
        pose, head_height_m, corrections, arms["arm_scale"], arms["arm_span_m"], head_offset_y_m=offset_y_m
    )


def _still_mean(samples: np.ndarray, devices: tuple[int, ...]) -> np.ndarray:
    """(N, D, 7) -> (D, 7) mean poses; raises when a needed device moved."""
    mean = samples.mean(axis=0)
    for d in devices:
        rotations = Rotation.from_quat(samples[:, d, 3:])
        mean_rot = rotations.mean()
        mean[d, 3:] = mean_rot.as_quat()
        moved_m = float(np.linalg.norm(samples[:, d, :3] - mean[d, :3], axis=-1).max())
        turned_deg = float(np.degrees((mean_rot.inv() * rotations).magnitude().max()))
        if moved_m > STILL_POSITION_M or turned_deg > STILL_ANGLE_DEG:
            raise CalibrationFailed(
                f"the {DEVICE_NAMES[d]} moved {moved_m * 100:.0f} cm / {turned_deg:.0f}° during calibration; "
                f"hold still (within {STILL_POSITION_M * 100:.0f} cm / {STILL_ANGLE_DEG:.0f}°)"
            )
    return mean


def _head_turn(head_pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The headset's rotation against a level head looking where it looks (its turn, 3×3 device-from-joint)
    and that level head frame (the heading, 3×3, a turn about y)."""
    device = quat_xyzw_to_matrix(head_pose[3:])
    forward = device @ np.array([0.0, 0.0, -1.0])  # OpenXR devices look along -z
    yaw = np.arctan2(forward[0], forward[2])  # SMPL's +z is the body's forward
    heading = Rotation.from_rotvec([0.0, yaw, 0.0]).as_matrix()
    turn = heading.T @ device
    tilt_deg = float(np.degrees(Rotation.from_matrix(turn @ DEVICE_FROM_JOINT.T).magnitude()))
    if tilt_deg > MAX_HEAD_TILT_DEG:
        raise CalibrationFailed(
            f"the headset is tilted {tilt_deg:.0f}° from level; stand straight and look ahead"
        )
    return turn, heading


def _check_height(head_height_m: float) -> None:
    low, high = (STANDING_HEAD_HEIGHT_M * s for s in SCALE_RANGE)
    if not low <= head_height_m <= high:
        raise CalibrationFailed(
            f"the head is {head_height_m:.2f} m above the floor; calibration needs the user standing straight "
            f"(head joint {low:.2f}-{high:.2f} m) in a stage reference space (floor at y = 0)"
        )


def _with_rotation(poses: np.ndarray, device: int, rotation: np.ndarray) -> np.ndarray:
    out = poses.copy()
    out[device, 3:] = Rotation.from_matrix(rotation).as_quat()
    return out


def _measure_arms(
    mean: np.ndarray, head_m: np.ndarray, heading: np.ndarray, scale: float, rig_offsets_m: np.ndarray
) -> dict:
    """The controllers' corrections (2, 3, 3), the arms' scale and the span, from a T-pose.

    The body's left axis is the line from the right controller to the left one; the shoulders sit where the
    mean body scaled to the height puts them under the head joint.
    """
    left_axis = (mean[1, :3] - mean[2, :3]) * [1.0, 0.0, 1.0]
    if np.linalg.norm(left_axis) < 0.6 * scale:
        raise CalibrationFailed("the controllers are too close together; stretch both arms out sideways")
    left_axis /= np.linalg.norm(left_axis)
    body = np.column_stack([left_axis, _UP, np.cross(left_axis, _UP)])  # columns: left, up, forward
    facing_deg = float(np.degrees(np.arccos(np.clip(body[:, 2] @ heading[:, 2], -1.0, 1.0))))
    if facing_deg > MAX_FACING_DEG:
        raise CalibrationFailed(
            f"the arms' line is {facing_deg:.0f}° off the way the head faces; face ahead with both arms out "
            "to the sides (a T-pose)"
        )
    corrections, lengths, wrists = [], [], []
    for side, (shoulder, wrist) in enumerate(((LEFT_SHOULDER, LEFT_WRIST), (RIGHT_SHOULDER, RIGHT_WRIST))):
        device = 1 + side
        shoulder_m = head_m + body @ ((REST_JOINTS_M[shoulder] - REST_JOINTS_M[HEAD]) * scale)
        # The grip's offset across the forearm (the rig's default) is taken off before aiming the arm.
        across_m = body @ (rig_offsets_m[device] * [0.0, 1.0, 1.0])
        reach = mean[device, :3] - across_m - shoulder_m
        height_m = float(reach @ _UP)
        if abs(height_m) > MAX_ARM_HEIGHT_M:
            where = "above" if height_m > 0 else "below"
            raise CalibrationFailed(
                f"the {('left', 'right')[side]} controller is {abs(height_m) * 100:.0f} cm {where} the "
                "shoulder; hold both arms out level (a T-pose)"
            )
        arm_axis = reach / np.linalg.norm(reach)
        # The wrist frame in a T-pose is the body's, turned so that the rest arm (shoulder to wrist, about
        # +x on the left, -x on the right) points at the controller: the arm may be a little raised,
        # lowered, forward or back.
        rest_arm = REST_JOINTS_M[wrist] - REST_JOINTS_M[shoulder]
        lift, _ = Rotation.align_vectors([arm_axis], [body @ (rest_arm / np.linalg.norm(rest_arm))])
        wrist_rot = lift.as_matrix() @ body
        turn = wrist_rot.T @ quat_xyzw_to_matrix(mean[device, 3:])
        grip_deg = float(np.degrees(Rotation.from_matrix(turn @ DEVICE_FROM_JOINT.T).magnitude()))
        if grip_deg > MAX_GRIP_TURN_DEG:
            raise CalibrationFailed(
                f"the {('left', 'right')[side]} controller is turned {grip_deg:.0f}° from how a hand holds it "
                "in a T-pose; arms out sideways, palms down"
            )
        along_m = abs(float(rig_offsets_m[device, 0]))  # the grip's offset along the forearm
        length_m = float(np.linalg.norm(reach)) - along_m
        corrections.append(turn.T @ DEVICE_FROM_JOINT)
        lengths.append(length_m)
        wrists.append(shoulder_m + arm_axis * length_m)
    rest_m = [np.linalg.norm(REST_JOINTS_M[w] - REST_JOINTS_M[s]) for s, w in ((16, 20), (17, 21))]
    arm_scale = float(np.clip(np.mean(np.divide(lengths, rest_m)), *ARM_SCALE_RANGE))
    span_m = float(lengths[0] + lengths[1] + np.linalg.norm(
        body.T @ ((REST_JOINTS_M[LEFT_SHOULDER] - REST_JOINTS_M[RIGHT_SHOULDER]) * scale)))  # fmt: skip
    return {"corrections": np.stack(corrections), "arm_scale": arm_scale, "arm_span_m": span_m}
