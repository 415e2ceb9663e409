"""One Euro filter (Casiez, Roussel and Vogel, CHI 2012), vectorised and driven by timestamps; cascades of
them (:class:`OneEuroCascade`); the tracked devices' poses smoothed (:class:`DevicePoseFilter`); and a
point's speed over a sliding time window (:class:`WindowSpeed`), which the planted feet and the steady stance
gate on; and how much of a gap is left while it fades out (:func:`fade_left`), which a found controller and
a foot that plants or steps close theirs by.

A One Euro filter is a first-order low-pass whose cutoff rises with speed: ``fc = min_cutoff_hz + beta *
|dx/dt|``. Slow motion is smoothed hard (less jitter), fast motion passes with little lag. Each element of
the signal (every joint coordinate, every visibility score) has its own adaptive cutoff.

A first-order low-pass lets white noise through at -6 dB per octave above its cutoff, while jerk (the third
derivative, which is what a viewer sees as jitter) amplifies it at +18 dB per octave: the noise near the
sample rate dominates. Two stages at twice the cutoff lag as much as one at low frequencies and pass that
noise at the square of one stage's gain, so the cascade is what smooths jitter for a given lag.

Shape legend: ``...`` = the signal's shape, fixed for a filter's lifetime (e.g. (22, 3) joints, (22,) ζ).
"""

from __future__ import annotations

import collections
import math

import numpy as np

from . import kernels


def smoothing_factor(dt_s: float, cutoff_hz: np.ndarray | float) -> np.ndarray | float:
    """Exponential-smoothing weight α of a first-order low-pass with cutoff ``cutoff_hz`` over ``dt_s``."""
    tau_s = 1.0 / (2.0 * math.pi * np.asarray(cutoff_hz))
    return 1.0 / (1.0 + tau_s / dt_s)


class OneEuroFilter:
    """Filter a stream of arrays sampled at (possibly irregular) times.

    min_cutoff_hz: cutoff at rest (lower = smoother, more lag at low speed).
    beta:          speed coefficient (higher = less lag when moving fast), in (cutoff Hz) per (unit/s).
    d_cutoff_hz:   cutoff of the low-pass on the derivative estimate.
    """

    def __init__(self, min_cutoff_hz: float = 1.0, beta: float = 0.0, d_cutoff_hz: float = 1.0) -> None:
        if min_cutoff_hz <= 0 or d_cutoff_hz <= 0 or beta < 0:
            raise ValueError(
                f"need min_cutoff_hz > 0, d_cutoff_hz > 0, beta >= 0; got {min_cutoff_hz}, {d_cutoff_hz}, {beta}"
            )
        self.min_cutoff_hz = min_cutoff_hz
        self.beta = beta
        self.d_cutoff_hz = d_cutoff_hz
        self.reset()

    def reset(self) -> None:
        """Forget the past: the next sample passes through unchanged."""
        self._x_hat: np.ndarray | None = None
        self._dx_hat: np.ndarray | None = None
        self._t_us: int | None = None

    def __call__(self, t_us: int, x: np.ndarray, fresh: np.ndarray | None = None) -> np.ndarray:
        """Filter sample ``x`` (...) taken at ``t_us``; returns the filtered value (a new array).

        fresh: optional bool mask over x's leading axis; those rows start afresh (pass through, as after a
        reset) while the others are filtered. A sample whose time does not advance returns the current
        estimate unchanged (no division by zero), but for its fresh rows.
        """
        x = np.asarray(x, dtype=np.float64)
        if not np.isfinite(x).all():
            raise ValueError("OneEuroFilter input must be finite")
        if self._x_hat is None or self._t_us is None:
            return self._start(t_us, x)
        if x.shape != self._x_hat.shape:
            raise ValueError(
                f"signal shape changed from {self._x_hat.shape} to {x.shape}; call reset() first"
            )
        dt_s = (int(t_us) - self._t_us) * 1e-6
        if dt_s > 0:
            # x̂ += α(fc)·(x - x̂) with fc = min_cutoff + β·|dx̂|, dx̂ += α(d_cutoff)·((x - x̂)/dt - dx̂): the
            # compiled step does exactly this (smoothing_factor's α), element by element, in place.
            kernels.one_euro_step(
                np.ascontiguousarray(x).reshape(-1), self._x_hat.reshape(-1), self._dx_hat.reshape(-1),
                dt_s, float(self.min_cutoff_hz), float(self.beta), float(self.d_cutoff_hz),
            )  # fmt: skip
            self._t_us = int(t_us)
        if fresh is not None:
            self._x_hat[fresh] = x[fresh]
            self._dx_hat[fresh] = 0.0
        return self._x_hat.copy()

    @property
    def value(self) -> np.ndarray | None:
        """The last output, or None before the first sample (or after a reset)."""
        return None if self._x_hat is None else self._x_hat.copy()

    def _start(self, t_us: int, x: np.ndarray) -> np.ndarray:
        # C-ordered copies: the compiled step updates them in place through flat views.
        self._x_hat, self._dx_hat, self._t_us = x.copy(order="C"), np.zeros(x.shape), int(t_us)
        return x.copy()


class OneEuroCascade:
    """``stages`` One Euro filters in a row, each with the same parameters; called and reset like one."""

    def __init__(self, min_cutoff_hz: float, beta: float, stages: int = 2, d_cutoff_hz: float = 1.0) -> None:
        if stages < 1:
            raise ValueError(f"need at least one stage, got {stages}")
        self.stages = [OneEuroFilter(min_cutoff_hz, beta, d_cutoff_hz) for _ in range(stages)]

    def reset(self) -> None:
        for stage in self.stages:
            stage.reset()

    def __call__(self, t_us: int, x: np.ndarray, fresh: np.ndarray | None = None) -> np.ndarray:
        for stage in self.stages:
            x = stage(t_us, x, fresh)
        return x

    @property
    def value(self) -> np.ndarray | None:
        """The last output, or None before the first sample (or after a reset)."""
        return self.stages[-1].value


class DevicePoseFilter:
    """The tracked devices' poses, smoothed: positions and rotations each through a
    :class:`OneEuroCascade`, every device its own rows. Trackers jitter by a fraction of a millimetre and a
    fraction of a degree per sample, which everything downstream (the network's inputs, the head anchor, the
    wrists' KPO targets) would pass on to the served body as jitter.

    A device that is not tracked is forgotten, so that it comes back where it is, not gliding from where it
    was lost; so is one that jumps more than ``jump_m`` from one sample to the next (a recentred reference
    space, a replay that starts over: no body moves that fast, and a glide would read as motion); a pause
    longer than ``max_gap_s`` or time going back forgets all of them. Rotations are
    filtered as quaternions on the hemisphere of the last output, then normalised (steps between samples
    are a few degrees at most, where that is as good as filtering on the sphere).

    Shape legend: ``D`` = 3 devices (head, left, right); a pose is [p xyz m, q xyzw].
    """

    def __init__(
        self,
        position: tuple[float, float],
        rotation: tuple[float, float],
        stages: int = 2,
        max_gap_s: float = 0.5,
        jump_m: float = 0.25,
    ) -> None:
        """position, rotation: (min_cutoff_hz, beta) of each, beta in Hz per m/s and Hz per (quaternion
        units)/s."""
        self._position = OneEuroCascade(*position, stages=stages)
        self._rotation = OneEuroCascade(*rotation, stages=stages)
        self.max_gap_s, self.jump_m = max_gap_s, jump_m
        self.reset()

    def reset(self) -> None:
        self._position.reset()
        self._rotation.reset()
        self._last_us: int | None = None
        self._tracked = np.zeros(3, dtype=bool)  # each device tracked at the last sample
        self._last_pos = np.zeros((3, 3))  # each device's position as given at the last sample, m
        self.jumped = np.zeros(3, dtype=bool)  # each tracked device jumped at the last sample (jump_m)

    def __call__(self, t_us: int, poses: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """poses (D, 7) with finite tracked rows, valid (D,) bool -> (D, 7) smoothed (a copy; untracked rows
        as given)."""
        if self._last_us is not None and not 0 <= t_us - self._last_us <= self.max_gap_s * 1e6:
            self.reset()
        self._last_us = int(t_us)
        valid = np.asarray(valid, dtype=bool)
        poses = np.asarray(poses, dtype=np.float64)
        self.jumped = (
            valid & self._tracked & (np.linalg.norm(poses[:, :3] - self._last_pos, axis=1) > self.jump_m)
        )
        fresh = ~(valid & self._tracked) | self.jumped  # lost now, back since the last sample, or teleported
        self._tracked, self._last_pos = valid.copy(), poses[:, :3].copy()
        out = poses.copy()
        out[:, :3] = self._position(t_us, out[:, :3], fresh)
        quats = out[:, 3:] / _norms(out[:, 3:])
        last = self._rotation.value
        if last is not None:  # each rotation on the side of its last output: q and -q are the same turn
            quats[(quats * last).sum(axis=1) < 0.0] *= -1.0
        quats = self._rotation(t_us, quats, fresh)
        out[:, 3:] = quats / _norms(quats)
        out[~valid] = poses[~valid]
        return out


def _norms(rows: np.ndarray) -> np.ndarray:
    """(D, 1) each row's length, 1 where it is 0 (an untracked device's numbers may be anything)."""
    norms = np.linalg.norm(rows, axis=1, keepdims=True)
    return np.where(norms > 0.0, norms, 1.0)


class WindowSpeed:
    """A point's speed over the last ``window_s``: its move since the oldest sample within that window (the
    move over a window, not per sample, so that a network's per-sample jitter does not read as motion)."""

    def __init__(self, window_s: float) -> None:
        self.window_s = window_s
        self._history: collections.deque[tuple[int, np.ndarray]] = collections.deque()

    def push(self, t_us: int, position: np.ndarray) -> float:
        """Record this sample's position (3,) m -> the speed, m/s (0 until time has passed)."""
        history = self._history
        history.append((t_us, np.array(position, dtype=np.float64)))
        while len(history) > 2 and (t_us - history[1][0]) * 1e-6 >= self.window_s:
            history.popleft()
        t0_us, position0 = history[0]
        if t_us <= t0_us:
            return 0.0
        return float(np.linalg.norm(history[-1][1] - position0)) / ((t_us - t0_us) * 1e-6)

    def about(self, pivot_m: np.ndarray) -> tuple[float, float]:
        """The window's move split about a pivot (3,) m: (radial, around) speed, m/s. Radial is how fast the
        point's distance from the pivot changed; around is the rest of its move (a point on a rigid arm that
        turns about the pivot moves only around it). Both 0 until time has passed."""
        if not self._history:
            return 0.0, 0.0
        (t0_us, position0), (t_us, position) = self._history[0], self._history[-1]
        if t_us <= t0_us:
            return 0.0, 0.0
        span_s = (t_us - t0_us) * 1e-6
        move = position - position0
        radial_m = float(np.linalg.norm(position - pivot_m) - np.linalg.norm(position0 - pivot_m))
        around_m = math.sqrt(max(float(move @ move) - radial_m * radial_m, 0.0))
        return abs(radial_m) / span_s, around_m / span_s

    @property
    def span_s(self) -> float:
        """How long the speed was measured over: up to a little more than ``window_s``."""
        return (self._history[-1][0] - self._history[0][0]) * 1e-6 if self._history else 0.0

    @property
    def step_s(self) -> float:
        """The time between the last two samples (0 before the second)."""
        return (self._history[-1][0] - self._history[-2][0]) * 1e-6 if len(self._history) > 1 else 0.0


def fade_left(elapsed_s: float, duration_s: float) -> float | None:
    """The share of a gap still left ``elapsed_s`` into its fade over ``duration_s``: 1 at the start, down a
    smoothstep (no jump in position or speed at either end) to 0; None outside [0, duration_s), the fade over."""
    share = elapsed_s / duration_s
    if not 0.0 <= share < 1.0:
        return None
    return 1.0 - share * share * (3.0 - 2.0 * share)


def settle_step(
    gap_m: np.ndarray, dt_s: float, speed_m_s: float, reseat: tuple[float, float] | None = None
) -> np.ndarray:
    """How far held points (a held leg, a planted foot's anchor) move this sample towards the mean of the
    network's placements of them: gap_m (N, 3) from each point to its mean, moved at most speed_m_s × dt_s
    (the longest row; the rows keep their proportions). With ``reseat = (slack_m, tau_s)``, a longest gap past
    slack_m also closes at (gap − slack_m) / tau_s: a hold begun on a wrong guess reaches the mean in a few
    tau_s instead of at speed_m_s. Returns the step (N, 3)."""
    longest_m = float(np.linalg.norm(gap_m, axis=1).max())
    most_m_s = speed_m_s
    if reseat is not None:
        slack_m, tau_s = reseat
        most_m_s = max(most_m_s, (longest_m - slack_m) / tau_s)
    most_m = most_m_s * dt_s
    return gap_m * (most_m / longest_m) if longest_m > most_m else gap_m
