"""How much an evaluation number would move with other people: bootstrap intervals over a split's people,
for each model's metrics and for the difference between two models served the same split.

Every metric ``eval`` reports (but fps) is a mean pooled over samples, so a set of sequences' value is
Σ sums / Σ counts of its sequences' totals (:func:`.evaluate.sequence_totals`). A resample draws the split's
people (:func:`.dataset.sequence_subject`) with replacement and takes each drawn person's sequences as many
times as they were drawn: one person's sequences are alike (the same body, the same way of moving), so
resampling sequences alone would understate the spread. The same draws serve every model, so a difference
is paired: people who are hard for both models move both values together and not their difference.
Intervals are the resampled values' percentiles (the plain percentile bootstrap).

Shape legend: ``S`` sequences, ``R`` resamples, ``K`` metrics.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Final

import numpy as np

LEVEL: Final = 0.95


def resample_weights(subjects: Sequence[str], resamples: int, seed: int = 0) -> np.ndarray:
    """(R, S) how many times each sequence is in each resample: its person's count among len(people) draws
    of the split's people with replacement."""
    if resamples < 1:
        raise ValueError(f"resamples must be at least 1, got {resamples}")
    people, person_of = np.unique(np.asarray(subjects, dtype=str), return_inverse=True)
    rng = np.random.default_rng(seed)
    drawn = rng.integers(0, len(people), size=(resamples, len(people)))
    counts = np.stack([np.bincount(row, minlength=len(people)) for row in drawn])  # (R, people)
    return counts[:, person_of].astype(np.float64)


def _stacked(totals: Sequence[dict[str, np.ndarray]], keys: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Sums (S, K) and counts (S, K) of each sequence's totals {metric: (2,) [sum, count]}."""
    table = np.array([[t[k] for k in keys] for t in totals], dtype=np.float64)  # (S, K, 2)
    return table[..., 0], table[..., 1]


def resampled_metrics(totals: Sequence[dict[str, np.ndarray]], weights: np.ndarray) -> dict[str, np.ndarray]:
    """{metric: (R,)} each resample's pooled value: Σ weight × sum / Σ weight × count over the sequences;
    NaN in a resample whose sequences have nothing to measure (no lost controller, say), and in every
    resample of a metric that fewer than two people have: one person's value has no spread to resample."""
    if len(totals) != weights.shape[1]:
        raise ValueError(
            f"{len(totals)} sequences for resamples of {weights.shape[1]}: a paired difference needs the same ones"
        )
    keys = list(totals[0])
    sums, counts = _stacked(totals, keys)
    with np.errstate(invalid="ignore", divide="ignore"):
        values = (weights @ np.nan_to_num(sums, nan=0.0)) / (weights @ counts)  # (R, K)
    # a sequence without a value (a NaN sum: jerk_devices) leaves the metric NaN wherever it is drawn
    values[weights @ np.isnan(sums).astype(np.float64) > 0] = np.nan
    for k in range(len(keys)):
        measured = weights[:, counts[:, k] > 0]  # (R, sequences that have it): one person's columns are equal
        if len(np.unique(measured, axis=1).T) < 2:
            values[:, k] = np.nan
    return {k: values[:, i] for i, k in enumerate(keys)}


def percentile_interval(values: np.ndarray, level: float = LEVEL) -> tuple[float, float]:
    """(low, high): the central ``level`` of the finite values; NaN if fewer than half are finite (the
    metric is unmeasurable on most resamples of the split's people)."""
    finite = values[np.isfinite(values)]
    if len(finite) * 2 < len(values) or not len(finite):
        return float("nan"), float("nan")
    tail = 50.0 * (1.0 - level)
    low, high = np.percentile(finite, [tail, 100.0 - tail])
    return float(low), float(high)


def metric_intervals(
    resampled: dict[str, np.ndarray], level: float = LEVEL
) -> dict[str, tuple[float, float]]:
    """{metric: (low, high)} of one model's :func:`resampled_metrics` {metric: (R,)}."""
    return {k: percentile_interval(v, level) for k, v in resampled.items()}


def difference_intervals(
    reference: dict[str, np.ndarray],
    other: dict[str, np.ndarray],
    level: float = LEVEL,
    relative: bool = False,
) -> dict[str, tuple[float, float]]:
    """{metric: (low, high)} of other − reference, each a model's :func:`resampled_metrics` {metric: (R,)} of
    the same sequences under the same resample weights (so the difference is paired); with ``relative``, of
    other / reference − 1 (a bar such as "40 % lower" is a statement about the ratio)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        changes = {
            k: other[k] / reference[k] - 1.0 if relative else other[k] - reference[k] for k in reference
        }
    return {k: percentile_interval(np.where(np.isfinite(v), v, np.nan), level) for k, v in changes.items()}
