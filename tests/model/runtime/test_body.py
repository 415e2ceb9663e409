"""Body size: the highest head sets the scale, within its range; legs the camera sees take their length;
a fitted regressor carries what the camera sees to the bones it never sees; the served skeleton follows the
estimate over several samples, never in one."""

import json

import numpy as np
import pytest

from egoposevr.model.runtime.body import (
    BODY_HOLD_AFTER_S,
    EARLY_BODY_SIGHTINGS,
    HELD_LEG_BONES,
    MIN_VISUAL_SAMPLES,
    QUIET_HEAD_RANGE_M,
    QUIET_HEAD_WINDOW_S,
    SCALE_RANGE,
    SERVED_SCALE_RATE_PER_S,
    STANDING_HEAD_HEIGHT_M,
    STEADY_SAMPLES,
    VISUAL_WINDOW,
    BodyCalibrator,
    BodyRegressor,
    QuietHead,
    ServedScale,
    height_scale,
    held_target,
    standing_head_height_m,
)
from egoposevr.model.skeleton import forward_kinematics, rest_offsets

ALL = np.ones(3, dtype=bool)
RNG = np.random.default_rng(4)


def head_at(y: float) -> np.ndarray:
    return np.array([[0.0, y, 0.0], [0.3, y - 0.6, 0.0], [-0.3, y - 0.6, 0.0]])


def test_the_highest_head_sets_the_scale():
    body = BodyCalibrator()
    assert np.allclose(body.bone_scale, 1.0)
    assert body.push(head_at(1.1 * STANDING_HEAD_HEIGHT_M), ALL)
    assert np.allclose(body.bone_scale, 1.1)
    assert not body.push(head_at(0.9), ALL)  # crouching does not shrink the body
    assert not body.push(head_at(1.1 * STANDING_HEAD_HEIGHT_M + 0.002), ALL)  # under the 5 mm step
    assert np.allclose(body.bone_scale, 1.1)


def test_a_head_higher_than_the_range_gives_the_largest_body():
    body = BodyCalibrator()
    body.push(head_at(3.0), ALL)
    assert np.allclose(body.bone_scale, SCALE_RANGE[1])


def test_a_head_lower_than_the_range_is_no_height_the_mean_body_stays():
    """A head at three quarters of a standing height is a seated wearer far more often than a tiny adult."""
    body = BodyCalibrator()
    body.push(head_at(0.75 * STANDING_HEAD_HEIGHT_M), ALL)
    assert np.allclose(body.bone_scale, 1.0)


def _legs_seen(body: BodyCalibrator, scale: float | np.ndarray, frames: int = STEADY_SAMPLES) -> None:
    """The camera sees a body of this scale (one for every bone, or (22,) per bone) for some frames."""
    keypoints, _ = forward_kinematics(
        np.broadcast_to(np.eye(3), (22, 3, 3)), np.zeros(3), rest_offsets(np.broadcast_to(scale, 22))
    )
    for _ in range(frames):
        body.push_visual(keypoints + RNG.normal(scale=0.003, size=keypoints.shape), np.ones(22, dtype=bool))


def test_a_seated_wearer_is_sized_by_the_legs_the_camera_measures_until_they_stand_up():
    body = BodyCalibrator()
    body.push(head_at(0.75 * 1.05 * STANDING_HEAD_HEIGHT_M), ALL)  # seated from the first sample
    _legs_seen(body, 1.05)
    assert body.height_scale == pytest.approx(1.05, abs=0.02)
    np.testing.assert_allclose(body.bone_scale[[3, 6, 9, 16, 18]], 1.05, atol=0.02)  # spine, arms: not 0.8
    body.push(head_at(1.12 * STANDING_HEAD_HEIGHT_M), ALL)  # stands up: the head is a height again
    assert body.height_scale == pytest.approx(1.12)


def test_a_standing_wearer_with_long_legs_keeps_the_heads_height():
    body = BodyCalibrator()
    body.push(head_at(0.95 * STANDING_HEAD_HEIGHT_M), ALL)
    _legs_seen(body, 1.02)  # 7 % longer than the head says: long legs, not a seat
    assert body.height_scale == pytest.approx(0.95)


def test_thighs_measured_long_do_not_sit_a_standing_wearer_down():
    """Another rig than the training pool's measures the thighs up to 10 % long (the bundled recordings);
    only the shins tell a seat."""
    body = BodyCalibrator()
    body.push(head_at(0.9 * STANDING_HEAD_HEIGHT_M), ALL)
    scale = np.full(22, 0.9)
    scale[[4, 5]] = 1.2  # thighs a third longer than the head says
    _legs_seen(body, scale)
    assert body.height_scale == pytest.approx(0.9)


def test_a_calibrated_height_is_a_standing_height_whatever_the_legs_say(tmp_path):
    body = BodyCalibrator()
    body.calibrate(0.85 * STANDING_HEAD_HEIGHT_M, None)
    _legs_seen(body, 1.1)
    assert body.height_scale == pytest.approx(0.85)


def test_an_untracked_headset_does_not_count():
    body = BodyCalibrator()
    assert not body.push(head_at(1.9), np.array([False, True, True]))
    assert body.highest_head_m == 0.0


def test_legs_seen_by_the_camera_take_their_measured_length_and_the_rest_keeps_the_height_scale():
    body = BodyCalibrator()
    body.push(head_at(1.1 * STANDING_HEAD_HEIGHT_M), ALL)
    legs = rest_offsets(np.where(np.isin(np.arange(22), [4, 5, 7, 8]), 1.2, 1.0))  # long thighs and shins
    keypoints, _ = forward_kinematics(np.broadcast_to(np.eye(3), (22, 3, 3)), np.zeros(3), legs)
    visible = np.ones(22, dtype=bool)
    visible[[4, 7, 10]] = False  # only the right leg in view: the left one follows it
    changed = [
        body.push_visual(keypoints + RNG.normal(scale=0.005, size=keypoints.shape), visible)
        for _ in range(60)
    ]
    assert any(changed) and not any(changed[: MIN_VISUAL_SAMPLES - 1])  # nothing before enough sightings
    assert body.measured[5] == pytest.approx(1.2, abs=0.02)
    np.testing.assert_allclose(body.bone_scale[[4, 5, 7, 8]], 1.2, atol=0.02)
    np.testing.assert_allclose(body.bone_scale[[10, 11]], 1.0, atol=0.02)  # the feet as measured
    np.testing.assert_allclose(body.bone_scale[[3, 16, 18, 20]], 1.1)  # spine and arms: the height scale


def test_a_later_height_keeps_the_measured_legs():
    body = BodyCalibrator()
    keypoints, _ = forward_kinematics(np.broadcast_to(np.eye(3), (22, 3, 3)), np.zeros(3), rest_offsets())
    for _ in range(STEADY_SAMPLES):
        body.push_visual(keypoints, np.ones(22, dtype=bool))
    body.push(head_at(1.2 * STANDING_HEAD_HEIGHT_M), ALL)
    np.testing.assert_allclose(body.bone_scale[[4, 7]], 1.0)
    np.testing.assert_allclose(body.bone_scale[0:4], 1.2)


def test_without_a_regressor_a_few_sightings_do_not_yet_move_the_legs():
    body = BodyCalibrator()
    keypoints, _ = forward_kinematics(
        np.broadcast_to(np.eye(3), (22, 3, 3)), np.zeros(3), rest_offsets(np.full(22, 1.2))
    )
    for _ in range(STEADY_SAMPLES - 1):
        body.push_visual(keypoints, np.ones(22, dtype=bool))
    assert 4 in body.measured and np.allclose(body.bone_scale, 1.0)  # measured, but not trusted alone yet
    body.push_visual(keypoints, np.ones(22, dtype=bool))
    np.testing.assert_allclose(body.bone_scale[4], 1.2)


# Two body families, as in the training data: scaled mean bodies, and bodies whose hips (1, 2) are wide and
# whose neck (12) and head (15) bones are long. The camera sees the hips; it never sees the neck or head.
WIDE_HIPS = np.where(np.isin(np.arange(22), [1, 2]), 1.5, 1.0) * np.where(
    np.isin(np.arange(22), [12, 15]), 1.6, 1.0
)


def family_rows(n: int) -> tuple[np.ndarray, list[dict[int, float]], np.ndarray]:
    """n bodies of random height, alternating families -> height scales, measured bones, true scales."""
    scales_h = RNG.uniform(0.9, 1.1, n)
    truth = np.array([h * (WIDE_HIPS if i % 2 else np.ones(22)) for i, h in enumerate(scales_h)])
    measured = [{b: float(t[b] * RNG.normal(1.0, 0.02)) for b in (1, 2, 4, 5)} for t in truth]
    return scales_h, measured, truth


def test_the_regressor_tells_the_families_apart_by_the_bones_the_camera_sees():
    regressor = BodyRegressor.fit(*family_rows(60), encoder_sha256="x", head_offset_y_m=0.024, ridge=0.1)
    wide = {1: 1.05 * 1.5, 2: 1.05 * 1.5, 4: 1.05, 5: 1.05}
    np.testing.assert_allclose(regressor.predict(1.05, wide)[[12, 15]], 1.05 * 1.6, rtol=0.03)
    narrow = {1: 0.95, 2: 0.95, 4: 0.95, 5: 0.95}
    np.testing.assert_allclose(regressor.predict(0.95, narrow)[[12, 15, 18]], 0.95, rtol=0.03)
    assert regressor.predict(0.95, narrow)[0] == 0.95  # the root follows the height


def test_a_calibrator_with_a_regressor_keeps_the_height_scale_until_the_camera_measures():
    regressor = BodyRegressor.fit(*family_rows(60), encoder_sha256="x", head_offset_y_m=0.024, ridge=0.1)
    body = BodyCalibrator(regressor)
    body.push(head_at(1.05 * STANDING_HEAD_HEIGHT_M), ALL)
    np.testing.assert_allclose(body.bone_scale, 1.05)
    keypoints, _ = forward_kinematics(
        np.broadcast_to(np.eye(3), (22, 3, 3)), np.zeros(3), rest_offsets(1.05 * WIDE_HIPS)
    )
    changed = [body.push_visual(keypoints, np.ones(22, dtype=bool)) for _ in range(MIN_VISUAL_SAMPLES)]
    assert changed[-1] and not any(changed[:-1])
    np.testing.assert_allclose(body.bone_scale[[1, 12, 15]], 1.05 * WIDE_HIPS[[1, 12, 15]], rtol=0.03)


def test_an_early_body_is_measured_from_the_first_sighting_and_then_as_the_default_one():
    """first_measure_sightings=EARLY_BODY_SIGHTINGS: the regressor answers from a bone's first sighting, where
    the default waits for MIN_VISUAL_SAMPLES; from then on the two estimates are the same."""
    regressor = BodyRegressor.fit(*family_rows(60), encoder_sha256="x", head_offset_y_m=0.024, ridge=0.1)
    early = BodyCalibrator(regressor, first_measure_sightings=EARLY_BODY_SIGHTINGS)
    default = BodyCalibrator(regressor)
    keypoints, _ = forward_kinematics(
        np.broadcast_to(np.eye(3), (22, 3, 3)), np.zeros(3), rest_offsets(1.05 * WIDE_HIPS)
    )
    for body in (early, default):
        body.push(head_at(1.05 * STANDING_HEAD_HEIGHT_M), ALL)
    assert early.push_visual(keypoints, np.ones(22, dtype=bool))
    assert not default.push_visual(keypoints, np.ones(22, dtype=bool))
    np.testing.assert_allclose(early.bone_scale[[1, 12, 15]], 1.05 * WIDE_HIPS[[1, 12, 15]], rtol=0.03)
    for _ in range(MIN_VISUAL_SAMPLES - 1):
        for body in (early, default):
            body.push_visual(keypoints, np.ones(22, dtype=bool))
    np.testing.assert_array_equal(early.bone_scale, default.bone_scale)
    with pytest.raises(ValueError, match="first_measure_sightings"):
        BodyCalibrator(regressor, first_measure_sightings=0)


def test_a_regressor_survives_a_round_trip_and_a_corrupt_file_is_refused(tmp_path):
    regressor = BodyRegressor.fit(*family_rows(20), encoder_sha256="abc", head_offset_y_m=0.024)
    path = tmp_path / "visual-rgbd.body.json"
    regressor.save(path)
    loaded = BodyRegressor.load(path)
    assert loaded.encoder_sha256 == "abc" and loaded.feature_bones == regressor.feature_bones
    assert loaded.head_offset_y_m == 0.024
    np.testing.assert_allclose(loaded.weights, regressor.weights, atol=1e-6)
    doc = json.loads(path.read_text())
    for broken in (
        "{not json",
        json.dumps({**doc, "weights": [[1.0]]}),
        json.dumps({**doc, "kind": "other"}),
        json.dumps({**doc, "head_offset_y_m": "high"}),
        json.dumps({**doc, "head_offset_y_m": float("nan")}),
    ):
        path.write_text(broken)
        with pytest.raises(ValueError, match="not a body regressor"):
            BodyRegressor.load(path)


def test_a_regressor_gives_a_model_with_another_head_offset_the_bones_it_gives_its_own():
    """One encoder's regressor serves models that put the head joint at different heights under the headset;
    the same wearer must get the same bones from each."""
    regressor = BodyRegressor.fit(*family_rows(60), encoder_sha256="x", head_offset_y_m=0.06, ridge=0.1)
    keypoints, _ = forward_kinematics(
        np.broadcast_to(np.eye(3), (22, 3, 3)), np.zeros(3), rest_offsets(1.05 * WIDE_HIPS)
    )
    view_y_m = 1.05 * STANDING_HEAD_HEIGHT_M + 0.06  # one headset height
    bones = []
    for offset_y_m in (0.06, 0.024):
        body = BodyCalibrator(regressor, head_offset_y_m=offset_y_m)
        body.push(head_at(view_y_m - offset_y_m), ALL)
        assert body.height_scale == pytest.approx((view_y_m - offset_y_m) / STANDING_HEAD_HEIGHT_M)
        for _ in range(MIN_VISUAL_SAMPLES):
            body.push_visual(keypoints, np.ones(22, dtype=bool))
        bones.append(body.bone_scale)
    np.testing.assert_allclose(bones[1], bones[0], rtol=1e-12)
    np.testing.assert_allclose(bones[0][[1, 12, 15]], 1.05 * WIDE_HIPS[[1, 12, 15]], rtol=0.03)


def test_a_regressor_file_from_before_head_offsets_were_recorded_was_fitted_at_the_old_offset(tmp_path):
    path = tmp_path / "visual-rgbd.body.json"
    BodyRegressor.fit(*family_rows(20), encoder_sha256="abc", head_offset_y_m=0.024).save(path)
    doc = json.loads(path.read_text())
    del doc["head_offset_y_m"]
    path.write_text(json.dumps(doc))
    assert BodyRegressor.load(path).head_offset_y_m == 0.06


def test_height_scale_is_one_before_any_sample_and_clipped_after():
    assert height_scale(0.0) == 1.0
    assert height_scale(10.0) == SCALE_RANGE[1]


def test_a_long_session_refreshes_the_medians_every_tenth_sighting_not_every_frame():
    body = BodyCalibrator()
    keypoints, _ = forward_kinematics(np.broadcast_to(np.eye(3), (22, 3, 3)), np.zeros(3), rest_offsets())
    changed = [body.push_visual(keypoints, np.ones(22, dtype=bool)) for _ in range(VISUAL_WINDOW + 100)]
    assert sum(changed[-100:]) == 10  # the window is full, the refresh rate stays the same


def test_one_body_in_the_training_rows_makes_one_family():
    scales_h, measured, truth = family_rows(2)
    regressor = BodyRegressor.fit(
        scales_h[:1].repeat(5), measured[:1] * 5, truth[:1].repeat(5, 0), "x", 0.024
    )
    assert regressor.weights.shape[0] == 1
    np.testing.assert_allclose(regressor.family_probabilities(1.0, measured[0]), [1.0])


def test_a_measurement_somewhat_off_stays_with_its_family():
    """A camera that measures the hips 10 % long must not get a body halfway to the wide-hipped family."""
    regressor = BodyRegressor.fit(*family_rows(60), encoder_sha256="x", head_offset_y_m=0.024, ridge=0.1)
    off = {1: 1.1, 2: 1.1, 4: 1.0, 5: 1.0}  # a mean body, hips measured 10 % long
    assert regressor.family_probabilities(1.0, off).max() > 0.99
    np.testing.assert_allclose(regressor.predict(1.0, off)[[12, 15]], 1.0, atol=0.05)


def test_the_served_scale_takes_its_first_target_at_once_and_then_follows_at_a_bounded_rate():
    served = ServedScale()
    first = np.full(22, 1.05)
    assert served.follow(0, first) and np.array_equal(served.scale, first)
    assert not served.follow(11_111, first)  # nothing to follow
    target = first.copy()
    target[[4, 5]] = 1.15  # the thighs measured 10 % longer
    steps, t_us = [], 11_111
    while not np.array_equal(served.scale, target):
        t_us += 11_111
        before = served.scale.copy()
        assert served.follow(t_us, target)
        steps.append(np.abs(served.scale - before).max())
        assert len(steps) < 1000
    assert max(steps) <= SERVED_SCALE_RATE_PER_S * 0.011111 + 1e-12
    assert len(steps) == pytest.approx(0.10 / SERVED_SCALE_RATE_PER_S / 0.011111, abs=1)
    assert np.array_equal(served.scale[[0, 1, 2, 3]], first[[0, 1, 2, 3]])  # the other bones stay


def test_a_long_pause_or_time_going_back_moves_the_served_scale_no_further_than_a_short_step():
    served = ServedScale()
    served.follow(0, np.ones(22))
    served.follow(60_000_000, np.full(22, 1.2))  # a minute later
    assert served.scale[1] == pytest.approx(1.0 + SERVED_SCALE_RATE_PER_S * 0.1)
    before = served.scale.copy()
    served.follow(0, np.full(22, 1.2))  # time went back
    assert np.array_equal(served.scale, before)


def test_a_held_target_keeps_the_leg_bones_once_the_first_measurement_is_old_enough():
    estimate, served = np.full(22, 1.10), np.full(22, 1.00)
    placing, others = list(HELD_LEG_BONES), [j for j in range(22) if j not in HELD_LEG_BONES]
    assert {1, 4, 7, 10} <= set(placing) and {3, 6, 9, 12, 15} <= set(others)  # hip to foot kept, spine not
    t0 = 5_000_000
    assert held_target(estimate, None, t0, t0) is estimate  # nothing served yet
    assert held_target(estimate, served, t0, None) is estimate  # the camera has measured nothing
    young = t0 + int(BODY_HOLD_AFTER_S * 1e6) - 1
    assert held_target(estimate, served, young, t0) is estimate  # the body is still arriving
    held = held_target(estimate, served, t0 + int(BODY_HOLD_AFTER_S * 1e6), t0)
    assert np.array_equal(held[placing], served[placing]) and np.array_equal(held[others], estimate[others])
    assert np.array_equal(estimate, np.full(22, 1.10))  # the estimate is not changed in place


def _serve_a_still_stander(body_hold: bool, seed: int, at_4_s) -> tuple[object, list[bool]]:
    """The whole pipeline (bundled egoposevr, headset only) on a procedural user standing still for 6 s at
    90 Hz: the camera's first measurement (legs of the mean body's length) arrives at the tenth sample, and
    ``at_4_s(pipeline)`` runs before the sample four seconds in. -> the pipeline after the stream, and
    whether the legs were held at each sample from four seconds on."""
    from egoposevr.model.runtime.loading import LoadedModel
    from egoposevr.model.runtime.pipeline import Pipeline
    from egoposevr.model.synth.headset import simulate_headset
    from egoposevr.model.synth.procedural import generate
    from egoposevr.model.weights import WEIGHTS_DIR

    rng = np.random.default_rng(seed)
    track = simulate_headset(generate("still_stand", 6.0, 60.0, rng), 90.0, rng)
    pipeline = Pipeline(LoadedModel.load(WEIGHTS_DIR / "egoposevr.onnx"), body_hold=body_hold)
    holds = []
    for i, t_us in enumerate(track.t_us):
        if i == 10:
            pipeline.body.measured = {4: 1.0, 5: 1.0, 7: 1.0, 8: 1.0}
            pipeline.body._rebuild()
        if i == 360:
            at_4_s(pipeline)
        pipeline.push_hmd(int(t_us), track.poses[i], track.valid[i])
        if i >= 360:
            holds.append(pipeline.legs.holding)
    return pipeline, holds


def test_with_body_hold_a_new_estimate_does_not_resize_still_legs_but_still_resizes_the_rest():
    """The camera's measured legs change 4 s in, while the leg hold holds. With body_hold the served hips and
    legs keep their size until the hold ends; without it they grow towards the new estimate; the spine and
    arms follow either way."""
    placing = list(HELD_LEG_BONES)
    others = [j for j in range(22) if j not in HELD_LEG_BONES]
    grown, held_share, before = {}, {}, {}

    def measure_longer_legs(pipeline) -> None:
        before["scale"] = pipeline.served_scale.scale.copy()  # each run's, before the change
        pipeline.body.measured = {4: 1.15, 5: 1.15, 7: 1.15, 8: 1.15}
        pipeline.body._rebuild()

    for body_hold in (True, False):
        pipeline, holds = _serve_a_still_stander(body_hold, 1, measure_longer_legs)
        after, was = pipeline.served_scale.scale, before["scale"]
        grown[body_hold] = np.abs(after[placing] - was[placing]).max()
        held_share[body_hold] = np.mean(holds)
        assert np.abs(after[others] - was[others]).max() > 0.01  # the spine and arms follow the estimate
        assert np.abs(after[[3, 6, 9]] - was[[3, 6, 9]]).max() > 0.005, (after - was)[[3, 6, 9]]
    assert held_share[True] > 0.9, held_share  # the legs were held after the change
    assert grown[True] < 0.2 * grown[False], grown


def test_with_body_hold_a_calibration_still_resizes_held_legs():
    """A calibration is the wearer's own measure: under a leg hold it resizes the legs as it does without the
    hold (the hold's clock starts again), where a new camera estimate would not."""
    from egoposevr.model.runtime.calibration import Calibration

    legs = list(HELD_LEG_BONES)
    served, holding, before = {}, [], {}

    def calibrate_a_much_taller_wearer(pipeline) -> None:
        before[pipeline.body_hold] = pipeline.served_scale.scale[legs].copy()
        holding.append(pipeline.legs.holding)
        pipeline.calibrate(Calibration("stand", 1.85, np.tile(np.eye(3), (3, 1, 1))))

    for body_hold in (True, False):
        pipeline, _ = _serve_a_still_stander(body_hold, 2, calibrate_a_much_taller_wearer)
        served[body_hold] = pipeline.served_scale.scale[legs]
    assert holding == [True, True]
    assert np.abs(served[True] - before[True]).max() > 0.1  # the held legs took the calibration's body ...
    np.testing.assert_allclose(served[True], served[False], atol=1e-3)  # ... as legs without the hold do


def test_bone_lengths_round_trip_through_a_scale_and_a_wrong_body_is_refused():
    from egoposevr.model.runtime.body import GIVEN_SCALE_RANGE, bone_lengths_m, scale_of_lengths

    scale = np.linspace(0.85, 1.2, 22)
    lengths = bone_lengths_m(scale)
    assert lengths.shape == (21,)
    assert np.allclose(lengths, np.linalg.norm(rest_offsets(scale), axis=-1)[1:])
    back = scale_of_lengths(lengths)
    assert back[0] == 1.0 and np.allclose(back[1:], scale[1:])
    too_long = lengths.copy()
    too_long[3] *= GIVEN_SCALE_RANGE[1] * 1.01 / scale[4]  # the left thigh (joint 4, the knee: hip to knee)
    with pytest.raises(ValueError, match="bone 4"):
        scale_of_lengths(too_long)
    with pytest.raises(ValueError, match="21 finite"):
        scale_of_lengths(lengths[:20])


@pytest.mark.parametrize("model_name", ["egoposevr", "procedural"])
def test_a_given_body_is_served_from_the_next_sample_kept_across_a_reset_and_taken_back(model_name):
    """GivenBody: a pipeline given a bone scale serves a skeleton of those bone lengths from the next sample,
    whatever the headset says about the wearer's height, keeps it after reset() (a reconnect), and estimates the
    body again once given None."""
    from egoposevr.model.runtime.body import bone_lengths_m
    from egoposevr.model.runtime.loading import LoadedModel
    from egoposevr.model.runtime.procedural import ProceduralModel, pipeline_for
    from egoposevr.model.skeleton import joint_bone_lengths
    from egoposevr.model.weights import WEIGHTS_DIR

    model = (
        ProceduralModel() if model_name == "procedural" else LoadedModel.load(WEIGHTS_DIR / "egoposevr.onnx")
    )
    pipeline = pipeline_for(model)
    tall = head_at(1.2 * STANDING_HEAD_HEIGHT_M)
    poses = np.concatenate([tall, np.tile([0.0, 0.0, 0.0, 1.0], (3, 1))], axis=1)

    def served_lengths(t_us: int) -> np.ndarray:
        joints = pipeline.push_hmd(t_us, poses, ALL).joints
        return joint_bone_lengths(joints)

    small = np.full(22, 0.9)
    assert pipeline.given_body is None
    served_lengths(0)
    pipeline.give_body(small)
    assert np.allclose(served_lengths(11_111), bone_lengths_m(small), atol=2e-3)
    assert np.array_equal(pipeline.given_body, small) and np.array_equal(pipeline.served_body()[0], small)
    pipeline.reset()
    assert np.allclose(served_lengths(22_222), bone_lengths_m(small), atol=2e-3)
    pipeline.give_body(None)
    assert pipeline.given_body is None
    for i in range(3, 200):  # the estimate from a tall headset: the skeleton grows back, a little per sample
        lengths = served_lengths(i * 11_111)
    assert lengths[3] > bone_lengths_m(small)[3] * 1.2


def test_a_body_is_worth_keeping_once_the_wearer_has_stood():
    """BodyCalibrator.stood: a standing head, or a calibration, gives a standing height; a head that only sat
    (below SCALE_RANGE, or with shins the camera measures far longer than its height says) does not."""
    seated = BodyCalibrator()
    seated.push(head_at(1.1), ALL)
    assert not seated.stood
    tall_sitter = BodyCalibrator()
    tall_sitter.push(head_at(0.85 * STANDING_HEAD_HEIGHT_M), ALL)
    tall_sitter.measured = {7: 1.15, 8: 1.15}  # shins 1.15 x the mean body's under a head of 0.85
    assert not tall_sitter.stood
    standing = BodyCalibrator()
    standing.push(head_at(STANDING_HEAD_HEIGHT_M), ALL)
    assert standing.stood
    seated.calibrate(STANDING_HEAD_HEIGHT_M, None)
    assert seated.stood


SAMPLE_US = 11_111  # 90 Hz


def _stand(body: BodyCalibrator, head_y_m: float, seconds: float, t0_us: int = 0, sway_m: float = 0.0) -> int:
    """The head held at head_y_m (swaying sway_m up and down at 1 Hz) for some seconds -> the next sample's time."""
    n = int(seconds * 1e6 / SAMPLE_US)
    for i in range(n):
        body.push(
            head_at(head_y_m + sway_m * np.sin(2 * np.pi * i * SAMPLE_US * 1e-6)), ALL, t0_us + i * SAMPLE_US
        )
    return t0_us + n * SAMPLE_US


def test_a_quiet_head_is_one_held_within_its_range_for_the_whole_window():
    quiet = QuietHead()
    window_samples = int(QUIET_HEAD_WINDOW_S * 1e6 / SAMPLE_US)
    head = np.array([0.1, 1.5, -0.2])
    highest = []
    for i in range(60):
        if quiet.push(i * SAMPLE_US, head + np.array([0.0, 0.4 * QUIET_HEAD_RANGE_M * (i % 2), 0.0]), True):
            highest.append((i, quiet.highest_m))
    assert highest[0] == (window_samples + 1, pytest.approx(1.5))  # not before the window is spanned in full
    assert highest[-1][1] == pytest.approx(1.5 + 0.4 * QUIET_HEAD_RANGE_M)  # the highest quiet one
    # a head that rises faster than the range allows over the window (a jump, a rise) is never quiet
    t_us = 60 * SAMPLE_US
    for i in range(90):
        assert not quiet.push(t_us + i * SAMPLE_US, head + np.array([0.0, 0.3 + 0.01 * i, 0.0]), True)
    assert quiet.highest_m < 1.51


def test_a_lost_head_or_a_pause_starts_the_quiet_window_again():
    quiet = QuietHead()
    head = np.array([0.0, 1.6, 0.0])
    for i in range(30):
        quiet.push(i * SAMPLE_US, head, True)
    quiet.push(30 * SAMPLE_US, head, False)  # lost: the window starts again
    assert not any(quiet.push((31 + i) * SAMPLE_US, head, True) for i in range(40))
    assert quiet.highest_m is None
    later_us = (71 + 60) * SAMPLE_US  # a pause longer than the window: again
    assert not any(quiet.push(later_us + i * SAMPLE_US, head, True) for i in range(40))
    assert quiet.push(later_us + 46 * SAMPLE_US, head, True)


def test_a_body_measured_short_is_lifted_to_reach_its_quiet_head_and_only_with_the_lift():
    """The camera measures the legs 10 % short: the body's standing head joint would sit under the head the
    wearer holds still, and its planted feet could not reach the floor."""
    head_y_m = 1.05 * STANDING_HEAD_HEIGHT_M
    for lift in (False, True):
        body = BodyCalibrator(lift_to_quiet_head=lift)
        t_us = _stand(body, head_y_m, 1.0)
        _legs_seen(body, 0.95)  # 0.95 against the head's 1.05: legs 10 % short
        _stand(body, head_y_m, 1.0, t_us)
        standing_m = standing_head_height_m(body.bone_scale)
        if lift:
            assert standing_m == pytest.approx(head_y_m, abs=1e-6)
            # one factor for every bone: the proportions the estimate had are kept
            assert body.bone_scale[4] / body.bone_scale[15] == pytest.approx(0.95 / 1.05, rel=2e-3)
        else:
            assert standing_m < head_y_m - 0.02


def test_a_jumps_height_or_a_tall_estimate_is_not_lifted_and_a_calibrated_height_wins():
    # a head that is never quiet at its highest (a jump) lifts nothing past what the height scale gives
    body = BodyCalibrator(lift_to_quiet_head=True)
    t_us = _stand(body, STANDING_HEAD_HEIGHT_M, 1.0)
    _legs_seen(body, 0.9)
    short_m = standing_head_height_m(body.bone_scale)
    _stand(body, STANDING_HEAD_HEIGHT_M - 0.2, 2.0, t_us, sway_m=0.25)  # jumping up to 5 cm over standing
    assert standing_head_height_m(body.bone_scale) == pytest.approx(
        max(short_m, STANDING_HEAD_HEIGHT_M), abs=1e-6
    )
    # an estimate already taller than the quiet head keeps its size
    body = BodyCalibrator(lift_to_quiet_head=True)
    _stand(body, STANDING_HEAD_HEIGHT_M, 1.0)
    _legs_seen(body, 1.2)
    assert body.quiet_head.highest_m == pytest.approx(STANDING_HEAD_HEIGHT_M)
    assert standing_head_height_m(body.bone_scale) > STANDING_HEAD_HEIGHT_M + 0.05
    assert body.bone_scale[15] == 1.0  # the height's scale, unlifted
    # a calibration measured the height: the quiet head no longer lifts
    body = BodyCalibrator(lift_to_quiet_head=True)
    body.calibrate(STANDING_HEAD_HEIGHT_M, None)
    _legs_seen(body, 0.8)
    _stand(body, 1.1 * STANDING_HEAD_HEIGHT_M, 1.0)
    assert standing_head_height_m(body.bone_scale) < STANDING_HEAD_HEIGHT_M


def test_standing_head_height_is_the_mean_bodys_for_the_mean_body_and_grows_with_the_bones():
    assert standing_head_height_m(np.ones(22)) == pytest.approx(STANDING_HEAD_HEIGHT_M, abs=1e-3)
    assert standing_head_height_m(np.full(22, 1.1)) > standing_head_height_m(np.ones(22))
