"""The One Euro filter is a first-order low-pass at rest that opens up with speed; two of them in a row smooth
jitter better for the same lag; the devices' poses are smoothed per device and forgotten when lost."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from egoposevr.model.runtime.filters import (
    DevicePoseFilter,
    OneEuroCascade,
    OneEuroFilter,
    WindowSpeed,
    settle_step,
    smoothing_factor,
)

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


def test_a_move_about_a_pivot_splits_into_radial_and_around():
    """A point on an arm that turns about the pivot moves only around it; one that slides straight away moves
    only radially; both at the speed they were moved at."""
    pivot, arm_m, rad_s = np.array([0.0, 1.0, 0.0]), 0.6, 0.5  # 0.3 m/s around
    turning, sliding = WindowSpeed(0.2), WindowSpeed(0.2)
    for i in range(45):
        t_s = i / 90
        turning.push(
            int(t_s * 1e6), pivot + arm_m * np.array([np.sin(rad_s * t_s), np.cos(rad_s * t_s), 0.0])
        )
        sliding.push(int(t_s * 1e6), pivot + np.array([0.0, arm_m + 0.2 * t_s, 0.0]))
    radial, around = turning.about(pivot)
    assert radial < 1e-3 and around == pytest.approx(arm_m * rad_s, rel=0.01)
    radial, around = sliding.about(pivot)
    assert radial == pytest.approx(0.2, rel=1e-6) and around < 1e-6
    once = WindowSpeed(0.2)
    assert once.about(pivot) == (0.0, 0.0)  # nothing pushed
    once.push(0, pivot + 1.0)
    assert once.about(pivot) == (0.0, 0.0)  # no time has passed


def _jerk(x: np.ndarray, dt_s: float) -> float:
    return float(np.abs(np.diff(x, n=3, axis=0)).mean() / dt_s**3)


def test_two_stages_at_twice_the_cutoff_lag_as_one_and_cut_the_jitter():
    """A slow ramp with 1 mm of white noise at 90 Hz (beta 0: fixed cutoffs): the cascade lags the ramp
    like the single stage (the sum of the stages' time constants) and its output's jerk is far lower."""
    dt_us, n = 11_111, 900
    t_us = np.arange(n) * dt_us
    ramp = 0.3 * t_us * 1e-6  # 0.3 m/s
    noisy = ramp + np.random.default_rng(0).normal(0.0, 0.001, n)
    one, two = OneEuroFilter(4.0, 0.0), OneEuroCascade(8.0, 0.0, stages=2)
    out_one = np.array([one(t, np.array([x]))[0] for t, x in zip(t_us, noisy, strict=True)])
    out_two = np.array([two(t, np.array([x]))[0] for t, x in zip(t_us, noisy, strict=True)])
    lag_one, lag_two = (float((ramp - out)[n // 2 :].mean()) for out in (out_one, out_two))
    assert lag_two == pytest.approx(lag_one, rel=0.1)
    assert _jerk(out_two, dt_us * 1e-6) < 0.5 * _jerk(out_one, dt_us * 1e-6)
    assert two.value == pytest.approx([out_two[-1]])
    two.reset()
    assert two.value is None
    with pytest.raises(ValueError, match="stage"):
        OneEuroCascade(4.0, 0.0, stages=0)


def _poses(position_m: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    """(3, 7) poses: every device at position_m (3, 3) with rotations rotvec (3, 3)."""
    return np.concatenate([position_m, Rotation.from_rotvec(rotvec).as_quat()], axis=1)


def test_device_poses_are_smoothed_per_device_and_stay_unit_quaternions():
    rng = np.random.default_rng(1)
    filt = DevicePoseFilter(position=(12.0, 40.0), rotation=(12.0, 10.0))
    rest = _poses(np.array([[0.0, 1.6, 0.0], [-0.3, 1.0, -0.3], [0.3, 1.0, -0.3]]), np.zeros((3, 3)))
    raw_spread, out = [], []
    for i in range(180):
        noisy = rest.copy()
        noisy[:, :3] += rng.normal(0.0, 0.001, (3, 3))
        noisy[:, 3:] = Rotation.from_rotvec(rng.normal(0.0, np.radians(0.3), (3, 3))).as_quat()
        noisy[1, 3:] *= -1.0 if i % 2 else 1.0  # the same rotation from either hemisphere
        raw_spread.append(noisy[:, :3])
        out.append(filt(i * 11_111, noisy, np.ones(3, dtype=bool)))
    out = np.array(out)[30:]
    assert np.allclose(np.linalg.norm(out[..., 3:], axis=-1), 1.0)
    dt_s = 0.011111
    assert _jerk(out[:, :, :3], dt_s) < 0.2 * _jerk(np.array(raw_spread)[30:], dt_s)
    turned_deg = np.degrees(Rotation.from_quat(out[:, 1, 3:]).magnitude())
    assert turned_deg.max() < 1.0  # the flipped quaternions did not average to nonsense (raw: 0.3° per axis)


def test_a_lost_device_comes_back_where_it_is_and_a_pause_forgets_all():
    filt = DevicePoseFilter(position=(12.0, 40.0), rotation=(12.0, 10.0))
    here = _poses(np.zeros((3, 3)), np.zeros((3, 3)))
    there = _poses(np.full((3, 3), 0.1), np.full((3, 3), 0.5))  # 17 cm away: a quick move, not a jump
    tracked = np.ones(3, dtype=bool)
    for i in range(20):
        filt(i * 11_111, here, tracked)
    lost_left = np.array([True, False, True])
    out = filt(20 * 11_111, there, lost_left)
    np.testing.assert_array_equal(out[1], there[1])  # not tracked: as given, and forgotten
    assert np.abs(out[0, :3] - there[0, :3]).min() > 0.01  # tracked: smoothed towards the move
    out = filt(21 * 11_111, there, tracked)
    np.testing.assert_allclose(out[1], there[1])  # back where it is, no glide from where it was lost
    out = filt(21 * 11_111 + 600_000, here, tracked)  # a pause longer than max_gap_s
    np.testing.assert_allclose(out, here)
    out = filt(0, there, tracked)  # time going back
    np.testing.assert_allclose(out, there)


def test_fresh_rows_start_afresh_while_the_others_are_filtered():
    filt = OneEuroFilter(1.0, 0.0)
    filt(0, np.zeros((2, 3)))
    out = filt(10_000, np.ones((2, 3)), fresh=np.array([False, True]))
    np.testing.assert_array_equal(out[1], np.ones(3))  # passed through
    assert (out[0] < 0.1).all()  # smoothed
    out = filt(20_000, np.full((2, 3), 2.0))
    assert (out[1] > 1.0).all() and (out[1] < 2.0).all()  # filtered again, from where it restarted


def test_a_device_that_jumps_starts_again_where_it_lands_and_says_so():
    """A recentred space or a replay that starts over moves a device metres in one sample: no glide across
    the room. A fast hand (5 m/s) is not a jump."""
    filt = DevicePoseFilter(position=(12.0, 40.0), rotation=(12.0, 10.0), jump_m=0.25)
    tracked, t_us = np.ones(3, dtype=bool), 0
    position = np.zeros((3, 3))
    for _ in range(30):  # the right hand moves at 5 m/s
        t_us += 11_111
        position[2, 0] += 5.0 * 0.011111
        out = filt(t_us, _poses(position, np.zeros((3, 3))), tracked)
        assert not filt.jumped.any()
    assert abs(out[2, 0] - position[2, 0]) > 0.005  # smoothed, so lagging a little
    landed = position + np.array([3.0, 0.0, -2.0])  # the whole space recentred
    out = filt(t_us + 11_111, _poses(landed, np.zeros((3, 3))), tracked)
    assert filt.jumped.all()
    np.testing.assert_allclose(out[:, :3], landed)


def test_each_update_is_the_one_euro_statement_bit_for_bit():
    """The compiled step against the filter written out in numpy (Casiez et al.'s update, smoothing_factor's
    α), over irregular times, repeated stamps and fresh rows: the same bits, not merely close ones."""
    rng = np.random.default_rng(5)
    filt = OneEuroFilter(min_cutoff_hz=1.7, beta=0.6, d_cutoff_hz=1.2)
    x_hat = dx_hat = None
    t_us = last_us = 0
    for i in range(300):
        t_us += int(rng.choice([0, 3_000, 11_111, 40_000]))
        x = rng.normal(size=(22, 3))
        fresh = rng.random(22) < 0.05
        got = filt(t_us, x, fresh)
        if x_hat is None:
            x_hat, dx_hat, last_us = x.copy(), np.zeros_like(x), t_us
        else:
            dt_s = (t_us - last_us) * 1e-6
            if dt_s > 0:
                dx_hat = dx_hat + smoothing_factor(dt_s, 1.2) * ((x - x_hat) / dt_s - dx_hat)
                x_hat = x_hat + smoothing_factor(dt_s, 1.7 + 0.6 * np.abs(dx_hat)) * (x - x_hat)
                last_us = t_us
            x_hat[fresh], dx_hat[fresh] = x[fresh], 0.0
        np.testing.assert_array_equal(got, x_hat, err_msg=f"sample {i}")


def test_a_held_point_settles_at_its_speed_and_one_far_from_its_mean_closes_the_gap_past_the_slack():
    gap_m = np.array([[0.0, 0.0, 0.10], [0.0, 0.05, 0.0]])  # the longest row 10 cm
    slow = settle_step(gap_m, 0.01, 0.0025)
    assert np.linalg.norm(slow, axis=1).max() == pytest.approx(0.0025 * 0.01)
    np.testing.assert_allclose(
        slow / np.linalg.norm(slow[0]), gap_m / 0.10
    )  # the rows keep their proportions
    fast = settle_step(gap_m, 0.01, 0.0025, reseat=(0.04, 0.5))
    assert np.linalg.norm(fast, axis=1).max() == pytest.approx((0.10 - 0.04) / 0.5 * 0.01)
    within = gap_m * 0.3  # 3 cm: inside the slack, as slow as without
    np.testing.assert_allclose(
        settle_step(within, 0.01, 0.0025, reseat=(0.04, 0.5)), settle_step(within, 0.01, 0.0025)
    )
    np.testing.assert_array_equal(
        settle_step(gap_m * 1e-4, 0.01, 0.0025, reseat=(0.04, 0.5)), gap_m * 1e-4
    )  # reached


def test_the_head_relative_filter_keeps_a_walkers_body_on_the_headset_where_the_anchored_one_trails():
    """Pipeline(head_relative_filter=True): the joints' filter smooths the pose relative to the head and the head
    goes where the headset puts it, so a walker's served head joint (bundled ``hmd``, no KPO to pull it back)
    stays on the tracked one; the filter of the head-anchored pose trails it by its lag. The served joints are
    FK of the served rotations either way."""
    from egoposevr.model.rig import joints_from_devices
    from egoposevr.model.runtime.loading import LoadedModel
    from egoposevr.model.runtime.pipeline import Pipeline
    from egoposevr.model.skeleton import forward_kinematics, rest_offsets
    from egoposevr.model.synth.headset import simulate_headset
    from egoposevr.model.synth.procedural import generate
    from egoposevr.model.weights import WEIGHTS_DIR

    rng = np.random.default_rng(2)
    track = simulate_headset(generate("walk", 4.0, 60.0, rng), 90.0, rng)
    model = LoadedModel.load(WEIGHTS_DIR / "hmd.onnx")
    tracked = joints_from_devices(track.poses, model.info.rig_offsets_m)[0][:, 0]
    trail_cm = {}
    for relative in (False, True):
        pipeline = Pipeline(model, head_relative_filter=relative)
        results = [
            pipeline.push_hmd(int(t), track.poses[i], track.valid[i]) for i, t in enumerate(track.t_us)
        ]
        heads = np.array([r.joints[15] for r in results])
        trail_cm[relative] = float(np.median(100 * np.linalg.norm(heads - tracked, axis=-1)[90:]))
        last = results[-1]
        fk, _ = forward_kinematics(last.local_rot, last.transl, rest_offsets(pipeline.served_scale.scale))
        assert np.allclose(fk, last.joints, atol=1e-6)
    assert trail_cm[True] < 1.0 and trail_cm[False] > 2 * trail_cm[True], trail_cm
