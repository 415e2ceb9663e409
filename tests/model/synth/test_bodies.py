"""Mesh bodies: the rendered body and the truth skeleton agree, the bank file is checked, the rasteriser draws
what geometry says."""

import importlib.util

import numpy as np
import pytest
from tubebodies import a_pose_joints, tube_bank

from egoposevr.model.skeleton import PARENTS, forward_kinematics
from egoposevr.model.synth import raster
from egoposevr.model.synth.bodies import (
    REGION_INNER,
    BodyBank,
    BodyBankError,
    body_bone_scale,
    fit_motion_to_body,
    joint_transforms,
    pose_vertices,
    rest_alignment,
)
from egoposevr.model.synth.headset import CameraModel
from egoposevr.model.synth.procedural import Body, generate
from egoposevr.model.synth.render import Renderer, prepare_mesh_body, random_appearance

HAS_ANNY = importlib.util.find_spec("anny") is not None and importlib.util.find_spec("torch") is not None


def random_pose(rng, bone_scale):
    local = np.stack([np.eye(3)] + [_small_rotation(rng, 50) for _ in range(21)])
    joints, global_rot = forward_kinematics(local, np.array([0.3, 1.0, -0.2]), _offsets(bone_scale))
    return joints, global_rot


def _offsets(bone_scale):
    from egoposevr.model.skeleton import rest_offsets

    return rest_offsets(bone_scale)


def _small_rotation(rng, max_deg):
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(rng.normal(size=3) * np.deg2rad(max_deg) / 2).as_matrix()


def test_each_bone_end_lands_on_the_truth_joint():
    """x -> R_j A_j (x - q_j) + p_j takes a body's rest child joint exactly onto forward kinematics' child."""
    bank = tube_bank()
    rng = np.random.default_rng(0)
    for body in range(bank.count):
        joints, global_rot = random_pose(rng, bank.bone_scale(body))
        rot, shift = joint_transforms(bank, body, global_rot, joints)
        for child in range(1, 22):
            moved = rot[PARENTS[child]] @ bank.rest_joints[body, child] + shift[PARENTS[child]]
            assert np.allclose(moved, joints[child], atol=1e-9), child


def test_a_tube_follows_its_bone_and_keeps_its_radius():
    bank = tube_bank()
    rng = np.random.default_rng(1)
    joints, global_rot = random_pose(rng, bank.bone_scale(1))
    vertices = pose_vertices(bank, 1, global_rot, joints)
    for tube, child in enumerate(range(1, 22)):
        ring = vertices[tube * 12 : tube * 12 + 12]
        a, b = joints[PARENTS[child]], joints[child]
        axis = (b - a) / np.linalg.norm(b - a)
        rel = ring - a
        radial = rel - np.outer(rel @ axis, axis)
        assert np.allclose(np.linalg.norm(radial, axis=1), 0.055, atol=1e-6)
        assert np.allclose(np.sort(rel @ axis)[[0, -1]], [0.0, np.linalg.norm(b - a)], atol=1e-6)


def test_rest_alignment_undoes_an_a_pose():
    joints = a_pose_joints(1.0)
    align = rest_alignment(joints)
    from egoposevr.model.skeleton import REST_JOINTS_M

    for joint, child in ((16, 18), (18, 20), (1, 4)):
        have = align[joint] @ (joints[child] - joints[joint])
        want = REST_JOINTS_M[child] - REST_JOINTS_M[joint]
        assert np.allclose(have / np.linalg.norm(have), want / np.linalg.norm(want), atol=1e-9)
    assert np.allclose(body_bone_scale(joints)[1:], 1.0)


def test_a_motion_fitted_to_a_body_has_its_bones_and_stands_on_the_floor():
    bank = tube_bank()
    motion = generate("walk", 2.0, 30.0, np.random.default_rng(2))
    fitted = fit_motion_to_body(motion, bank.rest_joints[1])
    assert np.allclose(fitted.bone_scale, bank.bone_scale(1))
    feet = fitted.joints()[:, [10, 11], 1].min(axis=1)
    assert abs(np.percentile(feet, 1) - 0.035) < 0.01  # the foot joint's height above the sole


def test_bank_round_trip_and_refusals(tmp_path):
    bank = tube_bank()
    path = bank.save(tmp_path / "bank.npz")
    again = BodyBank.load(path)
    assert again.source == bank.source and again.phenotype_names == bank.phenotype_names
    assert np.array_equal(again.rest_vertices, bank.rest_vertices) and np.array_equal(again.faces, bank.faces)
    assert bank.save(tmp_path / "again.npz").read_bytes() == path.read_bytes()  # deterministic bytes
    (tmp_path / "cut.npz").write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2])
    with pytest.raises(BodyBankError, match="not a readable body bank"):
        BodyBank.load(tmp_path / "cut.npz")
    np.savez(tmp_path / "other.npz", x=np.zeros(3))
    with pytest.raises(BodyBankError, match="not a body bank"):
        BodyBank.load(tmp_path / "other.npz")
    with pytest.raises(BodyBankError, match="face indices"):
        BodyBank(**{**bank.__dict__, "faces": bank.faces + 10_000})


def test_rasteriser_depth_and_barycentrics_match_the_plane():
    """One big triangle on the plane z = 1 + 0.5 x: every covered pixel's depth is the plane's, and the
    interpolated camera point lies on it (perspective-correct barycentrics)."""
    verts = np.array([[-0.5, -0.5, 0.75], [0.6, -0.4, 1.3], [0.0, 0.6, 1.0]])
    faces = np.array([[0, 1, 2]], dtype=np.int32)
    h, w, f = 64, 80, 60.0
    zbuf, face_id = np.full((h, w), np.inf), np.full((h, w), -1, dtype=np.int32)
    bary = np.zeros((h, w, 2), dtype=np.float32)
    raster.rasterize(verts, faces, f, f, (w - 1) / 2, (h - 1) / 2, zbuf, face_id, bary)
    v, u = np.nonzero(face_id == 0)
    assert len(v) > 500
    x = (u - (w - 1) / 2) / f * zbuf[v, u]
    assert np.allclose(zbuf[v, u], 1.0 + 0.5 * x, atol=1e-9)
    wb, wc = bary[v, u, 0].astype(float), bary[v, u, 1].astype(float)
    point = (1 - wb - wc)[:, None] * verts[0] + wb[:, None] * verts[1] + wc[:, None] * verts[2]
    assert np.allclose(point[:, 2], zbuf[v, u], atol=1e-5)


def test_the_mesh_body_is_drawn_where_its_joints_project():
    """Rendered from a camera in front: every joint projects onto the body's silhouette (depth in front of the
    back wall) and the body's depth there is within its radius of the joint's depth."""
    bank = tube_bank()
    camera = CameraModel(width=120, height=160, hfov_deg=60.0, max_depth_m=20.0)
    renderer = Renderer(camera)
    look = random_appearance(np.random.default_rng(3), np.zeros(2))
    look = type(look)(**{**look.__dict__, "boxes": np.zeros((0, 9))})
    joints, global_rot = forward_kinematics(
        np.broadcast_to(np.eye(3), (22, 3, 3)), bank.rest_joints[0, 0], _offsets(bank.bone_scale(0))
    )
    vertices = pose_vertices(bank, 0, global_rot, joints)
    world_from_camera = np.eye(4)
    world_from_camera[:3, :3] = np.diag([1.0, -1.0, -1.0])
    world_from_camera[:3, 3] = [0.0, 0.9, 2.4]
    _, depth = renderer.render_mesh_clean(
        world_from_camera, prepare_mesh_body(bank, 0), vertices, np.zeros((0, 8)), look
    )
    cam = np.linalg.inv(world_from_camera)
    joints_cam = joints @ cam[:3, :3].T + cam[:3, 3]
    uv = np.round(camera.project(joints_cam)).astype(int)
    for j in (0, 4, 7, 12, 16, 18):  # joints inside a tube (ends where tubes meet)
        assert abs(depth[uv[j, 1], uv[j, 0]] - joints_cam[j, 2]) < 0.07, j


@pytest.mark.skipif(
    not HAS_ANNY, reason="anny (training extras) is not installed: the anny body bank is untested"
)
def test_anny_bodies_hold_their_truth_skeleton_inside():
    """Two anny bodies walking: every truth joint stays inside the posed mesh (winding number), the feet stay
    within 3 cm of the floor, and the bank's bone lengths are the skeleton's."""
    from egoposevr.model.synth.anny_bodies import build_bank

    bank = build_bank(2, seed=5)
    assert bank.rest_vertices.shape[1] > 10_000 and set(np.unique(bank.region)) >= {0, 3, 7, 9, 10}
    rng = np.random.default_rng(4)
    for body in range(bank.count):
        height = bank.height_m(body)
        assert 1.45 < height < 2.05
        motion = generate("walk", 1.5, 10.0, rng, Body.from_scale(bank.bone_scale(body)))
        joints, global_rot = motion.fk()
        for k in range(0, motion.num_frames, 5):
            vertices = pose_vertices(bank, body, global_rot[k], joints[k])
            outer = bank.faces[bank.region != REGION_INNER]  # the mouth and eye sockets are shells inside
            inside = winding_numbers(vertices, outer, joints[k])
            assert (inside > 0.5).all(), (body, k, np.flatnonzero(inside <= 0.5), inside)
            assert abs(vertices[:, 1].min()) < 0.03


def winding_numbers(vertices, faces, points):
    """Generalised winding number of a closed-ish triangle mesh around points (P, 3): 1 inside, 0 outside."""
    out = []
    for p in points:
        a, b, c = (vertices[faces[:, k]] - p for k in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
        det = np.einsum("ij,ij->i", a, np.cross(b, c))
        div = la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", b, c) * la
        div += np.einsum("ij,ij->i", c, a) * lb
        out.append(abs(np.arctan2(det, div).sum() * 2 / (4 * np.pi)))
    return np.array(out)
