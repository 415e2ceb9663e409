"""The seated yaw: a folded body's pelvis keeps its heading inside a dead zone while no camera frame is in the
window, and the trunk is not turned with it (the whole pipeline: test_stance.py)."""

import math

import numpy as np
import pytest

from egoposevr.model.rotations import about_vertical, heading_of, wrap_angle
from egoposevr.model.runtime import kernels
from egoposevr.model.runtime.seated_yaw import (
    DEAD_ZONE_DEG,
    SPINE1,
    SeatedYaw,
    turn_pelvis,
)
from egoposevr.model.skeleton import NUM_JOINTS, PARENTS, rest_offsets

ZONE = math.radians(DEAD_ZONE_DEG)


def test_a_held_pelvis_stays_inside_the_dead_zone_and_follows_past_it():
    seat = SeatedYaw()
    assert seat.correction(0.3, holds=True) == 0.0  # the first folded sample is where the legs stay
    assert seat.correction(0.3 + 0.5 * ZONE, holds=True) == pytest.approx(-0.5 * ZONE)
    # turned past the zone: the legs follow at its edge, and stay there as the net turns back inside it
    assert seat.correction(0.3 + ZONE + 0.2, holds=True) == pytest.approx(-ZONE)
    assert seat.held_rad == pytest.approx(0.5)
    assert seat.correction(0.5, holds=True) == pytest.approx(0.0)


def test_the_hold_wraps_round_the_half_turn_and_lets_go_when_it_ends():
    seat = SeatedYaw()
    seat.correction(math.pi - 0.1, holds=True)
    assert seat.correction(-math.pi + 0.1, holds=True) == pytest.approx(-0.2)  # 0.2 rad on, not 2 pi - 0.2
    assert seat.correction(1.0, holds=False) == 0.0 and seat.held_rad is None
    assert seat.correction(1.0, holds=True) == 0.0  # held again from where the net is now


def test_turning_the_pelvis_turns_the_legs_and_keeps_the_trunk():
    rng = np.random.default_rng(0)
    local = np.stack([about_vertical(a) for a in rng.uniform(-0.5, 0.5, NUM_JOINTS)])
    offsets = rest_offsets()
    origin = np.zeros(3)
    joints, glob = kernels.forward_kinematics_one(local, origin, offsets, PARENTS)
    turned = local.copy()
    turn_pelvis(turned, 0.4)
    joints2, glob2 = kernels.forward_kinematics_one(turned, origin, offsets, PARENTS)
    assert wrap_angle(heading_of(glob2[0]) - heading_of(glob[0])) == pytest.approx(0.4)
    knees = [4, 5]
    assert not np.allclose(joints2[knees], joints[knees], atol=1e-3)  # the legs turned with the pelvis
    trunk = [SPINE1, 6, 9, 12, 15, 16, 17, 18, 19, 20, 21]
    np.testing.assert_allclose(glob2[trunk], glob[trunk], atol=1e-9)  # the trunk and arms face as before
    # ... and stay where they were relative to the spine's first joint (the head anchors the body later)
    np.testing.assert_allclose(joints2[trunk] - joints2[SPINE1], joints[trunk] - joints[SPINE1], atol=1e-9)
