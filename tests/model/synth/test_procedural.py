"""Procedural motion: every family is plausible (planted feet, floor contact, joint limits) and seeded."""

import numpy as np
import pytest

from egoposevr.model.rotations import geodesic_angle, matrix_to_axis_angle
from egoposevr.model.synth.motion import FOOT_JOINT_HEIGHT_M
from egoposevr.model.synth.procedural import FAMILIES, generate

REQUIRED = {
    "squat",
    "sit_to_stand",
    "kick",
    "high_knees",
    "lunge",
    "single_leg_stand",
    "side_step",
    "crouch_walk",
    "bend_pick_up",
    "jump",
}
FPS = 60.0
# Largest rotation of a joint against its parent, degrees (knee and elbow bend further than anything else).
LIMIT_DEG = {4: 150, 5: 150, 18: 150, 19: 150, 7: 55, 8: 55, 3: 40, 6: 40, 9: 40, 12: 45, 15: 45}


def test_at_least_ten_families_including_what_captures_lack():
    assert len(FAMILIES) >= 10 and set(FAMILIES) >= REQUIRED


@pytest.fixture(scope="module", params=sorted(FAMILIES))
def clip(request):
    return request.param, generate(request.param, 6.0, FPS, np.random.default_rng(11))


def test_feet_on_the_floor_do_not_slide(clip):
    _, motion = clip
    toes = motion.joints()[:, [10, 11]]
    assert toes[..., 1].min() >= FOOT_JOINT_HEIGHT_M - 1e-6  # never through the floor
    planted = toes[..., 1] < FOOT_JOINT_HEIGHT_M + 0.002
    speed = np.linalg.norm(np.diff(toes[..., [0, 2]], axis=0), axis=-1) * FPS
    both = planted[1:] & planted[:-1]
    assert both.any(), "some foot must touch the floor"
    assert np.percentile(speed[both], 99) < 0.05  # m/s


def test_joint_angles_stay_within_human_limits(clip):
    _, motion = clip
    angle = np.degrees(geodesic_angle(motion.local_rot, np.eye(3)))
    for joint, limit in LIMIT_DEG.items():
        assert angle[:, joint].max() <= limit, (joint, angle[:, joint].max())
    # knees only bend backwards: their rotation is about +x (SMPL's left), never a hyperextension
    knees = matrix_to_axis_angle(motion.local_rot[:, [4, 5]])
    bent = np.linalg.norm(knees, axis=-1) > np.deg2rad(10)
    assert (knees[..., 0][bent] > 0).all()


def test_the_head_stays_at_human_heights(clip):
    _, motion = clip
    head_y = motion.joints()[:, 15, 1]
    assert head_y.min() > 0.6 and head_y.max() < 2.3


@pytest.mark.parametrize("family", ["still_stand", "still_sit", "lean_stand", "lean_sit"])
def test_still_families_move_the_upper_body_only(family):
    """Legs held still (pelvis, knees, ankles, feet: under a millimetre) while the wrists travel and the
    torso turns; seated, the pelvis is at chair height. The leaning families' trunk also bends over the
    still hips, so their head travels a hand's width over the floor."""
    joints = generate(family, 8.0, FPS, np.random.default_rng(3)).joints()
    legs = joints[:, [0, 1, 2, 4, 5, 7, 8, 10, 11]]
    assert np.abs(legs - legs[0]).max() < 1e-3
    wrists = joints[:, [20, 21]]
    assert np.linalg.norm(wrists - wrists[0], axis=-1).max() > 0.2
    shoulders = joints[:, 17] - joints[:, 16]
    yaw = np.degrees(np.arctan2(shoulders[:, 2], shoulders[:, 0]))
    assert np.ptp(yaw) > 15  # the torso turns on still legs
    pelvis_y = joints[0, 0, 1]
    assert (pelvis_y < 0.75) if family.endswith("_sit") else (pelvis_y > 0.8)
    if family.startswith("lean_"):
        head_xz = joints[:, 15, [0, 2]]
        assert np.linalg.norm(head_xz - head_xz[0], axis=-1).max() > 0.08


def test_same_seed_same_motion_other_seed_other_motion():
    a = generate("lunge", 3.0, FPS, np.random.default_rng(5))
    b = generate("lunge", 3.0, FPS, np.random.default_rng(5))
    c = generate("lunge", 3.0, FPS, np.random.default_rng(6))
    assert np.array_equal(a.local_rot, b.local_rot) and np.array_equal(a.bone_scale, b.bone_scale)
    assert not np.allclose(a.local_rot, c.local_rot)


def test_arms_move_independently_of_the_legs():
    """Two squats with the same legs can carry different arm programs: headset signals stay ambiguous."""
    arms = [generate("squat", 4.0, FPS, np.random.default_rng(s)).local_rot[:, 18] for s in range(6)]
    spread = np.std([np.degrees(geodesic_angle(a, np.eye(3))).mean() for a in arms])
    assert spread > 5.0


def test_unknown_family_is_refused():
    with pytest.raises(ValueError, match="unknown procedural family"):
        generate("moonwalk", 1.0, FPS, np.random.default_rng(0))


@pytest.mark.parametrize(
    ("family", "category"),
    [
        ("walk", "walk"),
        ("squat", "crouch, bend"),
        ("stand_interact", "stand, upper body"),
        ("kick", "legs"),
        ("still_stand", "stand, upper body"),
        ("still_sit", "sit, upper body"),
        ("lean_stand", "stand, upper body"),
        ("lean_sit", "sit, upper body"),
    ],
)
def test_evaluation_reads_the_motion_category_from_the_truth(family, category):
    from egoposevr.model.training.evaluate import motion_category

    motion = generate(family, 6.0, 60.0, np.random.default_rng(11))
    seq = {"gt_joints_m": motion.joints(), "hmd_t_us": np.arange(motion.num_frames) * 16_667}
    assert motion_category(seq) == category


def _single_support(joints: np.ndarray) -> np.ndarray:
    """(F,) +1 while only the left foot is on the floor, -1 only the right, 0 otherwise."""
    down = joints[:, [10, 11], 1] < FOOT_JOINT_HEIGHT_M + 0.01
    return down[:, 0].astype(int) - down[:, 1].astype(int)


def _landings(joints: np.ndarray, foot: int) -> np.ndarray:
    """Samples where a foot (10 left, 11 right) comes down after being in the air."""
    down = joints[:, foot, 1] < FOOT_JOINT_HEIGHT_M + 0.01
    return np.nonzero(down[1:] & ~down[:-1])[0] + 1


@pytest.mark.parametrize("family", ["walk", "crouch_walk"])
def test_a_walk_moves_head_and_hands_in_step_with_the_feet(family):
    """What a headset sees of a walk keeps the feet's phase as captured walks do: the head sways toward the
    standing foot, is lower just after a landing than in mid single support, and each hand is furthest
    forward when the other side's foot lands."""
    sway, low, high, right_hand = [], [], [], {10: [], 11: []}
    for seed in range(8):
        joints = generate(family, 8.0, FPS, np.random.default_rng(seed)).joints()
        left = joints[:, 1] - joints[:, 2]
        left[:, 1] = 0.0
        left /= np.linalg.norm(left, axis=-1, keepdims=True)
        forward = np.cross(left, [0.0, 1.0, 0.0])
        path = np.stack([np.convolve(joints[:, 0, k], np.ones(61) / 61, mode="same") for k in range(3)], -1)
        head_left = np.einsum("ni,ni->n", joints[:, 15] - path, left)[40:-40]
        support = _single_support(joints)[40:-40]
        sway.append(np.mean(head_left[support == 1]) - np.mean(head_left[support == -1]))
        head_y = joints[:, 15, 1] - np.convolve(joints[:, 15, 1], np.ones(61) / 61, mode="same")
        for foot in (10, 11):
            for n in _landings(joints, foot):
                if 40 <= n < len(joints) - 40:
                    low.append(head_y[n : n + 6].mean())
                    high.append(head_y[n + 12 : n + 24].mean())
                    right_hand[foot].append(np.dot(joints[n, 21] - joints[n, 0], forward[n]))
    assert np.mean(sway) > 0.02  # metres toward the standing foot
    assert np.mean(low) < np.mean(high) - 0.005
    assert np.mean(right_hand[10]) > np.mean(right_hand[11]) + 0.03
