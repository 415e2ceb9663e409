"""The compiled serving kernels agree with the numpy/scipy reference, and serving never waits for the compiler."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from egoposevr.model import rotations as r
from egoposevr.model import skeleton as sk
from egoposevr.model.runtime import kernels, kpo
from egoposevr.model.runtime.calibration import Calibration
from egoposevr.model.runtime.loading import LoadedModel
from egoposevr.model.runtime.pipeline import Pipeline
from egoposevr.model.weights import WEIGHTS_DIR

RNG = np.random.default_rng(11)
PARENTS = sk.PARENTS.astype(np.int64)


def random_rotations(n: int) -> np.ndarray:
    return Rotation.random(n, random_state=int(RNG.integers(1 << 30))).as_matrix()


def test_fk_of_one_pose_matches_the_batched_reference():
    local, root, offsets = (
        random_rotations(22),
        RNG.normal(size=3),
        sk.rest_offsets(RNG.uniform(0.8, 1.2, 22)),
    )
    pos, glob = kernels.forward_kinematics_one(local, root, offsets, PARENTS)
    ref_pos, ref_glob = sk.forward_kinematics(local, root, offsets)
    np.testing.assert_allclose(pos, ref_pos, atol=1e-12)
    np.testing.assert_allclose(glob, ref_glob, atol=1e-12)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-4, 1.0, np.pi - 1e-6, np.pi])
def test_rotation_vectors_match_scipy_near_zero_and_half_turn(angle):
    axes = RNG.normal(size=(50, 3))
    rotvec = axes / np.linalg.norm(axes, axis=1, keepdims=True) * angle
    matrices = Rotation.from_rotvec(rotvec).as_matrix()
    np.testing.assert_allclose(kernels.rotvecs_to_matrices(rotvec), matrices, atol=1e-12)
    back = kernels.matrices_to_rotvecs(matrices)
    # at exactly π, v and -v are the same rotation: compare as rotations
    np.testing.assert_allclose(Rotation.from_rotvec(back).as_matrix(), matrices, atol=1e-9)
    if angle < np.pi - 1e-3:
        np.testing.assert_allclose(back, Rotation.from_matrix(matrices).as_rotvec(), atol=1e-9)


def test_quaternion_conversions_match_scipy_for_unnormalised_and_negative_w():
    quat = RNG.normal(size=(200, 4)) * RNG.uniform(0.1, 10, size=(200, 1))
    np.testing.assert_allclose(
        kernels.quats_to_matrices(quat), Rotation.from_quat(quat).as_matrix(), atol=1e-12
    )
    np.testing.assert_allclose(
        kernels.quats_to_rotvecs(quat), Rotation.from_quat(quat).as_rotvec(), atol=1e-12
    )


def test_rotation_wrappers_refuse_zero_quaternions_and_keep_batch_shapes():
    with pytest.raises(ValueError, match="non-zero"):
        r.quat_xyzw_to_matrix(np.zeros((2, 4)))
    assert r.axis_angle_to_matrix(np.zeros((4, 5, 3))).shape == (4, 5, 3, 3)
    assert r.matrix_to_axis_angle(np.broadcast_to(np.eye(3), (2, 22, 3, 3))).shape == (2, 22, 3)


def test_sixd_matches_gram_schmidt():
    sixd = RNG.normal(size=(22, 6)) * 3
    m = kernels.sixd_to_matrices(sixd)
    b1 = sixd[:, :3] / np.linalg.norm(sixd[:, :3], axis=1, keepdims=True)
    np.testing.assert_allclose(m[:, :, 0], b1, atol=1e-12)
    np.testing.assert_allclose(m @ np.swapaxes(m, 1, 2), np.broadcast_to(np.eye(3), m.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(m), 1.0, atol=1e-12)


def test_kpo_kernel_reaches_no_higher_energy_than_any_small_perturbation():
    local = random_rotations(22)
    pred, _ = sk.forward_kinematics(local, np.zeros(3))
    targets = pred + RNG.normal(scale=0.05, size=pred.shape)
    observed = np.zeros(22, dtype=bool)
    observed[[15, 20, 21]] = True
    w = kpo.KpoWeights(iterations=30)
    refined = kpo.solve_kpo(pred, targets, observed, w)
    best = kpo.kpo_energy(refined, pred, targets, observed, w)
    for _ in range(20):  # a local minimum of the numpy statement of the energy
        nudged = refined + RNG.normal(scale=1e-4, size=refined.shape)
        assert kpo.kpo_energy(nudged, pred, targets, observed, w) > best


def linked_spd_matrix(links, n: int) -> np.ndarray:
    """A random symmetric positive definite (3n, 3n) with nonzero 3×3 blocks only on the diagonal and at
    linked joints, as KPO's Hessian has."""
    a = np.diag(RNG.uniform(0.5, 100.0, 3 * n))
    for i, j in links:
        b = RNG.normal(size=(3, 3))
        block = b @ b.T * RNG.uniform(1.0, 1e4)  # bone-length stiffness reaches 1e4
        for row, col, sign in ((i, i, 1), (j, j, 1), (i, j, -1), (j, i, -1)):
            a[3 * row : 3 * row + 3, 3 * col : 3 * col + 3] += sign * block
    return a


def test_the_linked_block_solver_solves_kpos_systems_as_a_dense_solve_does():
    order, later = kpo.elimination_order(kpo.LINKS, sk.NUM_JOINTS)
    for _ in range(20):
        a, rhs = linked_spd_matrix(kpo.LINKS, sk.NUM_JOINTS), RNG.normal(size=3 * sk.NUM_JOINTS)
        want = np.linalg.solve(a, rhs)
        got = kernels.solve_linked_blocks(a.copy(), rhs, order, later)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-10 * np.abs(want).max())


def test_the_elimination_order_adds_no_link_and_refuses_a_graph_that_would():
    order, later = kpo.elimination_order(kpo.LINKS, sk.NUM_JOINTS)
    assert sorted(order.tolist()) == list(range(sk.NUM_JOINTS))
    linked = {frozenset(link) for link in kpo.LINKS}
    for joint in range(sk.NUM_JOINTS):
        after = [m for m in later[joint] if m >= 0]
        assert all(frozenset((joint, m)) in linked for m in after)
        assert all(frozenset((a, b)) in linked for a in after for b in after if a != b)  # no fill-in
    square = ((0, 1), (1, 2), (2, 3), (3, 0))  # eliminating any corner links its two neighbours
    with pytest.raises(ValueError, match="no perfect elimination order"):
        kpo.elimination_order(square, 4)


def test_quaternion_products_match_scipy():
    a, b = Rotation.random(5, random_state=3), Rotation.random(5, random_state=4)
    got = kernels.quats_multiply(a.as_quat(), b.as_quat())
    np.testing.assert_allclose(Rotation.from_quat(got).as_matrix(), (a * b).as_matrix(), atol=1e-12)


def test_serving_never_compiles_after_warm_up():
    """A pose after warm-up must not wait seconds for numba: every call's argument types were compiled then."""
    kernels.warm_up()
    compiled = {name: len(f.signatures) for name, f in _kernel_functions()}
    pipeline = Pipeline(LoadedModel.load(WEIGHTS_DIR / "egoposevr.onnx"))
    rgb, depth = np.zeros((96, 128, 3), np.uint8), np.full((96, 128), 1200, np.uint16)
    pipeline.push_rgbd(0, rgb, depth, np.array([100.0, 100.0, 64.0, 48.0]))
    head = np.array([0.0, 1.6, 0.0, 0.0, 0.0, 0.0, 1.0])
    hands = np.array([[0.2, -0.5, 0, 0, 0, 0, 0], [-0.2, -0.5, 0, 0, 0, 0, 0]])
    turns = Rotation.from_euler("x", [[5.0], [20.0], [-20.0]], degrees=True).as_matrix()
    pipeline.calibrate(
        Calibration("tpose", 1.6, turns, arm_scale=1.0)
    )  # device rotations go through a kernel
    for i in range(5):
        poses = np.vstack([head, head + hands])
        pipeline.push_hmd(i * 11_111, poses, np.array([True, i % 2 == 0, True]))
    assert {name: len(f.signatures) for name, f in _kernel_functions()} == compiled


def _kernel_functions():
    return [(n, f) for n, f in vars(kernels).items() if hasattr(f, "signatures") and not n.startswith("_")]


@pytest.mark.parametrize("channels", [3, 4])
def test_the_encoder_input_kernel_gives_network_inputs_numbers_bit_for_bit(channels):
    from egoposevr.model.inputs import DEPTH_SCALE_M, network_input

    rgb = RNG.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    depth = RNG.integers(0, 65536, (48, 64), dtype=np.uint16)
    depth[::7, ::5] = 0  # holes stay 0
    out = np.full((channels, 48, 64), np.nan, np.float32)
    kernels.fill_network_input(rgb, depth, 1000.0 * DEPTH_SCALE_M, out)
    np.testing.assert_array_equal(out, network_input(rgb, depth, channels))
