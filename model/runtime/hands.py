"""Where the served wrists are and which way the served head and hands face, from the devices, and what a
wrist does when its controller is lost (it reports its last pose with ``valid = False``).

- **Position of a lost wrist**: KPO holds the wrist at the network's position plus the correction tracking
  last gave it, fading with ``LOST_HAND_FADE_S``, for ``LOST_HAND_HOLD_S``; then the wrist is free like any
  untracked joint. Without it the served hand jumps where the network alone puts it at the moment of loss.
- **Orientation** (:meth:`LostHandPolicy.orientations`): a tracked device says how its joint is turned far
  better than the network does (the head and wrists are leaves, whose predicted rotations nothing else
  corrects), so the served head and each tracked hand take their device's global rotation. A lost hand
  keeps the turn that tracking last gave it against the network's, fading the same way but with no hold (a
  turn left at its end would snap).
- **A controller found again**: the served wrist goes from where it was while lost to the controller over
  ``REACQUIRE_S`` (moving with the controller all the while, the gap closing along a smoothstep), and so
  does its orientation, instead of jumping there in one sample.

MODEL_CARD.md ("Lost controllers", "Heads and hands that face as their devices") has the measurements.

Shape legend: ``J`` = 22 joints; devices 0 head, 1 left controller, 2 right controller.
"""

from __future__ import annotations

import numpy as np

from ..rig import TRACKED_JOINTS
from . import kernels
from .filters import fade_left

LOST_HAND_FADE_S = 0.5
LOST_HAND_HOLD_S = 1.5
REACQUIRE_S = 0.075
CONTROLLERS = (1, 2)
FADED = 1e-3  # a lost hand's turn this small is dropped


class LostHandPolicy:
    """Per-session memory of where each controller's wrist was when last tracked."""

    def __init__(self) -> None:
        self._last_tracked: dict[int, tuple[np.ndarray, int]] = {}  # device -> (wrist m, t_us)
        self._correction: dict[int, np.ndarray] = {}  # lost device -> last tracked - network, m
        self._last_rot: dict[int, np.ndarray] = {}  # device -> the wrist's last tracked global rotation
        # lost device -> (rotation vector from the network's wrist to the tracked one, the first lost t_us)
        self._turn: dict[int, tuple[np.ndarray, int]] = {}
        self._lost_pos: dict[int, np.ndarray] = {}  # lost device -> the wrist's last lost target, m
        self._lost_rot: dict[int, np.ndarray] = {}  # lost device -> the wrist's last served rotation
        # found device -> (served - tracked at the first found sample: m, or a rotation vector; that t_us)
        self._gap_pos: dict[int, tuple[np.ndarray, int]] = {}
        self._gap_rot: dict[int, tuple[np.ndarray, int]] = {}

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
                targets[wrist] = tracked_pos[device] + self.found_gap(t_us, device, tracked_pos[device])
                continue
            if device not in self._last_tracked:
                continue
            last_pos, since_us = self._last_tracked[device]
            age_s = max(t_us - since_us, 0) * 1e-6
            if age_s > LOST_HAND_HOLD_S:
                self.lost_wrist(device, joints[wrist])  # free: KPO leaves it about where the network has it
                continue
            correction = self._correction.setdefault(device, last_pos - joints[wrist])
            targets[wrist] = joints[wrist] + np.exp(-age_s / LOST_HAND_FADE_S) * correction
            observed[wrist] = True
            self.lost_wrist(device, targets[wrist])

    def lost_wrist(self, device: int, served_m: np.ndarray) -> None:
        """Where a lost controller's wrist is served this sample (3,), m: where it starts from when found."""
        self._lost_pos[device] = served_m.copy()
        self._gap_pos.pop(device, None)

    def found_gap(self, t_us: int, device: int, tracked_m: np.ndarray) -> np.ndarray:
        """A tracked controller's wrist (tracked_m (3,), m) -> the offset (3,) to serve it at: from where it
        was served while lost (:meth:`lost_wrist`) to zero over REACQUIRE_S after it is found; zero once
        closed, or if it was never lost."""
        if (lost_m := self._lost_pos.pop(device, None)) is not None:
            self._gap_pos[device] = (lost_m - tracked_m, t_us)
        gap = _closing(self._gap_pos, device, t_us)
        return np.zeros(3) if gap is None else gap

    def orientations(
        self, t_us: int, valid: np.ndarray, tracked_rot: np.ndarray, glob: np.ndarray
    ) -> tuple[list[int], list[np.ndarray]]:
        """The leaves whose served global rotation the devices give, and those rotations: the head and each
        tracked wrist their device's; a lost wrist the network's, turned by the difference at the loss,
        fading with LOST_HAND_FADE_S until under FADED. tracked_rot (3, 3, 3) the devices' joint
        rotations, glob (J, 3, 3) the served global rotations so far -> (joints, rotations (3, 3) each)."""
        leaves: list[int] = [TRACKED_JOINTS[0]] if valid[0] else []
        rotations: list[np.ndarray] = [tracked_rot[0]] if valid[0] else []
        for device in CONTROLLERS:
            wrist = TRACKED_JOINTS[device]
            if valid[device]:
                self._last_rot[device] = tracked_rot[device]
                self._turn.pop(device, None)
                if (lost_rot := self._lost_rot.pop(device, None)) is not None:
                    self._gap_rot[device] = (_rotvec(lost_rot @ tracked_rot[device].T), t_us)
                gap = _closing(self._gap_rot, device, t_us)
                leaves.append(wrist)
                rotations.append(tracked_rot[device] if gap is None else _matrix(gap) @ tracked_rot[device])
                continue
            self._gap_rot.pop(device, None)
            if device not in self._last_rot:
                continue
            if device not in self._turn:  # the first lost sample: from the last tracked rotation
                self._turn[device] = (_rotvec(self._last_rot[device] @ glob[wrist].T), t_us)
            turn, lost_us = self._turn[device]
            share = np.exp(-max(t_us - lost_us, 0) * 1e-6 / LOST_HAND_FADE_S)
            if share < FADED:  # unlike the position, no hold: a turn that is left when it ends would snap
                self._lost_rot[device] = glob[wrist]
                continue
            self._lost_rot[device] = _matrix(share * turn) @ glob[wrist]
            leaves.append(wrist)
            rotations.append(self._lost_rot[device])
        return leaves, rotations


def _closing(gaps: dict[int, tuple[np.ndarray, int]], device: int, t_us: int) -> np.ndarray | None:
    """What is left of a found controller's gap (a position m, or a rotation vector) at t_us: all of it at
    the first found sample, none after REACQUIRE_S (the entry is then dropped and None returned)."""
    if device not in gaps:
        return None
    gap, found_us = gaps[device]
    left = fade_left(max(t_us - found_us, 0) * 1e-6, REACQUIRE_S)
    if left is None:
        del gaps[device]
        return None
    return left * gap


def _rotvec(rotation: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> (3,) rotation vector."""
    return kernels.matrices_to_rotvecs(rotation[None])[0]


def _matrix(rotvec: np.ndarray) -> np.ndarray:
    """(3,) rotation vector -> (3, 3) rotation."""
    return kernels.rotvecs_to_matrices(rotvec[None])[0]
