"""Where a seated body's legs point while no camera frame shows them.

Served without a camera frame, the fusion nets fold a seated person's legs from the first sample but point them
where the head faces, and turn them as the head turns while the chair does not (MODEL_CARD.md, "Where a
camera-less seated person's legs go wrong"). :class:`SeatedYaw` keeps the pelvis's yaw where it was in the world
while the net's legs are folded and no frame is in its window, until the net's pelvis turns more than
``DEAD_ZONE_DEG`` past it (a swivel, a turn to stand up), and then follows it at that distance; any other
sample lets go, so a camera frame gives the legs back to the net at once. :func:`turn_pelvis` applies the
correction to the net's rotations: the pelvis, and with it the hips and legs, turn about the vertical, and the
spine keeps its orientation in the world, so the trunk and arms stay where the net put them.

Off by default (``Pipeline(seated_yaw=False)``): on a bank of bodies no training saw, camera-less sitters' legs
leaked 48 % less but were served 5.6 % further off, where no rise was allowed (MODEL_CARD.md, rule 65).

Pure numpy; shape legend: ``J`` = 22 joints.
"""

from __future__ import annotations

import math
from typing import Final

import numpy as np

from ..rotations import about_vertical, wrap_angle

# Seated, the trunk twists further before the chair turns; the feet, in front of the seat, would sweep round
# it with the hips. Not chosen on numbers: the procedural baseline's seated dead zone (its
# SEATED_DEAD_ZONE_DEG is this constant), twice its standing one (MODEL_CARD.md, rule 63).
DEAD_ZONE_DEG: Final = 60.0
# Folded legs: the pelvis less than this share of the legs' length above the ankles (a seated person's ~0.5, a
# standing one's ~0.95; evaluate.SEATED_LEG_SHARE's and stance.REBASE_FOLDED_SHARE's value).
FOLDED_SHARE: Final = 0.7
SPINE1: Final = 3  # the pelvis's child in the trunk (skeleton.JOINT_NAMES)


def turn_pelvis(local: np.ndarray, angle: float) -> None:
    """local (J, 3, 3) rotations, the pelvis's (index 0) global: turn the pelvis by angle (rad) about the
    vertical, in place, and counter-turn the spine's first joint so the trunk keeps its global orientation."""
    pelvis = local[0].copy()
    turned = about_vertical(angle) @ pelvis
    local[0] = turned
    local[SPINE1] = turned.T @ pelvis @ local[SPINE1]


class SeatedYaw:
    """The held yaw of one session's seated pelvis (module docstring)."""

    def __init__(self) -> None:
        self.held_rad: float | None = None  # the pelvis's world yaw being kept, None while nothing is held

    def reset(self) -> None:
        self.held_rad = None

    def correction(self, net_yaw_rad: float, holds: bool) -> float:
        """The turn (rad) to give the net's pelvis this sample, whose yaw is net_yaw_rad; ``holds``: its legs
        are folded and no camera frame is in its window. 0 where nothing is held."""
        if not holds:
            self.held_rad = None
            return 0.0
        if self.held_rad is None:
            self.held_rad = net_yaw_rad
        past = wrap_angle(net_yaw_rad - self.held_rad)
        zone = math.radians(DEAD_ZONE_DEG)
        if abs(past) > zone:  # the net has turned far past the held legs: they follow at the zone's edge
            self.held_rad = wrap_angle(net_yaw_rad - math.copysign(zone, past))
        return wrap_angle(self.held_rad - net_yaw_rad)
