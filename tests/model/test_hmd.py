"""HMD features match analytic motion exactly, whatever the timestamps do, and degrade sanely on dropouts."""

import numpy as np
import pytest

from egoposevr.model import hmd
from egoposevr.model.rotations import axis_angle_to_matrix, matrix_to_quat_xyzw, matrix_to_sixd

S = hmd.FEATURE_SLICES
RNG = np.random.default_rng(5)
# Constant linear (m/s) and body-frame angular (rad/s) velocity per device: head, left, right.
P0 = np.array([[0.1, 1.7, 0.2], [-0.3, 1.1, -0.2], [0.3, 1.0, -0.3]])
V = np.array([[0.5, 0.0, -1.2], [1.5, -0.4, 0.3], [-2.0, 0.8, 0.0]])
R0 = axis_angle_to_matrix(np.array([[0.0, 0.4, 0.0], [0.3, -0.2, 0.1], [-0.5, 0.0, 1.0]]))
W = np.array([[0.2, 1.5, 0.0], [3.0, -1.0, 2.0], [-4.0, 0.5, 0.0]])


def motion_at(t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Analytic device poses at t_s: positions (3, 3), rotations (3, 3, 3), and as wire poses (3, 7)."""
    pos = P0 + V * t_s
    rot = R0 @ axis_angle_to_matrix(W * t_s)
    return pos, rot, np.concatenate([pos, matrix_to_quat_xyzw(rot)], axis=1)


def jittered_times_us(rate_hz: float, seconds: float, jitter_s: float, drop: float) -> np.ndarray:
    t = np.arange(0.0, seconds, 1.0 / rate_hz)
    t = t + RNG.uniform(-jitter_s, jitter_s, size=t.shape)
    keep = RNG.random(t.shape) >= drop
    keep[0] = True
    return np.round(np.sort(t[keep] + 0.5) * 1e6).astype(np.int64)


def expected_features(t_us: int) -> np.ndarray:
    pos, rot, _ = motion_at(t_us * 1e-6)
    x = np.empty(hmd.FEATURE_DIM)
    for i, dev in enumerate(hmd.DEVICES):
        x[S[f"{dev}_pos"]] = pos[i]
        x[S[f"{dev}_rot6d"]] = matrix_to_sixd(rot[i])
        x[S[f"{dev}_vel"]] = V[i]
        x[S[f"{dev}_angvel6d"]] = matrix_to_sixd(axis_angle_to_matrix(W[i] * hmd.DT_REF_S))
    for c, dev in ((1, "left"), (2, "right")):
        x[S[f"{dev}_in_head_pos"]] = rot[0].T @ (pos[c] - pos[0])
        x[S[f"{dev}_in_head_rot6d"]] = matrix_to_sixd(rot[0].T @ rot[c])
    return x


def features_for(times_us, valid=None):
    poses = np.stack([motion_at(t * 1e-6)[2] for t in times_us])
    return hmd.hmd_features(times_us, poses, valid)


def test_layout_covers_72_dims_once():
    covered = np.zeros(hmd.FEATURE_DIM, dtype=int)
    for sl in S.values():
        covered[sl] += 1
    assert (covered == 1).all()


@pytest.mark.parametrize("rate_hz", [60, 72, 90, 120])
def test_constant_velocity_motion_with_jitter_and_drops_is_exact(rate_hz):
    times = jittered_times_us(rate_hz, seconds=2.0, jitter_s=0.3 / rate_hz, drop=0.2)
    x = features_for(times)
    expected = np.stack([expected_features(t) for t in times])
    np.testing.assert_allclose(x[1:], expected[1:], atol=1e-4)  # sample 0 has no velocity yet
    np.testing.assert_allclose(x[0, S["head_vel"]], 0.0)


def test_features_do_not_depend_on_the_headset_rate():
    at_60 = features_for(np.arange(0, 1_000_000, 16_667)[:40])
    at_120 = features_for(np.arange(0, 1_000_000, 8_333)[:80])
    np.testing.assert_allclose(at_60[-1], expected_features(16_667 * 39), atol=1e-4)
    common = features_for(np.array([0, 8_333, 16_667]))
    np.testing.assert_allclose(common[2], at_60[1], atol=1e-9)
    assert at_120.shape == (80, 72)


def test_near_coincident_timestamps_difference_against_an_older_sample():
    # The 4th sample was taken 0.8 ms after the 3rd but stamped 0.3 ms late: differencing over 0.8 ms would
    # be off by ~40 %; the older reference (11.9 ms back) keeps the error near 2.5 %.
    true_us = np.array([0, 11_111, 22_222, 23_000, 33_333])
    stamped_us = true_us + np.array([0, 0, 0, 300, 0])
    poses = np.stack([motion_at(t * 1e-6)[2] for t in true_us])
    x = hmd.hmd_features(stamped_us, poses)
    np.testing.assert_allclose(x[3, S["left_vel"]], V[1], rtol=0.05)
    np.testing.assert_allclose(x[2, S["left_vel"]], V[1], atol=1e-9)


def test_repeated_or_backwards_timestamp_keeps_velocity_and_stays_finite():
    extractor = hmd.HmdFeatureExtractor()
    for t in (0, 11_111, 22_222):
        extractor.push(t, motion_at(t * 1e-6)[2], [True] * 3)
    for t in (22_222, 15_000):
        x = extractor.push(t, motion_at(t * 1e-6)[2], [True] * 3)
        assert np.isfinite(x).all()
        np.testing.assert_allclose(x[S["head_vel"]], V[0], atol=1e-9)
    x = extractor.push(33_333, motion_at(0.033333)[2], [True] * 3)
    np.testing.assert_allclose(x[S["head_vel"]], V[0], atol=1e-9)


def test_long_gap_resets_velocity_to_zero():
    x = features_for(np.array([0, 11_111, 22_222, 22_222 + int(hmd.MAX_GAP_S * 1e6) + 1000]))
    np.testing.assert_allclose(x[2, S["right_vel"]], V[2], atol=1e-9)
    np.testing.assert_allclose(x[3, S["right_vel"]], 0.0)
    np.testing.assert_allclose(x[3, S["right_angvel6d"]], [1, 0, 0, 0, 1, 0])


def test_lost_controller_follows_the_head_and_recovers():
    times = np.arange(0, 20) * 11_111
    valid = np.ones((20, 3), dtype=bool)
    valid[8:12, 1] = False  # left controller lost for four samples
    x = features_for(times, valid)
    held = x[7, S["left_in_head_pos"]]
    for i in range(8, 12):
        np.testing.assert_allclose(x[i, S["left_in_head_pos"]], held, atol=1e-12)
        np.testing.assert_allclose(x[i, S["left_vel"]], 0.0)
        _, rot, _ = motion_at(times[i] * 1e-6)
        head_pos = x[i, S["head_pos"]]
        np.testing.assert_allclose(x[i, S["left_pos"]], head_pos + rot[0] @ held, atol=1e-12)
    np.testing.assert_allclose(x[12:], np.stack([expected_features(t) for t in times[12:]]), atol=1e-4)


def test_untracked_device_may_send_an_all_zero_pose():
    extractor = hmd.HmdFeatureExtractor()
    poses = motion_at(0.0)[2]
    poses[2] = 0.0
    x = extractor.push(0, poses, [True, True, False])
    assert np.isfinite(x).all()
    np.testing.assert_allclose(x[S["right_in_head_pos"]], hmd.DEFAULT_CONTROLLER_IN_HEAD_POS_M[1])


def test_never_tracked_controller_sits_at_the_default_pose():
    valid = np.ones((3, 3), dtype=bool)
    valid[:, 2] = False
    x = features_for(np.array([0, 11_111, 22_222]), valid)
    np.testing.assert_allclose(
        x[:, S["right_in_head_pos"]], np.tile(hmd.DEFAULT_CONTROLLER_IN_HEAD_POS_M[1], (3, 1))
    )


def test_streaming_equals_batch():
    times = jittered_times_us(90, seconds=0.5, jitter_s=0.004, drop=0.3)
    valid = RNG.random((len(times), 3)) > 0.1
    poses = np.stack([motion_at(t * 1e-6)[2] for t in times])
    extractor = hmd.HmdFeatureExtractor()
    streamed = np.stack([extractor.push(t, p, v) for t, p, v in zip(times, poses, valid, strict=True)])
    np.testing.assert_array_equal(streamed, hmd.hmd_features(times, poses, valid))


def test_bad_shapes_and_nan_are_refused():
    extractor = hmd.HmdFeatureExtractor()
    with pytest.raises(ValueError, match=r"poses must be \(3, 7\)"):
        extractor.push(0, np.zeros((3, 6)), [True] * 3)
    with pytest.raises(ValueError, match="finite"):
        extractor.push(0, np.full((3, 7), np.nan), [True] * 3)


def test_tracking_state_says_which_device_is_lost_and_for_how_long():
    from egoposevr.model.hmd import AGE_CAP_S, TrackingState, tracking_features

    state = TrackingState()
    t0 = 5_000_000
    assert np.allclose(
        state.push(t0, np.array([True, False, True])), [1, 0, 1, 0, 1, 0]
    )  # never seen: capped
    assert np.allclose(
        state.push(t0 + 500_000, np.array([True, True, False])), [1, 1, 0, 0, 0, 0.5 / AGE_CAP_S]
    )
    late = state.push(t0 + 10_000_000, np.array([False, True, False]))
    assert np.allclose(late, [0, 1, 0, 1, 0, 1])  # ages stop at the cap
    t_us = t0 + np.arange(4) * 100_000
    valid = np.array([[1, 1, 1], [1, 0, 1], [1, 0, 1], [1, 1, 1]], dtype=bool)
    batch = tracking_features(t_us, valid)
    assert batch.shape == (4, 6) and np.allclose(batch[:, 4], [0, 0.05, 0.1, 0])
