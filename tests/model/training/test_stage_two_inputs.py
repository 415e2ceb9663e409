"""Stage 2's keypoint inputs: the encoder's mistakes can be made larger, and only larger."""

import numpy as np
import pytest

pytest.importorskip("torch")
from egoposevr.model.inputs import normalise_uv
from egoposevr.model.training.train import frame_keypoints


def _projected(points_cam_m: np.ndarray, intrinsics: list[float], size_wh: tuple[int, int]):
    """Camera-frame points (K, J, 3) -> what a perfect encoder outputs: uv (K, J, 2), depth_m (K, J)."""
    fx, fy, cx, cy = intrinsics
    px = np.stack(
        [
            points_cam_m[..., 0] / points_cam_m[..., 2] * fx + cx,
            points_cam_m[..., 1] / points_cam_m[..., 2] * fy + cy,
        ],
        -1,
    )
    return normalise_uv(px, size_wh), points_cam_m[..., 2]


def test_a_keypoint_error_gain_scales_each_keypoints_error_in_the_world() -> None:
    rng = np.random.default_rng(3)
    k, j = 4, 22
    camera = {"width": 160, "height": 128, "intrinsics": [90.0, 90.0, 80.0, 64.0],
              "cam_from_head": np.eye(4)[[0, 2, 1, 3]].ravel().tolist()}  # fmt: skip
    truth_cam = np.stack(
        [rng.uniform(-0.4, 0.4, (k, j)), rng.uniform(-0.3, 0.3, (k, j)), rng.uniform(0.5, 1.5, (k, j))], -1
    )
    guessed_cam = truth_cam + rng.normal(0.0, 0.05, truth_cam.shape)
    heads = np.zeros((8, 7))
    heads[:, :3] = rng.normal(0, 1, 3)
    heads[:, 3:] = [0.0, np.sin(0.4), 0.0, np.cos(0.4)]  # turned 46 degrees about y
    frame_t_us, hmd_t_us = np.arange(k) * 33_333, np.arange(8) * 16_666
    size = (camera["width"], camera["height"])
    conf = np.ones((k, j))

    def world(points_cam, truth=None, gain=1.0):
        uv, depth_m = _projected(points_cam, camera["intrinsics"], size)
        return frame_keypoints(uv, depth_m, conf, frame_t_us, camera, hmd_t_us, heads, truth, gain)[0]

    truth_world, guessed_world = world(truth_cam), world(guessed_cam)
    np.testing.assert_allclose(world(guessed_cam, truth_cam, 1.0), guessed_world)
    np.testing.assert_allclose(
        world(guessed_cam, truth_cam, 2.5) - truth_world, 2.5 * (guessed_world - truth_world), atol=1e-9
    )
    np.testing.assert_allclose(
        world(guessed_cam, truth_cam, 0.0), truth_world, atol=1e-9
    )  # a perfect encoder
    np.testing.assert_allclose(
        world(truth_cam, truth_cam, 3.0), truth_world, atol=1e-9
    )  # no mistake to scale
