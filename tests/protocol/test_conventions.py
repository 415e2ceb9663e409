"""The frame conversions PROTOCOL.md gives for Unity and Unreal are the true change of basis."""

import numpy as np
from scipy.spatial.transform import Rotation

RNG = np.random.default_rng(1)
UNITY_FROM_OURS = np.diag([1.0, 1.0, -1.0])
UNREAL_FROM_OURS = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # then x100 for cm


def to_unity(p, q):  # as written in PROTOCOL.md §3.1
    return np.array([p[0], p[1], -p[2]]), np.array([-q[0], -q[1], q[2], q[3]])


def to_unreal(p, q):  # as written in PROTOCOL.md §3.2
    return 100.0 * np.array([-p[2], p[0], p[1]]), np.array([q[2], -q[0], -q[1], q[3]])


def from_unreal(p, q):
    return np.array([p[1], p[2], -p[0]]) / 100.0, np.array([-q[1], -q[2], q[0], q[3]])


def test_conversions_match_the_change_of_basis():
    for _ in range(50):
        p, q = RNG.normal(size=3), Rotation.random(random_state=RNG).as_quat()
        for convert, basis, scale in ((to_unity, UNITY_FROM_OURS, 1.0), (to_unreal, UNREAL_FROM_OURS, 100.0)):
            p2, q2 = convert(p, q)
            np.testing.assert_allclose(p2, scale * basis @ p, atol=1e-12)
            expected = basis @ Rotation.from_quat(q).as_matrix() @ basis.T
            np.testing.assert_allclose(Rotation.from_quat(q2).as_matrix(), expected, atol=1e-12)


def test_conversions_invert():
    p, q = RNG.normal(size=3), Rotation.random(random_state=RNG).as_quat()
    np.testing.assert_allclose(np.concatenate(to_unity(*to_unity(p, q))), np.concatenate([p, q]), atol=1e-12)
    np.testing.assert_allclose(
        np.concatenate(from_unreal(*to_unreal(p, q))), np.concatenate([p, q]), atol=1e-12
    )


def test_worked_example_quarter_turn_left():
    q = np.array([0.0, np.sqrt(0.5), 0.0, np.sqrt(0.5)])
    # A quarter turn about +Y turns the forward direction (-Z) to the left (-X).
    np.testing.assert_allclose(Rotation.from_quat(q).apply([0, 0, -1]), [-1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(to_unity([0, 0, 0], q)[1], [0.0, -np.sqrt(0.5), 0.0, np.sqrt(0.5)])
    np.testing.assert_allclose(to_unreal([0, 0, 0], q)[1], [0.0, 0.0, -np.sqrt(0.5), np.sqrt(0.5)])
