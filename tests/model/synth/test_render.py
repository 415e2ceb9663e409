"""The renderer and its labels: z-buffered depth, 2D = projected 3D, sane visibility, determinism."""

import numpy as np
import pytest

from egoposevr.model.rotations import axis_angle_to_matrix
from egoposevr.model.skeleton import NUM_JOINTS, forward_kinematics
from egoposevr.model.synth.headset import CameraModel, HeadsetRig, device_poses
from egoposevr.model.synth.pipeline import SynthConfig, nearest_pixel, synthesize_sequence
from egoposevr.model.synth.procedural import Body, generate
from egoposevr.model.synth.render import JOINT_RADIUS_M, Renderer, body_capsules, random_appearance

from .conftest import SMALL_CAMERA


def _decode_depth(png: bytes) -> np.ndarray:
    import cv2

    return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)


def test_two_d_labels_are_the_projection_of_the_three_d_labels(walk_sequence):
    frames = walk_sequence.frames
    assert np.allclose(SMALL_CAMERA.project(frames.joints_cam_m), frames.joints_uv_px, atol=1e-3)
    assert np.array_equal(SMALL_CAMERA.in_view(frames.joints_cam_m), frames.visible)


def test_three_d_labels_are_the_world_joints_in_the_camera_frame(walk_sequence, small_config):
    seq = walk_sequence
    k = len(seq.frames.t_us) // 2
    world = SMALL_CAMERA.world_from_camera(seq.frames.head_pose[k])
    back = seq.frames.joints_cam_m[k] @ world[:3, :3].T + world[:3, 3]
    t_s = (seq.frames.t_us[k] - seq.track.t_us[0]) / 1e6 + seq.track.motion_t_s[0]
    from egoposevr.model.synth.motion import sample_at

    local, root = sample_at(seq.motion, np.array([t_s]))
    joints, _ = forward_kinematics(local, root, seq.motion.offsets_m())
    assert np.allclose(back, joints[0], atol=1e-6)


def test_depth_at_visible_unoccluded_joints_is_within_the_body_radius(walk_sequence):
    frames = walk_sequence.frames
    checked = 0
    for k in range(len(frames.t_us)):
        depth_m = _decode_depth(frames.depth_png[k]) / 1000.0
        px = np.round(frames.joints_uv_px[k]).astype(int)
        for j in np.flatnonzero(frames.visible[k] & ~frames.occluded[k]):
            u, v = np.clip(px[j], 0, [SMALL_CAMERA.width - 1, SMALL_CAMERA.height - 1])
            if depth_m[v, u] == 0:  # a sensor hole
                continue
            z = frames.joints_cam_m[k, j, 2]
            radius = JOINT_RADIUS_M[j] * walk_sequence.appearance.girth * 1.3
            assert z - radius - 0.035 <= depth_m[v, u] <= z + 0.02, (
                k,
                j,
                z,
                depth_m[v, u],
            )  # labels: clean depth
            checked += 1
    assert checked > 100


def test_standing_and_looking_down_sees_the_feet():
    """Stand upright with the head pitched down 25°: both feet and ankles in view and not hidden."""
    body = Body.from_scale(np.ones(NUM_JOINTS))
    local = np.broadcast_to(np.eye(3), (NUM_JOINTS, 3, 3)).copy()
    local[16] = axis_angle_to_matrix(np.array([0, 0, -1.3]))  # arms down by the sides
    local[17] = axis_angle_to_matrix(np.array([0, 0, 1.3]))
    local[12] = axis_angle_to_matrix(np.array([np.deg2rad(10), 0, 0]))
    local[15] = axis_angle_to_matrix(np.array([np.deg2rad(15), 0, 0]))
    joints, rot = forward_kinematics(local[None], np.array([[0.0, body.stand_pelvis_y, 0.0]]), body.offsets)
    head = device_poses(joints, rot, HeadsetRig())[0, 0]
    cam = CameraModel()
    cam_from_world = np.linalg.inv(cam.world_from_camera(head))
    joints_cam = joints[0] @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    visible = cam.in_view(joints_cam)
    assert visible[[7, 8, 10, 11]].all(), visible
    look = random_appearance(np.random.default_rng(0), np.zeros(2))
    renderer = Renderer(cam)
    _, depth = renderer.render_clean(
        cam.world_from_camera(head), body_capsules(joints[0], body.bone_scale, 1.0), look
    )
    uv = np.round(cam.project(joints_cam)).astype(int)
    for j in (10, 11):  # the toes are seen at their own depth, not through something nearer
        assert depth[uv[j, 1], uv[j, 0]] == pytest.approx(joints_cam[j, 2], abs=JOINT_RADIUS_M[j] + 0.02)


def test_visibility_rates_over_a_walk_are_sane(walk_sequence):
    rate = walk_sequence.frames.visible.mean(axis=0)
    assert rate[[10, 11]].min() > 0.5  # feet mostly in view
    assert rate[[15, 12]].max() == 0.0  # the camera hangs below the face: head and neck never


def test_depth_is_a_true_z_buffer_for_a_sphere():
    cam = CameraModel(width=64, height=48)
    renderer = Renderer(cam)
    look = random_appearance(np.random.default_rng(1), np.zeros(2))
    world_from_cam = np.eye(4)
    world_from_cam[:3, :3] = np.diag([1.0, -1.0, -1.0])  # looking along world -z, level
    world_from_cam[:3, 3] = [0.0, 1.5, 0.0]
    near = np.array([[0.0, 1.5, -1.0, 0.0, 1.5, -1.0, 0.2, 0]])  # sphere 1 m ahead
    far = np.array([[0.0, 1.5, -2.0, 0.0, 1.5, -2.0, 0.5, 1]])  # bigger one behind it
    _, depth = renderer.render_clean(world_from_cam, np.concatenate([far, near]), look)
    fx, _, cx, cy = cam.intrinsics()
    centre = depth[round(cy), round(cx)]
    assert centre == pytest.approx(0.8, abs=0.01)  # the near sphere's front, whatever the order
    edge_u = round(cx + fx * 0.35 / 1.5)  # beside the near sphere, inside the far one
    row = round(cy)
    sx, sy = (edge_u - cx) / fx, (row - cy) / fx  # the ray (sx·z, sy·z, z) meets the far sphere at:
    a, b, c = sx**2 + sy**2 + 1, -4.0, 4.0 - 0.25
    expected_z = (-b - np.sqrt(b * b - 4 * a * c)) / (2 * a)
    assert depth[row, edge_u] == pytest.approx(expected_z, abs=1e-4)
    assert depth[0, 0] > 1.0  # a corner ray passes the spheres and meets the room


def test_same_seed_same_bytes(small_config, small_renderer):
    def make(seed):
        rng = np.random.default_rng(seed)
        return synthesize_sequence(generate("kick", 1.0, 60.0, rng), small_config, rng, small_renderer)

    a, b, c = make(3), make(3), make(4)
    assert a.frames.rgb_jpeg == b.frames.rgb_jpeg and a.frames.depth_png == b.frames.depth_png
    assert np.array_equal(a.track.poses, b.track.poses)
    assert a.frames.rgb_jpeg != c.frames.rgb_jpeg


def test_motion_blur_smears_moving_frames(small_renderer):
    rng_a, rng_b = np.random.default_rng(9), np.random.default_rng(9)
    sharp = SynthConfig(camera=SMALL_CAMERA)
    blurred = SynthConfig(camera=SMALL_CAMERA, blur_samples=3, exposure_s=0.04)
    a = synthesize_sequence(generate("high_knees", 1.0, 60.0, rng_a), sharp, rng_a, small_renderer)
    b = synthesize_sequence(generate("high_knees", 1.0, 60.0, rng_b), blurred, rng_b, small_renderer)
    assert a.frames.rgb_jpeg != b.frames.rgb_jpeg
    assert np.allclose(a.frames.joints_cam_m, b.frames.joints_cam_m)  # labels are for mid-exposure


def test_a_joint_at_the_lens_plane_gets_an_in_bounds_pixel_without_a_cast_warning():
    """A joint a hair in front of a distorting lens projects beyond what an int holds (numpy warns on that
    cast, and the tests turn warnings into errors); a degenerate one to NaN. Both get an in-bounds pixel;
    pixels in the image are rounded as before."""
    camera = CameraModel(width=40, height=32, hfov_deg=90.0, pitch_down_deg=70.0, k1=0.05)
    points = np.array([[0.3, -0.2, 1e-9], [0.0, 0.0, 1.0], [0.1, 0.05, 0.5]])
    uv = camera.project(points)
    assert np.abs(uv[0]).max() > 1e19  # off any int64
    uv[1, 0] = np.nan
    px = nearest_pixel(uv, camera.width, camera.height)
    assert px.dtype.kind == "i" and (px >= 0).all() and (px[:, 0] < 40).all() and (px[:, 1] < 32).all()
    assert px[2].tolist() == np.round(uv[2]).astype(int).tolist()
