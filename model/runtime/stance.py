"""A steady stance: both feet planted and the headset barely moving. While it lasts, a planted foot steps
only when the network lifts it (:mod:`.contact`), so a user who only moves the arms does not see the feet
slide with the network's wandering guess of the legs; and (:class:`LegHold`) the pelvis, hips and knees stay
where they were served instead of wandering with it.

- **steady** while both feet are planted and the headset is **quiet** over the last ``QUIET_WINDOW_S``;
- **not steady** as soon as a foot steps, the headset is lost or stops being quiet (walking, a lunge, a
  jump: the feet follow the network again).

The head is quiet while it moves slower than ``QUIET_SPEED_M_S``, or, given a pivot (the served pelvis: the lean
gate, on where the model file asks for it, ``ModelMetadata.lean_gate``; MODEL_CARD.md rules 37, 44 and 45 say
for which nets it helps), while it **leans**: it moves around the pivot at most ``LEAN_SPEED_M_S`` while its
distance from it changes slower than ``LEAN_RADIAL_M_S``. A trunk that leans or sways over still hips moves the
head round them, at a median 11-16 cm/s for the lean families (``synth``'s ``lean_stand`` / ``lean_sit``), which
the speed alone called a step; a squat, a bend, a jump or a rise from a chair moves it towards or away from
them; a side step moves it round them too, but faster (a median 25-35 cm/s) and with its distance changing more;
and a step that lifts a foot ends the stance anyway.

The head is the gate because it is the one body part the devices track: arms that move while the head
stays say nothing about the legs, and a step needs a weight shift that moves the head. A stance whose head
leaves slowly stays steady: the feet of a slow squat or bend stay where they are too. The constants were
chosen on the training split's sequences and procedural still-standing, leaning and stepping streams, never
on a validation split (MODEL_CARD.md).

:class:`LegHold` has a quicker gate of its own: both feet planted and the headset quiet over the last
``HOLD_WINDOW_S``, about the pelvis it holds. A still stretch is often a pause of a second or so between
movements, and a hold that waited for the steady stance's 0.3 s of quiet held too little of it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Final

import numpy as np

from ..skeleton import pelvis_over_legs
from .filters import WindowSpeed, settle_step

QUIET_SPEED_M_S: Final = 0.10
# A head that leans: round the pelvis at most this fast, while its distance from it changes slower than
# LEAN_RADIAL_M_S (chosen on training people's leaning, still and stepping streams: MODEL_CARD.md, rule 37)
LEAN_SPEED_M_S: Final = 0.30
LEAN_RADIAL_M_S: Final = 0.05
QUIET_WINDOW_S: Final = 0.3
MAX_GAP_S: Final = 0.5  # a longer pause between samples forgets the stance
HELD_JOINTS: Final = (0, 1, 2, 4, 5)  # pelvis, hips, knees: the ankles and feet are the planted feet's
HOLD_WINDOW_S: Final = 0.1
# A held joint moves towards the mean of the network's placements of it since the hold began, never faster than
# this: the planted feet's anchors do the same (contact.ANCHOR_SPEED_M_S). 0.1 cm/s held a worse early guess
# longer (MODEL_CARD.md, "Legs held while both feet are down").
SETTLE_SPEED_M_S: Final = 0.0025
# With ``reseat``, a held joint (and a planted foot's anchor: contact.py) whose mean placement is more than
# RESEAT_SLACK_M away also moves at (gap - slack) / RESEAT_TAU_S: a hold begun on a wrong guess (a seated
# session's first legs, the end of a wander) is not kept (off by default: it failed MODEL_CARD.md rules 38
# and 39).
RESEAT_SLACK_M: Final = 0.04
RESEAT_TAU_S: Final = 1.0
# With ``warm_reseat`` (Pipeline): once the network's input windows have filled (its first answers read few
# or no camera frames and a padded headset window), a hold's mean restarts from the next placement and for
# REBASE_S the held joints (and a steady stance's planted feet's anchors: contact.py) close the part of their
# gap to it past REBASE_SLACK_M at (gap - slack) / REBASE_TAU_S: a hold begun on the session's cold first
# guess is not what stays (MODEL_CARD.md, rules 59-62). No slack since rule 62, which re-seats folded legs
# only; rule 61's 5 cm slack, with every stream re-seated, kept a few crouches' nearer cold guesses and failed.
REBASE_S: Final = 0.3
REBASE_TAU_S: Final = 0.1
REBASE_SLACK_M: Final = 0.0
# ... and, with REBASE_FOLDED_SHARE set, only where the network's legs are folded when the windows fill: its
# pelvis less than that share of its legs' length above its ankles (a seated person ~0.5, standing ~0.95;
# evaluate.SEATED_LEG_SHARE's value). A seated person's cold guess is far off; a standing one's is a neutral
# stand about as near as the warm answers (MODEL_CARD.md, rule 62: chosen with no slack). None: every stream
# re-seats.
REBASE_FOLDED_SHARE: Final[float | None] = 0.7
RELEASE_TAU_S: Final = 0.06  # when the hold ends, what it moved the joints by decays with this time constant
_LET_GO_M: Final = 1e-3  # ... and below this they are served as without the hold again
_HELD: Final = np.array(HELD_JOINTS)


def _is_quiet(window: WindowSpeed, speed_m_s: float, pivot_m: np.ndarray | None) -> bool:
    """Whether a head that moved at speed_m_s over the window (pushed this sample) is quiet: slower than
    QUIET_SPEED_M_S, or leaning about the pivot (3,) m (module docstring); with pivot_m None, by its speed
    alone."""
    if speed_m_s < QUIET_SPEED_M_S:
        return True
    if pivot_m is None:
        return False
    radial_m_s, around_m_s = window.about(pivot_m)
    return radial_m_s < LEAN_RADIAL_M_S and around_m_s < LEAN_SPEED_M_S


def reseat_of(reseat: bool) -> tuple[float, float] | None:
    """filters.settle_step's ``reseat`` for a hold or an anchor that re-seats (RESEAT_SLACK_M, RESEAT_TAU_S),
    or None. Read at each call, so that the constants can be chosen by patching them."""
    return (RESEAT_SLACK_M, RESEAT_TAU_S) if reseat else None


def rebase_of(t_us: int, until_us: int | None, reseat: bool) -> tuple[float, float] | None:
    """filters.settle_step's ``reseat`` at t_us: a re-seat past REBASE_SLACK_M over REBASE_TAU_S before
    until_us (a rebase's end), else :func:`reseat_of`. Read at each call, as reseat_of."""
    if until_us is not None and t_us < until_us:
        return REBASE_SLACK_M, REBASE_TAU_S
    return reseat_of(reseat)


def legs_folded(joints: np.ndarray, share: float) -> bool:
    """Whether joints (J, 3) m put the pelvis less than ``share`` of the legs' length (the mean of the two
    sides) above the ankles' mean height (skeleton.pelvis_over_legs): a seated person's folded legs."""
    above_m, legs_m = pelvis_over_legs(joints)
    return float(above_m) < share * float(legs_m.mean())


def _stream_broke(last_us: int | None, t_us: int) -> bool:
    """Whether a sample at t_us after one at last_us breaks the stream: a pause longer than MAX_GAP_S, or
    time going back. Either forgets a stance or a hold."""
    return last_us is not None and not 0 <= t_us - last_us <= MAX_GAP_S * 1e6


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

    def observe_head(
        self, t_us: int, head_m: np.ndarray, head_valid: bool, pivot_m: np.ndarray | None = None
    ) -> bool:
        """The headset's head joint (3,) m this sample -> whether the stance is steady now. pivot_m (3,): the
        pelvis as served the sample before, about which a head may lean and stay quiet; None: the head's
        speed alone."""
        if _stream_broke(self._last_us, t_us):
            self._forget()
        self._last_us = t_us
        self._quiet = head_valid and self._head_quiet(t_us, head_m, pivot_m)
        return self.steady

    def observe_feet(self, planted: tuple[bool, bool]) -> None:
        """Each foot planted after this sample's targets: a step ends the stance; two feet down may begin
        one at the next sample."""
        self._both_planted = all(planted)

    def _head_quiet(self, t_us: int, head_m: np.ndarray, pivot_m: np.ndarray | None) -> bool:
        """Record the head; whether it was quiet over the last QUIET_WINDOW_S."""
        speed_m_s = self._head_speed.push(t_us, head_m)
        return self._head_speed.span_s >= 0.9 * QUIET_WINDOW_S and _is_quiet(
            self._head_speed, speed_m_s, pivot_m
        )


class LegHold:
    """Per-session: while both feet are planted and the headset is quiet, the pelvis, hips and knees
    (``HELD_JOINTS``) are KPO targets. Each sample: :meth:`targets` before KPO, :meth:`served` after it.

    - **the hold begins** where those joints were served the sample before (a target at the network's guess
      of this sample would jump, and fight the planted feet: MODEL_CARD.md), then moves towards the mean of
      the network's placements since the hold began, at most ``SETTLE_SPEED_M_S``;
    - **the hold ends** when a foot is let go, the headset stops being quiet over ``HOLD_WINDOW_S`` (with
      ``lean``, it may lean about the pelvis as served the sample before) or is lost: the targets are where
      KPO would serve those joints without the hold (``unheld``) plus the offset that the hold had put on
      them, decaying with ``RELEASE_TAU_S``, so the legs glide back instead of jumping. (Not the network's
      joints plus the offset: KPO with a target on the network's joint serves them there, and without one
      where the planted feet pull them, up to 2 cm away, which was a jump when the fade ended.)
    """

    def __init__(self, lean: bool = False, reseat: bool = False) -> None:
        self.lean = lean  # the head may lean about the served pelvis and stay quiet; False: its speed alone
        self.reseat = reseat  # a held joint far from the network's mean placement moves to it faster
        self._forget()

    @property
    def pivot_m(self) -> np.ndarray | None:
        """What a head may lean about and stay quiet, for this hold's gate and the steady stance's: with
        ``lean``, the pelvis (3,) m as served last sample; None without it, before the first sample or after a
        broken stream (the head's speed alone)."""
        return self._served[0] if self.lean and self._served is not None else None

    def _forget(self) -> None:
        self._head_speed = WindowSpeed(HOLD_WINDOW_S)
        self._last_us: int | None = None
        self._served: np.ndarray | None = None  # (5, 3) the held joints as served last sample
        self._held: np.ndarray | None = None  # (5, 3) the hold's targets while it lasts
        self._placed_sum: np.ndarray | None = None  # (5, 3) the network's placements since the hold began
        self._placed = 0
        self._offset: np.ndarray | None = None  # (5, 3) held minus unheld, decaying after the hold
        self._rebase_until_us: int | None = None  # a rebase's end (:meth:`rebase`)

    @property
    def holding(self) -> bool:
        """Whether the legs are held now (not while they glide back)."""
        return self._held is not None

    def targets(
        self,
        t_us: int,
        joints: np.ndarray,
        head_m: np.ndarray,
        head_valid: bool,
        planted: tuple[bool, bool],
        targets: np.ndarray,
        observed: np.ndarray,
        unheld: Callable[[], np.ndarray] | None = None,
    ) -> None:
        """joints (J, 3) the network's for this sample; head_m (3,) the headset's head joint. Fills KPO's
        targets (J, 3) and observed (J,) for the held joints while the hold lasts or fades. ``unheld()``
        gives the joints (J, 3) KPO would serve with the targets as they are when this is called (the feet's
        and the devices'): it is called only while the hold fades, before anything is written here; None
        takes the network's joints instead (no KPO)."""
        if _stream_broke(self._last_us, t_us):
            self._forget()
        dt_s = 0.0 if self._last_us is None else (t_us - self._last_us) * 1e-6
        self._last_us = t_us
        speed_m_s = self._head_speed.push(t_us, head_m)
        quiet = head_valid and _is_quiet(self._head_speed, speed_m_s, self.pivot_m)
        network = joints[_HELD]
        if quiet and all(planted) and self._served is not None:
            target = self._hold(network, dt_s, t_us)
        else:
            target = self._let_go(network, dt_s, unheld)
        if target is not None:
            targets[_HELD] = target
            observed[_HELD] = True

    def rebase(self, t_us: int) -> None:
        """The network's inputs have just filled (Pipeline's ``warm_reseat``): a hold's mean restarts from the
        next placement, and until REBASE_S from t_us the held joints close their gap to it at
        gap / REBASE_TAU_S."""
        if self._held is not None:
            self._placed_sum, self._placed = np.zeros_like(self._placed_sum), 0
        self._rebase_until_us = t_us + int(REBASE_S * 1e6)

    def served(self, joints: np.ndarray) -> None:
        """The joints (J, 3) served this sample (after KPO): where a hold that begins next sample starts."""
        self._served = joints[_HELD]  # a copy (fancy indexing)

    def _hold(self, network: np.ndarray, dt_s: float, t_us: int) -> np.ndarray:
        """This sample's held targets (5, 3): begun at the served joints, settling to the network's mean."""
        self._offset = None
        if self._held is None:
            self._held, self._placed_sum, self._placed = self._served.copy(), network.copy(), 1
            return self._held
        self._placed_sum += network
        self._placed += 1
        gap_m = self._placed_sum / self._placed - self._held
        reseat = rebase_of(t_us, self._rebase_until_us, self.reseat)
        self._held = self._held + settle_step(gap_m, dt_s, SETTLE_SPEED_M_S, reseat)
        return self._held

    def _let_go(
        self, network: np.ndarray, dt_s: float, unheld: Callable[[], np.ndarray] | None
    ) -> np.ndarray | None:
        """After a hold: where the joints would be served without it, plus the hold's offset, decaying; None
        once it is gone."""
        if self._held is None and self._offset is None:
            return None
        free = network if unheld is None else unheld()[_HELD]
        if self._held is not None:
            self._offset, self._held = self._held - free, None
        self._offset = self._offset * math.exp(-dt_s / RELEASE_TAU_S)
        if np.abs(self._offset).max() < _LET_GO_M:
            self._offset = None
            return None
        return free + self._offset
