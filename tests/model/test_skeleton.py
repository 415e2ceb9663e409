"""SMPL-22 constants are consistent and FK behaves as kinematics should."""

import numpy as np
import pytest

from egoposevr.model import skeleton as sk
from egoposevr.model.rotations import axis_angle_to_matrix

RNG = np.random.default_rng(3)
IDENTITY = np.broadcast_to(np.eye(3), (sk.NUM_JOINTS, 3, 3))


def random_local(*batch):
    return axis_angle_to_matrix(RNG.normal(size=(*batch, sk.NUM_JOINTS, 3)) * 0.6)


def test_constants_are_consistent():
    assert len(sk.JOINT_NAMES) == len(sk.PARENTS) == sk.NUM_JOINTS == len(sk.REST_JOINTS_M)
    assert all(sk.PARENTS[j] < j for j in range(1, sk.NUM_JOINTS))  # topological order
    assert sorted([*sk.UPPER_BODY, *sk.LOWER_BODY]) == list(range(sk.NUM_JOINTS))
    assert sk.JOINT_NAMES[sk.HEAD] == "head"
    assert (sk.JOINT_NAMES[sk.LEFT_WRIST], sk.JOINT_NAMES[sk.RIGHT_WRIST]) == ("left_wrist", "right_wrist")
    assert sk.REST_JOINTS_M[sk.JOINT_INDEX["left_wrist"], 0] > 0  # +x is the subject's left


def test_fk_of_rest_pose_is_the_rest_joints():
    pos, rot = sk.forward_kinematics(IDENTITY, np.zeros(3))
    np.testing.assert_allclose(pos, sk.REST_JOINTS_M, atol=1e-12)
    np.testing.assert_allclose(rot, IDENTITY)


def test_fk_translates_with_the_root_and_rotates_rigidly_with_the_pelvis():
    local = random_local()
    pos, _ = sk.forward_kinematics(local, np.zeros(3))
    turn = axis_angle_to_matrix(np.array([0.0, 1.0, 0.0]))
    turned = local.copy()
    turned[0] = turn @ local[0]
    pos2, _ = sk.forward_kinematics(turned, np.array([1.0, 2.0, 3.0]))
    np.testing.assert_allclose(pos2, pos @ turn.T + [1.0, 2.0, 3.0], atol=1e-12)


def test_fk_preserves_bone_lengths_for_any_pose_and_scale():
    scale = RNG.uniform(0.8, 1.2, size=(4, sk.NUM_JOINTS))
    offsets = sk.rest_offsets(scale)
    pos, _ = sk.forward_kinematics(random_local(4), RNG.normal(size=(4, 3)), offsets)
    lengths = sk.joint_bone_lengths(pos)
    np.testing.assert_allclose(lengths, sk.bone_lengths(offsets)[:, 1:], atol=1e-12)


def test_fk_is_batched_over_leading_dimensions():
    local, root = random_local(2, 3), RNG.normal(size=(2, 3, 3))
    pos, rot = sk.forward_kinematics(local, root)
    assert pos.shape == (2, 3, 22, 3) and rot.shape == (2, 3, 22, 3, 3)
    single, _ = sk.forward_kinematics(local[1, 2], root[1, 2])
    np.testing.assert_allclose(pos[1, 2], single, atol=1e-12)


def test_global_to_local_inverts_fk():
    local = random_local(5)
    _, global_rot = sk.forward_kinematics(local, np.zeros((5, 3)))
    np.testing.assert_allclose(sk.global_to_local(global_rot), local, atol=1e-12)


def test_smpl_axis_angle_round_trip():
    local = random_local(6)
    global_orient, body_pose = sk.local_rot_to_smpl(local)
    assert global_orient.shape == (6, 3) and body_pose.shape == (6, 63)
    np.testing.assert_allclose(sk.smpl_to_local_rot(global_orient, body_pose), local, atol=1e-12)


def test_bent_left_knee_moves_only_the_left_shin():
    local = IDENTITY.copy()
    local[sk.JOINT_INDEX["left_knee"]] = axis_angle_to_matrix(np.array([np.pi / 2, 0.0, 0.0]))
    pos, _ = sk.forward_kinematics(local, np.zeros(3))
    moved = np.flatnonzero(np.linalg.norm(pos - sk.REST_JOINTS_M, axis=-1) > 1e-9)
    assert [sk.JOINT_NAMES[j] for j in moved] == ["left_ankle", "left_foot"]


def test_wrong_shapes_are_refused():
    with pytest.raises(ValueError, match=r"local_rot must be"):
        sk.forward_kinematics(np.zeros((21, 3, 3)), np.zeros(3))
    with pytest.raises(ValueError, match=r"bone_scale must be"):
        sk.rest_offsets(np.ones(21))
