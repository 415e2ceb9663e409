"""Network inputs shared by training and the runtime: heading frame, images, keypoints, visual tokens."""

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from egoposevr.model.hmd import hmd_features
from egoposevr.model.inputs import (
    VISUAL_TOKEN_DIM,
    VisibilityFilter,
    camera_to_world,
    canonicalize_hmd,
    decode_rgbd,
    encoded_image_size,
    heading_frame,
    lift_keypoints,
    nearest_sample,
    network_input,
    normalise_uv,
    resize_frame,
    visual_tokens,
    visual_window,
)
from egoposevr.model.synth.headset import CameraModel


def random_track(rng, n=30):
    t_us = np.arange(n) * 11_111
    pos = np.array([0.0, 1.6, 0.0]) + np.cumsum(rng.normal(0, 0.01, (n, 3, 3)), axis=0)
    quat = Rotation.from_rotvec(rng.normal(0, 0.5, (n * 3, 3))).as_quat().reshape(n, 3, 4)
    return t_us, np.concatenate([pos, quat], axis=-1)


def move_world(poses, yaw_rad, shift_m):
    """The same motion walked elsewhere: turned about +y and moved on the floor."""
    turn = Rotation.from_euler("y", yaw_rad)
    out = poses.copy()
    out[..., :3] = turn.apply(poses[..., :3].reshape(-1, 3)).reshape(poses[..., :3].shape) + shift_m
    out[..., 3:] = (
        (turn * Rotation.from_quat(poses[..., 3:].reshape(-1, 4))).as_quat().reshape(poses[..., 3:].shape)
    )
    return out


def test_heading_frame_removes_yaw_and_floor_position_but_keeps_height():
    rng = np.random.default_rng(0)
    t_us, poses = random_track(rng)
    moved = move_world(poses, 1.2, np.array([3.0, 0.0, -2.0]))
    windows = []
    for p in (poses, moved):
        rot, origin = heading_frame(p[-1, 0])
        windows.append(canonicalize_hmd(hmd_features(t_us, p), rot, origin))
    np.testing.assert_allclose(windows[0], windows[1], atol=1e-4)
    assert abs(windows[0][-1, 1] - poses[-1, 0, 1]) < 1e-5  # the head's height survives


def test_heading_frame_is_a_pure_yaw():
    rot, origin = heading_frame(
        np.array([1.0, 1.7, 2.0, *Rotation.from_euler("yxz", [0.7, -1.2, 0.3]).as_quat()])
    )
    assert np.allclose(rot @ rot.T, np.eye(3)) and np.allclose(rot[1], [0, 1, 0]) and origin[1] == 0.0


def test_lifting_inverts_the_camera_projection_at_any_resolution():
    for cam in (CameraModel(), CameraModel(width=128, height=96)):
        points = np.array([[0.1, 0.3, 1.2], [-0.4, 0.2, 0.8], [0.0, 0.0, 2.0]])
        uv = normalise_uv(cam.project(points), (cam.width, cam.height))
        lifted = lift_keypoints(uv, points[:, 2], np.array(cam.intrinsics()), (cam.width, cam.height))
        np.testing.assert_allclose(lifted, points, atol=1e-9)


def test_camera_to_world_matches_the_camera_model():
    cam = CameraModel()
    head = np.array([0.3, 1.6, -0.2, *Rotation.from_euler("xy", [-0.4, 0.9]).as_quat()])
    points = np.array([[0.1, 0.2, 1.0], [0.0, 0.5, 1.5]])
    want = (cam.world_from_camera(head) @ np.c_[points, np.ones(2)].T).T[:, :3]
    np.testing.assert_allclose(camera_to_world(points, head, cam.cam_from_head()), want, atol=1e-9)


def test_network_input_is_c_contiguous_and_scaled():
    rgb = np.full((128, 160, 3), 255, np.uint8)
    depth = np.full((128, 160), 2000, np.uint16)
    small = resize_frame(rgb, depth, (80, 64))
    x = network_input(*small, 4)
    assert x.shape == (4, 64, 80) and x.flags["C_CONTIGUOUS"] and x.dtype == np.float32
    assert np.allclose(x[:3], 0.5) and np.allclose(x[3], 1.0)
    assert network_input(*small, 3).shape == (3, 64, 80)


def test_visual_window_takes_the_newest_frames_not_too_old():
    t = np.array([0, 100_000, 200_000, 300_000, 900_000])
    assert list(visual_window(t, 350_000, 2)) == [2, 3]
    assert list(visual_window(t, 250_000, 8)) == [0, 1, 2]
    assert list(visual_window(t, 1_300_000, 8)) == [4]  # the others are older than 0.5 s
    assert len(visual_window(t, 2_000_000, 8)) == 0


def test_visual_tokens_pad_at_the_front_and_zero_masked_joints():
    kp = np.ones((2, 22, 3))
    conf = np.ones((2, 22))
    conf[1, 5] = 0.0
    tokens = visual_tokens(kp, conf, np.array([0.1, 0.0]), 4, np.eye(3), np.zeros(3))
    assert tokens.shape == (4, VISUAL_TOKEN_DIM)
    assert not tokens[:2].any() and (tokens[2:, -2] == 1).all()
    assert (tokens[3, 15:18] == 0).all() and (tokens[2, 15:18] == 1).all()


def test_visibility_filter_masks_below_one_half():
    f = VisibilityFilter()
    out = f(0, np.array([0.2, 0.5, 0.9]))
    np.testing.assert_allclose(out, [0.0, 0.0, 0.8])


def test_nearest_sample():
    t = np.array([0, 10, 20])
    assert list(nearest_sample(np.array([-5, 4, 6, 19, 99]), t)) == [0, 0, 1, 2, 2]
    assert list(nearest_sample(np.array([7]), np.array([3]))) == [0]


@pytest.mark.parametrize("size_wh", [(80, 64), (321, 17)])
def test_encoded_image_size_reads_headers_without_decoding(size_wh):
    w, h = size_wh
    jpeg = cv2.imencode(".jpg", np.zeros((h, w, 3), np.uint8))[1].tobytes()
    png = cv2.imencode(".png", np.zeros((h, w), np.uint16))[1].tobytes()
    assert encoded_image_size(jpeg) == size_wh
    assert encoded_image_size(png) == size_wh
    rgb, depth = decode_rgbd(jpeg, png, expected_wh=size_wh)
    assert rgb.shape == (h, w, 3) and depth.shape == (h, w)


def test_a_header_claiming_a_huge_image_is_refused_before_decoding():
    png = bytearray(cv2.imencode(".png", np.zeros((4, 4), np.uint16))[1].tobytes())
    png[16:24] = (60000).to_bytes(4, "big") * 2  # IHDR says 60000 x 60000
    jpeg = cv2.imencode(".jpg", np.zeros((4, 4, 3), np.uint8))[1].tobytes()
    with pytest.raises(ValueError, match="60000x60000"):
        decode_rgbd(jpeg, bytes(png), expected_wh=(4, 4))
    with pytest.raises(ValueError, match="neither"):
        encoded_image_size(b"GIF89a....")
    with pytest.raises(ValueError, match="JPEG"):
        encoded_image_size(b"\xff\xd8\xff\xe0\x00")
