"""What the real world varies between users, drawn per sequence: the camera mount and lens, the headset's fit,
the controllers' grip, the tracking, the headset's rate, the sensor, the floor, and which body.

Two pools of draws. ``train`` is what the models learn from; ``heldout`` reserves camera mounts (a pitch band
and a field-of-view band inside the training range, and a resolution the training never sees), body shapes,
floors and sensor settings for validation only, so that a model's transfer to a rig it never saw can be
measured (``egoposevr synth --rig-pool heldout``). Every draw is recorded (:func:`record`).

Shape legend: none (scalars and small tuples).
"""

from __future__ import annotations

import dataclasses
import hashlib
from typing import Any, Final

import numpy as np

from ..rig import HEAD_OFFSET_M, LEFT_GRIP_OFFSET_M, RIGHT_GRIP_OFFSET_M
from .headset import TRACKING_CONE_DEG, CameraModel, HeadsetRig
from .render import (
    PATTERN_CARPET,
    PATTERN_CHECKER,
    PATTERN_CONCRETE,
    PATTERN_KNIT,
    PATTERN_MOTTLE,
    PATTERN_PLAIN,
    PATTERN_PRINT,
    PATTERN_STRIPES,
    PATTERN_TILES,
    PATTERN_WOOD,
    SensorNoise,
)

Interval = tuple[float, float]


@dataclasses.dataclass(frozen=True)
class RigPool:
    """The ranges one pool draws from. Bands are unions of intervals, each chosen by its width."""

    name: str
    pitch_down_deg: tuple[Interval, ...]
    hfov_deg: tuple[Interval, ...]
    resolutions: tuple[tuple[int, int], ...]
    floors: tuple[int, ...]
    heldout_bodies: bool  # the bank's held-out bodies (one in five, by a hash of the index) or the others
    hmd_rates_hz: tuple[float, ...] = (72.0, 90.0, 120.0)
    camera_yaw_sd_deg: float = 3.0
    camera_roll_sd_deg: float = 3.0
    camera_x_m: Interval = (-0.015, 0.015)  # on the visor, in the headset's frame
    camera_y_m: Interval = (-0.07, -0.02)
    camera_z_m: Interval = (-0.10, -0.05)
    ir_shadow_p: float = 0.5  # structured-light cameras (a projector beside the lens) show IR shadows
    distortion_p: float = 0.5  # leftover radial lens distortion the reported intrinsics do not describe
    k1: Interval = (-0.08, 0.05)
    two_lights_p: float = 0.4
    top_patterns: tuple[int, ...] = ()  # the shirts' patterns this pool may wear


POOLS: Final = {
    "train": RigPool(
        name="train",
        pitch_down_deg=((55.0, 66.0), (74.0, 88.0)),
        hfov_deg=((68.0, 86.0), (96.0, 112.0)),
        resolutions=((320, 256), (320, 240), (640, 480)),
        floors=(PATTERN_CHECKER, PATTERN_STRIPES, PATTERN_MOTTLE, PATTERN_WOOD, PATTERN_CARPET),
        heldout_bodies=False,
        top_patterns=(PATTERN_PLAIN, PATTERN_STRIPES, PATTERN_CHECKER, PATTERN_MOTTLE),
    ),
    "heldout": RigPool(
        name="heldout",
        pitch_down_deg=((66.0, 74.0),),
        hfov_deg=((86.0, 96.0),),
        resolutions=((424, 240),),
        floors=(PATTERN_TILES, PATTERN_CONCRETE),
        heldout_bodies=True,
        top_patterns=(PATTERN_PRINT, PATTERN_KNIT),
    ),
}
HELDOUT_BODY_SHARE: Final = 0.2


@dataclasses.dataclass(frozen=True)
class Rig:
    """One sequence's draws: the camera, the headset rig, the sensor and the headset's rate."""

    camera: CameraModel
    headset: HeadsetRig
    sensor: SensorNoise
    hmd_rate_hz: float
    jpeg_quality: int


def _band(rng: np.random.Generator, band: tuple[Interval, ...]) -> float:
    widths = np.array([hi - lo for lo, hi in band])
    lo, hi = band[int(rng.choice(len(band), p=widths / widths.sum()))]
    return float(rng.uniform(lo, hi))


def body_is_heldout(index: int) -> bool:
    """Whether a bank's body belongs to the held-out pool (a fixed hash of its index: one in five)."""
    digest = hashlib.sha256(f"body-{index}".encode()).digest()
    return digest[0] / 256 < HELDOUT_BODY_SHARE


def pool_bodies(count: int, pool: RigPool) -> list[int]:
    """The bank's bodies a pool may use (every body when the bank is too small to hold some out)."""
    chosen = [i for i in range(count) if body_is_heldout(i) == pool.heldout_bodies]
    return chosen or list(range(count))


def random_camera(rng: np.random.Generator, pool: RigPool) -> CameraModel:
    width, height = pool.resolutions[int(rng.integers(len(pool.resolutions)))]
    return CameraModel(
        width=width,
        height=height,
        hfov_deg=_band(rng, pool.hfov_deg),
        pitch_down_deg=_band(rng, pool.pitch_down_deg),
        yaw_deg=float(rng.normal(0.0, pool.camera_yaw_sd_deg)),
        roll_deg=float(rng.normal(0.0, pool.camera_roll_sd_deg)),
        position_m=(
            float(rng.uniform(*pool.camera_x_m)),
            float(rng.uniform(*pool.camera_y_m)),
            float(rng.uniform(*pool.camera_z_m)),
        ),
        k1=float(rng.uniform(*pool.k1)) if rng.random() < pool.distortion_p else 0.0,
    )


def _jitter(rng: np.random.Generator, offset: tuple[float, ...], sd_m: float) -> tuple[float, float, float]:
    x, y, z = np.asarray(offset) + rng.normal(0.0, sd_m, 3)
    return (float(x), float(y), float(z))


def random_headset(rng: np.random.Generator, head_offset_m: tuple[float, ...] = HEAD_OFFSET_M) -> HeadsetRig:
    """The headset's fit on this head, the grips in these hands, and this tracking system's behaviour."""
    return HeadsetRig(
        head_offset_m=_jitter(rng, head_offset_m, 0.008),
        left_grip_offset_m=_jitter(rng, LEFT_GRIP_OFFSET_M, 0.012),
        right_grip_offset_m=_jitter(rng, RIGHT_GRIP_OFFSET_M, 0.012),
        head_noise_m=float(rng.uniform(0.0002, 0.001)),
        hand_noise_m=float(rng.uniform(0.0008, 0.003)),
        head_noise_deg=float(rng.uniform(0.05, 0.2)),
        hand_noise_deg=float(rng.uniform(0.2, 0.8)),
        drift_m=float(rng.uniform(0.001, 0.004)),
        dropouts_per_min=float(rng.uniform(0.5, 5.0)),
        view_tilt_deg=(float(rng.normal(0.0, 4.0)), float(rng.normal(0.0, 2.0))),
        grip_tilt_deg=tuple(float(a) for a in rng.normal(0.0, 10.0, 2)),
        tracking_cone_deg=float(rng.uniform(*TRACKING_CONE_DEG)),
        occlusion_deg=float(rng.uniform(4.0, 10.0)),
        tracking_grace_s=float(rng.uniform(0.1, 0.5)),
    )


def random_sensor(rng: np.random.Generator, pool: RigPool) -> SensorNoise:
    return SensorNoise(
        depth_sigma_at_1m=float(rng.uniform(0.001, 0.005)),
        edge_hole_prob=float(rng.uniform(0.2, 0.7)),
        flying_pixel_prob=float(rng.uniform(0.05, 0.3)),
        dropout_prob=float(rng.uniform(0.001, 0.01)),
        dark_albedo=float(rng.uniform(0.01, 0.04)),  # near-black only: shaded renders are darker than albedo
        ir_baseline_m=float(rng.uniform(0.03, 0.06)) if rng.random() < pool.ir_shadow_p else 0.0,
        rgb_sigma=float(rng.uniform(1.0, 5.0)),
        vignetting=float(rng.uniform(0.1, 0.4)),
        exposure=float(np.exp(rng.normal(0.0, 0.25))),
        white_balance=tuple(float(g) for g in np.exp(rng.normal(0.0, 0.06, 3))),
    )


def random_rig(
    rng: np.random.Generator, pool: RigPool, head_offset_m: tuple[float, ...] = HEAD_OFFSET_M
) -> Rig:
    return Rig(
        camera=random_camera(rng, pool),
        headset=random_headset(rng, head_offset_m),
        sensor=random_sensor(rng, pool),
        hmd_rate_hz=float(pool.hmd_rates_hz[int(rng.integers(len(pool.hmd_rates_hz)))]),
        jpeg_quality=int(rng.integers(60, 96)),
    )


def record(rig: Rig) -> dict[str, Any]:
    """Every drawn parameter, JSON-ready (for the manifest)."""

    def plain(value: Any) -> Any:
        if isinstance(value, float):
            return round(value, 5)
        if isinstance(value, tuple | list):
            return [plain(v) for v in value]
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        return value

    return plain(dataclasses.asdict(rig))
