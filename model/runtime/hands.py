"""What the served wrist does when its controller is lost (it reports its last pose with ``valid = False``).

KPO holds the wrist at the network's position plus the correction tracking last gave it, fading with
``LOST_HAND_FADE_S``, for ``LOST_HAND_HOLD_S``; then the wrist is free like any untracked joint. Without it
the served hand jumps where the network alone puts it at the moment of loss. MODEL_CARD.md ("Lost
controllers") has the measurements that chose the policy and its constants.

Shape legend: ``J`` = 22 joints; devices 0 head, 1 left controller, 2 right controller.
"""

from __future__ import annotations

import numpy as np

from ..rig import TRACKED_JOINTS

LOST_HAND_FADE_S = 0.5
LOST_HAND_HOLD_S = 1.5
CONTROLLERS = (1, 2)


class LostHandPolicy:
    """Per-session memory of where each controller's wrist was when last tracked."""

    def __init__(self) -> None:
        self._last_tracked: dict[int, tuple[np.ndarray, int]] = {}  # device -> (wrist m, t_us)
        self._correction: dict[int, np.ndarray] = {}  # lost device -> last tracked - network, m

    def targets(
        self,
        t_us: int,
        joints: np.ndarray,
        valid: np.ndarray,
        tracked_pos: np.ndarray,
        targets: np.ndarray,
        observed: np.ndarray,
    ) -> None:
        """KPO targets for the wrists of lost controllers. joints (J, 3) the network's (filtered, anchored)
        joints, valid (3,), tracked_pos (3, 3) the devices' joints; targets (J, 3) and observed (J,) are
        filled in.

        At the first lost sample the correction is measured against the network's wrist of that sample, so
        the served wrist starts exactly where tracking left it (the network's answer itself moves when a
        controller's valid flag drops) and then follows the network's motion while the correction fades."""
        for device in CONTROLLERS:
            wrist = TRACKED_JOINTS[device]
            if valid[device]:
                self._last_tracked[device] = (tracked_pos[device].copy(), t_us)
                self._correction.pop(device, None)
                continue
            if device not in self._last_tracked:
                continue
            last_pos, since_us = self._last_tracked[device]
            age_s = max(t_us - since_us, 0) * 1e-6
            if age_s > LOST_HAND_HOLD_S:
                continue
            correction = self._correction.setdefault(device, last_pos - joints[wrist])
            targets[wrist] = joints[wrist] + np.exp(-age_s / LOST_HAND_FADE_S) * correction
            observed[wrist] = True
