"""Body size from the headset alone: a per-session running estimate of the skeleton's scale.

FK, KPO and the rotation re-derivation need the wearer's bone lengths. The runtime scales the mean SMPL body
by the highest head-joint height the headset has shown (people stand up at some point), within
``SCALE_RANGE``, assuming a stage reference space (floor at y = 0). With the true bone lengths the bundled
``egoposevr`` would score about a third lower MPJPE (MODEL_CARD.md), so this is where accuracy is left.

Tried and dropped: a per-bone ridge regression from five headset statistics (height, reach, raised and
hanging wrists, sideways reach) fitted on the training split. It learned the retargeted CMU proportions
(long hips and head bones, short spine) from statistics that procedural bodies share, and made validation
MPJPE worse overall (hmd upper body 3.71 -> 5.29 cm). Per-bone proportions need evidence the headset does
not give; the visual stream (feet and knees in view) is the next place to look.

Shape legend: ``J`` = 22 joints; tracked rows (head, left wrist, right wrist).
"""

from __future__ import annotations

from typing import Final

import numpy as np

from .skeleton import FOOT_JOINT_HEIGHT_M, HEAD, NUM_JOINTS, REST_JOINTS_M

# The head joint of the mean SMPL body standing straight, above the floor (left foot joint at 3.5 cm).
STANDING_HEAD_HEIGHT_M: Final = float(REST_JOINTS_M[HEAD, 1] - REST_JOINTS_M[10, 1] + FOOT_JOINT_HEIGHT_M)
SCALE_RANGE: Final = (0.8, 1.25)
UPDATE_STEP_M: Final = 0.005  # rescale when the head is 5 mm higher than ever (rebuilding offsets is cheap)


class BodyCalibrator:
    """Running body-scale estimate: ``push`` per headset sample; ``bone_scale`` (J,) changes only when push
    returns True."""

    def __init__(self) -> None:
        self.highest_head_m = 0.0
        self.bone_scale = np.ones(NUM_JOINTS)

    def push(self, joints_m: np.ndarray, valid: np.ndarray) -> bool:
        """joints_m (3, 3) tracked head / wrist joint positions, valid (3,) -> whether the scale changed."""
        head_y = float(joints_m[0, 1])
        if not valid[0] or head_y < self.highest_head_m + UPDATE_STEP_M:
            return False
        self.highest_head_m = head_y
        self.bone_scale = np.full(NUM_JOINTS, np.clip(head_y / STANDING_HEAD_HEIGHT_M, *SCALE_RANGE))
        return True
