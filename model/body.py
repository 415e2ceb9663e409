"""Body size from the headset and the camera: a per-session running estimate of the skeleton's bone lengths.

FK, KPO and the rotation re-derivation need the wearer's bone lengths. The runtime scales the mean SMPL body
by the highest head-joint height the headset has shown (people stand up at some point), within
``SCALE_RANGE``, assuming a stage reference space (floor at y = 0). With the true bone lengths the bundled
``egoposevr`` would score about a third lower MPJPE (MODEL_CARD.md), so this is where accuracy is left.

Legs from the camera: the visor camera sees thighs, shins and feet most of the time. Each frame whose
keypoints at both ends of a leg bone pass Alg. 1's visibility mask gives one length; once a bone has
``MIN_VISUAL_SAMPLES`` of them, its median replaces the height-scaled length. On the 35 validation sequences
the median lengths correlate 0.8-0.9 with the true ones and halve their error against the mean body (thigh
1.0 cm, shin 1.5 cm mean error). `egoposevr eval` on the validation split: lower-body MPJPE 7.21 -> 6.72 cm
for `egoposevr`, upper body unchanged. Tried and dropped: giving the spine what is left of the standing head
height (so the body stays as tall as the headset says) made both worse (7.78 cm lower, 3.17 upper); measuring
the forearms too (seen in 22 of 35 sequences) moved upper-body MPJPE 2.84 -> 2.87 cm. Arms and spine keep
the height scale.

Tried and dropped: a per-bone ridge regression from five headset statistics (height, reach, raised and
hanging wrists, sideways reach) fitted on the training split. It learned the retargeted CMU proportions
(long hips and head bones, short spine) from statistics that procedural bodies share, and made validation
MPJPE worse overall (hmd upper body 3.71 -> 5.29 cm): per-bone proportions need evidence the headset does
not give, which is why the legs come from the camera.

Shape legend: ``J`` = 22 joints; tracked rows (head, left wrist, right wrist).
"""

from __future__ import annotations

from collections import deque
from typing import Final

import numpy as np

from .skeleton import FOOT_JOINT_HEIGHT_M, HEAD, NUM_JOINTS, PARENTS, REST_JOINTS_M, rest_offsets

# The head joint of the mean SMPL body standing straight, above the floor (left foot joint at 3.5 cm).
STANDING_HEAD_HEIGHT_M: Final = float(REST_JOINTS_M[HEAD, 1] - REST_JOINTS_M[10, 1] + FOOT_JOINT_HEIGHT_M)
SCALE_RANGE: Final = (0.8, 1.25)
UPDATE_STEP_M: Final = 0.005  # rescale when the head is 5 mm higher than ever (rebuilding offsets is cheap)
# Leg bones measured by the camera (each joint's bone from its parent): knees (thighs), ankles (shins), feet.
VISUAL_BONES: Final = (4, 5, 7, 8, 10, 11)
MIN_VISUAL_SAMPLES: Final = 30  # one second of frames at 30 Hz with the bone in view
VISUAL_WINDOW: Final = 600  # the median over the last 20 s of sightings
VISUAL_SCALE_RANGE: Final = (0.7, 1.4)  # per bone, relative to the mean body
_REST_BONE_M: Final = np.linalg.norm(rest_offsets(), axis=-1)


class BodyCalibrator:
    """Running body-scale estimate: ``push`` per headset sample; ``bone_scale`` (J,) changes only when push
    returns True."""

    def __init__(self) -> None:
        self.highest_head_m = 0.0
        self.bone_scale = np.ones(NUM_JOINTS)
        self._sightings = {j: deque(maxlen=VISUAL_WINDOW) for j in VISUAL_BONES}
        self._leg_scale: dict[int, float] = {}  # bone -> scale, once measured

    def push(self, joints_m: np.ndarray, valid: np.ndarray) -> bool:
        """joints_m (3, 3) tracked head / wrist joint positions, valid (3,) -> whether the scale changed."""
        head_y = float(joints_m[0, 1])
        if not valid[0] or head_y < self.highest_head_m + UPDATE_STEP_M:
            return False
        self.highest_head_m = head_y
        self._rebuild()
        return True

    def push_visual(self, keypoints_m: np.ndarray, visible: np.ndarray) -> bool:
        """keypoints_m (J, 3) one frame's keypoints (any rigid frame), visible (J,) Alg. 1's mask -> whether
        the scale changed. Cheap per frame; the medians are refreshed every 10 sightings of a bone."""
        changed = False
        for j in VISUAL_BONES:
            if not (visible[j] and visible[PARENTS[j]]):
                continue
            seen = self._sightings[j]
            seen.append(float(np.linalg.norm(keypoints_m[j] - keypoints_m[PARENTS[j]])))
            if len(seen) >= MIN_VISUAL_SAMPLES and len(seen) % 10 == 0:
                scale = np.clip(np.median(seen) / _REST_BONE_M[j], *VISUAL_SCALE_RANGE)
                self._leg_scale[j] = float(scale)
                changed = True
        if changed:
            self._rebuild()
        return changed

    def _rebuild(self) -> None:
        """bone_scale: the height scale, with the measured leg bones in place (left and right averaged, so
        the body stays symmetric where only one side was seen)."""
        height_scale = float(np.clip(self.highest_head_m / STANDING_HEAD_HEIGHT_M, *SCALE_RANGE))
        scale = np.full(NUM_JOINTS, height_scale if self.highest_head_m > 0 else 1.0)
        for left, right in ((4, 5), (7, 8), (10, 11)):
            measured = [self._leg_scale[j] for j in (left, right) if j in self._leg_scale]
            if measured:
                scale[left] = scale[right] = float(np.mean(measured))
        self.bone_scale = scale
