"""Planted feet and a floor for the served body: which foot is on the ground, where it stays, and soles that
never go through the floor. Its output is KPO targets (:mod:`.kpo`), so knees and hips bend to keep a planted
foot where it is and the served rotations still agree with the joints.

Per session and per foot, a state machine over the network's joints (filtered, anchored at the head). A net
with a contact head (``FusionConfig.contact_head``, trained from the truth's contact labels) says when a foot
is down: it plants at ``PLANT_P`` (if the foot is within ``RELEASE_HEIGHT_M`` of the floor) and steps under
``RELEASE_P``. Without one, the runtime infers it from the network's feet:

- **free -> planted** when the foot joint (the ball of the foot) is within ``PLANT_HEIGHT_M`` of where it
  rests on the floor and it moved slower than ``PLANT_SPEED_M_S`` in the last ``SPEED_WINDOW_S``. The foot
  and ankle are anchored where they are, lowered or raised together so that the sole is on the floor.
- **planted**: the anchor is the foot's and ankle's KPO target. The network's own foot is only watched.
- **planted -> free** when the network steps: it lifts the foot more than ``RELEASE_HEIGHT_M`` off the floor,
  or moves it more than ``RELEASE_DISTANCE_M`` (scaled by the body) from the anchor over the floor, faster
  than ``STEP_SPEED_M_S``; or it is ``SURE_RELEASE`` times that far at any speed (a slow knee raise). A
  slow drift within that is the network's legs wandering while the user only moves the upper body, which is
  what the plant is there to hide.
- **a sure plant** (``sure_plant``): while a contact head is at least ``SURE_P`` sure that a planted foot is
  down, the network lifting its own foot is no step; only a drift over the floor past ``SURE_RELEASE`` is.
  Seated, the network's foot joint floats 12 cm over the floor with a contact probability of 1.0 when the
  served legs are not the wearer's, and letting the foot go there left it free above a floor it never left.
- **no jumps**: whenever a foot's state changes, what was served the sample before fades into the new
  target (smoothstep, ``LAND_S`` for a plant, ``BLEND_S`` for a release), so a foot lowered onto the floor,
  let go, or planted again at once elsewhere glides instead of moving centimetres in one sample (the jerk
  spikes that were most of the served legs' jerk).
- **a steady stance** (:mod:`.stance`: both feet planted, the headset still): a planted foot steps only when
  the network lifts it, however far its guess wanders over the floor, and the anchor moves towards the mean
  of the network's placements since the plant at most ``ANCHOR_SPEED_M_S`` (one early guess is a worse
  estimate of a still foot than their mean).
- **the floor**: a free foot or ankle below the floor is a target on the floor straight above it.

The plant thresholds are physical (the truth's own contact labels,
:mod:`~egoposevr.model.training.plausibility`, call a foot in contact below 3 cm off its resting height and
under 0.2 m/s); the release ones were chosen on training sequences and procedural still-standing streams,
never on a validation split (MODEL_CARD.md).
The floor is the session's ``floor_y_m``: y = 0 in a floor-level reference space (PROTOCOL.md §3). A foot
more than ``FLOOR_TRUST_M`` below it says the space has no floor there (``LOCAL``): that foot is left alone,
and once the session's own estimate from the network's feet (:class:`FloorEstimate`: the lower sole, a low
percentile over the last ``FLOOR_WINDOW_S``, after ``FLOOR_MIN_S``) is that far below y = 0, it is the floor.

Shape legend: ``J`` = 22 joints.
"""

from __future__ import annotations

import collections
import dataclasses
from typing import Final

import numpy as np

from ..skeleton import FOOT_JOINT_HEIGHT_M
from .filters import WindowSpeed, fade_left, settle_step
from .stance import REBASE_S, rebase_of

FEET: Final = ((7, 10), (8, 11))  # (ankle, foot joint): left, right
_FOOT_JOINTS: Final = [foot_j for _, foot_j in FEET]
PLANT_HEIGHT_M: Final = 0.05  # above the foot's resting height
PLANT_SPEED_M_S: Final = 0.25
RELEASE_HEIGHT_M: Final = 0.08
RELEASE_DISTANCE_M: Final = 0.10  # for a body of SMPL's size
STEP_SPEED_M_S: Final = 0.3  # a foot that leaves that far this fast steps; slower, it is the net wandering
SURE_RELEASE: Final = 1.5  # ... unless it is this many times as far: a slow knee raise or lunge
# A plant or a release never moves a foot in one sample: what was served then fades into the new target
# over this long (smoothstep), so a foot lowered onto the floor or let go is not a jump (a jerk spike).
BLEND_S: Final = 0.15
LAND_S: Final = 0.05  # a plant: shorter, or a landing foot would float (chosen on the training split)
# In a steady stance (stance.py) a planted foot's anchor moves to the mean of the network's placements of it
# since the plant, never faster than this: the foot is still, so the mean is its best estimate, but a foot
# seen to move faster than this would be skating, and every centimetre it moves is the still legs' leakage
# (0.25 cm/s chosen on the training split and procedural still streams; MODEL_CARD.md, "The steady anchor").
ANCHOR_SPEED_M_S: Final = 0.0025
SPEED_WINDOW_S: Final = 0.2  # a foot's speed is its move over this long: the network's feet jitter by ~1 cm
MAX_GAP_S: Final = 0.5  # a longer pause between samples forgets the feet
# A foot this far below y = 0 means the floor is not there (a LOCAL reference space, PROTOCOL.md §3): no
# planting and no floor for it, rather than pulling the body up to a floor that does not exist.
FLOOR_TRUST_M: Final = 0.3
FLOOR_WINDOW_S: Final = 5.0
FLOOR_MIN_S: Final = 1.0
FLOOR_EVERY_S: Final = 0.25  # the percentile is re-taken this often (it costs ~30 µs; the floor moves slowly)
FLOOR_PERCENTILE: Final = 20.0  # one foot is on the floor most of the time, standing, walking or sitting
PLANT_P: Final = 0.5  # a net with a contact head: plant at this probability, release under RELEASE_P
RELEASE_P: Final = 0.3
SURE_P: Final = 0.9  # with sure_plant: a contact this sure is let go by the foot's drift alone, not its lift


@dataclasses.dataclass
class _Foot:
    planted: bool = False
    anchor: np.ndarray | None = None  # (2, 3) ankle, foot joint, m
    # (2, 3) the network's placements on the floor since the plant, summed, and how many
    placed_sum: np.ndarray | None = None
    placed: int = 0
    served: np.ndarray | None = None  # (2, 3) what was served last sample (the network's own where no target)
    # (2, 3) what was served minus the new state's target when the state last changed, when that was, and
    # how long it takes to fade out (LAND_S or BLEND_S): a plant or a release never moves the foot in one sample
    blend_m: np.ndarray | None = None
    switched_us: int = 0
    blend_s: float = BLEND_S
    speed: WindowSpeed = dataclasses.field(
        default_factory=lambda: WindowSpeed(SPEED_WINDOW_S)
    )  # foot joint's


def _off_this_floor(lift_m: float) -> bool:
    """Whether a foot lift_m (m) over the floor is so far below it that the floor is not there (a LOCAL space):
    such a foot is left to the network, and the floor holds no foot."""
    return lift_m < -FLOOR_TRUST_M


class FloorEstimate:
    """The floor of a reference space that has none at y = 0: where the network puts the lower sole, the
    ``FLOOR_PERCENTILE`` of the last ``FLOOR_WINDOW_S``, re-taken every ``FLOOR_EVERY_S``."""

    def __init__(self) -> None:
        self._t_us: collections.deque[int] = collections.deque()
        self._sole_y_m: collections.deque[float] = collections.deque()
        self._floor_y_m: float | None = None
        self._taken_us = 0

    def push(self, t_us: int, sole_y_m: float) -> float | None:
        """The lower sole's height this sample -> the floor's height (m), or None while fewer than
        FLOOR_MIN_S of samples are in."""
        self._t_us.append(t_us)
        self._sole_y_m.append(sole_y_m)
        while (t_us - self._t_us[0]) * 1e-6 > FLOOR_WINDOW_S:
            self._t_us.popleft()
            self._sole_y_m.popleft()
        if (t_us - self._t_us[0]) * 1e-6 < FLOOR_MIN_S:
            return None
        if self._floor_y_m is None or not 0 <= (t_us - self._taken_us) * 1e-6 < FLOOR_EVERY_S:
            self._floor_y_m = float(np.percentile(np.fromiter(self._sole_y_m, float), FLOOR_PERCENTILE))
            self._taken_us = t_us
        return self._floor_y_m


class FootContacts:
    """Per-session foot contact state; :meth:`targets` adds the feet's KPO targets for one sample."""

    def __init__(self, floor_y_m: float = 0.0, reseat: bool = False, sure_plant: bool = False) -> None:
        self.floor_y_m = floor_y_m  # the reference space's floor
        self.reseat = reseat  # a steady anchor far from the network's mean placement moves to it faster
        self.sure_plant = sure_plant  # a foot the contact head is sure of is not let go by its lift
        self._estimate = FloorEstimate()  # the session's own, from the network's feet
        self._floor_now_m = floor_y_m
        # whether the last sample held a foot to the floor (one foot within FLOOR_TRUST_M of it)
        self._floor_held = False
        self._feet = (_Foot(), _Foot())
        self._last_us: int | None = None
        self._rebase_until_us: int | None = None  # a rebase's end (:meth:`rebase`)

    @property
    def planted(self) -> tuple[bool, bool]:
        """(left, right): each foot planted now."""
        return self._feet[0].planted, self._feet[1].planted

    @property
    def floor_now_m(self) -> float:
        """The floor's height that the feet are held to now, m."""
        return self._floor_now_m

    @property
    def floor_held_m(self) -> float | None:
        """The floor's height (m) if the last sample held a foot to it, else None: no foot came within
        FLOOR_TRUST_M of it (a LOCAL space's first second, before the session's own estimate is the floor)."""
        return self._floor_now_m if self._floor_held else None

    def rebase(self, t_us: int) -> None:
        """The network's inputs have just filled (Pipeline's ``warm_reseat``): each planted foot's mean
        placement restarts from the next sample, and until stance.REBASE_S from t_us, while the stance is
        steady, its anchor closes its gap to it at gap / stance.REBASE_TAU_S. (Re-seated outside a steady
        stance too, planted feet of crouches were dragged with the network's moving guess: MODEL_CARD.md,
        rule 60.)"""
        for foot in self._feet:
            if foot.planted:  # a foot planted later starts its mean at its plant
                foot.placed_sum, foot.placed = np.zeros_like(foot.placed_sum), 0
        self._rebase_until_us = t_us + int(REBASE_S * 1e6)

    def targets(
        self,
        t_us: int,
        joints: np.ndarray,
        body_scale: float,
        targets: np.ndarray,
        observed: np.ndarray,
        contact_p: np.ndarray | None = None,
        steady: bool = False,
    ) -> None:
        """joints (J, 3) the network's joints for this sample; body_scale the body's size against SMPL's
        (leg length); contact_p (2,) the network's probability that each foot is on the floor, if it has a
        contact head (None: inferred from its feet); steady: the stance is held (:mod:`.stance`: both feet
        down and the headset still), so a planted foot steps only when the network lifts it. KPO's targets
        (J, 3) and observed (J,) are filled in for the ankles and feet, which then pull with the devices'
        weight λa."""
        dt_s = 0.0 if self._last_us is None else max(t_us - self._last_us, 0) * 1e-6
        if dt_s > MAX_GAP_S:
            self._feet = (_Foot(), _Foot())
        self._last_us = t_us
        floor_y_m = self._floor(t_us, joints)
        rest_y = floor_y_m + FOOT_JOINT_HEIGHT_M
        self._floor_held = not all(_off_this_floor(foot_y - rest_y) for foot_y in joints[_FOOT_JOINTS, 1])
        for side, (foot, (ankle_j, foot_j)) in enumerate(zip(self._feet, FEET, strict=True)):
            predicted = joints[[ankle_j, foot_j]]
            p = None if contact_p is None else float(contact_p[side])
            target = self._step(foot, t_us, predicted, body_scale, p, floor_y_m, steady)
            if target is not None:
                targets[[ankle_j, foot_j]] = target
                observed[[ankle_j, foot_j]] = True

    def _floor(self, t_us: int, joints: np.ndarray) -> float:
        """The floor for this sample: the space's, unless the session's estimate from the feet is more than
        FLOOR_TRUST_M below it (a LOCAL space: y = 0 at the head)."""
        sole_y_m = float(joints[_FOOT_JOINTS, 1].min()) - FOOT_JOINT_HEIGHT_M
        estimate = self._estimate.push(t_us, sole_y_m)
        if estimate is not None and estimate < self.floor_y_m - FLOOR_TRUST_M:
            self._floor_now_m = estimate
        else:
            self._floor_now_m = self.floor_y_m
        return self._floor_now_m

    def _step(
        self,
        foot: _Foot,
        t_us: int,
        predicted: np.ndarray,
        body_scale: float,
        contact_p: float | None,
        floor_y_m: float,
        steady: bool = False,
    ) -> np.ndarray | None:
        """One foot's state for one sample -> its (2, 3) ankle and foot targets, or None (the network's)."""
        rest_y = floor_y_m + FOOT_JOINT_HEIGHT_M
        lift_m = predicted[1, 1] - rest_y
        if _off_this_floor(lift_m):
            foot.planted, foot.served, foot.blend_m = False, None, None
            return None
        speed_m_s = foot.speed.push(t_us, predicted[1])
        if foot.planted:
            assert foot.anchor is not None
            if self._steps(
                foot, predicted, lift_m, body_scale, speed_m_s, contact_p, steady, self.sure_plant
            ):
                foot.planted = False
                self._switch(foot, t_us, predicted, BLEND_S)
            else:
                if steady:  # a rebase re-seats only a still stance's feet: a moving one's would be dragged
                    on_floor = predicted - np.array([0.0, lift_m, 0.0])
                    self._settle(foot, on_floor, rebase_of(t_us, self._rebase_until_us, self.reseat))
                return self._serve(foot, t_us, foot.anchor, predicted, rest_y)
        elif self._plants(lift_m, speed_m_s, contact_p):
            foot.planted = True
            foot.anchor = predicted - np.array([0.0, lift_m, 0.0])  # sole on the floor, foot as predicted
            foot.placed_sum, foot.placed = foot.anchor.copy(), 1
            self._switch(foot, t_us, foot.anchor, LAND_S)
            return self._serve(foot, t_us, foot.anchor, predicted, rest_y)
        return self._serve(foot, t_us, None, predicted, rest_y)

    @staticmethod
    def _steps(
        foot: _Foot,
        predicted: np.ndarray,
        lift_m: float,
        body_scale: float,
        speed_m_s: float,
        contact_p: float | None,
        steady: bool,
        sure_plant: bool = False,
    ) -> bool:
        """Whether a planted foot steps now (module docstring: planted -> free)."""
        assert foot.anchor is not None
        drift_m = float(np.linalg.norm(predicted[1, [0, 2]] - foot.anchor[1, [0, 2]]))
        sure_down = sure_plant and contact_p is not None and contact_p >= SURE_P  # its lift is then no step
        lifted = 0.0 if sure_down else lift_m / RELEASE_HEIGHT_M
        away = max(lifted, drift_m / (RELEASE_DISTANCE_M * body_scale))
        if steady:  # the network's foot wandering over the floor is not a step while the head is still
            sure = contact_p is None or contact_p < RELEASE_P or lift_m > SURE_RELEASE * RELEASE_HEIGHT_M
            return lift_m > RELEASE_HEIGHT_M and sure
        if contact_p is not None:
            return contact_p < RELEASE_P or away > SURE_RELEASE
        return away > SURE_RELEASE or (away > 1.0 and speed_m_s > STEP_SPEED_M_S)

    @staticmethod
    def _switch(foot: _Foot, t_us: int, target_m: np.ndarray, blend_s: float) -> None:
        """The foot's state changed and its target is now target_m (2, 3): what was served last fades into
        it over blend_s."""
        if foot.served is not None:
            foot.blend_m, foot.switched_us, foot.blend_s = foot.served - target_m, t_us, blend_s

    @staticmethod
    def _serve(
        foot: _Foot, t_us: int, target: np.ndarray | None, predicted: np.ndarray, rest_y: float
    ) -> np.ndarray | None:
        """The state's target (2, 3), or None for the network's foot ``predicted``, plus what is left of the
        last change's blend; a free foot never below the floor. Returns None where that is the network's
        foot as it is."""
        out = predicted.copy() if target is None else target.copy()
        if foot.blend_m is not None:
            left = fade_left((t_us - foot.switched_us) * 1e-6, foot.blend_s)
            if left is None:
                foot.blend_m = None
            else:
                out += left * foot.blend_m
        below = out[:, 1] < rest_y if target is None else np.zeros(2, dtype=bool)
        out[below, 1] = rest_y
        foot.served = out
        return None if target is None and foot.blend_m is None and not below.any() else out

    @staticmethod
    def _settle(foot: _Foot, on_floor: np.ndarray, reseat: tuple[float, float] | None) -> None:
        """A planted foot in a steady stance: its anchor (2, 3) moves towards the mean of the network's
        placements on the floor since the plant or the rebase (``on_floor`` this sample's), at most
        ANCHOR_SPEED_M_S, or faster with ``reseat`` (filters.settle_step's)."""
        assert foot.anchor is not None and foot.placed_sum is not None
        foot.placed_sum += on_floor
        foot.placed += 1
        gap_m = foot.placed_sum / foot.placed - foot.anchor
        foot.anchor = foot.anchor + settle_step(gap_m, foot.speed.step_s, ANCHOR_SPEED_M_S, reseat)

    @staticmethod
    def _plants(lift_m: float, speed_m_s: float, contact_p: float | None) -> bool:
        """Whether a free foot goes down now: the network says so (and the foot is near the floor), or,
        without a contact head, the foot is near the floor and still."""
        if contact_p is not None:
            return contact_p >= PLANT_P and lift_m < RELEASE_HEIGHT_M
        return lift_m < PLANT_HEIGHT_M and speed_m_s < PLANT_SPEED_M_S
