"""The seated yaw: a folded body's pelvis keeps its heading inside a dead zone while no camera frame is in the
window, and the trunk is not turned with it."""

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
SEED = 1  # a still_sit draw whose trunk turns: 7.7 cm of leakage without the seated yaw


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


def test_a_seated_user_without_the_camera_keeps_the_legs_still_while_the_trunk_turns():
    """The whole pipeline (bundled egoposevr, no camera frame) on a procedural user who sits still and turns and
    moves only the upper body: the legs leak well under half as far with the seated yaw as without it, and the
    served joints are still FK of the rotations."""
    from egoposevr.model.runtime.loading import LoadedModel
    from egoposevr.model.runtime.pipeline import Pipeline
    from egoposevr.model.skeleton import forward_kinematics
    from egoposevr.model.synth.headset import simulate_headset
    from egoposevr.model.synth.procedural import generate
    from egoposevr.model.training.plausibility import plausibility, summarize_plausibility
    from egoposevr.model.weights import WEIGHTS_DIR

    rng = np.random.default_rng(SEED)
    track = simulate_headset(generate("still_sit", 8.0, 60.0, rng), 90.0, rng)
    model = LoadedModel.load(WEIGHTS_DIR / "egoposevr.onnx")
    leakage = {}
    for held in (True, False):
        pipeline = Pipeline(model, seated_yaw=held)
        results = [
            pipeline.push_hmd(int(t), track.poses[i], track.valid[i]) for i, t in enumerate(track.t_us)
        ]
        joints = np.array([r.joints for r in results])
        measured = plausibility(joints, track.joints_m, track.t_us)
        leakage[held] = summarize_plausibility([measured])["leg_leakage_cm"]
        last = results[-1]
        fk, _ = forward_kinematics(last.local_rot, last.transl, rest_offsets(pipeline.served_scale.scale))
        assert np.allclose(fk, last.joints, atol=1e-6)
    assert leakage[True] < 0.5 * leakage[False], leakage
