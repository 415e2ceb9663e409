"""Body proportions from headset statistics: the running statistics, the regression and its fallback."""

import numpy as np
import pytest

from egoposevr.model.body import (
    FEATURE_NAMES,
    STANDING_HEAD_HEIGHT_M,
    BodyCalibrator,
    BodyRegression,
    BodyStatistics,
    fit_body_regression,
    sequence_features,
)
from egoposevr.model.skeleton import NUM_JOINTS

ALL = np.ones(3, dtype=bool)


def tracked(head_y: float, left: tuple[float, float, float], right: tuple[float, float, float]) -> np.ndarray:
    """(3, 3) head joint at (0, head_y, 0), wrists relative to it."""
    head = np.array([0.0, head_y, 0.0])
    return np.stack([head, head + left, head + right])


def test_statistics_are_running_maxima_relative_to_the_head():
    stats = BodyStatistics()
    stats.push(tracked(1.6, (0.3, -0.6, 0.0), (-0.3, -0.6, 0.0)), ALL)
    stats.push(tracked(1.5, (0.0, 0.4, 0.0), (0.6, 0.0, -0.2)), ALL)  # arm raised, arm out sideways
    assert stats.height_m == pytest.approx(1.6)
    assert stats.raise_m == pytest.approx(0.4)
    assert stats.reach_m == pytest.approx(np.hypot(0.3, 0.6))  # the hanging arm reached farther
    assert stats.side_m == pytest.approx(np.hypot(0.6, 0.2))
    assert stats.hang_m == pytest.approx(0.6)  # the second sample was not standing (1.5 < 0.95 * 1.6)
    f = stats.features()
    assert f.shape == (len(FEATURE_NAMES),)
    assert f[0] == pytest.approx(np.log(1.6)) and f[1] == pytest.approx(np.hypot(0.3, 0.6) / 1.6)


def test_untracked_devices_do_not_count():
    stats = BodyStatistics()
    assert not stats.push(tracked(1.7, (0, 0, 0), (0, 0, 0)), np.array([False, True, True]))
    assert not stats.seen
    stats.push(
        tracked(1.6, (5.0, 0, 0), (0.2, -0.5, 0)), np.array([True, False, True])
    )  # left glitch ignored
    assert stats.reach_m == pytest.approx(np.hypot(0.2, 0.5))


def test_push_reports_only_moves_of_5_mm():
    stats = BodyStatistics()
    sample = tracked(1.6, (0.3, -0.6, 0.0), (-0.3, -0.6, 0.0))
    assert stats.push(sample, ALL)
    assert not stats.push(sample + np.array([0, 0.002, 0]), ALL)
    assert stats.push(sample + np.array([0, 0.01, 0]), ALL)


def test_fit_recovers_a_linear_log_scale_relation():
    rng = np.random.default_rng(0)
    features = rng.uniform([0.3, 0.3, 0.0, 0.2, 0.2], [0.6, 0.5, 0.3, 0.5, 0.4], (40, 5))
    true_coef = rng.normal(0, 0.2, (6, NUM_JOINTS))
    scales = np.exp(np.c_[np.ones(40), features] @ true_coef)
    regression = fit_body_regression(zip(features, scales, strict=True))
    assert np.allclose(regression.bone_scale(features[3]), scales[3], rtol=0.02)


def test_features_outside_the_training_range_are_clipped():
    regression = BodyRegression(
        np.r_[np.zeros((1, NUM_JOINTS)), np.ones((5, NUM_JOINTS))], np.zeros(5), np.full(5, 0.1)
    )
    assert np.allclose(regression.bone_scale(np.full(5, 100.0)), np.exp(0.5))


def test_regression_json_round_trip_and_refusals():
    regression = BodyRegression(np.full((6, NUM_JOINTS), 0.01), np.zeros(5), np.ones(5))
    again = BodyRegression.from_json(regression.to_json())
    assert np.allclose(again.coef, regression.coef)
    with pytest.raises(ValueError, match="features"):
        BodyRegression.from_json({"features": ["height"], "coef": [], "feature_min": [], "feature_max": []})
    bad = regression.to_json() | {"coef": [[1.0]]}
    with pytest.raises(ValueError, match="coef"):
        BodyRegression.from_json(bad)
    nan = regression.to_json() | {"feature_min": [float("nan")] * 5}
    with pytest.raises(ValueError, match="non-finite"):
        BodyRegression.from_json(nan)


def test_without_a_regression_the_body_scales_with_height_only():
    calibrator = BodyCalibrator()
    assert np.allclose(calibrator.bone_scale, 1.0)
    calibrator.push(tracked(STANDING_HEAD_HEIGHT_M * 1.1, (0.3, -0.6, 0), (-0.3, -0.6, 0)), ALL)
    assert np.allclose(calibrator.bone_scale, 1.1)
    calibrator.push(tracked(3.0, (0.3, -0.6, 0), (-0.3, -0.6, 0)), ALL)  # standing on a table: clipped
    assert np.allclose(calibrator.bone_scale, 1.25)


def test_sequence_features_equal_the_streamed_ones():
    rng = np.random.default_rng(1)
    joints = rng.normal([0, 1.5, 0], 0.3, (50, 3, 3))
    valid = rng.uniform(size=(50, 3)) > 0.2
    stats = BodyStatistics()
    for x, ok in zip(joints, valid, strict=True):
        stats.push(x, ok)
    assert np.allclose(sequence_features(joints, valid), stats.features())
