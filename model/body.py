"""Body proportions from the headset alone: a per-session running estimate of the 22 bone scales.

FK, KPO and the rotation re-derivation need the wearer's bone lengths. Position errors on the validation
split fall by a third when the true body is given (MODEL_CARD.md), so the runtime estimates it while the
session runs, from five running statistics of the tracked head and wrist joints (all O(1) per sample):

    height  highest head joint above the floor (people stand up at some point)
    reach   farthest wrist from the head joint            (arm + shoulder width)
    raise   highest wrist above the head joint           (arms overhead)
    hang    lowest wrist below the head joint while standing (torso + arm)
    side    farthest wrist from the head joint, horizontally

A ridge regression fitted on the training split (``fit_body_regression``; ``egoposevr train`` writes it,
export embeds it in every model) maps ``[1, log height, reach/h, raise/h, hang/h, side/h]`` to log bone
scales. Features are clipped to the range seen in training so an unusual session cannot extrapolate. Without
a regression the body is the mean SMPL body scaled by height alone (the fallback for older model files).

Shape legend: ``J`` = 22 joints; tracked rows (head, left wrist, right wrist).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterable
from typing import Any, Final

import numpy as np

from .skeleton import FOOT_JOINT_HEIGHT_M, HEAD, NUM_JOINTS, REST_JOINTS_M

# The head joint of the mean SMPL body standing straight, above the floor (left foot joint at 3.5 cm).
STANDING_HEAD_HEIGHT_M: Final = float(REST_JOINTS_M[HEAD, 1] - REST_JOINTS_M[10, 1] + FOOT_JOINT_HEIGHT_M)
FEATURE_NAMES: Final = ("log_height", "reach", "raise", "hang", "side")
UNIFORM_SCALE_RANGE: Final = (0.8, 1.25)
BONE_SCALE_RANGE: Final = (0.3, 3.0)
STANDING_FRACTION: Final = 0.95  # "standing": the head within 5 % of the highest it has been
UPDATE_STEP_M: Final = 0.005  # refit the body when a statistic moved by 5 mm
RIDGE: Final = 1e-2


@dataclasses.dataclass(frozen=True)
class BodyRegression:
    """coef (1 + F, J) from features to log bone scales; feature_min/max (F,) the training range."""

    coef: np.ndarray
    feature_min: np.ndarray
    feature_max: np.ndarray

    def bone_scale(self, features: np.ndarray) -> np.ndarray:
        x = np.clip(features, self.feature_min, self.feature_max)
        return np.clip(np.exp(np.r_[1.0, x] @ self.coef), *BONE_SCALE_RANGE)

    def to_json(self) -> dict[str, Any]:
        return {
            "features": list(FEATURE_NAMES),
            "coef": np.round(self.coef, 6).tolist(),
            "feature_min": np.round(self.feature_min, 6).tolist(),
            "feature_max": np.round(self.feature_max, 6).tolist(),
        }

    @classmethod
    def from_json(cls, data: dict[str, Any] | str) -> BodyRegression:
        data = json.loads(data) if isinstance(data, str) else data
        if list(data.get("features", [])) != list(FEATURE_NAMES):
            raise ValueError(f"body regression features must be {FEATURE_NAMES}, got {data.get('features')}")
        coef = np.asarray(data["coef"], dtype=np.float64)
        lo, hi = (np.asarray(data[k], dtype=np.float64) for k in ("feature_min", "feature_max"))
        f = len(FEATURE_NAMES)
        if coef.shape != (1 + f, NUM_JOINTS) or lo.shape != (f,) or hi.shape != (f,):
            raise ValueError(f"body regression must be coef ({1 + f}, {NUM_JOINTS}), ranges ({f},)")
        if not (np.isfinite(coef).all() and np.isfinite(lo).all() and np.isfinite(hi).all()):
            raise ValueError("body regression holds non-finite numbers")
        return cls(coef, lo, hi)


class BodyStatistics:
    """The running statistics of one session; ``push`` per headset sample."""

    def __init__(self) -> None:
        self.height_m = 0.0
        self.reach_m = self.raise_m = self.hang_m = self.side_m = 0.0
        self._last = np.zeros(5)

    @property
    def seen(self) -> bool:
        return self.height_m > 0.0

    def push(self, joints_m: np.ndarray, valid: np.ndarray) -> bool:
        """joints_m (3, 3) tracked head / wrists, valid (3,) -> whether a statistic moved by UPDATE_STEP_M."""
        if not valid[0]:
            return False
        head = joints_m[0]
        self.height_m = max(self.height_m, float(head[1]))
        wrists = joints_m[1:][valid[1:]] - head  # (k, 3) relative to the head joint
        if len(wrists):
            self.reach_m = max(self.reach_m, float(np.sqrt((wrists**2).sum(-1)).max()))
            self.raise_m = max(self.raise_m, float(wrists[:, 1].max()))
            if head[1] >= STANDING_FRACTION * self.height_m:
                self.hang_m = max(self.hang_m, float(-wrists[:, 1].min()))
            self.side_m = max(self.side_m, float(np.sqrt(wrists[:, 0] ** 2 + wrists[:, 2] ** 2).max()))
        now = np.array([self.height_m, self.reach_m, self.raise_m, self.hang_m, self.side_m])
        moved = bool(np.abs(now - self._last).max() >= UPDATE_STEP_M)
        if moved:
            self._last = now
        return moved

    def features(self) -> np.ndarray:
        """(F,) in FEATURE_NAMES order; lengths as fractions of the height."""
        h = max(self.height_m, 0.1)
        return np.array([np.log(h), self.reach_m / h, self.raise_m / h, self.hang_m / h, self.side_m / h])


class BodyCalibrator:
    """Running bone-scale estimate: ``push`` per sample; ``bone_scale`` (J,) changes only when push says so."""

    def __init__(self, regression: BodyRegression | None = None) -> None:
        self.regression = regression
        self.stats = BodyStatistics()
        self.bone_scale = np.ones(NUM_JOINTS)

    def push(self, joints_m: np.ndarray, valid: np.ndarray) -> bool:
        """joints_m (3, 3), valid (3,) -> True when ``bone_scale`` was re-estimated."""
        if not self.stats.push(joints_m, valid):
            return False
        if self.regression is None:
            scale = np.clip(self.stats.height_m / STANDING_HEAD_HEIGHT_M, *UNIFORM_SCALE_RANGE)
            self.bone_scale = np.full(NUM_JOINTS, scale)
        else:
            self.bone_scale = self.regression.bone_scale(self.stats.features())
        return True


def sequence_features(joints_m: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """The statistics a whole sequence ends with: joints_m (N, 3, 3), valid (N, 3) -> (F,)."""
    stats = BodyStatistics()
    for x, ok in zip(joints_m, np.asarray(valid, dtype=bool), strict=True):
        stats.push(x, ok)
    return stats.features()


def fit_body_regression(examples: Iterable[tuple[np.ndarray, np.ndarray]]) -> BodyRegression:
    """Ridge fit over (features (F,), bone_scale (J,)) pairs, one per training sequence."""
    pairs = list(examples)
    if len(pairs) < 2:
        raise ValueError(f"a body regression needs at least 2 sequences, got {len(pairs)}")
    x = np.array([f for f, _ in pairs])
    design = np.c_[np.ones(len(x)), x]  # (n, 1 + F)
    target = np.log(np.array([s for _, s in pairs]))  # (n, J)
    gram = design.T @ design + RIDGE * np.eye(design.shape[1])
    coef = np.linalg.solve(gram, design.T @ target)
    return BodyRegression(coef, x.min(0), x.max(0))
