"""Body-behaviour measures on synthetic sequences whose answers are known."""

import numpy as np
import pytest

from egoposevr.model.skeleton import FOOT_JOINT_HEIGHT_M, LOWER_BODY, REST_JOINTS_M
from egoposevr.model.training.plausibility import (
    WARM_UP_S,
    contact_timing,
    contacts,
    plausibility,
    still_stretches,
    summarize_plausibility,
)

RATE_HZ = 90.0


def standing(seconds: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """A body standing still with its feet flat on the floor: joints (N, J, 3), t_us (N,)."""
    n = round(seconds * RATE_HZ)
    pose = REST_JOINTS_M - [0.0, REST_JOINTS_M[[10, 11], 1].min() - FOOT_JOINT_HEIGHT_M, 0.0]
    pose[[10, 11], 1] = FOOT_JOINT_HEIGHT_M  # both feet exactly flat
    return np.repeat(pose[None], n, axis=0), (np.arange(n) * 1e6 / RATE_HZ).astype(np.int64)


def test_step_timing_counts_to_the_next_contact_change_and_from_the_last():
    """A foot down 0.5 s, up 0.25 s, down again to the end; the other foot down throughout. Times in units
    of the 1 s horizon, 1 where no change lies ahead (or behind)."""
    t_us = np.arange(0, 1_500_000, 250_000)  # 0, 0.25, ... 1.25 s
    left = np.array([1, 1, 0, 1, 1, 1], bool)
    timing = contact_timing(np.stack([left, np.ones(6, bool)], axis=1), t_us, horizon_s=1.0)
    np.testing.assert_allclose(timing[:, 0, 0], [0.5, 0.25, 0.25, 1.0, 1.0, 1.0])  # until the next change
    np.testing.assert_allclose(timing[:, 0, 1], [1.0, 1.0, 0.0, 0.0, 0.25, 0.5])  # since the last
    assert (timing[:, 1] == 1.0).all()  # never changes: a still stance
    half = contact_timing(left[:, None], t_us, horizon_s=0.25)  # clipped at the horizon
    np.testing.assert_allclose(half[:, 0, 0], [1.0, 1.0, 1.0, 1.0, 1.0, 1.0])
    np.testing.assert_allclose(half[:, 0, 1], [1.0, 1.0, 0.0, 0.0, 1.0, 1.0])


def test_a_standing_truth_is_in_contact_and_still_throughout():
    truth, t_us = standing()
    assert contacts(truth, t_us).all()
    assert still_stretches(truth, t_us) == [slice(0, len(t_us))]


def test_a_planted_foot_that_jitters_by_millimetres_at_uneven_sample_times_stays_in_contact():
    """A captured planted foot moves a few millimetres from sample to sample and the headset's samples come a
    few percent early or late: read from one sample to the next, that is over the contact speed."""
    rng = np.random.default_rng(0)
    truth, t_us = standing()
    truth[:, [10, 11]] += rng.normal(0.0, 0.003, (len(t_us), 2, 3)) * [1.0, 0.0, 1.0]
    t_us = t_us + rng.integers(-400, 400, len(t_us))
    assert contacts(truth, t_us).all()


def test_a_stance_broken_for_a_few_samples_stays_one_stance_and_a_swing_that_grazes_the_floor_stays_a_swing():
    """One foot down 0.5 s (lifted over the contact height for 3 samples in its middle), up 0.4 s (down for 3
    samples in its middle), down 0.5 s; 3 samples are 33 ms at 90 Hz. A stream that begins with a foot just
    before it lifts keeps that short contact: the stream cut it, not its noise."""
    truth, t_us = standing(seconds=1.4)
    up = np.zeros(len(t_us), bool)
    up[45:81] = True  # the swing: 0.5 s to 0.9 s
    up[21:24] = True  # a blip in the first stance
    up[62:65] = False  # the swing touches down for 3 samples
    truth[up, 10, 1] = FOOT_JOINT_HEIGHT_M + 0.08
    expected = np.ones(len(t_us), bool)
    expected[45:81] = False
    np.testing.assert_array_equal(contacts(truth, t_us)[:, 0], expected)
    assert contacts(truth, t_us)[:, 1].all()
    truth[3:, 11, 1] = FOOT_JOINT_HEIGHT_M + 0.08  # the right foot lifts after its stream's third sample
    assert contacts(truth, t_us)[:, 1].tolist() == [True] * 3 + [False] * (len(t_us) - 3)


def test_a_served_foot_sliding_at_10_cm_s_skates_10_cm_s_and_served_feet_2_cm_up_float_2_cm():
    truth, t_us = standing()
    served = truth.copy()
    served[:, 10, 0] += 0.10 * (t_us - t_us[0]) * 1e-6  # the left foot slides along x
    served[:, [10, 11], 1] += 0.02
    result = summarize_plausibility([plausibility(served, truth, t_us)])
    assert result["foot_skate_cm_s"] == pytest.approx(5.0, abs=0.01)  # one foot of two at 10 cm/s
    assert result["floor_float_cm"] == pytest.approx(2.0) and result["floor_penetration_cm"] == 0.0


def test_legs_drifting_while_the_truth_stands_still_leak_their_mean_displacement():
    truth, t_us = standing()
    served = truth.copy()
    served[:, [4, 5, 7, 8, 10, 11], 2] += np.linspace(0.0, 0.06, len(t_us))[:, None]  # the legs wander 6 cm
    leak = summarize_plausibility([plausibility(served, truth, t_us)])["leg_leakage_cm"]
    # six of the nine lower-body joints move, by 3 cm on average over the stretch
    assert leak == pytest.approx(6 / 9 * 3.0, rel=0.02)


def test_legs_that_move_to_the_truth_leak_but_do_not_wander_and_legs_that_leave_it_wander_as_far():
    """Wander is leakage less what brought the legs nearer the truth: a wrong first guess corrected towards
    the truth wanders 0, a drift away from the truth wanders as far as it leaks, and one round it (the same
    distance from the truth) does too."""
    truth, t_us = standing(seconds=3.0)
    ramp = np.clip((t_us - t_us[0]) * 1e-6 - 1.0, 0.0, 1.0)[:, None]  # 0 until 1 s, then 1 by 2 s

    def measured(served: np.ndarray) -> tuple[float, float]:
        result = summarize_plausibility([plausibility(served, truth, t_us)])
        return result["leg_leakage_cm"], result["leg_wander_cm"]

    corrected = truth.copy()
    corrected[:, LOWER_BODY, 0] += 0.12 * (1.0 - ramp)  # 12 cm off, then straight to the truth
    leak, wandered = measured(corrected)
    assert leak > 5.0 and wandered == pytest.approx(0.0, abs=1e-6)
    left = truth.copy()
    left[:, LOWER_BODY, 0] += 0.12 * ramp  # on the truth, then 12 cm away from it
    leak, wandered = measured(left)
    assert leak > 5.0 and wandered == pytest.approx(leak, rel=1e-6)
    angle = np.pi / 2 * ramp  # 12 cm off, then a quarter turn round the truth at that distance
    around = truth.copy()
    around[:, LOWER_BODY, 0] += 0.12 * np.cos(angle)
    around[:, LOWER_BODY, 2] += 0.12 * np.sin(angle)
    leak, wandered = measured(around)
    assert leak > 5.0 and wandered == pytest.approx(leak, rel=1e-6)


def test_legs_corrected_in_a_sessions_first_second_leak_and_skate_but_not_once_settled():
    """A cold session's first guess of the legs, corrected within its first second, counts in leakage from
    the stretch's start and not in settled leakage, and a foot that slides then counts in skating and not in
    settled skating; a drift later counts in both, and a stretch whose part after the first second is
    shorter than STILL_MIN_S has no settled leakage at all."""
    truth, t_us = standing(seconds=4.0)
    served = truth.copy()
    t_s = (t_us - t_us[0]) * 1e-6
    served[t_s >= 0.2, :, 2] += 0.09  # the whole body moves 9 cm at 0.2 s and stays there
    result = summarize_plausibility([plausibility(served, truth, t_us)])
    assert result["leg_leakage_cm"] == pytest.approx(9.0 * (4.0 - 0.2) / 4.0, rel=0.02)
    assert result["leg_leakage_settled_cm"] == 0.0
    served[:, :, 2] += np.maximum(t_s - 2.0, 0.0)[:, None] * 0.02  # then drifts 2 cm/s from 2 s on
    settled = summarize_plausibility([plausibility(served, truth, t_us)])["leg_leakage_settled_cm"]
    # the settled stretch runs from WARM_UP_S (1 s) to 4 s: still 1 s, then 2 s drifting 0 -> 4 cm
    assert settled == pytest.approx((0.0 * 1.0 + 2.0 * 2.0) / 3.0, rel=0.03)
    slid = truth.copy()
    slid[t_s < 0.5, 10, 0] += 0.2 * t_s[t_s < 0.5]  # the left foot slides at 20 cm/s for 0.5 s, then stays
    slid[t_s >= 0.5, 10, 0] += 0.1
    skating = summarize_plausibility([plausibility(slid, truth, t_us)])
    assert skating["foot_skate_cm_s"] == pytest.approx(20.0 * 0.5 / 4.0 / 2, rel=0.05)  # one foot of two
    assert skating["foot_skate_settled_cm_s"] == pytest.approx(0.0, abs=1e-9)
    short, t_short = standing(seconds=WARM_UP_S + 0.3)
    result = summarize_plausibility([plausibility(short, short, t_short)])
    assert result["leg_leakage_cm"] == 0.0 and np.isnan(result["leg_leakage_settled_cm"])


def test_a_walking_truth_has_no_still_legs_and_feet_in_the_air_are_not_in_contact():
    truth, t_us = standing()
    phase = 2 * np.pi * 1.0 * (t_us - t_us[0]) * 1e-6
    swing = np.maximum(np.sin(phase), 0)  # the left leg steps forward once a second, the right one stands
    truth[:, [4, 7, 10], 1] += swing[:, None] * 0.15
    truth[:, [4, 7, 10], 2] += 0.3 * np.cumsum(swing)[:, None] / RATE_HZ
    touch = contacts(truth, t_us)
    assert touch[:, 1].all() and 0.2 < touch[:, 0].mean() < 0.8
    assert still_stretches(truth, t_us) == []
    result = summarize_plausibility([plausibility(truth, truth, t_us)])
    assert np.isnan(result["leg_leakage_cm"]) and result["foot_skate_cm_s"] < 2.0
    assert result["jerk"] == pytest.approx(result["jerk_true"])


def test_penetration_is_the_depth_below_the_floor():
    truth, t_us = standing()
    served = truth.copy()
    served[:, 11, 1] -= 0.04
    result = summarize_plausibility([plausibility(served, truth, t_us)])
    assert result["floor_penetration_cm"] == pytest.approx(2.0) and result["floor_float_cm"] == 0.0


def test_the_devices_jerk_is_the_truths_with_the_head_and_tracked_wrists_where_the_devices_put_them():
    from egoposevr.model.rig import DEFAULT_OFFSETS_M, DEVICE_FROM_JOINT, TRACKED_JOINTS
    from egoposevr.model.rotations import matrix_to_quat_xyzw
    from egoposevr.model.training.evaluate import truth_on_devices

    truth, t_us = standing()
    noise_m = np.random.default_rng(0).normal(0.0, 0.002, (len(t_us), 3, 3))  # tracking noise, 2 mm
    poses = np.zeros((len(t_us), 3, 7))  # each device on its joint, which is not turned
    poses[..., :3] = truth[:, list(TRACKED_JOINTS)] + DEFAULT_OFFSETS_M + noise_m
    poses[..., 3:] = matrix_to_quat_xyzw(DEVICE_FROM_JOINT)
    valid = np.ones((len(t_us), 3), dtype=bool)
    valid[:, 2] = False  # the right controller is lost throughout: its wrist stays the truth's
    pinned = truth_on_devices(truth, {"hmd_poses": poses, "hmd_valid": valid})
    np.testing.assert_allclose(
        pinned[:, list(TRACKED_JOINTS[:2])], truth[:, list(TRACKED_JOINTS[:2])] + noise_m[:, :2]
    )
    np.testing.assert_array_equal(
        np.delete(pinned, TRACKED_JOINTS[:2], axis=1), np.delete(truth, TRACKED_JOINTS[:2], axis=1)
    )

    result = summarize_plausibility([plausibility(truth, truth, t_us, pinned)])
    assert result["jerk_true"] == pytest.approx(0.0, abs=1e-6)
    # White noise of s per axis: its third difference has s * sqrt(20) per axis; two noisy joints of 22.
    expected = 2 / 22 * 0.002 * np.sqrt(20) * RATE_HZ**3 * np.sqrt(8 / np.pi)  # the mean of a 3-D normal norm
    assert result["jerk_devices"] == pytest.approx(expected, rel=0.1)
    assert np.isnan(summarize_plausibility([plausibility(truth, truth, t_us)])["jerk_devices"])
