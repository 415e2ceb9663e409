"""Headset tracks and the camera model."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from egoposevr.model.skeleton import forward_kinematics
from egoposevr.model.synth.headset import CameraModel, HeadsetRig, device_poses, simulate_headset
from egoposevr.model.synth.procedural import generate

QUIET = HeadsetRig(
    head_noise_m=0,
    hand_noise_m=0,
    head_noise_deg=0,
    hand_noise_deg=0,
    drift_m=0,
    jitter_us=0,
    dropouts_per_min=0,
    behind_head_m=10.0,
)


@pytest.fixture(scope="module")
def motion():
    return generate("walk", 4.0, 60.0, np.random.default_rng(2))


@pytest.mark.parametrize("rate", [60.0, 72.0, 90.0])
def test_tracks_at_headset_rates(motion, rate):
    track = simulate_headset(motion, rate, np.random.default_rng(0))
    assert len(track.t_us) == int(4.0 * rate)
    dt_us = np.diff(track.t_us)
    assert (dt_us >= 0).all() and np.median(dt_us) == pytest.approx(1e6 / rate, abs=20)
    assert np.allclose(np.linalg.norm(track.poses[..., 3:], axis=-1), 1.0, atol=1e-6)
    assert track.valid[:, 0].all()  # the headset itself always tracks


def test_devices_sit_ahead_of_their_joints_and_look_where_the_head_looks(motion):
    track = simulate_headset(motion, 60.0, np.random.default_rng(0), QUIET)
    joints, rot = forward_kinematics(track.local_rot, track.root_pos_m, motion.offsets_m())
    head_fwd = rot[:, 15] @ np.array([0.0, 0.0, 1.0])  # SMPL faces +z
    device_fwd = Rotation.from_quat(track.poses[:, 0, 3:]).apply([0.0, 0.0, -1.0])  # OpenXR looks along -z
    assert np.allclose(head_fwd, device_fwd, atol=1e-9)
    offset = np.linalg.norm(track.poses[:, 0, :3] - joints[:, 15], axis=-1)
    assert np.allclose(offset, np.linalg.norm(QUIET.head_offset_m))
    grip = np.linalg.norm(track.poses[:, 1, :3] - joints[:, 20], axis=-1)
    assert np.allclose(grip, np.linalg.norm(QUIET.left_grip_offset_m))
    assert np.allclose(device_poses(joints, rot, QUIET), track.poses)


def test_noise_is_small_and_dropouts_hold_the_last_pose(motion):
    rig = HeadsetRig(dropouts_per_min=60.0)
    noisy = simulate_headset(motion, 60.0, np.random.default_rng(4), rig)
    clean = simulate_headset(motion, 60.0, np.random.default_rng(4), QUIET)
    head_err = np.linalg.norm(noisy.poses[:, 0, :3] - clean.poses[:, 0, :3], axis=-1)
    assert 0 < np.median(head_err) < 0.01
    lost = ~noisy.valid[:, 1:]
    assert lost.any() and not lost.all()
    for k in (1, 2):
        idx = np.flatnonzero(~noisy.valid[1:, k]) + 1
        assert np.array_equal(noisy.poses[idx, k], noisy.poses[idx - 1, k])


def test_a_controller_behind_the_head_is_lost():
    motion = generate("walk", 1.0, 60.0, np.random.default_rng(0))
    rig = HeadsetRig(behind_head_m=-10.0, dropouts_per_min=0.0)  # everything counts as behind
    track = simulate_headset(motion, 60.0, np.random.default_rng(0), rig)
    assert not track.valid[:, 1:].any()


def test_camera_defaults_and_extrinsics():
    cam = CameraModel()
    fx, fy, cx, cy = cam.intrinsics()
    assert (cam.width, cam.height) == (320, 256) and fx == pytest.approx(160.0) and cx == 159.5
    m = cam.cam_from_head()
    assert np.allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3)) and np.isclose(np.linalg.det(m[:3, :3]), 1.0)
    # the optical axis points forward (-z) and down (-y) in the headset frame, pitched as configured
    axis = cam.device_from_camera()[:3, :3] @ np.array([0.0, 0.0, 1.0])
    assert np.degrees(np.arctan2(-axis[1], -axis[2])) == pytest.approx(cam.pitch_down_deg)
    point = np.array([[0.1, 0.2, 1.5]])
    uv = cam.project(point)
    assert np.allclose(uv, [[fx * 0.1 / 1.5 + cx, fy * 0.2 / 1.5 + cy]])
    assert cam.in_view(point).all() and not cam.in_view(np.array([[0.0, 0.0, -1.0]])).any()
