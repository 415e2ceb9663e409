"""Body size from the headset and the camera: a per-session running estimate of the skeleton's bone lengths.

FK, KPO and the rotation re-derivation need the wearer's bone lengths. Four sources, in order of evidence:

1. **Height.** The highest head-joint height the headset has shown (people stand up at some point) scales
   the mean SMPL body, within ``SCALE_RANGE``, assuming a stage reference space (floor at y = 0). That
   height is a lower bound, not a measurement: a head lower than the range allows (a seated or crouching
   wearer) gives the mean body until the camera has measured the legs, and shins the camera measures more
   than ``SEATED_RATIO`` times as long as the head's height says (a seated wearer, who may never stand up)
   give the height instead (:meth:`BodyCalibrator.height_scale`).
2. **Camera sightings.** The visor camera sees the hips, the lower spine and the legs most of the time. Each
   frame whose keypoints at both ends of one of ``SIGHTED_BONES`` pass Alg. 1's visibility mask gives one
   length; once a bone has ``first_measure_sightings`` of them (the pipeline's ``EARLY_BODY_SIGHTINGS``, one,
   since rule 86; ``MIN_VISUAL_SAMPLES`` without it), their median is its measurement.
3. **A fitted body regressor** (:class:`BodyRegressor`, one per RGB-D visual encoder, made by ``egoposevr
   fit-body`` from the training split): from the height and the measured lengths to every bone's length,
   including the arms, collars, neck and head the camera never sees. Proportions come in families (the
   retargeted CMU bodies against the scaled SMPL ones), and the hips and lower spine the camera sees tell
   them apart: the regressor finds the families in its training bodies (k-means), tells them apart with a
   linear discriminant and has one ridge expert per family. It records how far under the headset the head
   joints it was fitted on were (models with different head offsets share an encoder), and a calibrator
   converts its own head height to that before asking it.
4. **A calibration** (:meth:`BodyCalibrator.calibrate`, runtime/calibration.py), when the session asked for
   one: its standing head height replaces the running one and its arms replace the estimated ones.

With ``lift_to_quiet_head``, the estimate is never shorter than a quiet head says the wearer is: the highest
head joint seen while the head was quiet (:class:`QuietHead`: within ``QUIET_HEAD_RANGE_M`` on every axis over
``QUIET_HEAD_WINDOW_S``) is a standing height's lower bound that no jump reaches, and a body whose standing
head joint (:func:`standing_head_height_m`) is lower is scaled up, every bone alike, until it reaches it. The
camera can measure a wearer's legs short, and the regressor follows it (MODEL_CARD.md, "Where the eyes' anchor
loses the folds"): a served skeleton too short to reach the floor from its head floats its planted feet.

The served skeleton (:class:`ServedScale`) follows the estimate at a bounded rate, so the body grows or
shrinks over a few samples, never in one.

Without a regressor, RGB-D models keep the height scale and put the measured thigh, shin and foot medians
(30 sightings or more) in place. RGB-only models measure nothing: their keypoints guess depth
(LoadedModel.measures_body). MODEL_CARD.md ("Body regressor") has the measurements behind these choices and
what was tried and dropped.

Shape legend: ``J`` = 22 joints (bone j joins joint j to its parent; bone 0 is unused); ``B`` sighted bones;
``F = 2 + 2B`` regressor features; tracked rows (head, left wrist, right wrist).
"""

from __future__ import annotations

import json
import re
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import numpy as np

from ..provenance import file_digest
from ..rig import STILLNESS_OFFSET_M
from ..skeleton import (
    FOOT_JOINT_HEIGHT_M,
    HEAD,
    NUM_JOINTS,
    PARENTS,
    REST_JOINTS_M,
    bone_lengths,
    bone_scale_of,
    forward_kinematics,
    rest_offsets,
)

# The head joint of the mean SMPL body standing straight, above the floor (left foot joint at 3.5 cm).
STANDING_HEAD_HEIGHT_M: Final = float(REST_JOINTS_M[HEAD, 1] - REST_JOINTS_M[10, 1] + FOOT_JOINT_HEIGHT_M)
SCALE_RANGE: Final = (0.8, 1.25)
# Measured shins this many times as long as the head's height scale says are a wearer whose head is not at
# standing height: seated 1.35-1.71 on procedural seated streams, standing 0.95-1.11, and 0.94-1.02 on the
# bundled recordings' other rig. Then the shins' scale is the height's. Not the thighs: a rig unlike the
# training pool's measures them up to 10 % long, and thighs with shins sat a standing walker down at 1.10
# (MODEL_CARD.md, "A false seat on another rig").
SEATED_RATIO: Final = 1.25
SEATED_BONES: Final = (7, 8)  # shins
UPDATE_STEP_M: Final = 0.005  # rescale when the head is 5 mm higher than ever (rebuilding offsets is cheap)
# Bones the downward camera sees (each joint's bone from its parent): hips, lower spine, thighs, shins, feet.
SIGHTED_BONES: Final = tuple(range(1, 12))
# What the fallback without a regressor takes from the camera, as (left, right) pairs: thighs, shins, feet.
LEG_BONES: Final = (4, 5, 7, 8, 10, 11)
ARM_BONES: Final = (18, 19, 20, 21)  # upper arms and forearms, which a T-pose calibration measures
# A median of 5 sightings is a measurement for the regressor, which was fitted on such early medians too
# (validation upper-body MPJPE 2.59 cm with 30, 2.49 cm with 5: the CMU clips there last 2-4 s). The fallback
# trusts a leg bone from STEADY_SAMPLES on; medians are refreshed every frame until then, every 10th after.
MIN_VISUAL_SAMPLES: Final = 5
# A stream's body measured from its first sighting on (Pipeline(early_body=True)): the height's body, which the
# first answers serve until then, has still standers' legs about 2 cm short of where the camera puts them a
# quarter second later, and held legs then lengthen under a still person (MODEL_CARD.md, "Where a still
# person's first second goes under today's pair"). The pipeline's default since rule 86.
EARLY_BODY_SIGHTINGS: Final = 1
STEADY_SAMPLES: Final = 30  # one second of frames at 30 Hz with the bone in view
VISUAL_WINDOW: Final = 600  # the median over the last 20 s of sightings
VISUAL_SCALE_RANGE: Final = (0.7, 1.4)  # per leg bone in the fallback, relative to the mean body
MEASURED_SCALE_RANGE: Final = (0.25, 4.0)  # a measurement outside this is a broken keypoint, not a body
PREDICTED_SCALE_RANGE: Final = (0.3, 2.5)  # the regressor's output, per bone (CMU spine2 is 0.4, head 1.9)
FAMILIES: Final = 2  # body proportion families the regressor looks for in its training bodies
DISCRIMINANT_RIDGE: Final = 1e-3  # added to the features' covariance (the constant feature has none)
# The served skeleton follows the estimate at most this fast (scale per second, per bone). A new measurement
# (the regressor's first answers, from a session's first camera frames, change the legs by ~5 %) never resizes the
# body in one sample: KPO plants the soles on the position filter's body, whose bones lag behind, so a jump
# put planted feet up to 7 cm off or through the floor for the next few samples. 0.5 is the slowest of 0.25 /
# 0.5 / 1 that cost the training split at most 0.03 cm of lower body (MODEL_CARD.md, "A body that grows").
SERVED_SCALE_RATE_PER_S: Final = 0.5
SERVED_SCALE_MAX_STEP_S: Final = 0.1  # a longer pause between samples counts as this long
# With Pipeline(body_hold=True), the default, while the legs are held: the hips, thighs, shins and feet keep
# their served size once the camera's first measurement (or the last calibration) is BODY_HOLD_AFTER_S old
# (:func:`held_target`). The spine follows the estimate: kept too, the standing upper body was 3.4 % further
# off (MODEL_CARD.md, rule 56); the legs alone cost it nothing (rule 57).
HELD_LEG_BONES: Final = (1, 2, *LEG_BONES)
BODY_HOLD_AFTER_S: Final = 1.0
# A quiet head: within QUIET_HEAD_RANGE_M on each axis over QUIET_HEAD_WINDOW_S (:class:`QuietHead`): the
# first values the probe behind rule 77 read (MODEL_CARD.md), not chosen on any number.
QUIET_HEAD_WINDOW_S: Final = 0.5
QUIET_HEAD_RANGE_M: Final = 0.02
REGRESSOR_KIND: Final = "egoposevr.body_regressor"
REGRESSOR_SUFFIX: Final = ".body.json"  # beside its encoder: visual-rgbd.onnx -> visual-rgbd.body.json
# The head offset's height (rig.HEAD_OFFSET_M[1]) of the head joints a regressor file without one was fitted
# on: every model's until 2026-11-27, which rig keeps as the stillness gates' point.
LEGACY_REGRESSOR_HEAD_OFFSET_Y_M: Final = STILLNESS_OFFSET_M[1]
_REST_BONE_M: Final = bone_lengths(rest_offsets())
_SIGHTED: Final = np.array(SIGHTED_BONES)
_SIGHTED_PARENTS: Final = PARENTS[_SIGHTED]
_HELD_LEGS: Final = np.array(HELD_LEG_BONES)
_REST_POSE: Final = np.broadcast_to(np.eye(3), (NUM_JOINTS, 3, 3))  # every joint's local rotation at rest
_FEET: Final = np.array([10, 11])  # the foot joints, left and right
_QUIET_HEAD_WINDOW_US: Final = int(QUIET_HEAD_WINDOW_S * 1e6)


def standing_head_height_m(bone_scale: np.ndarray) -> float:
    """The head joint's height above the floor (m) of a body with this bone scale (J,) standing straight: the
    rest pose with its lower foot joint FOOT_JOINT_HEIGHT_M up (STANDING_HEAD_HEIGHT_M for the mean body)."""
    rest_m, _ = forward_kinematics(_REST_POSE, np.zeros(3), rest_offsets(bone_scale))
    return float(rest_m[HEAD, 1] - rest_m[_FEET, 1].min()) + FOOT_JOINT_HEIGHT_M


class QuietHead:
    """The highest head joint (world y, m) seen while the head was quiet: every sample of the last
    QUIET_HEAD_WINDOW_S (the window spanned in full) within QUIET_HEAD_RANGE_M of each other on each axis. A
    person's head is at most their standing height while both feet are on the floor, and a jump, a step or a
    rise never keeps it that still. A lost head or a pause longer than the window starts the window again."""

    def __init__(self) -> None:
        self.highest_m: float | None = None
        self._t_us: deque[int] = deque()
        self._head_m: deque[np.ndarray] = deque()

    def push(self, t_us: int, head_m: np.ndarray, valid: bool) -> bool:
        """One headset sample's head joint (3,) m -> whether ``highest_m`` rose (by UPDATE_STEP_M or more)."""
        window_us = _QUIET_HEAD_WINDOW_US
        if not valid or (self._t_us and not 0 <= t_us - self._t_us[-1] <= window_us):
            self._t_us.clear()
            self._head_m.clear()
        if not valid:
            return False
        self._t_us.append(t_us)
        self._head_m.append(np.array(head_m, dtype=np.float64))
        while len(self._t_us) > 1 and t_us - self._t_us[1] >= window_us:  # keep one sample at the edge
            self._t_us.popleft()
            self._head_m.popleft()
        higher = self.highest_m is None or head_m[1] >= self.highest_m + UPDATE_STEP_M
        if not higher or t_us - self._t_us[0] < window_us:
            return False
        if np.ptp(np.array(self._head_m), axis=0).max() > QUIET_HEAD_RANGE_M:
            return False
        self.highest_m = float(head_m[1])
        return True


def height_scale(highest_head_m: float) -> float:
    """The mean body's scale for a head joint seen at most this high (1.0 before any sample)."""
    if highest_head_m <= 0:
        return 1.0
    return float(np.clip(highest_head_m / STANDING_HEAD_HEIGHT_M, *SCALE_RANGE))


@dataclass(frozen=True)
class BodyRegressor:
    """Height + camera-measured bone scales -> all bone scales, fitted on one visual encoder's keypoints.

    A mixture of ``K`` linear experts, one per body family. Features (F,): ``[1, log h, (seen_b,
    seen_b·(log m_b − log h)) for b in feature_bones]`` with ``h`` the height scale and ``m_b`` bone b's
    measured scale; an unmeasured bone contributes zeros. A linear discriminant on the same features gives
    each family's probability; each expert predicts the log of every bone's scale relative to ``h``; the
    prediction is their probability-weighted mean.

    Why a mixture: one linear map across families interpolates between them, so a camera that measures the
    hips or mid-spine 10 % off (another resolution, another lens) got a body halfway to the other family —
    neck and head bones 15 % off on the bundled 128×96 recordings, worse than no regressor. A measurement
    that is 10 % off is still far nearer its own family, so the discriminant stays sure of it and that
    family's expert, whose slopes are small, moves little.
    """

    feature_bones: tuple[int, ...]
    weights: np.ndarray  # (K, F, J - 1): each family's expert, bones 1..J-1
    discriminant: np.ndarray  # (K, F + 1): each family's linear score on the features, then its offset
    encoder_sha256: str
    # How far under the view pose the head joints whose heights it was fitted on were (the fitting model's
    # rig offset). An encoder serves models with different head offsets, and h must mean what it meant then.
    head_offset_y_m: float = LEGACY_REGRESSOR_HEAD_OFFSET_Y_M
    record: dict[str, Any] = field(default_factory=dict)  # what it was fitted on and how well it did

    def features(self, scale_h: float, measured: dict[int, float]) -> np.ndarray:
        """scale_h the height scale, measured {bone: scale} -> (F,)."""
        return _features(self.feature_bones, scale_h, measured)

    def family_probabilities(self, scale_h: float, measured: dict[int, float]) -> np.ndarray:
        """-> (K,) the probability of each family given the evidence."""
        return self._probabilities(self.features(scale_h, measured))

    def _probabilities(self, x: np.ndarray) -> np.ndarray:
        """Features (F,) -> (K,) family probabilities (softmax of the discriminant's scores)."""
        scores = self.discriminant[:, :-1] @ x + self.discriminant[:, -1]
        scores = np.exp(scores - scores.max())
        return scores / scores.sum()

    def predict(self, scale_h: float, measured: dict[int, float]) -> np.ndarray:
        """-> bone_scale (J,), bone 0 (the root) at the height scale."""
        x = self.features(scale_h, measured)
        log_relative = self._probabilities(x) @ (x @ self.weights)  # (J - 1,)
        return np.concatenate([[scale_h], np.clip(scale_h * np.exp(log_relative), *PREDICTED_SCALE_RANGE)])

    @classmethod
    def fit(
        cls,
        scales_h: np.ndarray,
        measured: list[dict[int, float]],
        true_scale: np.ndarray,
        encoder_sha256: str,
        head_offset_y_m: float,
        ridge: float = 1.0,
        row_weight: np.ndarray | None = None,
        families: int = FAMILIES,
        feature_bones: tuple[int, ...] = SIGHTED_BONES,
    ) -> BodyRegressor:
        """Fit over N rows: scales_h (N,), measured N dicts, true_scale (N, J), row_weight (N,) (default 1);
        the height scales are of head joints head_offset_y_m under the view pose.

        Families are found, not given: k-means on the rows' true proportions (log scale relative to the
        height scale). Then a weighted ridge expert per family (intercept not penalised) and a linear
        discriminant with a shared, slightly regularised covariance."""
        if len(scales_h) == 0:
            raise ValueError("no rows to fit a body regressor on: the camera measured no bone")
        x = np.array([_features(feature_bones, h, m) for h, m in zip(scales_h, measured, strict=True)])
        y = np.log(np.asarray(true_scale)[:, 1:]) - np.log(np.asarray(scales_h))[:, None]
        w = np.ones(len(x)) if row_weight is None else np.asarray(row_weight, dtype=np.float64)
        label = _k_means(y, w, min(families, len(np.unique(y, axis=0))))
        label = np.unique(label, return_inverse=True)[1].ravel()  # no empty family
        families = int(label.max()) + 1
        weights = np.stack(
            [_ridge(x[label == k], y[label == k], w[label == k], ridge) for k in range(families)]
        )
        record = {"ridge": ridge, "rows": len(x), "families": np.bincount(label, minlength=families).tolist()}
        discriminant = _discriminant(x, label, w, families)
        return cls(tuple(feature_bones), weights, discriminant, encoder_sha256, head_offset_y_m, record)

    def save(self, path: Path) -> None:
        doc = {
            "kind": REGRESSOR_KIND,
            "version": 2,
            "encoder_sha256": self.encoder_sha256,
            "head_offset_y_m": self.head_offset_y_m,
            "feature_bones": list(self.feature_bones),
            "weights": self.weights.round(6).tolist(),
            "discriminant": self.discriminant.round(6).tolist(),
            "record": self.record,
        }
        # One line per list of numbers (a weight row), so that the file reads, and diffs, row by row.
        text = re.sub(
            r"\[\s+([-+0-9.e,\s]+?)\s+\]",
            lambda m: "[" + re.sub(r"\s+", " ", m[1]) + "]",
            json.dumps(doc, indent=1),
        )
        path.write_text(text + "\n")

    @classmethod
    def load(cls, path: Path) -> BodyRegressor:
        """Raises ValueError for a file that is not a well-formed regressor."""
        try:
            doc = json.loads(path.read_text())
            if doc.get("kind") != REGRESSOR_KIND or doc.get("version") != 2:
                raise ValueError(f"kind/version {doc.get('kind')!r}/{doc.get('version')!r}")
            bones = tuple(int(b) for b in doc["feature_bones"])
            weights = np.asarray(doc["weights"], dtype=np.float64)
            discriminant = np.asarray(doc["discriminant"], dtype=np.float64)
            n_features = 2 + 2 * len(bones)
            if not all(0 < b < NUM_JOINTS for b in bones) or weights.ndim != 3:
                raise ValueError(f"feature bones {bones}, weights {weights.shape}")
            if weights.shape[1:] != (n_features, NUM_JOINTS - 1):
                raise ValueError(f"{len(bones)} feature bones with weights {weights.shape}")
            if discriminant.shape != (weights.shape[0], n_features + 1):
                raise ValueError(f"discriminant {discriminant.shape} for weights {weights.shape}")
            if not (np.isfinite(weights).all() and np.isfinite(discriminant).all()):
                raise ValueError("weights are not finite")
            offset_y_m = float(doc.get("head_offset_y_m", LEGACY_REGRESSOR_HEAD_OFFSET_Y_M))
            if not abs(offset_y_m) < 0.5:
                raise ValueError(f"head_offset_y_m {offset_y_m}")
            sha = str(doc["encoder_sha256"])
            return cls(bones, weights, discriminant, sha, offset_y_m, dict(doc.get("record", {})))
        except (OSError, KeyError, TypeError, ValueError) as exc:  # json.JSONDecodeError is a ValueError
            raise ValueError(f"{path}: not a body regressor ({exc})") from exc


def _features(feature_bones: tuple[int, ...], scale_h: float, measured: dict[int, float]) -> np.ndarray:
    log_h = np.log(scale_h)
    out = [1.0, log_h]
    for b in feature_bones:
        out += [1.0, float(np.log(measured[b])) - log_h] if b in measured else [0.0, 0.0]
    return np.array(out)


def _ridge(x: np.ndarray, y: np.ndarray, w: np.ndarray, ridge: float) -> np.ndarray:
    """Weighted ridge, x (N, F) with the intercept in column 0 (not penalised), y (N, T) -> (F, T)."""
    penalty = ridge * np.eye(x.shape[1])
    penalty[0, 0] = 0.0
    return np.linalg.solve(x.T @ (w[:, None] * x) + penalty, x.T @ (w[:, None] * y))


def _k_means(y: np.ndarray, w: np.ndarray, k: int, iterations: int = 50) -> np.ndarray:
    """Weighted k-means of rows y (N, T) -> labels (N,). Deterministic: farthest-point initialisation."""
    centres = [y[np.argmax(np.linalg.norm(y - np.average(y, axis=0, weights=w), axis=1))]]
    while len(centres) < k:
        distance = np.min([np.linalg.norm(y - c, axis=1) for c in centres], axis=0)
        centres.append(y[np.argmax(distance)])
    centre = np.array(centres)
    for _ in range(iterations):
        label = np.argmin(np.linalg.norm(y[:, None] - centre[None], axis=-1), axis=1)
        for j in range(k):
            if (label == j).any():
                centre[j] = np.average(y[label == j], axis=0, weights=w[label == j])
    return np.argmin(np.linalg.norm(y[:, None] - centre[None], axis=-1), axis=1)


def _discriminant(x: np.ndarray, label: np.ndarray, w: np.ndarray, k: int) -> np.ndarray:
    """Linear discriminant (shared covariance, + DISCRIMINANT_RIDGE) -> (K, F + 1) scores and offsets."""
    means = np.array([np.average(x[label == j], axis=0, weights=w[label == j]) for j in range(k)])
    centred = x - means[label]
    covariance = (w[:, None] * centred).T @ centred / w.sum() + DISCRIMINANT_RIDGE * np.eye(x.shape[1])
    slopes = np.linalg.solve(covariance, means.T).T  # (K, F)
    prior = np.array([w[label == j].sum() for j in range(k)]) / w.sum()
    offsets = -0.5 * np.einsum("kf,kf->k", slopes, means) + np.log(prior)
    return np.concatenate([slopes, offsets[:, None]], axis=1)


def regressor_path(encoder_path: Path) -> Path:
    """Where the regressor of an encoder lives: visual-rgbd.onnx -> visual-rgbd.body.json."""
    return encoder_path.with_name(encoder_path.stem + REGRESSOR_SUFFIX)


def load_regressor_for(encoder_path: Path) -> BodyRegressor | None:
    """The encoder's regressor, or None when it has none. Raises ValueError for a corrupt file or one fitted
    on another encoder (its features would be another network's keypoints)."""
    path = regressor_path(encoder_path)
    if not path.exists():
        return None
    regressor = BodyRegressor.load(path)
    if regressor.encoder_sha256 != file_digest(encoder_path):
        raise ValueError(
            f"{path.name} was fitted on another {encoder_path.name}; run egoposevr fit-body again"
        )
    return regressor


class BodyCalibrator:
    """Running body-scale estimate: ``push`` per headset sample, ``push_visual`` per camera frame;
    ``bone_scale`` (J,) changes only when one of them returns True."""

    def __init__(
        self,
        regressor: BodyRegressor | None = None,
        head_offset_y_m: float | None = None,
        lift_to_quiet_head: bool = False,
        first_measure_sightings: int = MIN_VISUAL_SAMPLES,
    ) -> None:
        """head_offset_y_m: how far under the view pose the pushed head joints are (the model's rig offset);
        None when it is the regressor's own. lift_to_quiet_head: the estimate is never shorter than the highest
        quiet head (:class:`QuietHead`; ignored once a calibration measured the height).
        first_measure_sightings: how many sightings of a bone make its first measurement (MIN_VISUAL_SAMPLES,
        or EARLY_BODY_SIGHTINGS for a body measured from the first frame on)."""
        if first_measure_sightings < 1:
            raise ValueError(f"first_measure_sightings {first_measure_sightings}: at least 1")
        self.first_measure_sightings = first_measure_sightings
        self.regressor = regressor
        self.quiet_head = QuietHead() if lift_to_quiet_head else None
        # What the regressor's height scale needs added to the heights pushed here to mean what it did when
        # it was fitted: the head joint is the offset's height under the view pose.
        self._regressor_lift_m = (
            0.0
            if regressor is None or head_offset_y_m is None
            else head_offset_y_m - regressor.head_offset_y_m
        )
        self.highest_head_m = 0.0
        self.bone_scale = np.ones(NUM_JOINTS)
        self._sightings = {j: deque(maxlen=VISUAL_WINDOW) for j in SIGHTED_BONES}
        self._count = dict.fromkeys(SIGHTED_BONES, 0)
        self.measured: dict[int, float] = {}  # bone -> median length / mean-body length, once measured
        self.height_locked = False  # a calibration measured the height: push() no longer raises it
        self.arm_scale: float | None = None  # a calibration's arms (upper arm and forearm), else estimated

    @property
    def height_scale(self) -> float:
        """The height scale the prior reads (:meth:`_height_scale_at` of the highest head joint seen)."""
        return self._height_scale_at(self.highest_head_m)

    def _height_scale_at(self, head_m: float) -> float:
        """The height scale for a highest head joint at head_m: the head's (:func:`height_scale`), unless the
        wearer is evidently not standing. A calibration measured a standing height: it is read as it is.
        Otherwise, once a head was seen, measured shins more than SEATED_RATIO times the head's unclipped scale
        give it; a head below SCALE_RANGE (or none yet) without such shins gives the mean body (1.0)."""
        if self.height_locked:
            return height_scale(head_m)
        head_scale = max(head_m, 0.0) / STANDING_HEAD_HEIGHT_M
        shins = [self.measured[j] for j in SEATED_BONES if j in self.measured]
        shin_scale = float(np.mean(shins)) if shins else 0.0
        if head_scale > 0 and shin_scale > SEATED_RATIO * head_scale:
            return float(np.clip(shin_scale, *SCALE_RANGE))
        if head_scale < SCALE_RANGE[0]:
            return 1.0
        return height_scale(head_m)

    @property
    def stood(self) -> bool:
        """Whether the height is a standing wearer's: a calibration's, or a highest head within SCALE_RANGE
        that the measured shins do not call seated (:meth:`_height_scale_at`). A body sized while the wearer
        only sat has its height from the legs or the mean body's."""
        if self.height_locked:
            return True
        head_scale = max(self.highest_head_m, 0.0) / STANDING_HEAD_HEIGHT_M
        shins = [self.measured[j] for j in SEATED_BONES if j in self.measured]
        seated = bool(shins) and float(np.mean(shins)) > SEATED_RATIO * head_scale
        return head_scale >= SCALE_RANGE[0] and not seated

    def calibrate(self, head_height_m: float | None, arm_scale: float | None) -> None:
        """A calibration's standing head-joint height and arm scale (runtime/calibration.py) replace the
        running estimates; None, None goes back to estimating (from the height reached so far)."""
        self.height_locked = head_height_m is not None
        if head_height_m is not None:
            self.highest_head_m = float(head_height_m)
        self.arm_scale = arm_scale
        self._rebuild()

    def push(self, joints_m: np.ndarray, valid: np.ndarray, t_us: int = 0) -> bool:
        """joints_m (3, 3) tracked head / wrist joint positions, valid (3,), the sample's time t_us (read only
        with ``lift_to_quiet_head``) -> whether the scale changed."""
        quieter = self.quiet_head is not None and self.quiet_head.push(t_us, joints_m[0], bool(valid[0]))
        head_y = float(joints_m[0, 1])
        higher = not self.height_locked and valid[0] and head_y >= self.highest_head_m + UPDATE_STEP_M
        if higher:
            self.highest_head_m = head_y
        if not (higher or (quieter and not self.height_locked)):
            return False
        self._rebuild()
        return True

    def push_visual(self, keypoints_m: np.ndarray, visible: np.ndarray) -> bool:
        """keypoints_m (J, 3) one frame's keypoints (any rigid frame), visible (J,) Alg. 1's mask -> whether
        the scale changed. Cheap per frame; the medians are refreshed every 10 sightings of a bone."""
        changed = False
        in_view = np.asarray(visible[_SIGHTED], dtype=bool) & np.asarray(
            visible[_SIGHTED_PARENTS], dtype=bool
        )
        lengths = np.linalg.norm(keypoints_m[_SIGHTED] - keypoints_m[_SIGHTED_PARENTS], axis=-1)
        for k in np.flatnonzero(in_view):
            j = SIGHTED_BONES[k]
            seen = self._sightings[j]
            seen.append(float(lengths[k]))
            self._count[j] += 1  # the window stops growing at VISUAL_WINDOW; the count does not
            count = self._count[j]
            if count >= self.first_measure_sightings and (count < STEADY_SAMPLES or count % 10 == 0):
                self.measured[j] = float(np.clip(np.median(seen) / _REST_BONE_M[j], *MEASURED_SCALE_RANGE))
                changed = True
        if changed:
            self._rebuild()
        return changed

    def _rebuild(self) -> None:
        """bone_scale from what is known: the regressor once the camera measured anything (it was fitted on
        measured bodies only), else the height scale with the measured leg bones in place (left and right
        averaged, so the body stays symmetric where only one side was seen); a calibration's arms win."""
        if self.regressor is not None and self.measured:
            scale = self.regressor.predict(self._regressor_height_scale(), self.measured)
        else:
            scale = self._height_and_legs(self.height_scale)
        scale = self._lifted(scale)
        if self.arm_scale is not None:
            scale[list(ARM_BONES)] = self.arm_scale
        self.bone_scale = scale

    def _lifted(self, scale: np.ndarray) -> np.ndarray:
        """scale (J,), or with ``lift_to_quiet_head`` every bone of it scaled up just enough for its standing
        head joint to reach the highest quiet head (never above SCALE_RANGE's tallest body: a head that high
        stands on something); as it is once a calibration measured the height."""
        if self.quiet_head is None or self.quiet_head.highest_m is None or self.height_locked:
            return scale
        reach_m = min(self.quiet_head.highest_m, SCALE_RANGE[1] * STANDING_HEAD_HEIGHT_M)
        standing_m = standing_head_height_m(scale)
        if reach_m <= standing_m:
            return scale
        # the foot joint's height over the floor is the sole's, not a bone's: it does not scale
        return scale * ((reach_m - FOOT_JOINT_HEIGHT_M) / (standing_m - FOOT_JOINT_HEIGHT_M))

    def _regressor_height_scale(self) -> float:
        """The height scale as the regressor's fitting model would have measured it."""
        if self.highest_head_m <= 0:
            return self.height_scale
        return self._height_scale_at(self.highest_head_m + self._regressor_lift_m)

    def _height_and_legs(self, scale_h: float) -> np.ndarray:
        scale = np.full(NUM_JOINTS, scale_h)
        for left, right in zip(LEG_BONES[::2], LEG_BONES[1::2], strict=True):
            measured = [
                self.measured[j]
                for j in (left, right)
                if j in self.measured and self._count[j] >= STEADY_SAMPLES
            ]
            if measured:
                scale[left] = scale[right] = float(np.clip(np.mean(measured), *VISUAL_SCALE_RANGE))
        return scale


# A body a client gives (PROTOCOL.md §4.2, ``set_body``): each bone between these multiples of the mean body's.
GIVEN_SCALE_RANGE: Final = (0.5, 2.0)


def bone_lengths_m(bone_scale: np.ndarray) -> np.ndarray:
    """The skeleton's bone lengths (J - 1,) m, joints 1..21 (each from its parent), for a bone scale (J,)."""
    return bone_lengths(rest_offsets(bone_scale))[1:]


def scale_of_lengths(lengths_m: np.ndarray) -> np.ndarray:
    """The bone scale (J,) of bone lengths (J - 1,) m as :func:`bone_lengths_m` gives them; the pelvis row is 1.
    Raises ValueError naming the first bone outside GIVEN_SCALE_RANGE times the mean body's."""
    lengths_m = np.asarray(lengths_m, dtype=np.float64)
    if lengths_m.shape != (NUM_JOINTS - 1,) or not np.isfinite(lengths_m).all():
        raise ValueError(f"bone lengths must be {NUM_JOINTS - 1} finite numbers, got shape {lengths_m.shape}")
    scale = bone_scale_of(lengths_m)
    low, high = GIVEN_SCALE_RANGE
    for j in range(1, NUM_JOINTS):
        if not low <= scale[j] <= high:
            raise ValueError(
                f"bone {j} ({lengths_m[j - 1]:.3f} m) is not {low}-{high} times the mean body's "
                f"({_REST_BONE_M[j]:.3f} m)"
            )
    return scale


class GivenBody:
    """A pipeline's body as a client gives it (``set_body``, PROTOCOL.md §4.2) or estimates it. The pipeline
    holds ``fixed_body``, ``bone_scale`` (J,) and ``body`` (its :class:`BodyCalibrator`), and says what to do when
    the body changes (``_body_changed``) and what it serves while it estimates (``_estimated_scale``)."""

    fixed_body: bool
    bone_scale: np.ndarray
    body: BodyCalibrator

    def give_body(self, bone_scale: np.ndarray | None) -> None:
        """Serve this bone scale (J,) from the next sample on, across reset() and calibrations; None: estimate
        the wearer's body again, from where the estimate is."""
        self.fixed_body = bone_scale is not None
        self.bone_scale = (
            np.ones(NUM_JOINTS) if bone_scale is None else np.array(bone_scale, dtype=np.float64)
        )
        self._body_changed()

    @property
    def given_body(self) -> np.ndarray | None:
        """The bone scale (J,) a client gave, or None while the body is estimated."""
        return self.bone_scale.copy() if self.fixed_body else None

    def served_body(self) -> tuple[np.ndarray, bool]:
        """The wearer's bone scale (J,) as the session knows it now (the one given, or the running estimate,
        which the served skeleton follows), and whether it is worth keeping for their next session: the camera
        has measured some of their bones and they have stood (or calibrated) this session
        (:attr:`BodyCalibrator.stood`). A body learnt while the wearer only sat, given to them standing, made
        their feet skate six times as fast (MODEL_CARD.md, "A known wearer's body from the first sample")."""
        scale = self.bone_scale if self.fixed_body else self._estimated_scale()
        return np.array(scale, dtype=np.float64), bool(self.body.measured) and self.body.stood

    def _body_changed(self) -> None:
        raise NotImplementedError

    def _estimated_scale(self) -> np.ndarray:
        raise NotImplementedError


def held_target(
    estimate: np.ndarray, served: np.ndarray | None, t_us: int, since_us: int | None
) -> np.ndarray:
    """What the served skeleton follows while the legs are held: the estimate (J,) with HELD_LEG_BONES at
    their served size (J,; None before the first sample), once the hold's clock (since_us: the camera's first
    measurement, or the first sample after a later calibration; None: none yet) is BODY_HOLD_AFTER_S old.
    Before that the body is still arriving (the height's body, the regressor's first answers), and keeping it
    keeps a wrong one (MODEL_CARD.md, "A body that keeps its size while the legs are held"). After it, every
    change of the estimate under still legs moves held knees and planted feet: on ten-second still streams
    the estimate's changes, not its error, are what a still stander's leg leakage is (MODEL_CARD.md, rule
    55's diagnosis)."""
    if served is None or since_us is None or (t_us - since_us) * 1e-6 < BODY_HOLD_AFTER_S:
        return estimate
    out = np.array(estimate, dtype=np.float64)
    out[_HELD_LEGS] = served[_HELD_LEGS]
    return out


class ServedScale:
    """The bone scale (J,) the served skeleton uses: it follows a target (the running estimate) at most
    ``SERVED_SCALE_RATE_PER_S`` per second per bone. The first target is taken at once: there is no served
    body yet to disturb."""

    def __init__(self) -> None:
        self.scale: np.ndarray | None = None
        self._last_us: int | None = None

    def follow(self, t_us: int, target: np.ndarray) -> bool:
        """Step towards target (J,) for a sample at t_us -> whether the scale changed."""
        elapsed_s = 0.0 if self._last_us is None else (t_us - self._last_us) * 1e-6
        self._last_us = t_us
        if self.scale is None:
            self.scale = np.array(target, dtype=np.float64)
            return True
        gap = target - self.scale
        if not gap.any():
            return False
        max_step = SERVED_SCALE_RATE_PER_S * float(np.clip(elapsed_s, 0.0, SERVED_SCALE_MAX_STEP_S))
        self.scale = self.scale + np.clip(gap, -max_step, max_step)
        return True
