"""Rotation conversions in numpy, batched over any leading dimensions.

Representations (``...`` = any batch shape):
- matrix      (..., 3, 3)  rotation matrices acting on column vectors (v' = R v)
- quat_xyzw   (..., 4)     unit quaternions, scalar last (the wire format's order)
- axis_angle  (..., 3)     rotation vectors: unit axis times angle in radians (SMPL's pose format)
- sixd        (..., 6)     the continuous 6D representation of Zhou et al. (CVPR 2019): the first two
                           *columns* of the matrix, concatenated [R[:,0], R[:,1]]. (pytorch3d uses rows; we
                           do not.) Any 6-vector maps back to a rotation through Gram-Schmidt.

Matrix -> quaternion delegates to ``scipy.spatial.transform.Rotation`` (well kept, numerically careful near 0
and pi). The conversions on the serving path (quaternion or rotation vector -> matrix, quaternion or matrix ->
rotation vector, 6D -> matrix) run as compiled kernels (:mod:`.kernels`): scipy's Rotation costs 15-30 µs of
set-up per call on the three devices of one headset sample; tests hold the kernels to scipy within 1e-12.
The 6D pair is ours because scipy has no 6D. The yaw helpers at the end are the runtime's, for one turn
about +y at a time.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from .runtime import kernels


def _check_last(x: np.ndarray, shape: tuple[int, ...], name: str) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.shape[x.ndim - len(shape) :] != shape:
        raise ValueError(f"{name} must be (..., {', '.join(map(str, shape))}), got {x.shape}")
    return x


def quat_xyzw_to_matrix(quat_xyzw: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions (normalised here; zero ones raise) -> (..., 3, 3) matrices."""
    q = _rows(quat_xyzw, (4,), "quat_xyzw")
    _check_nonzero(q)
    return kernels.quats_to_matrices(q).reshape(*np.shape(quat_xyzw)[:-1], 3, 3)


def _rows(x: np.ndarray, shape: tuple[int, ...], name: str) -> np.ndarray:
    """x (..., *shape) -> a contiguous float64 (n, *shape) stack for the kernels."""
    x = _check_last(x, shape, name)
    return np.ascontiguousarray(x.reshape(-1, *shape))


def _check_nonzero(q: np.ndarray) -> None:
    norm = np.sqrt((q * q).sum(-1))
    if not (norm > 1e-12).all():  # also catches NaN
        raise ValueError("quaternions must be finite and non-zero")


def matrix_to_quat_xyzw(matrix: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 4) unit quaternions with w >= 0."""
    m = _check_last(matrix, (3, 3), "matrix")
    q = Rotation.from_matrix(m.reshape(-1, 3, 3)).as_quat(canonical=True)
    return q.reshape(*m.shape[:-2], 4)


def axis_angle_to_matrix(axis_angle: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors -> (..., 3, 3)."""
    a = _rows(axis_angle, (3,), "axis_angle")
    return kernels.rotvecs_to_matrices(a).reshape(*np.shape(axis_angle)[:-1], 3, 3)


def matrix_to_axis_angle(matrix: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 3) rotation vectors with angle in [0, pi]."""
    m = _rows(matrix, (3, 3), "matrix")
    return kernels.matrices_to_rotvecs(m).reshape(*np.shape(matrix)[:-2], 3)


def quat_xyzw_to_axis_angle(quat_xyzw: np.ndarray) -> np.ndarray:
    """(..., 4) -> (..., 3)."""
    q = _rows(quat_xyzw, (4,), "quat_xyzw")
    _check_nonzero(q)
    return kernels.quats_to_rotvecs(q).reshape(*np.shape(quat_xyzw)[:-1], 3)


def axis_angle_to_quat_xyzw(axis_angle: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 4) with w >= 0."""
    a = _check_last(axis_angle, (3,), "axis_angle")
    return Rotation.from_rotvec(a.reshape(-1, 3)).as_quat(canonical=True).reshape(*a.shape[:-1], 4)


def matrix_to_sixd(matrix: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 6): the first two columns, [R[:,0], R[:,1]]."""
    m = _check_last(matrix, (3, 3), "matrix")
    return np.concatenate([m[..., :, 0], m[..., :, 1]], axis=-1)


def sixd_to_matrix(sixd: np.ndarray) -> np.ndarray:
    """(..., 6) -> (..., 3, 3) by Gram-Schmidt: any 6-vector (with independent halves) gives a rotation."""
    x = _rows(sixd, (6,), "sixd")
    return kernels.sixd_to_matrices(x).reshape(*np.shape(sixd)[:-1], 3, 3)


def quat_xyzw_to_sixd(quat_xyzw: np.ndarray) -> np.ndarray:
    """(..., 4) -> (..., 6)."""
    return matrix_to_sixd(quat_xyzw_to_matrix(quat_xyzw))


def geodesic_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(..., 3, 3) x (..., 3, 3) -> (...,) angle in radians of the rotation taking ``a`` to ``b``."""
    rel = np.swapaxes(_check_last(a, (3, 3), "a"), -1, -2) @ _check_last(b, (3, 3), "b")
    # atan2 of sin and cos stays accurate near 0 and pi, where arccos of the trace alone loses digits.
    cos = (np.trace(rel, axis1=-2, axis2=-1) - 1.0) / 2.0
    skew = np.stack(
        [rel[..., 2, 1] - rel[..., 1, 2], rel[..., 0, 2] - rel[..., 2, 0], rel[..., 1, 0] - rel[..., 0, 1]],
        axis=-1,
    )
    sin = 0.5 * np.linalg.norm(skew, axis=-1)
    return np.arctan2(sin, cos)


def wrap_angle(angle_rad: float) -> float:
    """An angle (rad) wrapped to [-pi, pi)."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


def about_vertical(angle_rad: float) -> np.ndarray:
    """(3, 3) a turn by angle_rad about +y (inputs.heading_frame's yaw convention)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def heading_of(matrix: np.ndarray) -> float:
    """The heading (rad, about +y) of a rotation (3, 3): where its +z axis points over the floor."""
    return math.atan2(float(matrix[0, 2]), float(matrix[2, 2]))
