"""Rig draws: the held-out pool never overlaps the training pool, every draw is recorded, seeds repeat; and the
depth sensor's imperfections follow their formulas."""

import dataclasses

import numpy as np
import pytest

from egoposevr.model.synth.headset import CameraModel
from egoposevr.model.synth.render import Renderer, SensorNoise, ir_shadow
from egoposevr.model.synth.variation import POOLS, Rig, body_is_heldout, pool_bodies, random_rig, record


def _inside(value, band):
    return any(lo <= value <= hi for lo, hi in band)


def test_the_heldout_pool_shares_no_mount_lens_resolution_floor_or_body_with_training():
    train, heldout = POOLS["train"], POOLS["heldout"]
    rng = np.random.default_rng(0)
    for _ in range(200):
        cam = random_rig(rng, heldout).camera
        assert _inside(cam.pitch_down_deg, heldout.pitch_down_deg)
        assert not any(lo < cam.pitch_down_deg < hi for lo, hi in train.pitch_down_deg)
        assert not any(lo < cam.hfov_deg < hi for lo, hi in train.hfov_deg)
    assert not set(train.resolutions) & set(heldout.resolutions)
    assert not set(train.floors) & set(heldout.floors)
    bodies = {name: set(pool_bodies(100, pool)) for name, pool in POOLS.items()}
    assert not bodies["train"] & bodies["heldout"] and len(bodies["heldout"]) in range(10, 31)
    assert all(body_is_heldout(i) for i in bodies["heldout"])


def test_every_drawn_parameter_is_recorded_and_a_seed_repeats_its_draws():
    rig = random_rig(np.random.default_rng([4, 2]), POOLS["train"])
    assert rig == random_rig(np.random.default_rng([4, 2]), POOLS["train"])
    assert rig != random_rig(np.random.default_rng([4, 3]), POOLS["train"])
    recorded = record(rig)
    for field in dataclasses.fields(Rig):
        value = getattr(rig, field.name)
        assert field.name in recorded
        if dataclasses.is_dataclass(value):
            assert {f.name for f in dataclasses.fields(value)} == set(recorded[field.name])
    assert 68 <= recorded["camera"]["hfov_deg"] <= 112 and recorded["hmd_rate_hz"] in (72.0, 90.0, 120.0)


FLAT = CameraModel(width=64, height=48, hfov_deg=60.0, min_depth_m=0.1, max_depth_m=6.0)


def _sensor(**changes):
    quiet = dict(edge_hole_prob=0.0, dropout_prob=0.0, rgb_sigma=0.0, vignetting=0.0)
    return SensorNoise(**{**quiet, **changes})


def test_depth_noise_grows_with_the_square_of_the_distance():
    renderer = Renderer(FLAT)
    rng = np.random.default_rng(1)
    for z in (0.5, 1.5, 3.0):
        depth = np.full((48, 64), z)
        _, depth_mm = renderer.add_noise(
            np.full((48, 64, 3), 128.0), depth, rng, _sensor(depth_sigma_at_1m=0.004)
        )
        error = depth_mm / 1000.0 - z
        assert np.std(error) == pytest.approx(np.hypot(0.004 * z * z, 0.001 / np.sqrt(12)), rel=0.12)
        assert abs(np.mean(error)) < 0.0015


def test_edges_give_holes_and_flying_pixels_between_the_two_sides():
    depth = np.full((48, 64), 2.0)
    depth[:, :32] = 1.0
    renderer = Renderer(FLAT)
    noise = _sensor(depth_sigma_at_1m=0.0, edge_hole_prob=0.3, flying_pixel_prob=0.5)
    _, depth_mm = renderer.add_noise(np.full((48, 64, 3), 128.0), depth, np.random.default_rng(2), noise)
    edge = depth_mm[:, 31:33] / 1000.0
    assert 0.15 < np.mean(edge == 0) < 0.45
    between = (edge > 1.0) & (edge < 2.0)
    assert 0.3 < np.mean(between) < 0.7
    assert (depth_mm[:, :30] == 1000).all() and (depth_mm[:, 34:] == 2000).all()


def test_dark_surfaces_and_out_of_range_return_nothing():
    renderer = Renderer(FLAT)
    rgb = np.full((48, 64, 3), 200.0)
    rgb[:, :16] = 5.0
    depth = np.full((48, 64), 1.0)
    depth[:, 48:] = 7.0
    noise = _sensor(dark_albedo=0.1, dark_hole_prob=1.0)
    _, depth_mm = renderer.add_noise(rgb, depth, np.random.default_rng(3), noise)
    assert (depth_mm[:, :16] == 0).all() and (depth_mm[:, 48:] == 0).all() and (depth_mm[:, 16:48] > 0).all()


def test_the_ir_shadow_is_as_wide_as_the_projector_baseline_says():
    """A near object (0.5 m) on the left of a wall (2 m): the projector b to the left cannot light the wall for
    f·b·(1/0.5 - 1/2) pixels right of the object's edge."""
    depth = np.full((10, 200), 2.0)
    depth[:, :80] = 0.5
    fb = 100.0 * 0.05
    shadow = ir_shadow(depth, fb)
    width = fb * (1 / 0.5 - 1 / 2.0)
    assert not shadow[:, :80].any()
    assert (shadow[:, 80 : 80 + int(width)]).all() and not shadow[:, 80 + int(np.ceil(width)) + 1 :].any()


def test_exposure_and_white_balance_scale_the_image():
    renderer = Renderer(FLAT)
    rgb8, _ = renderer.add_noise(
        np.full((48, 64, 3), 100.0), np.full((48, 64), 1.0), np.random.default_rng(4),
        _sensor(exposure=1.5, white_balance=(1.0, 0.8, 1.2)),
    )  # fmt: skip
    assert tuple(rgb8[0, 0]) == (150, 120, 180)


def test_heldout_shirts_are_never_worn_in_training():
    assert not set(POOLS["train"].top_patterns) & set(POOLS["heldout"].top_patterns)


def test_lens_distortion_moves_labels_with_the_image():
    """Where a point projects with distortion, the distortion map points back at its pinhole projection, so a
    label drawn with ``project`` sits on the remapped render."""
    camera = CameraModel(width=160, height=120, hfov_deg=90.0, k1=-0.08, k2=0.01)
    pinhole = dataclasses.replace(camera, k1=0.0, k2=0.0)
    renderer = Renderer(camera)
    rng = np.random.default_rng(5)
    points = np.stack([rng.uniform(-0.8, 0.8, 50), rng.uniform(-0.6, 0.6, 50), np.ones(50)], axis=-1)
    distorted, straight = camera.project(points), pinhole.project(points)
    map_u, map_v = renderer._distortion_maps
    inside = (distorted[:, 0] > 1) & (distorted[:, 0] < 158) & (distorted[:, 1] > 1) & (distorted[:, 1] < 118)
    u, v = np.round(distorted[inside]).astype(int).T
    back = np.stack([map_u[v, u], map_v[v, u]], axis=-1)
    assert inside.sum() > 30
    assert np.abs(back - straight[inside]).max() < 1.5  # rounding to the pixel, scaled by the local stretch
    image = np.zeros((120, 160, 3))
    assert renderer.distort(image, np.ones((120, 160)))[1].dtype == np.float64
