"""Kinematic pose optimisation (paper §3.4, Eqs. 9-10) and the rotations that reproduce its result.

Energy over the 22 joint positions p (66 unknowns), given the network's joints p~ and the tracked targets q:

    E_A = Σ_{k∈O} λa |p_k - q_k|² + Σ_{k∉O} λs |p_k - p~_k|²                    (align, stay)
    E_S = Σ_links λl (|p_c - p_par| - |p~_c - p~_par|)² + λd,link |(p_c - p_par) - (p~_c - p~_par)|²

O is the set of joints with a target: the tracked joints that are valid now (head, and each wrist whose
controller is tracked), a lost controller's wrist for a while (:mod:`.hands`), and the ankles and feet that
:mod:`.contact` plants or keeps off the floor. Every
term but the bone length is linear, so Gauss-Newton converges in a few steps: each is one 66×66 solve.

The paper stops at positions; avatars animate with rotations. :func:`rederive_rotations` turns each joint's
predicted global rotation by the smallest rotation that points its bone at the refined child (Kabsch where a
joint has several), keeping the predicted twist, so FK of the result reproduces the refined joints up to the
small bone-length changes KPO allows. All joints at once: a corrected rotation does not depend on the
parent's (walking the tree level by level gave MPJRE 0.05° lower and cost 3× the time), except the legs,
which are walked down from the corrected pelvis (see _WALKED).

Shape legend: ``J`` = 22 joints, ``L`` = 27 links (21 bones + 6 sibling pairs, see LINKS).
"""

from __future__ import annotations

import dataclasses
from typing import Final

import numpy as np

from ..skeleton import NUM_JOINTS, PARENTS, forward_kinematics
from . import kernels

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
    torso_direction: float = 10.0  # λd multiplier on the links among TORSO_JOINTS
    iterations: int = 8


# Joints whose links to their parents (and siblings) count as torso: pelvis to head, collars and shoulders.
# Stiffer in direction (torso_direction), so that reaching a controller bends the elbow and turns the arm
# rather than the spine, neck and collars, whose short bones turn far for a small move. On every third
# validation clip (12), against one λd for all links (x1): MPJRE-U 10.40 -> 8.40°, MPJPE-U 3.39 -> 3.28 cm,
# MPJPE-L 7.40 -> 7.23 cm, at a cost on the tracked joints: head 0.59 -> 0.98 cm, wrists 3.55 -> 3.79 cm.
# x100 gave 7.78° and 3.30 cm but head 1.32, wrists 4.01 cm; a higher λa to pin them (300, 1000) gave
# back most of the rotation gain; leaving the shoulders out of the set, x100: 9.68° at 3.22 cm.
TORSO_JOINTS: Final = frozenset({3, 6, 9, 12, 13, 14, 15, 16, 17})


def link_direction_weights(w: KpoWeights) -> np.ndarray:
    """(L,) λd per link: ``direction``, times ``torso_direction`` where both ends belong to the torso."""
    torso = [(a in TORSO_JOINTS or a == 0) and (b in TORSO_JOINTS or b == 0) for a, b in LINKS]
    return np.where(torso, w.direction * w.torso_direction, w.direction)


def kpo_energy(
    p: np.ndarray, p_pred: np.ndarray, targets: np.ndarray, observed: np.ndarray, w: KpoWeights
) -> float:
    """E_A + E_S for positions p (J, 3); targets (J, 3) are read only where observed (J,) is True."""
    anchor = np.where(observed[:, None], targets, p_pred)
    weight = np.where(observed, w.align, w.stay)
    e_a = float((weight * ((p - anchor) ** 2).sum(-1)).sum())
    bones, bones_pred = INCIDENCE @ p, INCIDENCE @ p_pred
    lengths = np.linalg.norm(bones, axis=-1) - np.linalg.norm(bones_pred, axis=-1)
    e_s = w.length * float((lengths**2).sum())
    e_s += float((link_direction_weights(w) * ((bones - bones_pred) ** 2).sum(-1)).sum())
    return e_a + e_s


def solve_kpo(
    p_pred: np.ndarray, targets: np.ndarray, observed: np.ndarray, w: KpoWeights = KpoWeights()
) -> np.ndarray:
    """Minimise E_A + E_S from p = p_pred. p_pred, targets (J, 3); observed (J,) bool -> p (J, 3).

    Newton with Levenberg-Marquardt damping on the exact (PSD part of the) Hessian: a step is kept only if it
    lowers the energy (plain Gauss-Newton overshoots on the stiff bone-length term and can climb). Stops when
    no step lowers it, or when a step moved no joint by 0.5 mm (Newton's next one would be ~0.03 mm).
    Compiled (:func:`.kernels.solve_kpo_one`); :func:`kpo_energy` is the numpy statement tests hold it to.
    """
    return kernels.solve_kpo_one(
        _float_array(p_pred, "p_pred"),
        _float_array(targets, "targets"),
        np.ascontiguousarray(observed, dtype=np.bool_),
        _LINK_ARRAY,
        np.array([w.align, w.stay, w.length]),
        link_direction_weights(w),
        int(w.iterations),
        _ORDER,
        _LATER,
    )


def _float_array(x: np.ndarray, name: str) -> np.ndarray:
    x = np.ascontiguousarray(x, dtype=np.float64)
    if x.shape != (NUM_JOINTS, 3):
        raise ValueError(f"{name} must be ({NUM_JOINTS}, 3), got {x.shape}")
    return x


_LINK_ARRAY: Final = np.array(LINKS, dtype=np.int64)


def elimination_order(links: tuple[tuple[int, int], ...], n: int) -> tuple[np.ndarray, np.ndarray]:
    """A perfect elimination order of the graph of n joints with these links -> order (n,) and later
    (n, K): each joint's linked joints that come after it, -1 padded (kernels.solve_linked_blocks).

    Each step takes the joint with the fewest remaining links whose remaining linked joints are all linked
    to one another, so that eliminating it adds no link: leaves first, up the chains to the hubs. The
    skeleton's bones with the sibling triangles always have one; raises ValueError for a graph without."""
    linked = [set() for _ in range(n)]
    for a, b in links:
        linked[a].add(b)
        linked[b].add(a)
    remaining, order = set(range(n)), []
    while remaining:
        cliques = [j for j in sorted(remaining) if all(b in linked[a] for a in linked[j] & remaining
                                                       for b in linked[j] & remaining if a != b)]  # fmt: skip
        if not cliques:
            raise ValueError("the links' graph has no perfect elimination order")
        order.append(min(cliques, key=lambda j: len(linked[j] & remaining)))
        remaining.remove(order[-1])
    position = {j: i for i, j in enumerate(order)}
    after = [sorted(m for m in linked[j] if position[m] > position[j]) for j in range(n)]
    later = np.full((n, max(1, *map(len, after))), -1, dtype=np.int64)
    for j, joints in enumerate(after):
        later[j, : len(joints)] = joints
    return np.array(order, dtype=np.int64), later


_ORDER, _LATER = elimination_order(LINKS, NUM_JOINTS)


# Joints whose rotation points one bone (single child), several (multi-child hubs: pelvis, spine3), or none.
_SINGLE: Final = np.array([j for j in range(NUM_JOINTS) if len(CHILDREN[j]) == 1], dtype=np.int64)
_SINGLE_CHILD: Final = np.array([CHILDREN[j][0] for j in _SINGLE], dtype=np.int64)
_MULTI: Final = np.array([j for j in range(NUM_JOINTS) if len(CHILDREN[j]) > 1], dtype=np.int64)
_MULTI_CHILDREN: Final = np.array([CHILDREN[j] for j in _MULTI], dtype=np.int64)  # (M, 3): both hubs have 3
_LEAVES: Final = np.array([j for j in range(NUM_JOINTS) if not CHILDREN[j]], dtype=np.int64)
_PARENTS: Final = PARENTS.astype(np.int64)
# The legs are walked down from the corrected pelvis: where KPO turns the pelvis (planted feet, the hips'
# sibling links), each thigh's, shin's and foot's twist turns with its parent instead of staying as the
# network had it, where the child's local rotation would absorb the parent's correction. MPJRE-L on the
# training split 9.82 -> 9.52° (MODEL_CARD.md, "Legs hung from their corrected parents"). Hips, knees,
# ankles (the feet are leaves, always hung from their parent), as indices into _SINGLE, each after its parent.
_WALKED: Final = np.array([list(_SINGLE).index(j) for j in (1, 2, 4, 5, 7, 8)], dtype=np.int64)


def orient_leaves(
    local: np.ndarray, glob: np.ndarray, leaves: list[int], leaf_rot: np.ndarray | list[np.ndarray]
) -> None:
    """Turn leaf joints (head, wrists, feet: no child) so that their global rotations are ``leaf_rot``
    (L, 3, 3). local (J, 3, 3) and glob (J, 3, 3), its FK's global rotations, change in place in the leaves'
    rows; a leaf moves no joint, so FK's positions stay as they were."""
    for joint, rot in zip(leaves, leaf_rot, strict=True):
        if CHILDREN[joint]:
            raise ValueError(f"joint {joint} is not a leaf")
        local[joint] = glob[PARENTS[joint]].T @ rot
        glob[joint] = rot


def rederive_rotations(
    local_pred: np.ndarray, joints: np.ndarray, offsets: np.ndarray, glob_pred: np.ndarray | None = None
) -> np.ndarray:
    """Local rotations (J, 3, 3) whose FK from joints[0] with ``offsets`` (J, 3) reproduces ``joints`` (J, 3).

    local_pred (J, 3, 3): the predicted local rotations (row 0 the pelvis' global rotation); glob_pred
    (J, 3, 3) their global rotations, if the caller has them from FK. Each joint keeps its predicted global
    rotation, turned by the smallest rotation that points its bone at its child (Kabsch over the children at
    the pelvis and spine3): every joint at once, no walk down the tree, because a joint's corrected
    rotation does not depend on its parent's; except the hips, knees and ankles, each turned from its corrected
    parent and its predicted local rotation (_WALKED). Leaves (head, wrists, feet) keep their predicted local
    rotation under their corrected parent; they move no joint. Compiled
    (:func:`.kernels.rederive_rotations_one`).
    """
    local_pred = np.ascontiguousarray(local_pred, dtype=np.float64)
    offsets = np.ascontiguousarray(offsets, dtype=np.float64)
    joints = _float_array(joints, "joints")
    if glob_pred is None:
        glob_pred = forward_kinematics(local_pred, np.zeros(3), offsets)[1]
    return kernels.rederive_rotations_one(
        local_pred, joints, offsets, np.ascontiguousarray(glob_pred, dtype=np.float64),
        _PARENTS, _SINGLE, _SINGLE_CHILD, _MULTI, _MULTI_CHILDREN, _LEAVES, _WALKED,
    )  # fmt: skip
