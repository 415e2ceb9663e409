"""Body size: the highest head sets the scale, within its range; legs the camera sees take their length."""

import numpy as np
import pytest

from egoposevr.model.body import MIN_VISUAL_SAMPLES, SCALE_RANGE, STANDING_HEAD_HEIGHT_M, BodyCalibrator
from egoposevr.model.skeleton import forward_kinematics, rest_offsets

ALL = np.ones(3, dtype=bool)
RNG = np.random.default_rng(4)


def head_at(y: float) -> np.ndarray:
    return np.array([[0.0, y, 0.0], [0.3, y - 0.6, 0.0], [-0.3, y - 0.6, 0.0]])


def test_the_highest_head_sets_the_scale():
    body = BodyCalibrator()
    assert np.allclose(body.bone_scale, 1.0)
    assert body.push(head_at(1.1 * STANDING_HEAD_HEIGHT_M), ALL)
    assert np.allclose(body.bone_scale, 1.1)
    assert not body.push(head_at(0.9), ALL)  # crouching does not shrink the body
    assert not body.push(head_at(1.1 * STANDING_HEAD_HEIGHT_M + 0.002), ALL)  # under the 5 mm step
    assert np.allclose(body.bone_scale, 1.1)


@pytest.mark.parametrize(("height_m", "scale"), [(3.0, SCALE_RANGE[1]), (0.5, SCALE_RANGE[0])])
def test_implausible_heights_are_clipped(height_m, scale):
    body = BodyCalibrator()
    body.push(head_at(height_m), ALL)
    assert np.allclose(body.bone_scale, scale)


def test_an_untracked_headset_does_not_count():
    body = BodyCalibrator()
    assert not body.push(head_at(1.9), np.array([False, True, True]))
    assert body.highest_head_m == 0.0


def test_legs_seen_by_the_camera_take_their_measured_length_and_the_rest_keeps_the_height_scale():
    body = BodyCalibrator()
    body.push(head_at(1.1 * STANDING_HEAD_HEIGHT_M), ALL)
    legs = rest_offsets(np.where(np.isin(np.arange(22), [4, 5, 7, 8]), 1.2, 1.0))  # long thighs and shins
    keypoints, _ = forward_kinematics(np.broadcast_to(np.eye(3), (22, 3, 3)), np.zeros(3), legs)
    visible = np.ones(22, dtype=bool)
    visible[[4, 7, 10]] = False  # only the right leg in view: the left one follows it
    changed = [
        body.push_visual(keypoints + RNG.normal(scale=0.005, size=keypoints.shape), visible)
        for _ in range(60)
    ]
    assert any(changed) and not any(changed[: MIN_VISUAL_SAMPLES - 1])  # nothing before enough sightings
    np.testing.assert_allclose(body.bone_scale[[4, 5, 7, 8]], 1.2, atol=0.02)
    np.testing.assert_allclose(body.bone_scale[[10, 11]], 1.0, atol=0.02)  # the feet as measured
    np.testing.assert_allclose(body.bone_scale[[3, 16, 18, 20]], 1.1)  # spine and arms: the height scale


def test_a_later_height_keeps_the_measured_legs():
    body = BodyCalibrator()
    keypoints, _ = forward_kinematics(np.broadcast_to(np.eye(3), (22, 3, 3)), np.zeros(3), rest_offsets())
    for _ in range(MIN_VISUAL_SAMPLES):
        body.push_visual(keypoints, np.ones(22, dtype=bool))
    body.push(head_at(1.2 * STANDING_HEAD_HEIGHT_M), ALL)
    np.testing.assert_allclose(body.bone_scale[[4, 7]], 1.0)
    np.testing.assert_allclose(body.bone_scale[0:4], 1.2)
