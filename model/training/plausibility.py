"""Does the served body behave like a body: planted feet that stay put, soles on the floor, legs that stay
still while only the arms move. Measured against the truth of a dataset sequence (numpy, no torch).

- **Contact** (from the truth): a foot touches the floor while its foot joint (the ball of the foot) is
  below ``CONTACT_HEIGHT_M`` and moves slower than ``CONTACT_SPEED_M_S`` over the floor, its speed taken over
  ``CONTACT_SPAN_S`` centred on the sample; then every contact, and every gap between two contacts, shorter
  than ``CONTACT_MIN_S`` is dropped (gaps first). A captured planted foot moves by millimetres from sample
  to sample and the headset's sample times vary by a few percent: read sample by sample, its label flickered
  3-7 times a second on data/v3h's training split (MODEL_CARD, "Contact labels that hold through a stance").
- **Foot skating** (cm/s): the served foot joint's speed over the floor while the true foot is in contact;
  **settled skating** the same after a session's first ``WARM_UP_S`` (see settled leakage below).
- **Floor error** (cm): the served sole's height while the true foot is in contact (sole = foot joint minus
  its height above the sole when flat), as floating (above the floor) and penetration (below), each the mean
  over contact samples of the positive part.
- **Leg leakage** (cm): over stretches of at least ``STILL_MIN_S`` where the true lower body is still (every
  lower-body joint slower than ``STILL_SPEED_M_S``), the served lower-body joints' mean distance from where
  they were at the stretch's start, averaged over the stretch. **Settled leakage** is the same over the
  stretches' parts after a session's first ``WARM_UP_S``: a cold session's first guess of the legs, made
  before its windows hold any real history, is corrected once the camera shows them, and that correction
  is a move of the served legs too, but not the wandering while the arms move that leakage is there to catch.
  **Leg wander** (cm) is leakage less what of it brought the legs nearer the truth: each joint's distance
  from its start less how much its error shrank since then (never below 0). Legs that move straight to where
  the truth is wander 0 (a wrong first guess corrected late); legs that move away from it, or round it,
  wander as far as they leak. A user sees both; wander says which of them a leakage was.
- **Jerk** (m/s³): the mean norm of the third time derivative of the joints, served and true; and, where
  the caller gives it, of the truth with its head and tracked wrists moved to where the devices put them
  (``jerk_devices``): what a perfect network would serve with the head and hands exactly on their devices,
  whose tracking noise is then in every served head and hand and not in the truth.

The world is a stage space: the floor is y = 0 (PROTOCOL.md §3).

Shape legend: ``N`` headset samples, ``J`` = 22 joints.
"""

from __future__ import annotations

from typing import Final

import numpy as np

from ..skeleton import FOOT_JOINT_HEIGHT_M, LOWER_BODY

FEET: Final = (10, 11)  # left, right foot joints (the balls of the feet)
CONTACT_HEIGHT_M: Final = FOOT_JOINT_HEIGHT_M + 0.03
CONTACT_SPEED_M_S: Final = 0.2
CONTACT_SPAN_S: Final = 0.1  # a contact's speed: the displacement over this span (6-12 samples at 60-120 Hz)
CONTACT_MIN_S: Final = 0.1  # no stance or swing is shorter: such a run is the threshold's noise, not a step
STILL_SPEED_M_S: Final = 0.08
STILL_MIN_S: Final = 0.5
# A session's first second: a model's windows still hold padding until then (the zoo's 40 headset samples take
# 0.67 s at 60 Hz; its 8 camera frames 0.27 s, plus their latency), so what it serves is a first guess.
WARM_UP_S: Final = 1.0
# contact_timing's clip: about one step's stance or swing at a slow walk, so a still foot reads as never moving
TIMING_HORIZON_S: Final = 1.0


def _seconds(t_us: np.ndarray) -> np.ndarray:
    """(N,) float64 seconds since the first of the sample times t_us (N,)."""
    return (np.asarray(t_us, dtype=np.float64) - t_us[0]) * 1e-6


def _speeds(joints: np.ndarray, t_us: np.ndarray, horizontal: bool) -> np.ndarray:
    """(N, J) speed of each joint (m/s) by central differences over the samples' own times."""
    t_s = _seconds(t_us)
    points = joints[..., [0, 2]] if horizontal else joints
    if len(t_s) < 2:
        return np.zeros(joints.shape[:2])
    velocity = np.gradient(points, t_s, axis=0)
    return np.linalg.norm(velocity, axis=-1)


def contacts(true_joints: np.ndarray, t_us: np.ndarray) -> np.ndarray:
    """(N, 2) bool: each foot (left, right) touching the floor, from the true joints (N, J, 3)."""
    t_s = _seconds(t_us)
    height = true_joints[:, FEET, 1]
    speed = _span_speeds(true_joints[:, FEET][..., [0, 2]], t_s, CONTACT_SPAN_S)
    touch = (height < CONTACT_HEIGHT_M) & (speed < CONTACT_SPEED_M_S)
    for foot in range(touch.shape[1]):
        touch[:, foot] = _without_short_runs(touch[:, foot], t_s, CONTACT_MIN_S, of=False)
        touch[:, foot] = _without_short_runs(touch[:, foot], t_s, CONTACT_MIN_S, of=True)
    return touch


def _span_speeds(points: np.ndarray, t_s: np.ndarray, span_s: float) -> np.ndarray:
    """(N, ...) speed of points (N, ..., D) over span_s centred on each sample (shorter at the ends): the
    displacement between the samples half a span before and after, over the time between them."""
    if len(t_s) < 2:
        return np.zeros(points.shape[:-1])
    half = max(1, round(0.5 * span_s / np.median(np.diff(t_s))))
    index = np.arange(len(t_s))
    before, after = np.maximum(index - half, 0), np.minimum(index + half, len(t_s) - 1)
    elapsed_s = (t_s[after] - t_s[before]).reshape(-1, *[1] * (points.ndim - 2))
    return np.linalg.norm(points[after] - points[before], axis=-1) / elapsed_s


def _without_short_runs(labels: np.ndarray, t_s: np.ndarray, min_s: float, of: bool) -> np.ndarray:
    """labels (N,) bool with every run of the value ``of`` that lasts less than min_s (its first sample to the
    sample after its last) flipped, except runs at either end, whose length the sequence cuts."""
    out = labels.copy()
    edges = np.flatnonzero(np.diff(np.r_[False, labels == of, False].astype(np.int8)))  # run starts, stops
    for start, stop in zip(edges[::2], edges[1::2], strict=True):
        if start > 0 and stop < len(labels) and t_s[stop] - t_s[start] < min_s:
            out[start:stop] = not of
    return out


def contact_timing(contact: np.ndarray, t_us: np.ndarray, horizon_s: float = TIMING_HORIZON_S) -> np.ndarray:
    """(N, F, 2) float in [0, 1]: for each sample and foot of contact (N, F) bool, the time until its label
    next changes and the time since it last changed, each in units of horizon_s and at most 1. A label that
    never changes again (or never did) is 1 on that side: a still stance reads (1, 1). With the label itself
    they say where a foot is in its step (a stance about to end, a swing just begun)."""
    t_s = _seconds(t_us)
    out = np.full((len(t_s), contact.shape[1], 2), horizon_s)
    for foot in range(contact.shape[1]):
        changed_at = t_s[1:][np.diff(contact[:, foot].astype(np.int8)) != 0]  # samples whose label is new
        after = np.searchsorted(changed_at, t_s, side="right")  # each sample's next change
        has_next, has_last = after < len(changed_at), after > 0
        out[has_next, foot, 0] = changed_at[after[has_next]] - t_s[has_next]
        out[has_last, foot, 1] = t_s[has_last] - changed_at[after[has_last] - 1]
    return np.minimum(out / horizon_s, 1.0)


def _lasts(stretch: slice, t_us: np.ndarray) -> bool:
    """Whether a non-empty sample range spans at least STILL_MIN_S, first sample to last."""
    return (
        stretch.start < stretch.stop and (t_us[stretch.stop - 1] - t_us[stretch.start]) * 1e-6 >= STILL_MIN_S
    )


def still_stretches(true_joints: np.ndarray, t_us: np.ndarray) -> list[slice]:
    """Sample ranges of at least STILL_MIN_S where every true lower-body joint is slower than
    STILL_SPEED_M_S."""
    still = (_speeds(true_joints[:, LOWER_BODY], t_us, horizontal=False) < STILL_SPEED_M_S).all(axis=1)
    stretches, start = [], None
    for i, now in enumerate([*still, False]):
        if now and start is None:
            start = i
        elif not now and start is not None:
            if _lasts(slice(start, i), t_us):
                stretches.append(slice(start, i))
            start = None
    return stretches


def warmed_up(t_us: np.ndarray) -> int:
    """The first sample after the session's first WARM_UP_S (the first sample is the session's start)."""
    return int(np.searchsorted(t_us, t_us[0] + WARM_UP_S * 1e6)) if len(t_us) else 0


def settled(stretches: list[slice], t_us: np.ndarray) -> list[slice]:
    """The stretches' parts after the session's first WARM_UP_S, each still at least STILL_MIN_S long."""
    first = warmed_up(t_us)
    parts = [slice(max(s.start, first), s.stop) for s in stretches]
    return [s for s in parts if _lasts(s, t_us)]


def leakage(served: np.ndarray, stretches: list[slice]) -> np.ndarray:
    """(S,) m: each stretch's mean distance of the served lower-body joints (N, J, 3) from where they were
    at its start."""
    return np.array(
        [
            np.linalg.norm(served[s][:, LOWER_BODY] - served[s][:1, LOWER_BODY], axis=-1).mean()
            for s in stretches
        ]
    )


def wander(served: np.ndarray, truth: np.ndarray, stretches: list[slice]) -> np.ndarray:
    """(S,) m: each stretch's mean, over its samples and the lower-body joints of served (N, J, 3), of the
    distance from where the joint was at the stretch's start less how much nearer the truth (N, J, 3) it is
    now than then (floored at 0 per joint and sample)."""
    out = []
    for s in stretches:
        now, true_now = served[s][:, LOWER_BODY], truth[s][:, LOWER_BODY]
        moved = np.linalg.norm(now - now[:1], axis=-1)
        error = np.linalg.norm(now - true_now, axis=-1)
        nearer = np.maximum(error[:1] - error, 0.0)
        out.append(np.maximum(moved - nearer, 0.0).mean())
    return np.array(out)


def jerk(joints: np.ndarray, t_us: np.ndarray) -> np.ndarray:
    """(N-3,) mean over joints of |d³x/dt³| (m/s³), on the mean sample interval."""
    if len(joints) < 4:
        return np.zeros(0)
    dt_s = np.diff(t_us).mean() * 1e-6
    return np.linalg.norm(np.diff(joints, n=3, axis=0) / dt_s**3, axis=-1).mean(-1)


def plausibility(
    served: np.ndarray, truth: np.ndarray, t_us: np.ndarray, on_devices: np.ndarray | None = None
) -> dict[str, np.ndarray]:
    """Per-sample (or per-stretch) values for one sequence, pooled later by :func:`summarize_plausibility`:
    served (N, J, 3), truth (N, J, 3), t_us (N,); on_devices (N, J, 3) the truth moved onto the devices
    (evaluate.truth_on_devices), or None."""
    touch = contacts(truth, t_us)
    served_speed = _speeds(served[:, FEET], t_us, horizontal=True)
    sole = served[:, FEET, 1] - FOOT_JOINT_HEIGHT_M
    still, first = still_stretches(truth, t_us), warmed_up(t_us)
    return {
        "skate": served_speed[touch],
        "skate_settled": served_speed[first:][touch[first:]],
        "sole": sole[touch],
        "leakage": leakage(served, still),
        "leakage_settled": leakage(served, settled(still, t_us)),
        "wander": wander(served, truth, still),
        "jerk": jerk(served, t_us),
        "jerk_true": jerk(truth, t_us),
    } | ({} if on_devices is None else {"jerk_devices": jerk(on_devices, t_us)})


def pooled_means(totals: dict[str, np.ndarray]) -> dict[str, float]:
    """Metrics from totals {key: (2,) [sum, count]}: sum / count, NaN where the count is 0 (or a part had no
    value: its sum is NaN)."""
    return {k: float(t[0] / t[1]) if t[1] > 0 else float("nan") for k, t in totals.items()}


def add_totals(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Element-wise sum of several sequences' totals {key: (2,) [sum, count]} (same keys in each)."""
    return {k: np.sum([p[k] for p in parts], axis=0) for k in parts[0]} if parts else {}


def total(values: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """(2,) [sum × scale, count] of any array of per-sample values: what a pooled mean needs of it."""
    return np.array([float(values.sum()) * scale, float(values.size)])


def plausibility_totals(part: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """One sequence's :func:`plausibility` as (2,) [sum, count] per metric of :func:`summarize_plausibility`:
    every one is a mean pooled over samples (or still stretches), so a set of sequences' value is the ratio of
    its summed totals. A part without ``jerk_devices`` gives it a NaN sum: NaN for any set that holds it."""
    sole = part["sole"]
    return {
        "foot_skate_cm_s": total(part["skate"], 100.0),
        "foot_skate_settled_cm_s": total(part["skate_settled"], 100.0),
        "floor_float_cm": total(np.maximum(sole, 0.0), 100.0),
        "floor_penetration_cm": total(np.maximum(-sole, 0.0), 100.0),
        "leg_leakage_cm": total(part["leakage"], 100.0),
        "leg_leakage_settled_cm": total(part["leakage_settled"], 100.0),
        "leg_wander_cm": total(part["wander"], 100.0),
        "jerk": total(part["jerk"]),
        "jerk_true": total(part["jerk_true"]),
        "jerk_devices": total(part["jerk_devices"]) if "jerk_devices" in part else np.array([np.nan, 0.0]),
    }


def summarize_plausibility(parts: list[dict[str, np.ndarray]]) -> dict[str, float]:
    """Pooled over sequences: foot_skate_cm_s, foot_skate_settled_cm_s, floor_float_cm, floor_penetration_cm,
    leg_leakage_cm, leg_leakage_settled_cm and leg_wander_cm (NaN where nothing was in contact or still),
    jerk, jerk_true and jerk_devices (m/s³; NaN unless every part has it)."""
    if not parts:
        return {k: float("nan") for k in plausibility_totals(_EMPTY)}
    return pooled_means(add_totals([plausibility_totals(p) for p in parts]))


_EMPTY: Final = {
    k: np.zeros(0)
    for k in ("skate", "skate_settled", "sole", "leakage", "leakage_settled", "wander", "jerk", "jerk_true")
}
