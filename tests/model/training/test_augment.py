"""Augmentation keeps labels true: mirrored sequences are bodies, cropped and flipped frames are cameras."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from egoposevr.model.hmd import hmd_features, tracking_features
from egoposevr.model.inputs import (
    HMD_MIRROR_ORDER,
    HMD_MIRROR_SIGNS,
    SIXD_MIRROR_SIGNS,
    VISUAL_MIRROR_ORDER,
    VISUAL_MIRROR_SIGNS,
    canonicalize_hmd,
    heading_frame,
    lift_keypoints,
    visual_tokens,
)
from egoposevr.model.rig import DEFAULT_OFFSETS_M, DEVICE_FROM_JOINT, TRACKED_JOINTS, joints_from_devices
from egoposevr.model.rotations import matrix_to_sixd
from egoposevr.model.skeleton import LOWER_BODY, NUM_JOINTS, forward_kinematics, rest_offsets
from egoposevr.model.training.augment import (
    MIRROR_JOINTS,
    crop_and_flip,
    lose_hanging_arms,
    mirror_sequence,
    mirror_world_keypoints,
    narrow_tracking_cone,
    retime_sequence,
    swap_arms,
)


def _sequence(rng: np.random.Generator, n: int = 5) -> dict:
    """A random posed body with its devices where the rig puts them."""
    local = Rotation.random(n * NUM_JOINTS, random_state=1).as_matrix().reshape(n, NUM_JOINTS, 3, 3)
    local = np.einsum("...ij->...ij", local)
    scale = rng.uniform(0.9, 1.1, NUM_JOINTS)
    root = rng.normal(0, 1, (n, 3))
    joints, glob = forward_kinematics(local, root, rest_offsets(scale))
    poses = np.zeros((n, 3, 7))
    for d, j in enumerate(TRACKED_JOINTS):
        poses[:, d, :3] = joints[:, j] + np.einsum("nij,j->ni", glob[:, j], DEFAULT_OFFSETS_M[d])
        poses[:, d, 3:] = Rotation.from_matrix(glob[:, j] @ DEVICE_FROM_JOINT).as_quat()
    return {
        "name": "s", "key": "val/0", "hmd_t_us": np.arange(n) * 11_111, "cam_t_us": np.arange(2) * 33_333,
        "hmd_poses": poses.astype(np.float32), "hmd_valid": rng.random((n, 3)) < 0.7,
        "gt_local_quat": Rotation.from_matrix(local.reshape(-1, 3, 3)).as_quat().reshape(n, NUM_JOINTS, 4),
        "gt_joints_m": joints, "gt_root_m": root, "bone_scale": scale,
    }  # fmt: skip


def test_a_mirrored_sequence_is_a_body_with_its_devices_on_it() -> None:
    seq = _sequence(np.random.default_rng(0))
    mirrored = mirror_sequence(seq)
    local = (
        Rotation.from_quat(mirrored["gt_local_quat"].reshape(-1, 4)).as_matrix().reshape(-1, NUM_JOINTS, 3, 3)
    )
    # The mean body is not exactly symmetric; with a symmetric rest skeleton FK would match to 1e-9.
    offsets = rest_offsets(mirrored["bone_scale"])
    offsets[MIRROR_JOINTS] = rest_offsets(seq["bone_scale"]) * [-1.0, 1.0, 1.0]
    joints, _ = forward_kinematics(local, mirrored["gt_root_m"], offsets)
    np.testing.assert_allclose(joints, mirrored["gt_joints_m"], atol=1e-9)
    tracked, _ = joints_from_devices(mirrored["hmd_poses"].astype(np.float64))
    np.testing.assert_allclose(tracked, mirrored["gt_joints_m"][:, list(TRACKED_JOINTS)], atol=1e-5)
    np.testing.assert_array_equal(mirrored["hmd_valid"][:, 1], seq["hmd_valid"][:, 2])
    assert mirrored["mirror_of"] is seq and mirrored["images_key"] == "val/0"


def test_retiming_scales_the_clocks_only() -> None:
    seq = _sequence(np.random.default_rng(1))
    fast = retime_sequence(seq, 2.0)
    np.testing.assert_array_equal(fast["hmd_t_us"], seq["hmd_t_us"] // 2)
    np.testing.assert_array_equal(fast["cam_t_us"], seq["cam_t_us"] // 2)
    assert fast["hmd_poses"] is seq["hmd_poses"] and fast["images_key"] == "val/0"


def test_a_narrower_tracking_cone_loses_a_controller_once_its_hand_has_left_it_for_the_grace() -> None:
    n, rate_hz = 91, 90.0
    t_us = np.round(np.arange(n) * 1e6 / rate_hz).astype(np.int64) + 5_000_000
    angle_deg = np.linspace(0.0, 90.0, n)  # the left hand sweeps from straight ahead to the side in 1 s
    wrists_m = np.zeros((n, 22, 3))
    wrists_m[:, 20] = 0.5 * np.stack(
        [-np.sin(np.radians(angle_deg)), 0 * angle_deg, -np.cos(np.radians(angle_deg))], 1
    )
    wrists_m[:, 21] = [0.1, -0.2, -0.5]  # the right one stays in view
    poses = np.zeros((n, 3, 7))
    poses[..., 6] = 1.0  # the headset at the origin looking down -z; devices turned as the head
    poses[:, 1:, :3] = (
        wrists_m[:, [20, 21]] + 0.01 * np.arange(n)[:, None, None]
    )  # reported poses, all distinct
    valid = np.ones((n, 3), dtype=bool)
    valid[10:15, 2] = False  # a loss the render already had, reporting the last tracked pose
    poses[10:15, 2] = poses[9, 2]
    seq = {"key": "train/3", "hmd_t_us": t_us, "hmd_poses": poses.astype(np.float32), "hmd_valid": valid,
           "gt_joints_m": wrists_m}  # fmt: skip

    narrowed = narrow_tracking_cone(seq, cone_deg=60.0, grace_s=0.25)
    outside_s = (t_us - t_us[np.argmax(angle_deg > 60.0)]) * 1e-6
    np.testing.assert_array_equal(narrowed["hmd_valid"][:, 1], outside_s <= 0.25)
    np.testing.assert_array_equal(narrowed["hmd_valid"][:, [0, 2]], valid[:, [0, 2]])
    last = np.flatnonzero(narrowed["hmd_valid"][:, 1])[-1]
    assert (narrowed["hmd_poses"][last:, 1] == seq["hmd_poses"][last, 1]).all()  # its last tracked pose
    np.testing.assert_array_equal(narrowed["hmd_poses"][: last + 1], seq["hmd_poses"][: last + 1])
    assert (
        narrowed["key"] != seq["key"] and narrowed["images_key"] == "train/3"
    )  # other HMD features, same frames

    unchanged = narrow_tracking_cone(seq, cone_deg=180.0)
    np.testing.assert_array_equal(unchanged["hmd_valid"], valid)
    np.testing.assert_array_equal(unchanged["hmd_poses"], seq["hmd_poses"])


def test_a_hand_that_hangs_loses_its_controller_once_it_has_hung_for_the_grace() -> None:
    n, rate_hz = 91, 90.0
    t_us = np.round(np.arange(n) * 1e6 / rate_hz).astype(np.int64) + 2_000_000
    joints_m = np.zeros((n, 22, 3))
    joints_m[:, 16] = [0.2, 1.4, 0.0]  # left shoulder
    joints_m[:, 17] = [-0.2, 1.4, 0.0]  # right shoulder
    joints_m[:, 20] = [0.3, 1.4, 0.3]  # the left hand held out in front, then dropping to hang in 1 s
    joints_m[:, 20, 1] = np.linspace(1.4, 0.8, n)
    joints_m[:, 21] = [-0.3, 1.2, 0.3]  # the right one 0.2 m under its shoulder: not hanging
    poses = np.zeros((n, 3, 7))
    poses[..., 6] = 1.0
    poses[:, 1:, :3] = joints_m[:, [20, 21]] + 0.01 * np.arange(n)[:, None, None]  # all distinct
    valid = np.ones((n, 3), dtype=bool)
    valid[10:15, 2] = False  # a loss the render already had
    poses[10:15, 2] = poses[9, 2]
    seq = {"key": "train/4", "hmd_t_us": t_us, "hmd_poses": poses.astype(np.float32), "hmd_valid": valid,
           "gt_joints_m": joints_m}  # fmt: skip

    hung = lose_hanging_arms(seq, drop_m=0.3, grace_s=0.25)
    hanging_s = (t_us - t_us[np.argmax(joints_m[:, 20, 1] < 1.1)]) * 1e-6
    np.testing.assert_array_equal(hung["hmd_valid"][:, 1], hanging_s <= 0.25)
    np.testing.assert_array_equal(hung["hmd_valid"][:, [0, 2]], valid[:, [0, 2]])
    last = np.flatnonzero(hung["hmd_valid"][:, 1])[-1]
    assert last < n - 20 and (hung["hmd_poses"][last:, 1] == seq["hmd_poses"][last, 1]).all()
    np.testing.assert_array_equal(hung["hmd_poses"][: last + 1], seq["hmd_poses"][: last + 1])
    assert hung["key"] != seq["key"] and hung["images_key"] == "train/4"

    unchanged = lose_hanging_arms(seq, drop_m=1.0)
    np.testing.assert_array_equal(unchanged["hmd_valid"], valid)
    np.testing.assert_array_equal(unchanged["hmd_poses"], seq["hmd_poses"])


def test_swapped_arms_move_on_the_same_legs_and_carry_their_controllers() -> None:
    person, donor = _sequence(np.random.default_rng(4), n=12), _sequence(np.random.default_rng(5), n=7)
    donor["key"] = "val/1"
    swapped = swap_arms(person, donor, start=3, cone_deg=180.0)

    local = (
        Rotation.from_quat(swapped["gt_local_quat"].reshape(-1, 4)).as_matrix().reshape(-1, NUM_JOINTS, 3, 3)
    )
    joints, _ = forward_kinematics(local, person["gt_root_m"], rest_offsets(person["bone_scale"]))
    np.testing.assert_allclose(joints, swapped["gt_joints_m"], atol=1e-5)  # a body, on the person's bones
    np.testing.assert_allclose(
        swapped["gt_joints_m"][:, LOWER_BODY], person["gt_joints_m"][:, LOWER_BODY], atol=1e-6
    )
    donor_local = (
        Rotation.from_quat(donor["gt_local_quat"].reshape(-1, 4)).as_matrix().reshape(-1, NUM_JOINTS, 3, 3)
    )
    np.testing.assert_allclose(local[:, 18], donor_local[(3 + np.arange(12)) % 7, 18], atol=1e-6)  # wrapping
    tracked, _ = joints_from_devices(swapped["hmd_poses"].astype(np.float64))
    np.testing.assert_allclose(
        tracked[:, 1:], swapped["gt_joints_m"][:, [20, 21]], atol=1e-4
    )  # on the new wrists
    assert swapped["hmd_valid"][:, 1:].all()  # a cone of 180 degrees sees every controller
    assert swapped["arms_unseen"] and swapped["images_key"] == "val/0" and swapped["key"] != person["key"]

    itself = swap_arms(person, person, start=0, cone_deg=180.0)  # the same arms: the same controllers
    seen = person["hmd_valid"][:, 1:]
    np.testing.assert_allclose(
        itself["hmd_poses"][:, 1:, :3][seen], person["hmd_poses"][:, 1:, :3][seen], atol=1e-5
    )
    narrow = swap_arms(person, donor, start=3, cone_deg=5.0, grace_s=0.0)
    assert not narrow["hmd_valid"][1:, 1:].any()  # lost from the second sample (no grace)
    np.testing.assert_array_equal(narrow["hmd_valid"][:, 0], person["hmd_valid"][:, 0])  # the headset's own


@pytest.mark.parametrize(("crop_p", "flip_p"), [(1.0, 0.0), (0.0, 1.0), (1.0, 1.0)])
def test_cropped_and_flipped_frames_lift_to_their_joints(crop_p: float, flip_p: float) -> None:
    rng = np.random.default_rng(2)
    b, w, h = 6, 40, 32
    cam_wh = np.array([[320.0, 256.0]] * b)
    intrinsics = np.array([[160.0, 150.0, 161.0, 120.0]] * b)
    joints = np.stack([rng.uniform(-1.0, 1.0, NUM_JOINTS), rng.uniform(-0.8, 0.8, NUM_JOINTS),
                       rng.uniform(1.0, 2.0, NUM_JOINTS)], -1)[None].repeat(b, 0)  # fmt: skip
    px = joints[..., :2] / joints[..., 2:] * intrinsics[:, None, :2] + intrinsics[:, None, 2:]
    uv = (px + 0.5) / cam_wh[:, None]
    visible = ((uv >= 0) & (uv <= 1)).all(-1)
    rgb = rng.integers(0, 255, (b, h, w, 3), dtype=np.uint8)
    depth = rng.integers(0, 5000, (b, h, w), dtype=np.uint16)
    out = crop_and_flip(rng, rgb, depth, uv, visible, intrinsics, cam_wh, joints, crop_p, flip_p)
    rgb2, depth2, uv2, visible2, intrinsics2, wh2, joints2 = out
    assert rgb2.shape == rgb.shape and depth2.shape == depth.shape
    for k in range(b):
        lifted = lift_keypoints(uv2[k].astype(np.float64), joints2[k, :, 2], intrinsics2[k], wh2[k])
        np.testing.assert_allclose(lifted[visible2[k]], joints2[k][visible2[k]], atol=1e-4)
        assert (((uv2[k] >= 0) & (uv2[k] <= 1)).all(-1) >= visible2[k]).all()
    if flip_p:
        np.testing.assert_allclose(joints2[:, 1, 0], -joints[:, 2, 0])
    if flip_p and not crop_p:
        np.testing.assert_array_equal(rgb2[:, :, ::-1], rgb)
    if crop_p:
        assert (wh2[:, 1] < cam_wh[:, 1]).all() and visible2.sum() < visible.sum()


def test_the_mirrored_persons_net_inputs_are_the_served_ones_reordered_and_signed() -> None:
    """inputs.py's mirror layouts give exactly what the featurisation gives the mirrored sequence (lost
    controllers included), so a net served both answers for two people it was trained on."""
    rng = np.random.default_rng(4)
    seq = _sequence(rng, n=60)
    mirrored = mirror_sequence(seq)

    def window(s: dict, i: int) -> np.ndarray:
        poses, valid = np.asarray(s["hmd_poses"], np.float64), np.asarray(s["hmd_valid"])
        x = np.concatenate(
            [hmd_features(s["hmd_t_us"], poses, valid), tracking_features(s["hmd_t_us"], valid)], -1
        )
        return canonicalize_hmd(x[i - 11 : i + 1], *heading_frame(poses[i, 0]))

    assert (~seq["hmd_valid"][:, 1:]).any() and (seq["hmd_valid"][:, 1] != seq["hmd_valid"][:, 2]).any()
    for i in (11, 30, 59):
        np.testing.assert_allclose(
            window(seq, i)[..., HMD_MIRROR_ORDER] * HMD_MIRROR_SIGNS, window(mirrored, i), atol=1e-5
        )
    kp, confidence = rng.normal(size=(3, NUM_JOINTS, 3)), rng.random((3, NUM_JOINTS))
    age_s, head = np.array([0.07, 0.03, 0.0]), (seq["hmd_poses"][7, 0], mirrored["hmd_poses"][7, 0])
    tokens = visual_tokens(kp, confidence, age_s, 4, *heading_frame(head[0]))
    tokens_mirrored = visual_tokens(
        *mirror_world_keypoints(kp, confidence), age_s, 4, *heading_frame(head[1])
    )
    np.testing.assert_allclose(
        tokens[..., VISUAL_MIRROR_ORDER] * VISUAL_MIRROR_SIGNS, tokens_mirrored, atol=1e-5
    )
    sixd = [
        matrix_to_sixd(Rotation.from_quat(s["gt_local_quat"].reshape(-1, 4)).as_matrix())
        for s in (seq, mirrored)
    ]
    sixd = [x.reshape(-1, NUM_JOINTS, 6) for x in sixd]
    np.testing.assert_allclose(sixd[0][:, MIRROR_JOINTS] * SIXD_MIRROR_SIGNS, sixd[1], atol=1e-6)
