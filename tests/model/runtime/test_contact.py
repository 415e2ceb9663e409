"""Planted feet and the floor (runtime/contact.py): synthetic streams with known answers, then the pipeline."""

import numpy as np
import pytest

from egoposevr.model.runtime.contact import (
    BLEND_S,
    FEET,
    LAND_S,
    MAX_GAP_S,
    PLANT_SPEED_M_S,
    RELEASE_DISTANCE_M,
    RELEASE_HEIGHT_M,
    SURE_P,
    SURE_RELEASE,
    FootContacts,
)
from egoposevr.model.skeleton import FOOT_JOINT_HEIGHT_M, REST_JOINTS_M

STEP_US = 11_111  # 90 Hz
LEFT_ANKLE, LEFT_FOOT = FEET[0]


def standing_joints(rng: np.random.Generator, jitter_m: float = 0.005) -> np.ndarray:
    """(J, 3) the rest skeleton standing on the floor (soles at y = 0), each joint jittered like a network's."""
    joints = REST_JOINTS_M - np.array([0.0, REST_JOINTS_M[[10, 11], 1].min() - FOOT_JOINT_HEIGHT_M, 0.0])
    return joints + rng.normal(0.0, jitter_m, joints.shape)


def run(
    contacts: FootContacts, frames: list[np.ndarray], t0_us: int = 0
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each frame's (targets, observed) for the feet."""
    out = []
    for i, joints in enumerate(frames):
        targets, observed = np.zeros((22, 3)), np.zeros(22, dtype=bool)
        contacts.targets(t0_us + i * STEP_US, joints, 1.0, targets, observed)
        out.append((targets, observed))
    return out


def test_a_still_foot_is_planted_and_held_while_the_network_jitters():
    rng = np.random.default_rng(0)
    contacts = FootContacts()
    frames = [standing_joints(rng) for _ in range(90)]
    out = run(contacts, frames)
    assert contacts.planted == (True, True)
    held = np.array([t[LEFT_FOOT] for t, o in out[30:] if o[LEFT_FOOT]])
    assert len(held) == 60
    assert np.ptp(held, axis=0).max() == 0.0  # one anchor: not a millimetre of skating
    assert held[0, 1] == pytest.approx(FOOT_JOINT_HEIGHT_M)  # the sole on the floor


def test_a_moving_foot_is_not_planted():
    rng = np.random.default_rng(1)
    frames = []
    for i in range(60):
        joints = standing_joints(rng, 0.0)
        joints[[LEFT_ANKLE, LEFT_FOOT], 0] += (
            2.0 * PLANT_SPEED_M_S * i * STEP_US * 1e-6
        )  # sliding over the floor
        frames.append(joints)
    contacts = FootContacts()
    run(contacts, frames)
    assert contacts.planted == (False, True)


@pytest.mark.parametrize("move", ["lift", "drift"])
def test_a_plant_ends_when_the_network_steps_and_the_foot_slides_back_without_a_pop(move):
    rng = np.random.default_rng(2)
    frames = [standing_joints(rng, 0.0) for _ in range(30)]
    for i in range(1, 60):
        joints = standing_joints(rng, 0.0)
        if move == "lift":
            joints[[LEFT_ANKLE, LEFT_FOOT], 1] += min(i * 0.01, 0.2)
        else:
            joints[[LEFT_ANKLE, LEFT_FOOT], 2] += i * 0.01  # a slide that goes on: no new plant
        frames.append(joints)
    contacts = FootContacts()
    out = run(contacts, frames)
    assert contacts.planted[0] is False
    served = np.array(
        [t[LEFT_FOOT] if o[LEFT_FOOT] else f[LEFT_FOOT] for (t, o), f in zip(out, frames, strict=True)]
    )
    steps_m = np.linalg.norm(np.diff(served, axis=0), axis=1)
    threshold = RELEASE_HEIGHT_M if move == "lift" else RELEASE_DISTANCE_M
    # The release happens once the network is `threshold` away: a pop would move the foot that far (and more)
    # in one sample; the slide spreads it over BLEND_S.
    assert steps_m.max() < 0.5 * threshold
    assert (steps_m > 0.001).sum() * STEP_US * 1e-6 >= BLEND_S - 2 * STEP_US * 1e-6
    assert np.allclose(served[-1], frames[-1][LEFT_FOOT])  # and then it is the network's foot again


def test_a_foot_below_the_floor_is_put_on_it_and_one_above_is_left_alone():
    rng = np.random.default_rng(3)
    joints = standing_joints(rng, 0.0)
    joints[[LEFT_ANKLE, LEFT_FOOT], 1] -= 0.1  # through the floor
    joints[[LEFT_ANKLE, LEFT_FOOT], 0] += 1.0  # and far from any plant: the first sample cannot plant yet
    ((targets, observed),) = run(FootContacts(), [joints])
    assert observed[LEFT_FOOT] and targets[LEFT_FOOT, 1] == pytest.approx(FOOT_JOINT_HEIGHT_M)
    assert targets[LEFT_ANKLE, 1] >= FOOT_JOINT_HEIGHT_M - 1e-12
    assert targets[LEFT_FOOT, 0] == pytest.approx(joints[LEFT_FOOT, 0])

    high = standing_joints(rng, 0.0)
    high[:, 1] += 0.5  # jumping: both feet in the air
    ((targets, observed),) = run(FootContacts(), [high])
    assert not observed.any()


def test_a_floor_other_than_zero_is_where_the_soles_go():
    rng = np.random.default_rng(4)
    frames = [standing_joints(rng) + np.array([0.0, 0.3, 0.0]) for _ in range(40)]
    out = run(FootContacts(floor_y_m=0.3), frames)
    targets, observed = out[-1]
    assert observed[LEFT_FOOT] and targets[LEFT_FOOT, 1] == pytest.approx(0.3 + FOOT_JOINT_HEIGHT_M)


def test_a_long_pause_forgets_the_plant():
    rng = np.random.default_rng(5)
    contacts = FootContacts()
    run(contacts, [standing_joints(rng) for _ in range(40)])
    anchor = run(contacts, [standing_joints(rng)], t0_us=40 * STEP_US)[0][0][LEFT_FOOT]
    moved = standing_joints(rng, 0.0) + np.array(
        [0.5, 0.0, 0.0]
    )  # the user walked away while the stream paused
    later_us = 41 * STEP_US + int(2 * MAX_GAP_S * 1e6)
    targets, observed = run(contacts, [moved], t0_us=later_us)[0]
    assert not np.allclose(targets[LEFT_FOOT], anchor)
    assert not observed[LEFT_FOOT] or targets[LEFT_FOOT, 0] == pytest.approx(moved[LEFT_FOOT, 0])


def test_the_served_feet_of_a_user_who_only_moves_the_arms_stay_planted_on_the_floor():
    """The whole pipeline (bundled egoposevr, KPO) on a procedural user who stands still and moves only the
    upper body: planted feet hardly skate and stay on the floor (without contacts the same stream skates at
    10-19 cm/s with soles 4-6 cm above the floor), and the served joints are still FK of the rotations."""
    from egoposevr.model.runtime.loading import LoadedModel
    from egoposevr.model.runtime.pipeline import Pipeline
    from egoposevr.model.skeleton import forward_kinematics, rest_offsets
    from egoposevr.model.synth.headset import simulate_headset
    from egoposevr.model.synth.procedural import generate
    from egoposevr.model.training.plausibility import plausibility, summarize_plausibility
    from egoposevr.model.weights import WEIGHTS_DIR

    rng = np.random.default_rng(0)
    track = simulate_headset(generate("still_stand", 6.0, 60.0, rng), 90.0, rng)
    pipeline = Pipeline(LoadedModel.load(WEIGHTS_DIR / "egoposevr.onnx"))
    results = [pipeline.push_hmd(int(t), track.poses[i], track.valid[i]) for i, t in enumerate(track.t_us)]
    joints = np.array([r.joints for r in results])
    after = slice(90, None)  # once the height estimate has settled
    measured = summarize_plausibility([plausibility(joints[after], track.joints_m[after], track.t_us[after])])
    assert measured["foot_skate_cm_s"] < 3.0
    assert measured["floor_float_cm"] < 1.5 and measured["floor_penetration_cm"] < 0.5
    last = results[-1]
    fk, _ = forward_kinematics(last.local_rot, last.transl, rest_offsets(pipeline.served_scale.scale))
    assert np.allclose(fk, last.joints, atol=1e-6)


@pytest.mark.parametrize("factor", [0.98, 1.05])
def test_a_body_that_changes_size_grows_or_shrinks_over_samples_and_planted_feet_do_not_jump(factor):
    """A calibration mid-stream (the camera's first measurement does the same) makes the body 2 % smaller or
    5 % larger: the skeleton used to change in one sample, and KPO, which plants the soles on the position
    filter's lagging body, moved the soles 1.8 / 4.5 cm in one sample, to 4.4 cm through the floor."""
    from egoposevr.model.runtime.calibration import Calibration
    from egoposevr.model.runtime.loading import LoadedModel
    from egoposevr.model.runtime.pipeline import Pipeline
    from egoposevr.model.synth.headset import simulate_headset
    from egoposevr.model.synth.procedural import generate
    from egoposevr.model.weights import WEIGHTS_DIR

    rng = np.random.default_rng(1)
    track = simulate_headset(generate("still_stand", 5.0, 60.0, rng), 90.0, rng)
    pipeline = Pipeline(LoadedModel.load(WEIGHTS_DIR / "egoposevr.onnx"))
    soles, change = [], 270  # 3 s in, the stance long settled
    for i, t_us in enumerate(track.t_us):
        if i == change:
            head_m = factor * pipeline.body.highest_head_m
            pipeline.calibrate(Calibration("stand", head_m, np.tile(np.eye(3), (3, 1, 1))))
        result = pipeline.push_hmd(int(t_us), track.poses[i], track.valid[i])
        soles.append(result.joints[[10, 11], 1] - FOOT_JOINT_HEIGHT_M)
    around = np.array(soles[change - 45 : change + 90])
    assert np.abs(np.diff(around, axis=0)).max() < 0.01  # no sample moves a sole by a centimetre (now 5 mm)
    assert np.abs(around).max() < 0.025  # within 2.5 cm of the floor (now 1.5 / 1.9 cm)
    assert np.allclose(pipeline.served_scale.scale, pipeline.body.bone_scale)  # it got there


def test_a_contact_head_decides_when_a_foot_is_down_and_when_it_steps():
    """With the network's contact probability the speed gate is not needed: a sliding foot that the net calls
    down is planted, and a still foot that it calls up steps."""
    rng = np.random.default_rng(6)
    contacts = FootContacts()
    sliding = []
    for i in range(20):
        joints = standing_joints(rng, 0.0)
        joints[[LEFT_ANKLE, LEFT_FOOT], 0] += 0.01 * i
        sliding.append(joints)
    for i, joints in enumerate(sliding):
        contacts.targets(i * STEP_US, joints, 1.0, np.zeros((22, 3)), np.zeros(22, dtype=bool), np.ones(2))
    assert contacts.planted == (True, True)
    still = standing_joints(rng, 0.0)
    contacts.targets(
        20 * STEP_US, still, 1.0, np.zeros((22, 3)), np.zeros(22, dtype=bool), np.array([0.1, 0.9])
    )
    assert contacts.planted == (False, True)


@pytest.mark.parametrize("sure_plant", [False, True])
def test_with_sure_plant_a_foot_the_head_is_sure_of_stays_down_however_high_the_net_lifts_it(sure_plant):
    """A seated network's foot joint floats well over the floor while its contact head is sure the foot is
    down: with sure_plant the plant stays; without it, a lift that far is a step. Less sure, or drifted that
    far over the floor, the foot steps either way (and is planted again past the old plant)."""

    def left_foot_after(lift_m: float, shift_m: float, p_left: float) -> tuple[bool, float]:
        """Whether the left foot is planted after the net's drift, and how far its target moved (m)."""
        rng = np.random.default_rng(7)
        contacts = FootContacts(sure_plant=sure_plant)
        for i in range(40):  # planted
            joints = standing_joints(rng, 0.0)
            contacts.targets(
                i * STEP_US, joints, 1.0, np.zeros((22, 3)), np.zeros(22, dtype=bool), np.ones(2)
            )
        start = joints[LEFT_FOOT].copy()
        for i in range(40, 80):  # the net's left foot drifts up and over the floor, slowly
            joints = standing_joints(rng, 0.0)
            share = (i - 39) / 40
            joints[[LEFT_ANKLE, LEFT_FOOT], 1] += lift_m * share
            joints[[LEFT_ANKLE, LEFT_FOOT], 0] += shift_m * share
            targets = np.zeros((22, 3))
            p = np.array([p_left, 1.0])
            contacts.targets(i * STEP_US, joints, 1.0, targets, np.zeros(22, dtype=bool), p)
        for i in range(80, 140):  # the net keeps it there; any release's blend has faded
            targets = np.zeros((22, 3))
            contacts.targets(i * STEP_US, joints, 1.0, targets, np.zeros(22, dtype=bool), p)
        moved_m = float(np.linalg.norm(targets[LEFT_FOOT, [0, 2]] - start[[0, 2]]))
        return contacts.planted[0], moved_m

    high = 1.2 * SURE_RELEASE * RELEASE_HEIGHT_M
    far = 1.2 * SURE_RELEASE * RELEASE_DISTANCE_M
    assert left_foot_after(high, 0.0, 1.0)[0] is sure_plant
    assert left_foot_after(0.0, 0.0, 1.0)[0]  # the net's foot where the plant is: down either way
    assert not left_foot_after(high, 0.0, SURE_P - 0.05)[0]  # less sure: a step
    planted, moved_m = left_foot_after(0.0, far, 1.0)  # drifted that far: a step, and down again past it
    assert planted and moved_m > SURE_RELEASE * RELEASE_DISTANCE_M


def test_without_a_floor_at_y_zero_the_feet_are_left_to_the_network_until_the_session_finds_one():
    """A LOCAL reference space puts y = 0 at the head: feet 1.5 m below it are not through a floor. Once a
    second of the network's feet is in, the session's own floor is under them and they are planted on it."""
    rng = np.random.default_rng(7)
    frames = [standing_joints(rng) - np.array([0.0, 1.6, 0.0]) for _ in range(40)]
    contacts = FootContacts()
    out = run(contacts, frames)
    assert contacts.planted == (False, False)
    assert not any(observed.any() for _, observed in out)
    assert contacts.floor_held_m is None  # what a pose then says of the floor: none is holding a foot

    out = run(contacts, [standing_joints(rng) - np.array([0.0, 1.6, 0.0]) for _ in range(150)], 40 * STEP_US)
    assert contacts.floor_now_m == pytest.approx(-1.6, abs=0.01)  # the lower sole, a low percentile
    assert contacts.floor_held_m == contacts.floor_now_m
    assert contacts.planted == (True, True)
    targets, observed = out[-1]
    assert observed[LEFT_FOOT]
    assert targets[LEFT_FOOT, 1] == pytest.approx(contacts.floor_now_m + FOOT_JOINT_HEIGHT_M, abs=0.003)


def test_the_floor_of_a_floor_level_space_stays_where_it_is():
    """Feet the network puts a few centimetres above or below y = 0 do not move a floor-level space's floor."""
    rng = np.random.default_rng(8)
    contacts = FootContacts()
    for lift_m in (0.04, -0.05):
        run(contacts, [standing_joints(rng) + np.array([0.0, lift_m, 0.0]) for _ in range(200)])
        assert contacts.floor_now_m == 0.0
        assert contacts.floor_held_m == 0.0


def served_feet(contacts: FootContacts, frames: list[np.ndarray], contact_p: list[np.ndarray]) -> np.ndarray:
    """(N, 3) the left foot joint served at each frame: its target, or the network's where it has none."""
    served = []
    for i, (joints, p) in enumerate(zip(frames, contact_p, strict=True)):
        targets, observed = np.zeros((22, 3)), np.zeros(22, dtype=bool)
        contacts.targets(i * STEP_US, joints, 1.0, targets, observed, p)
        served.append(targets[LEFT_FOOT] if observed[LEFT_FOOT] else joints[LEFT_FOOT])
    return np.array(served)


def test_a_plant_lowers_a_hovering_foot_onto_the_floor_over_land_s_not_in_one_sample():
    """The network calls a foot down while it holds it 6 cm up: the sole goes onto the floor, smoothly."""
    rng = np.random.default_rng(9)
    hover_m = 0.06
    frames = [standing_joints(rng, 0.0) + np.array([0.0, hover_m, 0.0]) for _ in range(40)]
    frames = [f - np.array([0.0, hover_m, 0.0]) * np.isin(np.arange(22), [8, 11])[:, None] for f in frames]
    up, down = np.array([0.0, 1.0]), np.array([1.0, 1.0])  # the right foot stands throughout
    served = served_feet(FootContacts(), frames, [up] * 10 + [down] * 30)
    assert served[9, 1] == pytest.approx(FOOT_JOINT_HEIGHT_M + hover_m, abs=0.001)  # free: the network's
    drops_m = -np.diff(served[:, 1])
    assert drops_m.max() < 0.4 * hover_m  # a jump would drop it all in one sample
    landed = 10 + int(np.ceil(LAND_S / (STEP_US * 1e-6)))
    assert served[landed:, 1] == pytest.approx(FOOT_JOINT_HEIGHT_M)  # and then it stands on the floor


def test_a_foot_let_go_and_planted_again_glides_to_its_new_place():
    """The contact head flickers (down, up for a few samples, down again) while the network moves the foot
    12 cm: the second plant is where the network puts the foot, reached without a jump from the first."""
    rng = np.random.default_rng(10)
    frames = [standing_joints(rng, 0.0) for _ in range(30)]
    for _ in range(50):
        joints = standing_joints(rng, 0.0)
        joints[[LEFT_ANKLE, LEFT_FOOT], 2] += 0.12
        frames.append(joints)
    down, left_up = np.ones(2), np.array([0.1, 1.0])
    contact_p = [down] * 30 + [left_up] * 3 + [down] * 47
    contacts = FootContacts()
    served = served_feet(contacts, frames, contact_p)
    assert contacts.planted == (True, True)
    steps_m = np.linalg.norm(np.diff(served, axis=0), axis=1)
    assert steps_m.max() < 0.4 * 0.12  # planted again at once, the old code jumped ~0.9 of it
    assert served[-1, [0, 2]] == pytest.approx(
        frames[-1][LEFT_FOOT, [0, 2]]
    )  # planted where the network put it
