"""The procedural baseline: planted feet that stay, steps when the body moves away, arms to the controllers."""

import numpy as np
import pytest

from egoposevr.model.rig import joints_from_devices
from egoposevr.model.runtime.hands import REACQUIRE_S
from egoposevr.model.runtime.procedural import (
    TURN_DEAD_ZONE_DEG,
    ProceduralModel,
    ProceduralPipeline,
    pipeline_for,
)
from egoposevr.model.skeleton import forward_kinematics, rest_offsets
from egoposevr.model.synth.headset import simulate_headset
from egoposevr.model.synth.procedural import generate
from egoposevr.model.training.plausibility import plausibility, summarize_plausibility


@pytest.fixture(scope="module")
def model():
    return ProceduralModel()


def served(model, family, seconds=6.0, seed=3, **options):
    rng = np.random.default_rng(seed)
    motion = generate(family, seconds, 60.0, rng)
    track = simulate_headset(motion, 90.0, rng)
    pipeline = pipeline_for(model, **options)
    poses = [pipeline.push_hmd(int(t), track.poses[i], track.valid[i]) for i, t in enumerate(track.t_us)]
    return poses, track


def test_standing_and_gesturing_keeps_the_feet_planted_and_on_the_floor(model):
    poses, track = served(model, "stand_interact")
    joints = np.array([p.joints for p in poses])
    after = joints[90:]  # once the height estimate has settled
    result = summarize_plausibility([plausibility(after, track.joints_m[90:], track.t_us[90:])])
    assert result["foot_skate_cm_s"] < 1.0 and result["floor_penetration_cm"] < 0.5
    assert result["floor_float_cm"] < 1.5
    lower = np.linalg.norm(joints - track.joints_m, axis=-1)[:, [0, 1, 2, 4, 5, 7, 8, 10, 11]].mean()
    assert lower < 0.08


def test_a_still_wearers_head_joint_is_the_tracked_one_and_the_spine_keeps_its_bones(model):
    """The head joint the model's ``head_joint_m`` names (PROTOCOL.md §model-head-joint) is where a still
    wearer's served one is: the spine is placed with its bones at their lengths, so the served pose's forward
    kinematics reaches the tracked head (a spine of joints on a straight line served it 1.8 cm behind)."""
    _, track = served(model, "stand_interact", seconds=1.0)
    pipeline = pipeline_for(model)
    for k in range(90):  # one second of the stream's first sample: a wearer who stands still
        pose = pipeline.push_hmd(int(track.t_us[0]) + k * 11_111, track.poses[0], track.valid[0])
    tracked = joints_from_devices(track.poses[0], model.info.rig_offsets_m)[0][0]
    assert np.linalg.norm(pose.joints[15] - tracked) < 0.002
    offsets = rest_offsets(pipeline.body.bone_scale)
    for joint, parent in ((3, 0), (6, 3), (9, 6), (12, 9), (15, 12)):
        length = np.linalg.norm(pose.joints[joint] - pose.joints[parent])
        assert length == pytest.approx(np.linalg.norm(offsets[joint]), abs=1e-6)


def ahead_of_pelvis_m(joints: np.ndarray) -> np.ndarray:
    """(N,) how far the ankles' midpoint is from the pelvis over the floor, joints (N, J, 3)."""
    return np.linalg.norm((joints[:, [7, 8]].mean(axis=1) - joints[:, 0])[:, [0, 2]], axis=-1)


def test_a_stream_that_begins_seated_puts_the_feet_in_front_of_a_seat_that_stays(model):
    """A person sitting from the first sample has the feet in front of the seat, not under a crouch; the seat
    and the feet stay while the upper body moves."""
    poses, track = served(model, "still_sit", seconds=4.0, seat=True)
    joints = np.array([p.joints for p in poses])
    true_ahead, served_ahead = ahead_of_pelvis_m(track.joints_m), ahead_of_pelvis_m(joints)
    assert true_ahead.min() > 0.25  # the truth sits with its feet forward
    assert np.abs(served_ahead - true_ahead).max() < 0.12  # a crouch puts them under the pelvis (~0.3 off)
    knees_m = np.abs(joints[:, [4, 5], 1] - track.joints_m[:, [4, 5], 1]).mean()
    assert knees_m < 0.08  # at the seat's height (a crouch's knees are 10-25 cm lower)
    moved_m = np.linalg.norm(joints[:, [0, 7, 8, 10, 11]] - joints[:1, [0, 7, 8, 10, 11]], axis=-1).max()
    assert moved_m < 0.03


def test_a_stream_that_begins_standing_has_no_seat_and_the_seat_can_be_turned_off(model):
    """A stander's first sample sets no seat: the legs are served as with the seat off. Off (seat=False, as
    eval's procedural@no-seat serves it) a sitter is served the crouch of before, and pipeline_for passes the
    option to the procedural pipeline only, beside the network pipeline's options it drops."""
    standing = [
        np.array([p.joints for p in served(model, "stand_interact", seat=on)[0]]) for on in (True, False)
    ]
    assert np.array_equal(*standing)
    sitting = [
        np.array([p.joints for p in served(model, "still_sit", 2.0, seat=on)[0]]) for on in (True, False)
    ]
    assert np.abs(ahead_of_pelvis_m(sitting[0]) - ahead_of_pelvis_m(sitting[1])).min() > 0.15
    assert pipeline_for(model, seat=True, warm_reseat=True).seat is True


def test_walking_makes_it_step_after_the_body(model):
    poses, track = served(model, "walk", seconds=5.0)
    feet = np.array([p.joints[[10, 11]] for p in poses])
    travelled = np.linalg.norm(feet[-1, :, [0, 2]] - feet[0, :, [0, 2]], axis=0)
    pelvis_travel = np.linalg.norm(track.joints_m[-1, 0, [0, 2]] - track.joints_m[0, 0, [0, 2]])
    assert pelvis_travel > 1.0 and (travelled > 0.6 * pelvis_travel).all()
    final_gap = np.linalg.norm((poses[-1].joints[0] - track.joints_m[-1, 0])[[0, 2]])
    assert final_gap < 0.25  # the body keeps up with the walker
    # what each pose tells a client (PROTOCOL.md §planted-feet)
    planted = np.array([p.planted for p in poses])
    assert (~planted).any(axis=0).all() and planted.any(axis=1).all()  # each foot steps, one at a time
    assert all(p.floor_y_m == 0.0 for p in poses)
    stepping = ~planted[1:, 0] & ~planted[:-1, 0]
    moved_m = np.linalg.norm(np.diff(feet[:, 0], axis=0), axis=1)
    assert moved_m[planted[1:, 0] & planted[:-1, 0]].mean() < 0.1 * moved_m[stepping].mean()  # down is still


def turning_stander(yaw_deg: np.ndarray, rate_hz: float = 90.0) -> tuple[np.ndarray, np.ndarray]:
    """A headset track (t_us (N,), poses (N, 3, 7)) of a person standing on one spot whose head and hands turn
    to ``yaw_deg`` (N,) about the vertical: the controllers in front of the chest, turning with the head."""
    t_us = (np.arange(len(yaw_deg)) * 1e6 / rate_hz).astype(np.int64)
    poses = np.zeros((len(yaw_deg), 3, 7))
    for i, yaw in enumerate(np.radians(yaw_deg)):
        turn = np.array([[np.cos(yaw), 0.0, np.sin(yaw)], [0.0, 1.0, 0.0], [-np.sin(yaw), 0.0, np.cos(yaw)]])
        quat = [0.0, np.sin(yaw / 2), 0.0, np.cos(yaw / 2)]  # devices look along -z at yaw 0
        for device, at in enumerate(([0.0, 1.65, 0.0], [-0.2, 1.1, -0.35], [0.2, 1.1, -0.35])):
            poses[i, device] = [*(turn @ np.array(at)), *quat]
    return t_us, poses


def test_a_stander_who_turns_the_head_and_torso_keeps_the_hips_and_feet_still_until_the_turn_is_large(model):
    """Within TURN_DEAD_ZONE_DEG of the hips (a glance, a torso twist) the served pelvis, hips and feet stay
    where they are; a head that stays turned farther turns the hips after it and steps the feet round."""
    t = np.arange(6 * 90) / 90
    glancing = 0.8 * TURN_DEAD_ZONE_DEG * np.sin(2 * np.pi * 0.5 * t)
    t_us, poses = turning_stander(glancing)
    pipeline = ProceduralPipeline(model)
    joints = np.array(
        [pipeline.push_hmd(int(u), poses[i], np.ones(3, bool)).joints for i, u in enumerate(t_us)]
    )
    settled = joints[90:]  # once the height estimate has settled
    moved_m = np.linalg.norm(settled[:, [0, 1, 2, 10, 11]] - settled[:1, [0, 1, 2, 10, 11]], axis=-1).max()
    assert moved_m < 0.01  # the hips turned with it would move ~4 cm

    turned = np.concatenate([np.zeros(90), np.full(4 * 90, 2.5 * TURN_DEAD_ZONE_DEG)])
    t_us, poses = turning_stander(turned)
    pipeline = ProceduralPipeline(model)
    for i, u in enumerate(t_us):
        pose = pipeline.push_hmd(int(u), poses[i], np.ones(3, bool))
    hips = pose.joints[2] - pose.joints[1]  # left to right hip: +x at yaw 0, facing -z as the devices
    hips_yaw = np.degrees(np.arctan2(-hips[2], hips[0]))
    assert 2.5 * TURN_DEAD_ZONE_DEG - hips_yaw <= TURN_DEAD_ZONE_DEG + 1.0
    feet = pose.joints[11] - pose.joints[10]
    assert np.degrees(np.arctan2(-feet[2], feet[0])) > 10.0  # the feet stepped round after them


def test_served_rotations_give_the_served_joints_and_lost_controllers_let_the_arms_hang(model):
    rng = np.random.default_rng(1)
    motion = generate("stand_interact", 2.0, 60.0, rng)
    track = simulate_headset(motion, 90.0, rng)
    pipeline = ProceduralPipeline(model)
    valid = track.valid.copy()
    valid[90:, 1] = False
    for i, t in enumerate(track.t_us):
        pose = pipeline.push_hmd(int(t), track.poses[i], valid[i])
    joints, _ = forward_kinematics(pose.local_rot, pose.transl, rest_offsets(pipeline.body.bone_scale))
    assert np.allclose(joints, pose.joints, atol=1e-6)
    left_hand, left_shoulder = pose.joints[20], pose.joints[16]
    assert left_hand[1] < left_shoulder[1] - 0.4 and abs(left_hand[0] - left_shoulder[0]) < 0.15
    assert pose.camera is None and not pipeline.push_rgbd(0, None, None, None)


def test_a_controller_found_again_brings_the_hanging_arm_back_without_a_jump(model):
    rng = np.random.default_rng(1)
    track = simulate_headset(generate("stand_interact", 3.0, 60.0, rng), 90.0, rng)
    valid = track.valid.copy()
    valid[:, 1] = True
    valid[90:180, 1] = False  # the left controller lost for a second: the arm hangs
    pipeline = ProceduralPipeline(model)
    wrist = np.array(
        [pipeline.push_hmd(int(t), track.poses[i], valid[i]).joints[20] for i, t in enumerate(track.t_us)]
    )
    controller = joints_from_devices(track.poses)[0][:, 1]  # where the controller puts the wrist (unsmoothed)
    gap_m = np.linalg.norm(wrist[179] - controller[180])
    assert gap_m > 0.15  # the hanging hand was far from it
    assert np.linalg.norm(wrist[180] - wrist[179]) < 0.05 * gap_m  # found: no jump
    assert np.linalg.norm(np.diff(wrist[179:200], axis=0), axis=1).max() < 0.3 * gap_m  # over several samples
    closed = 180 + round(REACQUIRE_S * 90) + 1
    assert np.linalg.norm(wrist[closed:] - controller[closed:], axis=1).max() < 0.03  # back on the controller


def test_pipeline_for_picks_the_network_pipeline_for_onnx_models(model):
    assert isinstance(pipeline_for(model, naive=True), ProceduralPipeline)
    assert model.info.name == "procedural" and model.info.inputs == ("hmd",) and model.visual is None
