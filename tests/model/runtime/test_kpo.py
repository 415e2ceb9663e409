"""KPO (paper Eqs. 9-10) and the rotations re-derived from its joints."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from egoposevr.model.rig import TRACKED_JOINTS
from egoposevr.model.runtime.kpo import INCIDENCE, KpoWeights, kpo_energy, rederive_rotations, solve_kpo
from egoposevr.model.skeleton import forward_kinematics, rest_offsets

OFFSETS = rest_offsets()


def random_pose(seed: int, spread: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    local = Rotation.from_rotvec(rng.normal(0.0, spread, (22, 3))).as_matrix()
    joints, _ = forward_kinematics(local, np.array([0.0, 1.0, 0.0]), OFFSETS)
    return local, joints


def displaced_targets(joints: np.ndarray, seed: int, scale_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Controllers off the predicted wrists by ~scale_m; the head nearly on its target, as serving anchors the
    predicted body at the headset before KPO."""
    targets = joints.copy()
    spread = np.array([[0.05], [1.0], [1.0]]) * scale_m
    targets[list(TRACKED_JOINTS)] += np.random.default_rng(seed + 100).normal(0.0, 1.0, (3, 3)) * spread
    observed = np.zeros(22, dtype=bool)
    observed[list(TRACKED_JOINTS)] = True
    return targets, observed


@pytest.mark.parametrize("seed", range(6))
def test_kpo_lowers_the_energy_pulls_tracked_joints_and_keeps_bone_lengths(seed):
    _, pred = random_pose(seed)
    targets, observed = displaced_targets(pred, seed, 0.02)
    w = KpoWeights()
    refined = solve_kpo(pred, targets, observed, w)
    assert kpo_energy(refined, pred, targets, observed, w) < 0.5 * kpo_energy(
        pred, pred, targets, observed, w
    )
    before = np.linalg.norm(pred[observed] - targets[observed], axis=-1)
    after = np.linalg.norm(refined[observed] - targets[observed], axis=-1)
    assert after[1:].mean() < 0.4 * before[1:].mean()  # the wrists reach for their controllers
    # The stiff torso lets the wrists drag the head a little (validation clips: head error 0.59 -> 0.98 cm)
    assert after[0] < 0.015
    lengths = np.linalg.norm(INCIDENCE @ refined, axis=-1) - np.linalg.norm(INCIDENCE @ pred, axis=-1)
    assert np.abs(lengths).max() < 2e-3  # metres


def test_kpo_leaves_a_pose_that_already_fits_alone():
    _, pred = random_pose(3)
    observed = np.zeros(22, dtype=bool)
    observed[list(TRACKED_JOINTS)] = True
    np.testing.assert_allclose(solve_kpo(pred, pred, observed), pred, atol=1e-9)


def test_an_untracked_controller_is_not_a_target():
    _, pred = random_pose(4)
    targets, observed = displaced_targets(pred, 4, 0.05)
    observed[21] = False  # right controller lost: its (stale) target must not pull
    refined = solve_kpo(pred, targets, observed)
    assert np.linalg.norm(refined[21] - targets[21]) > 0.5 * np.linalg.norm(pred[21] - targets[21])


@pytest.mark.parametrize("seed", range(4))
def test_rederived_rotations_are_the_predicted_ones_when_joints_agree(seed):
    local, joints = random_pose(seed, spread=0.6)
    np.testing.assert_allclose(rederive_rotations(local, joints, OFFSETS), local, atol=1e-9)


@pytest.mark.parametrize("seed", range(6))
def test_fk_of_rederived_rotations_reproduces_kpo_joints_within_5_mm(seed):
    local, pred = random_pose(seed)
    targets, observed = displaced_targets(pred, seed, 0.02)
    refined = solve_kpo(pred, targets, observed)
    rotations = rederive_rotations(local, refined, OFFSETS)
    replayed, _ = forward_kinematics(rotations, refined[0], OFFSETS)
    assert np.linalg.norm(replayed - refined, axis=-1).max() < 5e-3
    assert np.allclose(np.linalg.det(rotations), 1.0)


def test_rederivation_turns_a_bone_that_must_point_the_opposite_way():
    local = np.tile(np.eye(3), (22, 1, 1))
    joints, _ = forward_kinematics(local, np.zeros(3), OFFSETS)
    flipped = joints.copy()
    flipped[19] = joints[17] - (joints[19] - joints[17])  # right elbow folded back through the shoulder
    flipped[21] = flipped[19] + (joints[21] - joints[19])
    rotations = rederive_rotations(local, flipped, OFFSETS)
    replayed, _ = forward_kinematics(rotations, flipped[0], OFFSETS)
    np.testing.assert_allclose(replayed[19], flipped[19], atol=1e-6)


def test_legs_turn_with_a_pelvis_that_kpo_turned():
    """The whole body served turned 20° about the vertical from what the network put (planted feet and a
    held stance turn the pelvis back this way): the legs' local rotations stay the network's, so the thighs'
    twist turns with the pelvis instead of the hips' local rotations absorbing the turn."""
    local, joints = random_pose(7)
    turn = Rotation.from_euler("y", 20.0, degrees=True).as_matrix()
    turned = (joints - joints[0]) @ turn.T + joints[0]
    rotations = rederive_rotations(local, turned, OFFSETS)
    np.testing.assert_allclose(rotations[0], turn @ local[0], atol=1e-6)
    legs = [1, 2, 4, 5, 7, 8, 10, 11]
    np.testing.assert_allclose(rotations[legs], local[legs], atol=1e-6)
    replayed, _ = forward_kinematics(rotations, turned[0], OFFSETS)
    np.testing.assert_allclose(replayed[legs], turned[legs], atol=1e-6)


def test_a_leg_swung_at_the_hip_keeps_the_networks_knee_and_ankle():
    """The left leg below the hip swung 25° about an axis across the thigh (KPO moved the knee to keep a
    planted foot): the hip takes the whole swing, and the knee and ankle keep the network's local rotations,
    each hung from its corrected parent, instead of the shortest turn onto their bones, which would twist them."""
    local, joints = random_pose(11)
    thigh = joints[4] - joints[1]
    axis = np.cross(thigh, [0.3, 0.2, 1.0])
    swing = Rotation.from_rotvec(np.radians(25.0) * axis / np.linalg.norm(axis)).as_matrix()
    moved = joints.copy()
    moved[[4, 7, 10]] = (joints[[4, 7, 10]] - joints[1]) @ swing.T + joints[1]
    rotations = rederive_rotations(local, moved, OFFSETS)
    np.testing.assert_allclose(rotations[[7, 10]], local[[7, 10]], atol=1e-6)  # ankle, foot
    assert np.degrees(Rotation.from_matrix(rotations[4].T @ local[4]).magnitude()) < 1e-4  # knee
    replayed, _ = forward_kinematics(rotations, moved[0], OFFSETS)
    np.testing.assert_allclose(replayed[[4, 7, 10]], moved[[4, 7, 10]], atol=1e-6)
