"""Rotation conversions round-trip and agree with each other, over arbitrary batch shapes."""

import numpy as np
import pytest

from egoposevr.model import rotations as r

RNG = np.random.default_rng(7)


def random_matrices(*shape):
    return r.axis_angle_to_matrix(RNG.normal(size=(*shape, 3)) * 1.5)


def test_matrix_quat_matrix_round_trip():
    m = random_matrices(4, 5)
    np.testing.assert_allclose(r.quat_xyzw_to_matrix(r.matrix_to_quat_xyzw(m)), m, atol=1e-12)


def test_matrix_axis_angle_matrix_round_trip():
    m = random_matrices(3, 22)
    np.testing.assert_allclose(r.axis_angle_to_matrix(r.matrix_to_axis_angle(m)), m, atol=1e-12)


def test_sixd_round_trip_is_exact_for_rotations():
    m = random_matrices(2, 3, 4)
    sixd = r.matrix_to_sixd(m)
    assert sixd.shape == (2, 3, 4, 6)
    np.testing.assert_allclose(r.sixd_to_matrix(sixd), m, atol=1e-12)


def test_sixd_is_the_first_two_columns():
    m = random_matrices(1)[0]
    np.testing.assert_array_equal(r.matrix_to_sixd(m), np.concatenate([m[:, 0], m[:, 1]]))


def test_any_sixd_vector_maps_to_a_proper_rotation():
    m = r.sixd_to_matrix(RNG.normal(size=(100, 6)) * 10)
    np.testing.assert_allclose(m @ np.swapaxes(m, -1, -2), np.broadcast_to(np.eye(3), m.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(m), 1.0, atol=1e-12)


def test_quaternion_axis_angle_agree_with_known_values():
    quarter_turn_about_y = np.array([0.0, np.sin(np.pi / 4), 0.0, np.cos(np.pi / 4)])
    np.testing.assert_allclose(
        r.quat_xyzw_to_axis_angle(quarter_turn_about_y), [0.0, np.pi / 2, 0.0], atol=1e-12
    )
    np.testing.assert_allclose(
        r.axis_angle_to_quat_xyzw(np.array([0.0, np.pi / 2, 0.0])), quarter_turn_about_y
    )
    # x axis turned a quarter about y points to -z (right-handed)
    np.testing.assert_allclose(
        r.quat_xyzw_to_matrix(quarter_turn_about_y) @ [1, 0, 0], [0, 0, -1], atol=1e-12
    )


def test_geodesic_angle_is_accurate_near_zero_and_pi():
    for angle in (1e-9, 0.3, np.pi - 1e-7):
        a = random_matrices(1)[0]
        b = a @ r.axis_angle_to_matrix(np.array([0.0, 0.0, angle]))
        assert r.geodesic_angle(a, b) == pytest.approx(angle, rel=1e-5)


def test_wrong_shapes_say_what_was_expected():
    with pytest.raises(ValueError, match=r"sixd must be \(\.\.\., 6\), got \(4, 5\)"):
        r.sixd_to_matrix(np.zeros((4, 5)))


def test_the_kernels_quaternion_product_matches_scipy_composition():
    from scipy.spatial.transform import Rotation

    from egoposevr.model.runtime import kernels

    a, b = Rotation.random(20, random_state=1), Rotation.random(20, random_state=2)
    product = np.stack([kernels._quat_multiply(p, q) for p, q in zip(a.as_quat(), b.as_quat(), strict=True)])
    np.testing.assert_allclose(r.quat_xyzw_to_matrix(product), (a * b).as_matrix(), atol=1e-12)
