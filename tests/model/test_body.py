"""Body size from the headset: the highest head sets the scale, within its range."""

import numpy as np
import pytest

from egoposevr.model.body import SCALE_RANGE, STANDING_HEAD_HEIGHT_M, BodyCalibrator

ALL = np.ones(3, dtype=bool)


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
