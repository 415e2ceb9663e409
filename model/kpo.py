"""Kinematic pose optimisation (paper §3.4, Eqs. 9-10) and the rotations that reproduce its result.

Energy over the 22 joint positions p (66 unknowns), given the network's joints p~ and the tracked targets q:

    E_A = Σ_{k∈O} λa |p_k - q_k|² + Σ_{k∉O} λs |p_k - p~_k|²                    (align, stay)
    E_S = Σ_links λl (|p_c - p_par| - |p~_c - p~_par|)² + λd |(p_c - p_par) - (p~_c - p~_par)|²

O is the set of tracked joints that are valid now (head, and each wrist whose controller is tracked). Every
term but the bone length is linear, so Gauss-Newton converges in a few steps: each is one 66×66 solve.

The paper stops at positions; avatars animate with rotations. :func:`rederive_rotations` turns each joint's
predicted global rotation by the smallest rotation that points its bone at the refined child (Kabsch where a
joint has several), keeping the predicted twist, so FK of the result reproduces the refined joints up to the
small bone-length changes KPO allows. All joints at once: a corrected rotation does not depend on the
parent's (walking the tree level by level gave MPJRE 0.05° lower and cost 3× the time).

Shape legend: ``J`` = 22 joints, ``L`` = 27 links (21 bones + 6 sibling pairs, see LINKS).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Final

import numpy as np

from .skeleton import NUM_JOINTS, PARENTS, forward_kinematics

CHILDREN: Final = tuple(tuple(int(c) for c in np.flatnonzero(j == PARENTS)) for j in range(NUM_JOINTS))
# Links (child, parent): the 21 bones, plus the pairs of siblings under a multi-child joint (hips and spine1
# under the pelvis; neck and collars under spine3). Those triangles are rigid in the skeleton; holding them
# lets a rotation at the shared parent reproduce all children at once.
_SIBLINGS: Final = tuple(
    (a, b) for kids in (c for c in CHILDREN if len(c) > 1) for i, a in enumerate(kids) for b in kids[i + 1 :]
)
LINKS: Final = tuple((c, int(PARENTS[c])) for c in range(1, NUM_JOINTS)) + _SIBLINGS
# Incidence (L, J): link vectors = INCIDENCE @ positions.
INCIDENCE: Final = np.zeros((len(LINKS), NUM_JOINTS))
INCIDENCE[np.arange(len(LINKS)), [a for a, _ in LINKS]] = 1.0
INCIDENCE[np.arange(len(LINKS)), [b for _, b in LINKS]] = -1.0


@dataclasses.dataclass(frozen=True)
class KpoWeights:
    align: float = 100.0  # λa: tracked joints onto their devices
    stay: float = 1.0  # λs: untracked joints near the prediction
    length: float = 1e4  # λl: bone lengths (stiff: FK with fixed bones must reproduce the result)
    direction: float = 10.0  # λd: link vectors
    iterations: int = 8


def kpo_energy(
    p: np.ndarray, p_pred: np.ndarray, targets: np.ndarray, observed: np.ndarray, w: KpoWeights
) -> float:
    """E_A + E_S for positions p (J, 3); targets (J, 3) are read only where observed (J,) is True."""
    anchor = np.where(observed[:, None], targets, p_pred)
    weight = np.where(observed, w.align, w.stay)
    e_a = float((weight * ((p - anchor) ** 2).sum(-1)).sum())
    bones, bones_pred = INCIDENCE @ p, INCIDENCE @ p_pred
    lengths = np.linalg.norm(bones, axis=-1) - np.linalg.norm(bones_pred, axis=-1)
    e_s = w.length * float((lengths**2).sum()) + w.direction * float(((bones - bones_pred) ** 2).sum())
    return e_a + e_s


def solve_kpo(
    p_pred: np.ndarray, targets: np.ndarray, observed: np.ndarray, w: KpoWeights = KpoWeights()
) -> np.ndarray:
    """Minimise E_A + E_S from p = p_pred. p_pred, targets (J, 3); observed (J,) bool -> p (J, 3).

    Newton with Levenberg-Marquardt damping: a step is kept only if it lowers the energy (plain
    Gauss-Newton overshoots on the stiff bone-length term and can climb).
    """
    p_pred = np.asarray(p_pred, dtype=np.float64)
    anchor = np.where(observed[:, None], targets, p_pred)
    weight = np.where(observed, w.align, w.stay)
    links_pred = INCIDENCE @ p_pred
    lengths_pred = np.linalg.norm(links_pred, axis=-1)
    h_linear = _linear_hessian(tuple(weight), w.direction)

    def energy(p: np.ndarray) -> float:
        lengths = np.linalg.norm(INCIDENCE @ p, axis=-1)
        return float(
            (weight * ((p - anchor) ** 2).sum(-1)).sum()
            + w.length * ((lengths - lengths_pred) ** 2).sum()
            + w.direction * ((INCIDENCE @ p - links_pred) ** 2).sum()
        )

    p, e, damping = p_pred.copy(), energy(p_pred), 1e-6
    for _ in range(w.iterations):
        links = INCIDENCE @ p
        lengths = np.linalg.norm(links, axis=-1)
        unit = links / np.maximum(lengths, 1e-9)[:, None]
        residual = lengths - lengths_pred
        grad = weight[:, None] * (p - anchor) + w.direction * INCIDENCE.T @ (links - links_pred)
        grad = grad + w.length * INCIDENCE.T @ (residual[:, None] * unit)
        # Exact Hessian of ½ r² per link: u uᵀ + (r / |d|)(I - u uᵀ). Gauss-Newton's u uᵀ alone converges
        # only linearly here, because the stiff length term is curved wherever bones turn.
        outer = unit[:, :, None] * unit[:, None, :]
        curvature = np.maximum(residual, 0.0) / np.maximum(lengths, 1e-9)  # the PSD part only
        blocks = outer + curvature[:, None, None] * (np.eye(3) - outer)
        hess = h_linear + w.length * _link_hessian(blocks)
        grad = grad.ravel()
        while damping < 1e6:
            step = np.linalg.solve(hess + damping * np.diag(np.diag(hess)), grad).reshape(NUM_JOINTS, 3)
            e_new = energy(p - step)
            if e_new < e:
                p, e, damping = p - step, e_new, max(damping / 10, 1e-9)
                break
            damping *= 10
        else:
            break  # no step lowers the energy: converged
        if np.abs(step).max() < 5e-4:
            break  # the last step moved no joint by 0.5 mm: Newton's next one would be ~0.03 mm
    return p


@functools.lru_cache(maxsize=64)
def _linear_hessian(weight: tuple[float, ...], direction: float) -> np.ndarray:
    """The quadratic terms' Hessian, the same for x, y and z: (J, J) ⊗ I3 -> (3J, 3J). Cached: it depends
    only on which devices are tracked."""
    h = np.kron(np.diag(weight) + direction * INCIDENCE.T @ INCIDENCE, np.eye(3))
    h.flags.writeable = False
    return h


def _scatter_links() -> np.ndarray:
    """(J·J, L): the ±1 pattern of Σ_links (e eᵀ) — each link adds to (a,a), (b,b) and subtracts at (a,b), (b,a)."""
    s = np.zeros((NUM_JOINTS, NUM_JOINTS, len(LINKS)))
    for k, (a, b) in enumerate(LINKS):
        s[a, a, k] += 1
        s[b, b, k] += 1
        s[a, b, k] -= 1
        s[b, a, k] -= 1
    return s.reshape(NUM_JOINTS * NUM_JOINTS, len(LINKS))


_SCATTER: Final = _scatter_links()


def _link_hessian(blocks: np.ndarray) -> np.ndarray:
    """Σ_links (e eᵀ) ⊗ B for per-link blocks (L, 3, 3), e the link's incidence row -> (3J, 3J).

    One matrix product with a precomputed scatter pattern (np.add.at costs ~20 µs a call)."""
    h = (_SCATTER @ blocks.reshape(len(LINKS), 9)).reshape(NUM_JOINTS, NUM_JOINTS, 3, 3)
    return h.transpose(0, 2, 1, 3).reshape(3 * NUM_JOINTS, 3 * NUM_JOINTS)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (n, 3) arrays (np.cross costs ~60 µs of axis handling per call)."""
    return np.stack(
        [
            a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1],
            a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0],
        ],
        axis=-1,
    )


def _swing(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotations (n, 3, 3) turning directions a (n, 3) onto b (n, 3).

    Rodrigues with v = a × b, c = a · b: R = I + [v]× + [v]×² / (1 + c), written out element-wise (the
    per-level call is on the serving hot path; this form is 4x faster than building skew matrices).
    Opposite directions (c = -1) take half a turn about an axis perpendicular to a.
    """
    a = a / np.maximum(np.sqrt((a * a).sum(-1)), 1e-12)[:, None]
    b = b / np.maximum(np.sqrt((b * b).sum(-1)), 1e-12)[:, None]
    c = (a * b).sum(-1)
    v = _cross(a, b)
    opposite = c < -1.0 + 1e-9
    if opposite.any():  # rare: pick a perpendicular axis, then the formula's limit is 2 k kᵀ - I
        helper = np.where(np.abs(a[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        axis = _cross(a, helper)
        axis /= np.sqrt((axis * axis).sum(-1))[:, None]
    k = 1.0 / np.maximum(1.0 + c, 1e-12)
    r = (v[:, :, None] * v[:, None, :]) * k[:, None, None]
    diagonal = 1.0 - (v * v).sum(-1) * k
    r[:, 0, 0] += diagonal
    r[:, 1, 1] += diagonal
    r[:, 2, 2] += diagonal
    r[:, 0, 1] -= v[:, 2]
    r[:, 0, 2] += v[:, 1]
    r[:, 1, 0] += v[:, 2]
    r[:, 1, 2] -= v[:, 0]
    r[:, 2, 0] -= v[:, 1]
    r[:, 2, 1] += v[:, 0]
    if opposite.any():
        r[opposite] = 2.0 * axis[opposite, :, None] * axis[opposite, None, :] - np.eye(3)
    return r


def _kabsch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) best turning the rows of a (n, 3) onto the rows of b (n, 3), least squares."""
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    return vt.T @ np.diag([1.0, 1.0, d]) @ u.T


# Joints whose rotation points one bone (single child), several (multi-child hubs: pelvis, spine3), or none.
_SINGLE: Final = np.array([j for j in range(NUM_JOINTS) if len(CHILDREN[j]) == 1])
_SINGLE_CHILD: Final = np.array([CHILDREN[j][0] for j in _SINGLE])
_MULTI: Final = tuple(j for j in range(NUM_JOINTS) if len(CHILDREN[j]) > 1)
_LEAVES: Final = np.array([j for j in range(NUM_JOINTS) if not CHILDREN[j]])
_PARENT_OR_SELF: Final = np.where(PARENTS < 0, 0, PARENTS)


def rederive_rotations(
    local_pred: np.ndarray, joints: np.ndarray, offsets: np.ndarray, glob_pred: np.ndarray | None = None
) -> np.ndarray:
    """Local rotations (J, 3, 3) whose FK from joints[0] with ``offsets`` (J, 3) reproduces ``joints`` (J, 3).

    local_pred (J, 3, 3): the predicted local rotations (row 0 the pelvis' global rotation); glob_pred
    (J, 3, 3) their global rotations, if the caller has them from FK. Each joint keeps its predicted global
    rotation, turned by the smallest rotation that points its bone at its child (Kabsch over the children at
    the pelvis and spine3): every joint at once, no walk down the tree, because a joint's corrected
    rotation does not depend on its parent's. Leaves (head, wrists, feet) keep their predicted local
    rotation under their corrected parent; they move no joint.
    """
    local_pred = np.asarray(local_pred, dtype=np.float64)
    if glob_pred is None:
        glob_pred = forward_kinematics(local_pred, np.zeros(3), offsets)[1]
    glob = np.array(glob_pred, dtype=np.float64)
    have = np.einsum("nij,nj->ni", glob_pred[_SINGLE], offsets[_SINGLE_CHILD])
    glob[_SINGLE] = _swing(have, joints[_SINGLE_CHILD] - joints[_SINGLE]) @ glob_pred[_SINGLE]
    for j in _MULTI:
        kids = list(CHILDREN[j])
        glob[j] = _kabsch(offsets[kids] @ glob_pred[j].T, joints[kids] - joints[j]) @ glob_pred[j]
    glob[_LEAVES] = glob[PARENTS[_LEAVES]] @ local_pred[_LEAVES]
    local = np.swapaxes(glob[_PARENT_OR_SELF], -1, -2) @ glob
    local[0] = glob[0]
    return local
