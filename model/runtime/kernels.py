"""Compiled kernels for the per-sample serving path: one pose's 6D → matrices, FK, KPO, the rotation
re-derivation (and its ``swing``, which the procedural model's spine also turns by) and the SMPL axis-angle
export, a One Euro step, and a camera frame's encoder input.

Why compiled: these work on 3×3 to 66×66 arrays, where numpy spends 1-3 µs of call overhead per operation
whatever its size; a pose took ~1.4 ms of such calls against ~0.2 ms of arithmetic. numba turns each
function into one machine-code call, and ``nogil=True`` lets sessions on other worker threads run Python
meanwhile (the numpy versions held the GIL in every small call, so sessions queued behind one another).

The batched numpy versions (:mod:`.skeleton`, :mod:`.rotations`) stay the reference for training, synthesis
and evaluation metrics; tests hold these kernels to them. Compiled once per machine (``cache=True`` writes
next to this file, or to ``NUMBA_CACHE_DIR``); :func:`warm_up` compiles or loads everything before a server
takes traffic, so no pose waits for the compiler.

Shape legend: ``n`` any count, ``J`` joints (22 for SMPL-22), ``L`` KPO links, ``M`` multi-child joints.
"""

from __future__ import annotations

import logging
import math
import time

import numba
import numpy as np

log = logging.getLogger("egoposevr.model")

_JIT = {"nogil": True, "cache": True}
_EPS = 1e-8  # as rotations.sixd_to_matrix


@numba.njit(**_JIT)
def sixd_to_matrices(sixd: np.ndarray) -> np.ndarray:
    """(n, 6) -> (n, 3, 3) by Gram-Schmidt, columns [b1, b2, b1 × b2] (rotations.sixd_to_matrix's)."""
    out = np.empty((sixd.shape[0], 3, 3))
    for j in range(sixd.shape[0]):
        a1, a2 = sixd[j, :3], sixd[j, 3:]
        b1 = a1 / max(math.sqrt(a1 @ a1), _EPS)
        c2 = a2 - (b1 @ a2) * b1
        b2 = c2 / max(math.sqrt(c2 @ c2), _EPS)
        out[j, :, 0] = b1
        out[j, :, 1] = b2
        out[j, :, 2] = _cross(b1, b2)
    return out


@numba.njit(**_JIT)
def forward_kinematics_one(
    local_rot: np.ndarray, root_pos_m: np.ndarray, offsets_m: np.ndarray, parents: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """One pose's FK (skeleton.forward_kinematics): local (J, 3, 3), root (3,), offsets (J, 3), parents (J,)
    with parents[j] < j -> positions (J, 3), global rotations (J, 3, 3)."""
    n = local_rot.shape[0]
    glob = np.empty((n, 3, 3))
    pos = np.empty((n, 3))
    glob[0] = local_rot[0]
    pos[0] = root_pos_m
    for j in range(1, n):
        parent = glob[parents[j]]
        glob[j] = parent @ local_rot[j]
        pos[j] = pos[parents[j]] + parent @ offsets_m[j]
    return pos, glob


@numba.njit(**_JIT)
def matrices_to_rotvecs(matrix: np.ndarray) -> np.ndarray:
    """(n, 3, 3) rotations -> (n, 3) rotation vectors, angle in [0, π] (rotations.matrix_to_axis_angle's).

    Through the quaternion, extracted from whichever of w, x, y, z is largest (Shepperd), so no branch
    divides by a small number."""
    out = np.empty((matrix.shape[0], 3))
    for j in range(matrix.shape[0]):
        out[j] = _quat_to_rotvec(_matrix_to_quat_xyzw(matrix[j]))
    return out


@numba.njit(**_JIT)
def _matrix_to_quat_xyzw(m: np.ndarray) -> np.ndarray:
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    q = np.empty(4)
    if trace >= max(m[0, 0], m[1, 1], m[2, 2]):
        q[3] = 1.0 + trace
        q[0], q[1], q[2] = m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]
    else:
        i = 0 if m[0, 0] >= max(m[1, 1], m[2, 2]) else (1 if m[1, 1] >= m[2, 2] else 2)
        j, k = (i + 1) % 3, (i + 2) % 3
        q[i] = 1.0 + 2.0 * m[i, i] - trace
        q[j] = m[j, i] + m[i, j]
        q[k] = m[k, i] + m[i, k]
        q[3] = m[k, j] - m[j, k]
    return q / math.sqrt(q @ q)


@numba.njit(**_JIT)
def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


@numba.njit(**_JIT)
def quats_to_matrices(quat_xyzw: np.ndarray) -> np.ndarray:
    """(n, 4) quaternions, normalised here (callers reject zero ones) -> (n, 3, 3)."""
    out = np.empty((quat_xyzw.shape[0], 3, 3))
    for i in range(quat_xyzw.shape[0]):
        q = quat_xyzw[i]
        x, y, z, w = q / math.sqrt(q @ q)
        out[i, 0, 0], out[i, 0, 1], out[i, 0, 2] = (
            1 - 2 * (y * y + z * z),
            2 * (x * y - z * w),
            2 * (x * z + y * w),
        )
        out[i, 1, 0], out[i, 1, 1], out[i, 1, 2] = (
            2 * (x * y + z * w),
            1 - 2 * (x * x + z * z),
            2 * (y * z - x * w),
        )
        out[i, 2, 0], out[i, 2, 1], out[i, 2, 2] = (
            2 * (x * z - y * w),
            2 * (y * z + x * w),
            1 - 2 * (x * x + y * y),
        )
    return out


@numba.njit(**_JIT)
def quats_to_rotvecs(quat_xyzw: np.ndarray) -> np.ndarray:
    """(n, 4) quaternions -> (n, 3) rotation vectors of the shorter turn (angle in [0, π])."""
    out = np.empty((quat_xyzw.shape[0], 3))
    for i in range(quat_xyzw.shape[0]):
        out[i] = _quat_to_rotvec(quat_xyzw[i] / math.sqrt(quat_xyzw[i] @ quat_xyzw[i]))
    return out


@numba.njit(**_JIT)
def quats_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise Hamilton products a[i]·b[i] of (n, 4) xyzw quaternions (the rotations a[i] @ b[i])."""
    out = np.empty((a.shape[0], 4))
    for i in range(a.shape[0]):
        out[i] = _quat_multiply(a[i], b[i])
    return out


@numba.njit(**_JIT)
def rotvecs_to_matrices(rotvec: np.ndarray) -> np.ndarray:
    """(n, 3) rotation vectors -> (n, 3, 3), through the quaternion [sin(θ/2) k, cos(θ/2)] (series near 0)."""
    quat = np.empty((rotvec.shape[0], 4))
    for i in range(rotvec.shape[0]):
        angle = math.sqrt(rotvec[i] @ rotvec[i])
        # sin(θ/2)/θ -> 1/2 - θ²/48 as θ -> 0
        scale = math.sin(0.5 * angle) / angle if angle > 1e-6 else 0.5 - angle * angle / 48.0
        quat[i, :3] = scale * rotvec[i]
        quat[i, 3] = math.cos(0.5 * angle)
    return quats_to_matrices(quat)


@numba.njit(**_JIT)
def _quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    """Unit quaternion (4,) -> rotation vector (3,), angle = 2 atan2(|v|, |w|), accurate near 0 and π."""
    if q[3] < 0.0:
        q = -q
    sin_half = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2])
    angle = 2.0 * math.atan2(sin_half, q[3])
    # angle / sin(angle/2) -> 2 + angle²/12 as the angle -> 0
    scale = angle / sin_half if sin_half > 1e-7 else 2.0 + angle * angle / 12.0
    return scale * q[:3]


# ----------------------------------------------------------------------------------------------- KPO
@numba.njit(**_JIT)
def one_euro_step(
    x: np.ndarray,
    x_hat: np.ndarray,
    dx_hat: np.ndarray,
    dt_s: float,
    min_cutoff_hz: float,
    beta: float,
    d_cutoff_hz: float,
) -> None:
    """One One Euro update (``filters.OneEuroFilter``), in place on the estimates x_hat and dx_hat; all
    three (n,) float64. The same operations in the same order as the numpy statement, so the same bits,
    in one call instead of a dozen (each ~1.5 µs of numpy overhead on a 66-element signal)."""
    alpha_d = 1.0 / (1.0 + (1.0 / (2.0 * math.pi * d_cutoff_hz)) / dt_s)
    for i in range(x.shape[0]):
        dx = (x[i] - x_hat[i]) / dt_s
        dx_hat[i] = dx_hat[i] + alpha_d * (dx - dx_hat[i])
        tau_s = 1.0 / (2.0 * math.pi * (min_cutoff_hz + beta * abs(dx_hat[i])))
        x_hat[i] = x_hat[i] + 1.0 / (1.0 + tau_s / dt_s) * (x[i] - x_hat[i])


@numba.njit(**_JIT)
def fill_network_input(rgb: np.ndarray, depth_mm: np.ndarray, depth_divisor: float, out: np.ndarray) -> None:
    """A resized frame, rgb (h, w, 3) uint8 and depth (h, w) uint16 mm -> out (C, h, w) float32, in place:
    RGB / 255 - 0.5, then with C = 4 depth / ``depth_divisor``. One pass for the numpy chain of
    ``inputs.network_input`` (six temporaries, ~0.3 ms a frame), which stays the reference: bit for bit."""
    scale, centre = np.float32(255.0), np.float32(0.5)
    divisor = np.float32(depth_divisor)
    for c in range(3):  # plane by plane: the writes run along memory
        for y in range(rgb.shape[0]):
            for x in range(rgb.shape[1]):
                out[c, y, x] = np.float32(rgb[y, x, c]) / scale - centre
    if out.shape[0] == 4:
        for y in range(rgb.shape[0]):
            for x in range(rgb.shape[1]):
                out[3, y, x] = np.float32(depth_mm[y, x]) / divisor


@numba.njit(**_JIT)
def solve_kpo_one(
    p_pred: np.ndarray,
    targets: np.ndarray,
    observed: np.ndarray,
    links: np.ndarray,
    weights: np.ndarray,
    direction: np.ndarray,
    iterations: int,
    order: np.ndarray,
    later: np.ndarray,
) -> np.ndarray:
    """Paper Eqs. 9-10 (kpo.solve_kpo documents the energy): p_pred, targets (J, 3); observed (J,) bool;
    links (L, 2) (child, parent); weights (align, stay, length); direction (L,) each link's direction weight;
    order, later: the links' elimination order (:func:`solve_linked_blocks`) -> refined positions (J, 3).

    Newton with Levenberg-Marquardt damping on the exact PSD Hessian; a step is kept only if it lowers the
    energy; stops when no step does, or when the last one moved no joint by 0.5 mm."""
    align, stay, length_w = weights[0], weights[1], weights[2]
    n = p_pred.shape[0]
    anchor, weight = p_pred.copy(), np.full(n, stay)
    for j in range(n):
        if observed[j]:
            anchor[j], weight[j] = targets[j], align
    links_pred = _link_vectors(p_pred, links)
    lengths_pred = np.sqrt((links_pred * links_pred).sum(axis=1))
    h_linear = _kpo_linear_hessian(weight, links, direction)
    p = p_pred.copy()
    energy = _kpo_energy(p, anchor, weight, links, links_pred, lengths_pred, length_w, direction)
    damping = 1e-6
    for _ in range(iterations):
        grad, hess = _kpo_newton_system(
            p, anchor, weight, links, links_pred, lengths_pred, length_w, direction
        )
        hess += h_linear
        diagonal = np.diag(hess).copy()
        step = np.zeros((n, 3))
        accepted = False
        while damping < 1e6:
            damped = hess.copy()
            for i in range(3 * n):
                damped[i, i] += damping * diagonal[i]
            step = solve_linked_blocks(damped, grad, order, later).reshape(n, 3)
            trial = p - step
            e_new = _kpo_energy(trial, anchor, weight, links, links_pred, lengths_pred, length_w, direction)
            if e_new < energy:
                p, energy, damping, accepted = trial, e_new, max(damping / 10.0, 1e-9), True
                break
            damping *= 10.0
        if not accepted or np.abs(step).max() < 5e-4:
            break  # converged: no step lowers the energy, or Newton's next one would be ~0.03 mm
    return p


@numba.njit(**_JIT)
def solve_linked_blocks(a: np.ndarray, rhs: np.ndarray, order: np.ndarray, later: np.ndarray) -> np.ndarray:
    """x with a x = rhs, for a symmetric positive definite a (3n, 3n) whose only nonzero 3×3 blocks are the
    diagonal ones and those of linked joints; ``a`` is overwritten. order (n,) is a perfect elimination
    order of the links' graph and later (n, K) each joint's linked joints that come after it in that order
    (-1 pads; kpo.elimination_order makes both).

    Block Cholesky in that order: eliminating a joint couples only joints that are already linked, so the
    factor has no block the matrix lacks, and KPO's 66×66 system costs a few dozen 3×3 products instead of
    a dense factorisation (most of KPO's time before). Explicit loops: numpy's calls cost more than 3×3
    arithmetic."""
    for k in order:  # a = L Lᵀ: L's diagonal block (k, k) and its blocks (m, k) below it, in place
        kk = 3 * k
        _cholesky3(a, kk)
        for m in later[k]:
            if m < 0:
                break
            for r in range(3):  # L_mk = A_mk L_kᵀ⁻¹, row by row: L_k (row r of L_mk)ᵀ = (row r of A_mk)ᵀ
                row = 3 * m + r
                for c in range(3):
                    total = a[row, kk + c]
                    for q in range(c):
                        total -= a[kk + c, kk + q] * a[row, kk + q]
                    a[row, kk + c] = total / a[kk + c, kk + c]
        for m in later[k]:  # the Schur complement on the later joints, which are linked to one another
            if m < 0:
                break
            for m2 in later[k]:
                if m2 < 0:
                    break
                for r in range(3):
                    for c in range(3):
                        total = 0.0
                        for q in range(3):
                            total += a[3 * m + r, kk + q] * a[3 * m2 + c, kk + q]
                        a[3 * m + r, 3 * m2 + c] -= total
    x = rhs.copy()
    for k in order:  # L y = rhs
        kk = 3 * k
        for r in range(3):
            total = x[kk + r]
            for q in range(r):
                total -= a[kk + r, kk + q] * x[kk + q]
            x[kk + r] = total / a[kk + r, kk + r]
        for m in later[k]:
            if m < 0:
                break
            for r in range(3):
                for q in range(3):
                    x[3 * m + r] -= a[3 * m + r, kk + q] * x[kk + q]
    for k in order[::-1]:  # Lᵀ x = y
        kk = 3 * k
        for m in later[k]:
            if m < 0:
                break
            for q in range(3):
                for r in range(3):
                    x[kk + q] -= a[3 * m + r, kk + q] * x[3 * m + r]
        for r in range(2, -1, -1):
            total = x[kk + r]
            for q in range(r + 1, 3):
                total -= a[kk + q, kk + r] * x[kk + q]
            x[kk + r] = total / a[kk + r, kk + r]
    return x


@numba.njit(**_JIT)
def _cholesky3(a: np.ndarray, kk: int) -> None:
    """In place: the lower triangle of a's positive definite diagonal block at (kk, kk) becomes its Cholesky
    factor (NaN where it is not positive definite, which KPO's energy test then refuses)."""
    for j in range(kk, kk + 3):
        d = a[j, j]
        for q in range(kk, j):
            d -= a[j, q] * a[j, q]
        a[j, j] = math.sqrt(d) if d > 0.0 else math.nan
        for i in range(j + 1, kk + 3):
            total = a[i, j]
            for q in range(kk, j):
                total -= a[i, q] * a[j, q]
            a[i, j] = total / a[j, j]


@numba.njit(**_JIT)
def _link_vectors(p: np.ndarray, links: np.ndarray) -> np.ndarray:
    out = np.empty((links.shape[0], 3))
    for k in range(links.shape[0]):
        out[k] = p[links[k, 0]] - p[links[k, 1]]
    return out


@numba.njit(**_JIT)
def _kpo_energy(
    p: np.ndarray,
    anchor: np.ndarray,
    weight: np.ndarray,
    links: np.ndarray,
    links_pred: np.ndarray,
    lengths_pred: np.ndarray,
    length_w: float,
    direction: np.ndarray,
) -> float:
    d = p - anchor
    energy = (weight * (d * d).sum(axis=1)).sum()
    for k in range(links.shape[0]):
        v = p[links[k, 0]] - p[links[k, 1]]
        stretch = math.sqrt(v @ v) - lengths_pred[k]
        turn = v - links_pred[k]
        energy += length_w * stretch * stretch + direction[k] * (turn @ turn)
    return energy


@numba.njit(**_JIT)
def _kpo_linear_hessian(weight: np.ndarray, links: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """The quadratic terms' Hessian (3J, 3J): align/stay on the diagonal, direction on each link's pattern."""
    n = weight.shape[0]
    h = np.zeros((3 * n, 3 * n))
    for j in range(n):
        for c in range(3):
            h[3 * j + c, 3 * j + c] = weight[j]
    for k in range(links.shape[0]):
        a, b = 3 * links[k, 0], 3 * links[k, 1]
        for c in range(3):
            h[a + c, a + c] += direction[k]
            h[b + c, b + c] += direction[k]
            h[a + c, b + c] -= direction[k]
            h[b + c, a + c] -= direction[k]
    return h


@numba.njit(**_JIT)
def _kpo_newton_system(
    p: np.ndarray,
    anchor: np.ndarray,
    weight: np.ndarray,
    links: np.ndarray,
    links_pred: np.ndarray,
    lengths_pred: np.ndarray,
    length_w: float,
    direction: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Gradient (3J,) and the links' nonlinear Hessian part (3J, 3J) at p.

    Per link, the exact Hessian of ½ r² with r the length change is u uᵀ + (r / |d|)(I - u uᵀ); Gauss-Newton's
    u uᵀ alone converges only linearly, because the stiff length term is curved wherever bones turn. Only the
    PSD part (r > 0) is kept."""
    n = p.shape[0]
    grad = (weight.reshape(n, 1) * (p - anchor)).ravel()
    hess = np.zeros((3 * n, 3 * n))
    for k in range(links.shape[0]):
        a, b = links[k, 0], links[k, 1]
        v = p[a] - p[b]
        raw_length = math.sqrt(v @ v)
        length = max(raw_length, 1e-9)
        unit = v / length
        residual = raw_length - lengths_pred[k]
        g = direction[k] * (v - links_pred[k]) + length_w * residual * unit
        curvature = max(residual, 0.0) / length
        for r in range(3):
            grad[3 * a + r] += g[r]
            grad[3 * b + r] -= g[r]
            for c in range(3):
                block = unit[r] * unit[c] * (1.0 - curvature) + (curvature if r == c else 0.0)
                block *= length_w
                hess[3 * a + r, 3 * a + c] += block
                hess[3 * b + r, 3 * b + c] += block
                hess[3 * a + r, 3 * b + c] -= block
                hess[3 * b + r, 3 * a + c] -= block
    return grad, hess


# --------------------------------------------------------------------------------- rotation re-derivation
@numba.njit(**_JIT)
def rederive_rotations_one(
    local_pred: np.ndarray,
    joints: np.ndarray,
    offsets: np.ndarray,
    glob_pred: np.ndarray,
    parents: np.ndarray,
    single: np.ndarray,
    single_child: np.ndarray,
    multi: np.ndarray,
    multi_children: np.ndarray,
    leaves: np.ndarray,
    walked: np.ndarray,
) -> np.ndarray:
    """kpo.rederive_rotations for one pose (it documents the method) -> local rotations (J, 3, 3).

    single (S,) joints with one child single_child (S,); multi (M,) joints with the children
    multi_children (M, C) (-1 pads); leaves (E,) joints without children; walked (W,) indices into
    single, each after its parent's: those joints start from their corrected parent and their own
    predicted local rotation instead of their predicted global one."""
    glob = glob_pred.copy()
    later = np.zeros(single.shape[0], dtype=np.bool_)  # walked below, from their corrected parents
    later[walked] = True
    for i in range(single.shape[0]):
        if later[i]:
            continue
        j, c = single[i], single_child[i]
        have = glob_pred[j] @ offsets[c]
        glob[j] = swing(have, joints[c] - joints[j]) @ glob_pred[j]
    for i in range(multi.shape[0]):
        j = multi[i]
        count = 0
        for c in multi_children[i]:
            if c >= 0:
                count += 1
        have, want = np.empty((count, 3)), np.empty((count, 3))
        for k in range(count):
            c = multi_children[i, k]
            have[k] = glob_pred[j] @ offsets[c]
            want[k] = joints[c] - joints[j]
        glob[j] = _kabsch(have, want) @ glob_pred[j]
    for i in walked:
        j, c = single[i], single_child[i]
        hung = glob[parents[j]] @ local_pred[j]
        glob[j] = swing(hung @ offsets[c], joints[c] - joints[j]) @ hung
    for j in leaves:
        glob[j] = glob[parents[j]] @ local_pred[j]
    local = np.empty_like(glob)
    local[0] = glob[0]
    for j in range(1, glob.shape[0]):
        local[j] = glob[parents[j]].T @ glob[j]
    return local


@numba.njit(**_JIT)
def swing(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation (3, 3) turning direction a (3,) onto b (3,): Rodrigues with v = a × b, c = a · b,
    R = I + [v]× + [v]×² / (1 + c); opposite directions take half a turn about an axis perpendicular to a."""
    a = a / max(math.sqrt(a @ a), 1e-12)
    b = b / max(math.sqrt(b @ b), 1e-12)
    c = a @ b
    if c < -1.0 + 1e-9:
        helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        axis = _cross(a, helper)
        axis /= math.sqrt(axis @ axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    v = _cross(a, b)
    k = 1.0 / max(1.0 + c, 1e-12)
    r = np.outer(v, v) * k + np.eye(3) * (1.0 - (v @ v) * k)
    r[0, 1] -= v[2]
    r[0, 2] += v[1]
    r[1, 0] += v[2]
    r[1, 2] -= v[0]
    r[2, 0] -= v[1]
    r[2, 1] += v[0]
    return r


@numba.njit(**_JIT)
def _kabsch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) best turning the rows of a (n, 3) onto the rows of b (n, 3), least squares."""
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    fix = np.eye(3)
    fix[2, 2] = d
    return vt.T @ fix @ u.T


# ------------------------------------------------------------------------------------------- HMD features
@numba.njit(**_JIT)
def hmd_feature_step(
    t_us: int,
    poses: np.ndarray,
    valid: np.ndarray,
    history_t_us: np.ndarray,
    history_pose: np.ndarray,
    history_len: np.ndarray,
    velocity: np.ndarray,
    last_t_us: np.ndarray,
    held: np.ndarray,
    timing: np.ndarray,
) -> np.ndarray:
    """One headset sample -> x_t (72,), updating the extractor's state in place (hmd.py states the rules).

    poses (3, 7) [p xyz, q xyzw]; valid (3,) bool. State: history_t_us (3, H) and history_pose (3, H, 7)
    oldest first, history_len (3,); velocity (3, 6) [linear m/s, body angular rad/s]; last_t_us (2,)
    [time, set?]; held (3, 4, 3) [head pos + rotation rows; each controller's pos + rotation rows in the head
    frame]. timing (3,) = (MIN_DT_S, MAX_GAP_S, DT_REF_S)."""
    min_dt_s, max_gap_s, dt_ref_s = timing[0], timing[1], timing[2]
    advancing = last_t_us[1] == 0 or t_us > last_t_us[0]
    quat = np.empty((3, 4))
    for d in range(3):
        if valid[d]:
            quat[d] = poses[d, 3:] / math.sqrt(poses[d, 3:] @ poses[d, 3:])
        else:  # an untracked device's pose is meaningless (may be all zeros): never convert it
            quat[d] = np.array([0.0, 0.0, 0.0, 1.0])
    pos, rot = poses[:, :3].copy(), quats_to_matrices(quat)
    _resolve_held_poses(pos, rot, valid, held)
    for d in range(3):
        if not valid[d]:
            velocity[d] = 0.0
        elif advancing:
            _update_velocity(d, t_us, pos[d], quat[d], history_t_us, history_pose, history_len, velocity,
                             min_dt_s, max_gap_s)  # fmt: skip
    if advancing:
        last_t_us[0], last_t_us[1] = t_us, 1
    return _assemble_features(pos, rot, velocity, dt_ref_s)


@numba.njit(**_JIT)
def _resolve_held_poses(pos: np.ndarray, rot: np.ndarray, valid: np.ndarray, held: np.ndarray) -> None:
    """Untracked devices take their held pose (controllers relative to the head); tracked ones refresh it."""
    if valid[0]:
        held[0, 0], held[0, 1:] = pos[0], rot[0]
    else:
        pos[0], rot[0] = held[0, 0], held[0, 1:]
    for c in (1, 2):
        if valid[c]:
            held[c, 0] = rot[0].T @ (pos[c] - pos[0])
            held[c, 1:] = rot[0].T @ rot[c]
        else:
            pos[c] = pos[0] + rot[0] @ held[c, 0]
            rot[c] = rot[0] @ held[c, 1:]


@numba.njit(**_JIT)
def _update_velocity(
    d: int,
    t_us: int,
    pos: np.ndarray,
    quat: np.ndarray,
    history_t_us: np.ndarray,
    history_pose: np.ndarray,
    history_len: np.ndarray,
    velocity: np.ndarray,
    min_dt_s: float,
    max_gap_s: float,
) -> None:
    """Finite differences against the newest tracked sample at least MIN_DT_S and at most MAX_GAP_S older;
    none in range: keep the last velocity, or stop after a gap. Then the sample joins the history."""
    size = history_t_us.shape[1]
    n = history_len[d]
    reference = -1
    for i in range(n - 1, -1, -1):
        age_s = (t_us - history_t_us[d, i]) * 1e-6
        if age_s > max_gap_s:
            break
        if age_s >= min_dt_s:
            reference = i
            break
    if reference >= 0:
        dt_s = (t_us - history_t_us[d, reference]) * 1e-6
        ref_quat = history_pose[d, reference, 3:]
        relative = _quat_multiply(np.array([-ref_quat[0], -ref_quat[1], -ref_quat[2], ref_quat[3]]), quat)
        velocity[d, :3] = (pos - history_pose[d, reference, :3]) / dt_s
        velocity[d, 3:] = _quat_to_rotvec(relative / math.sqrt(relative @ relative)) / dt_s
    elif n > 0 and (t_us - history_t_us[d, n - 1]) * 1e-6 > max_gap_s:
        velocity[d] = 0.0
    if n == size:  # full: drop the oldest
        history_t_us[d, :-1] = history_t_us[d, 1:].copy()
        history_pose[d, :-1] = history_pose[d, 1:].copy()
        n -= 1
    history_t_us[d, n] = t_us
    history_pose[d, n, :3] = pos
    history_pose[d, n, 3:] = quat
    history_len[d] = n + 1


@numba.njit(**_JIT)
def _quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a·b of xyzw quaternions (4,)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ])  # fmt: skip


@numba.njit(**_JIT)
def _assemble_features(pos: np.ndarray, rot: np.ndarray, velocity: np.ndarray, dt_ref_s: float) -> np.ndarray:
    """x_t (72,) = [g_head, g_left, g_right (18 each: pos, 6D, vel, angular-velocity 6D), r_left, r_right
    (9 each: position and 6D in the head frame)]."""
    x = np.empty(72)
    step_rot = rotvecs_to_matrices(velocity[:, 3:] * dt_ref_s)
    for d in range(3):
        base = 18 * d
        x[base : base + 3] = pos[d]
        x[base + 3 : base + 9] = _sixd(rot[d])
        x[base + 9 : base + 12] = velocity[d, :3]
        x[base + 12 : base + 18] = _sixd(step_rot[d])
    for c in (1, 2):
        base = 54 + 9 * (c - 1)
        x[base : base + 3] = rot[0].T @ (pos[c] - pos[0])
        x[base + 3 : base + 9] = _sixd(rot[0].T @ rot[c])
    return x


@numba.njit(**_JIT)
def _sixd(m: np.ndarray) -> np.ndarray:
    """(3, 3) -> (6,): the first two columns."""
    return np.array([m[0, 0], m[1, 0], m[2, 0], m[0, 1], m[1, 1], m[2, 1]])


def warm_up() -> None:
    """Compile (or load from the cache) every kernel on a tiny valid input, so the first pose does not wait.
    Logs when that took long: the first start on a machine compiles (~25 s on 2 cores), later ones load."""
    started = time.perf_counter()
    _call_every_kernel()
    elapsed_s = time.perf_counter() - started
    if elapsed_s > 2.0:
        log.info("compiled the serving kernels in %.0f s (numba caches them for later starts)", elapsed_s)


def _call_every_kernel() -> None:
    eye = np.broadcast_to(np.eye(3), (3, 3, 3)).copy()
    offsets = np.array([[0.0, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.1, 0.0]])
    parents = np.array([-1, 0, 1], dtype=np.int64)
    sixd_to_matrices(np.tile([1.0, 0.0, 0.0, 0.0, 1.0, 0.0], (3, 1)))
    pos, glob = forward_kinematics_one(eye, np.zeros(3), offsets, parents)
    matrices_to_rotvecs(glob)
    quats_to_rotvecs(np.array([[0.0, 0.0, 0.0, 1.0]]))
    quats_multiply(np.array([[0.0, 0.0, 0.0, 1.0]]), np.array([[0.0, 0.0, 0.0, 1.0]]))
    rotvecs_to_matrices(np.zeros((1, 3)))
    one_euro_step(np.ones(2), np.zeros(2), np.zeros(2), 0.01, 1.0, 0.1, 1.0)
    fill_network_input(
        np.zeros((2, 2, 3), np.uint8), np.zeros((2, 2), np.uint16), 2000.0, np.empty((4, 2, 2), np.float32)
    )
    links = np.array([[1, 0], [2, 1]], dtype=np.int64)
    observed = np.array([False, False, True])
    later = np.array([[1], [2], [-1]], dtype=np.int64)
    solve_kpo_one(
        pos, pos + 0.01, observed, links, np.array([100.0, 1.0, 1e4]), np.full(2, 10.0), 2,
        np.arange(3, dtype=np.int64), later,
    )  # fmt: skip
    none = np.zeros(0, dtype=np.int64)
    hmd_feature_step(
        0, np.tile([0.0, 1.6, 0.0, 0.0, 0.0, 0.0, 1.0], (3, 1)), np.ones(3, dtype=np.bool_),
        np.zeros((3, 2), dtype=np.int64), np.zeros((3, 2, 7)), np.zeros(3, dtype=np.int64), np.zeros((3, 6)),
        np.zeros(2, dtype=np.int64), np.zeros((3, 4, 3)), np.array([0.004, 0.25, 1 / 60]),
    )  # fmt: skip
    rederive_rotations_one(
        eye, pos, offsets, glob, parents, np.array([0, 1]), np.array([1, 2]), none,
        np.zeros((0, 3), dtype=np.int64), np.array([2]), np.array([1]),
    )  # fmt: skip
    swing(np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0]))
