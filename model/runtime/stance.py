"""A steady stance: both feet planted and the headset barely moving. While it lasts, a planted foot steps
only when the network lifts it (:mod:`.contact`), so a user who only moves the arms does not see the feet
slide with the network's wandering guess of the legs.

- **steady** while both feet are planted and the headset moved slower than ``QUIET_SPEED_M_S`` over the
  last ``QUIET_WINDOW_S``;
- **not steady** as soon as a foot steps, the headset is lost or moves faster (walking, a lunge, a jump: the
  feet follow the network again).

The head is the gate because it is the one body part the devices track: arms that move while the head
stays say nothing about the legs, and a step needs a weight shift that moves the head. A stance whose head
leaves slowly stays steady: the feet of a slow squat or bend stay where they are too. The constants were
chosen on the training split's sequences and procedural still-standing streams, never on a validation split
(MODEL_CARD.md).
"""

from __future__ import annotations

from typing import Final

import numpy as np

from .filters import WindowSpeed

QUIET_SPEED_M_S: Final = 0.10
QUIET_WINDOW_S: Final = 0.3
MAX_GAP_S: Final = 0.5  # a longer pause between samples forgets the stance


class SteadyStance:
    """Per-session stance state. Each sample: :meth:`observe_head` before the feet's targets (its answer
    is theirs to use), :meth:`observe_feet` after them."""

    def __init__(self) -> None:
        self._forget()

    def _forget(self) -> None:
        self._head_speed = WindowSpeed(QUIET_WINDOW_S)
        self._last_us: int | None = None
        self._quiet = False
        self._both_planted = False

    @property
    def steady(self) -> bool:
        return self._quiet and self._both_planted

    def observe_head(self, t_us: int, head_m: np.ndarray, head_valid: bool) -> bool:
        """The headset's head joint (3,) m this sample -> whether the stance is steady now."""
        if self._last_us is not None and not 0 <= t_us - self._last_us <= MAX_GAP_S * 1e6:
            self._forget()  # a long pause, or time going back: start afresh
        self._last_us = t_us
        self._quiet = head_valid and self._head_quiet(t_us, head_m)
        return self.steady

    def observe_feet(self, planted: tuple[bool, bool]) -> None:
        """Each foot planted after this sample's targets: a step ends the stance; two feet down may begin
        one at the next sample."""
        self._both_planted = all(planted)

    def _head_quiet(self, t_us: int, head_m: np.ndarray) -> bool:
        """Record the head; whether it moved slower than QUIET_SPEED_M_S over the last QUIET_WINDOW_S."""
        speed_m_s = self._head_speed.push(t_us, head_m)
        return self._head_speed.span_s >= 0.9 * QUIET_WINDOW_S and speed_m_s < QUIET_SPEED_M_S
