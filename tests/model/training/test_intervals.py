"""Bootstrap intervals over a split's people (model/training/intervals.py) and the per-sequence totals that
every eval metric pools (evaluate.sequence_totals)."""

import numpy as np
import pytest

from egoposevr.model.skeleton import LOWER_BODY
from egoposevr.model.training.evaluate import METRIC_KEYS, sequence_totals, summarize
from egoposevr.model.training.intervals import (
    difference_intervals,
    metric_intervals,
    percentile_interval,
    resample_weights,
    resampled_metrics,
)
from egoposevr.model.training.plausibility import plausibility


def _totals(values_by_sequence: list[np.ndarray]) -> list[dict[str, np.ndarray]]:
    """One metric ``m``, each sequence's per-sample values as its (sum, count)."""
    return [{"m": np.array([v.sum(), v.size], dtype=float)} for v in values_by_sequence]


def _resampled(values_by_sequence: list[np.ndarray], weights: np.ndarray) -> dict[str, np.ndarray]:
    return resampled_metrics(_totals(values_by_sequence), weights)


def test_a_person_is_drawn_with_all_their_sequences():
    people = ["a", "a", "a", "b", "c", "c"]
    weights = resample_weights(people, 500, seed=3)
    assert weights.shape == (500, 6)
    assert (weights[:, 0] == weights[:, 1]).all() and (weights[:, 0] == weights[:, 2]).all()
    assert (weights[:, 4] == weights[:, 5]).all()
    # three draws of three people: each resample holds three people's worth of sequences
    draws_per_resample = weights[:, 0] + weights[:, 3] + weights[:, 4]
    assert (draws_per_resample == 3).all()
    assert (weights[:, 3] == 0).any() and (weights[:, 3] >= 2).any()  # b left out, b drawn twice
    np.testing.assert_array_equal(weights, resample_weights(people, 500, seed=3))
    with pytest.raises(ValueError, match="at least 1"):
        resample_weights(people, 0)


def test_the_interval_is_as_wide_as_the_people_differ_however_many_sequences_each_has():
    # Two people, 40 sequences each: one always errs 1 cm, the other 9. Resampling sequences would give a
    # narrow interval around 5; there are only two people, so any of 1, 5 and 9 is as likely a split.
    rng = np.random.default_rng(0)
    values = [np.full(50, 1.0) + rng.normal(0, 0.01, 50) for _ in range(40)]
    values += [np.full(50, 9.0) + rng.normal(0, 0.01, 50) for _ in range(40)]
    people = ["a"] * 40 + ["b"] * 40
    low, high = metric_intervals(_resampled(values, resample_weights(people, 2000, seed=1)))["m"]
    assert low < 1.1 and high > 8.9


def test_people_alike_give_a_narrow_interval_around_the_pooled_value():
    rng = np.random.default_rng(0)
    values = [rng.normal(5.0, 1.0, 200) for _ in range(30)]
    low, high = metric_intervals(_resampled(values, resample_weights([str(i) for i in range(30)], 2000)))["m"]
    pooled = np.concatenate(values).mean()
    assert low < pooled < high and high - low < 0.2


def test_a_paired_difference_sees_a_small_gain_that_the_spread_between_people_hides():
    # People differ by several cm; the second model is 0.3 cm better on every sample of every person.
    rng = np.random.default_rng(2)
    base = [np.full(100, rng.uniform(3.0, 12.0)) + rng.normal(0, 0.2, 100) for _ in range(20)]
    better = [v - 0.3 for v in base]
    weights = resample_weights([str(i) for i in range(20)], 2000, seed=0)
    first, second = (
        metric_intervals(_resampled(base, weights))["m"],
        metric_intervals(_resampled(better, weights))["m"],
    )
    assert second[1] > first[0]  # each model's interval overlaps the other's
    low, high = difference_intervals(_resampled(base, weights), _resampled(better, weights))["m"]
    assert -0.31 < low <= high < -0.29
    low, high = difference_intervals(_resampled(base, weights), _resampled(better, weights), relative=True)[
        "m"
    ]
    assert -0.3 / 3.0 < low <= high < -0.3 / 12.0  # 0.3 cm of people erring 3-12 cm
    with pytest.raises(ValueError, match="the same ones"):
        _resampled(better[:-1], weights)  # a sequence short of the weights: not paired


def test_a_metric_that_one_person_has_has_no_interval():
    people = list("abcdefghij")
    weights = resample_weights(people, 500)
    one = [np.zeros(0)] * 9 + [np.ones(10)]  # one person in ten lost a controller
    assert np.isnan(metric_intervals(_resampled(one, weights))["m"]).all()
    two = [np.zeros(0)] * 8 + [np.ones(10), np.full(10, 3.0)]
    low, high = metric_intervals(_resampled(two, weights))["m"]
    assert low == pytest.approx(1.0) and high == pytest.approx(3.0)
    assert np.isnan(percentile_interval(np.array([np.nan, np.nan, 1.0]))).all()


def test_summarize_pools_every_metric_as_its_sequences_totals_say():
    rng = np.random.default_rng(4)
    errors = []
    for n in (40, 70):
        t_us = np.arange(n) * 11_111
        truth = rng.normal(0, 0.3, (n, 22, 3))
        truth[:, [10, 11]] = [[-0.1, 0.04, 0.0], [0.1, 0.04, 0.0]]  # feet planted: skating and floor metrics
        served = truth + rng.normal(0, 0.02, (n, 22, 3))
        lost = np.zeros((n, 2), bool)
        lost[n // 2 :, 0] = True
        errors.append({
            "pos": np.linalg.norm(served - truth, axis=-1), "pa": rng.uniform(0, 0.05, (n, 22)),
            "rot": rng.uniform(0, 20, (n, 22)), "facing": rng.uniform(0, 10, (n, 3)),
            "jitter": rng.uniform(0, 100, n - 3), "lost": lost,
            "plausibility": plausibility(served, truth, t_us, truth),
        })  # fmt: skip
    metrics = summarize(errors)
    assert set(metrics) | {"fps"} == set(METRIC_KEYS)
    pos = np.concatenate([e["pos"] for e in errors])
    lost = np.concatenate([e["lost"] for e in errors])
    assert metrics["mpjpe_l_cm"] == pytest.approx(100 * pos[:, LOWER_BODY].mean())
    assert metrics["hpe_lost_cm"] == pytest.approx(100 * pos[:, [20, 21]][lost].mean())
    assert metrics["facing_hands_deg"] == pytest.approx(
        np.concatenate([e["facing"][:, 1:] for e in errors]).mean()
    )
    skate = np.concatenate([e["plausibility"]["skate"] for e in errors])
    assert metrics["foot_skate_cm_s"] == pytest.approx(100 * skate.mean())
    assert set(sequence_totals(errors[0])) == set(metrics)
