"""One Euro filter (Casiez, Roussel and Vogel, CHI 2012), vectorised and driven by timestamps; and a point's
speed over a sliding time window (:class:`WindowSpeed`), which the planted feet and the steady stance gate on.

A first-order low-pass whose cutoff rises with speed: ``fc = min_cutoff_hz + beta * |dx/dt|``. Slow motion
is smoothed hard (less jitter), fast motion passes with little lag. Each element of the signal (every joint
coordinate, every visibility score) has its own adaptive cutoff.

Shape legend: ``...`` = the signal's shape, fixed for a filter's lifetime (e.g. (22, 3) joints, (22,) ζ).
"""

from __future__ import annotations

import collections
import math

import numpy as np


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

    def __call__(self, t_us: int, x: np.ndarray) -> np.ndarray:
        """Filter sample ``x`` (...) taken at ``t_us``; returns the filtered value (a new array).

        A sample whose time does not advance returns the current estimate unchanged (no division by zero).
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
        if dt_s <= 0:
            return self._x_hat.copy()
        dx = (x - self._x_hat) / dt_s
        self._dx_hat = self._dx_hat + smoothing_factor(dt_s, self.d_cutoff_hz) * (dx - self._dx_hat)
        cutoff_hz = self.min_cutoff_hz + self.beta * np.abs(self._dx_hat)
        self._x_hat = self._x_hat + smoothing_factor(dt_s, cutoff_hz) * (x - self._x_hat)
        self._t_us = int(t_us)
        return self._x_hat.copy()

    def _start(self, t_us: int, x: np.ndarray) -> np.ndarray:
        self._x_hat, self._dx_hat, self._t_us = x.copy(), np.zeros_like(x), int(t_us)
        return x.copy()


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

    @property
    def span_s(self) -> float:
        """How long the speed was measured over: up to a little more than ``window_s``."""
        return (self._history[-1][0] - self._history[0][0]) * 1e-6 if self._history else 0.0

    @property
    def step_s(self) -> float:
        """The time between the last two samples (0 before the second)."""
        return (self._history[-1][0] - self._history[-2][0]) * 1e-6 if len(self._history) > 1 else 0.0
