"""The One Euro filter is a first-order low-pass at rest that opens up with speed."""

import numpy as np
import pytest

from egoposevr.model.runtime.filters import OneEuroFilter, WindowSpeed, smoothing_factor

DT_US = 10_000  # 100 Hz


def step_response(filt: OneEuroFilter, n: int, shape=(22, 3)) -> np.ndarray:
    """Output sequence (n, *shape) for a unit step at sample 1."""
    out = [filt(0, np.zeros(shape))]
    out += [filt(i * DT_US, np.ones(shape)) for i in range(1, n)]
    return np.stack(out)


def test_first_sample_passes_through():
    x = np.arange(6.0).reshape(2, 3)
    np.testing.assert_array_equal(OneEuroFilter()(123, x), x)


def test_step_response_with_beta_zero_is_the_exact_first_order_lowpass():
    y = step_response(OneEuroFilter(min_cutoff_hz=2.0, beta=0.0), 50)
    alpha = smoothing_factor(DT_US * 1e-6, 2.0)
    expected = 1.0 - (1.0 - alpha) ** np.arange(50)
    np.testing.assert_allclose(y[:, 0, 0], expected, atol=1e-12)
    assert np.all(np.diff(y[:, 5, 1]) > 0) and y.max() < 1.0  # monotone, no overshoot


def test_time_constant_matches_the_cutoff():
    # After one time constant tau = 1 / (2 pi fc) a first-order low-pass has covered 1 - 1/e of a step.
    fc = 1.0
    dt_us = 100  # fine steps approximate continuous time
    filt = OneEuroFilter(min_cutoff_hz=fc)
    filt(0, np.zeros(1))
    tau_us = int(1e6 / (2 * np.pi * fc))
    y = [filt(t, np.ones(1)) for t in range(dt_us, tau_us + 1, dt_us)][-1]
    assert y[0] == pytest.approx(1 - np.exp(-1), abs=2e-3)


def test_speed_coefficient_reduces_lag():
    slow = step_response(OneEuroFilter(min_cutoff_hz=1.0, beta=0.0), 20)
    fast = step_response(OneEuroFilter(min_cutoff_hz=1.0, beta=0.5), 20)
    assert (fast[1:, 0, 0] > slow[1:, 0, 0]).all()
    assert fast.max() <= 1.0 + 1e-12


def test_irregular_timestamps_follow_the_time_not_the_sample_count():
    a = OneEuroFilter(min_cutoff_hz=3.0)
    b = OneEuroFilter(min_cutoff_hz=3.0)
    a(0, np.zeros(3)), b(0, np.zeros(3))
    one_big = a(20_000, np.ones(3))
    b(10_000, np.ones(3))
    two_small = b(20_000, np.ones(3))
    # Same elapsed time, similar progress (exactly equal only in the continuous limit).
    assert one_big[0] == pytest.approx(two_small[0], rel=0.15)


def test_repeated_timestamp_returns_the_current_estimate():
    filt = OneEuroFilter()
    filt(0, np.zeros(2))
    y = filt(10_000, np.ones(2))
    np.testing.assert_array_equal(filt(10_000, np.full(2, 5.0)), y)
    np.testing.assert_array_equal(filt(5_000, np.full(2, 5.0)), y)


def test_elements_are_filtered_independently():
    filt = OneEuroFilter(min_cutoff_hz=1.0, beta=1.0)
    filt(0, np.zeros(2))
    y = filt(10_000, np.array([0.0, 10.0]))
    assert y[0] == 0.0 and y[1] > 0.0


def test_reset_and_bad_input():
    filt = OneEuroFilter()
    filt(0, np.zeros(3))
    with pytest.raises(ValueError, match="shape changed"):
        filt(10_000, np.zeros(4))
    with pytest.raises(ValueError, match="finite"):
        filt(10_000, np.array([np.nan, 0, 0]))
    filt.reset()
    np.testing.assert_array_equal(filt(20_000, np.ones(4)), np.ones(4))
    with pytest.raises(ValueError, match="min_cutoff_hz"):
        OneEuroFilter(min_cutoff_hz=0.0)


def test_a_window_speed_is_the_move_over_the_window_not_the_per_sample_jitter():
    rng = np.random.default_rng(0)
    speed = WindowSpeed(0.2)
    for i in range(90):  # 1 s at 90 Hz: 0.5 m/s along x, with 5 mm of jitter per sample
        t_us = i * 11_111
        measured = speed.push(t_us, np.array([0.5 * t_us * 1e-6, 0.0, 0.0]) + rng.normal(0.0, 0.005, 3))
    assert measured == pytest.approx(0.5, abs=0.06)  # per-sample differences alone would read ~1 m/s
    assert 0.2 <= speed.span_s < 0.2 + 0.012 and speed.step_s == pytest.approx(0.011111)
