"""Human mesh bodies for the renderer: a bank of body shapes, posed every frame by SMPL-22 motion.

A :class:`BodyBank` holds one mesh topology (triangles, per-face region, skinning onto the 22 SMPL joints)
and many body shapes (rest vertices, the SMPL-22 joints of that body, the rest alignment). It is made once
by :mod:`.anny_bodies` (the open ``anny`` body model, which needs torch) and saved as ``.npz``; rendering
from it needs only numpy and numba.

How a body follows a motion, so that the truth joints are the rendered body's joints:

- the body's **bone lengths** are the distances between its own joints (``bone_scale``), and the motion is
  retargeted to them (:func:`fit_motion_to_body`: the pelvis path is scaled by the leg length, then grounded);
- each joint j has a rest alignment ``A_j`` that turns the body's rest limb (anny stands in an A-pose) onto
  SMPL's T-pose direction; a vertex skinned to joint j moves as ``x -> R_j A_j (x - q_j) + p_j`` (R_j, p_j:
  the joint's global rotation and position from SMPL FK, q_j: its rest position on this body), blended over
  up to four joints (linear blend skinning). A joint's child ``c`` lands exactly on FK's ``p_c``, so the
  skeleton the network learns is the one inside the rendered skin.

Shape legend: ``B`` bodies, ``V`` vertices, ``F`` triangles, ``J`` = 22 joints, ``K`` = 4 skinning slots.
"""

from __future__ import annotations

import dataclasses
import zipfile
from pathlib import Path
from typing import Final

import numpy as np
from numba import njit, prange

from ..skeleton import NUM_JOINTS, PARENTS, REST_JOINTS_M, bone_scale_of, joint_bone_lengths, rest_offsets
from .archive import write_npz
from .bvh import best_rotations, smallest_rotations
from .motion import ANKLE_JOINT_HEIGHT_M, Motion, ground

SKIN_SLOTS: Final = 4
# Regions of the surface (one per triangle): what clothing can cover it.
# REGION_INNER: the inside of the mouth and the eye sockets (shells inside the head).
(
    REGION_TORSO, REGION_UPPER_ARM, REGION_FOREARM, REGION_HAND, REGION_HIPS, REGION_THIGH, REGION_SHIN,
    REGION_FOOT, REGION_NECK, REGION_FACE, REGION_SCALP, REGION_INNER,
) = range(12)  # fmt: skip
REGION_NAMES: Final = (
    "torso", "upper_arm", "forearm", "hand", "hips", "thigh", "shin", "foot", "neck", "face", "scalp", "inner",
)  # fmt: skip
BANK_FORMAT: Final = 1
LEG_CHAIN: Final = (1, 4, 7)  # hip, knee, ankle: the pelvis's height above the floor scales with these


class BodyBankError(ValueError):
    """A body bank file that cannot be used: unreadable, truncated, or inconsistent."""


@dataclasses.dataclass(frozen=True)
class BodyBank:
    """faces (F, 3) int32; region (F,) uint8 (REGION_*); skin_joint (V, K) int32 and skin_weight (V, K) float32
    (rows sum to 1); rest_vertices (B, V, 3) float32, metres, SMPL axes (y up, facing +z, x to the body's
    left), feet on y = 0; rest_joints (B, J, 3): the SMPL-22 joints of each body in that pose;
    align (B, J, 3, 3): rest alignment per joint; eyes_m (B, 3): between the eyes (where a headset sits);
    phenotype (B, P) the body model's shape parameters with their ``phenotype_names``; source: what made it."""

    faces: np.ndarray
    region: np.ndarray
    skin_joint: np.ndarray
    skin_weight: np.ndarray
    rest_vertices: np.ndarray
    rest_joints: np.ndarray
    align: np.ndarray
    eyes_m: np.ndarray
    phenotype: np.ndarray
    phenotype_names: tuple[str, ...]
    source: str

    def __post_init__(self) -> None:
        bodies, vertices = self.rest_vertices.shape[:2]
        checks = {
            "faces": self.faces.ndim == 2 and self.faces.shape[1] == 3,
            "face indices": self.faces.size > 0 and self.faces.min() >= 0 and self.faces.max() < vertices,
            "region": self.region.shape == (len(self.faces),),
            "skin": self.skin_joint.shape == self.skin_weight.shape == (vertices, SKIN_SLOTS),
            "skin joints": self.skin_joint.min() >= 0 and self.skin_joint.max() < NUM_JOINTS,
            "rest_joints": self.rest_joints.shape == (bodies, NUM_JOINTS, 3),
            "align": self.align.shape == (bodies, NUM_JOINTS, 3, 3),
            "eyes_m": self.eyes_m.shape == (bodies, 3),
            "phenotype": self.phenotype.shape == (bodies, len(self.phenotype_names)),
            "finite": all(
                np.isfinite(a).all()
                for a in (self.rest_vertices, self.rest_joints, self.align, self.skin_weight)
            ),
        }
        bad = [name for name, ok in checks.items() if not ok]
        if bad or bodies == 0:
            raise BodyBankError(f"inconsistent body bank ({', '.join(bad) or 'no bodies'})")

    @property
    def count(self) -> int:
        return len(self.rest_vertices)

    def bone_scale(self, body: int) -> np.ndarray:
        """(J,) this body's bone lengths against SMPL's rest skeleton (the pelvis row is 1)."""
        return body_bone_scale(self.rest_joints[body])

    def head_offset_m(self, body: int) -> tuple[float, float, float]:
        """Between the eyes (where OpenXR's view pose is) in the head joint's frame, metres."""
        head = 15
        offset = self.align[body, head] @ (self.eyes_m[body] - self.rest_joints[body, head])
        return (float(offset[0]), float(offset[1]), float(offset[2]))

    def height_m(self, body: int) -> float:
        return float(self.rest_vertices[body, :, 1].max() - self.rest_vertices[body, :, 1].min())

    def save(self, path: str | Path) -> Path:
        """Write as ``.npz`` (archive.write_npz: equal banks give equal bytes)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        arrays = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        arrays["phenotype_names"] = np.array(self.phenotype_names)
        arrays["source"] = np.array(self.source)
        arrays["format"] = np.array(BANK_FORMAT)
        write_npz(path, arrays)
        return path

    @classmethod
    def load(cls, path: str | Path) -> BodyBank:
        """Raises BodyBankError for anything that is not a complete bank of this format."""
        try:
            with (
                open(path, "rb") as handle,
                np.load(handle, allow_pickle=False) as data,
            ):  # np.load leaks on a bad zip
                arrays = {key: data[key] for key in data.files}
        except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
            raise BodyBankError(f"{path}: not a readable body bank ({exc})") from exc
        if int(arrays.pop("format", -1)) != BANK_FORMAT:
            raise BodyBankError(f"{path}: not a body bank of format {BANK_FORMAT}")
        try:
            return cls(
                faces=arrays["faces"].astype(np.int32),
                region=arrays["region"].astype(np.uint8),
                skin_joint=arrays["skin_joint"].astype(np.int32),
                skin_weight=arrays["skin_weight"].astype(np.float32),
                rest_vertices=arrays["rest_vertices"].astype(np.float32),
                rest_joints=arrays["rest_joints"].astype(np.float64),
                align=arrays["align"].astype(np.float64),
                eyes_m=arrays["eyes_m"].astype(np.float64),
                phenotype=arrays["phenotype"].astype(np.float64),
                phenotype_names=tuple(str(n) for n in arrays["phenotype_names"]),
                source=str(arrays["source"]),
            )
        except KeyError as exc:
            raise BodyBankError(f"{path}: body bank without {exc}") from exc


def body_bone_scale(rest_joints: np.ndarray) -> np.ndarray:
    """(J,) bone-length scales of a body whose SMPL-22 joints are rest_joints (J, 3)."""
    return bone_scale_of(joint_bone_lengths(rest_joints))


# Which children set each joint's rest alignment: one child -> the smallest rotation onto SMPL's bone, several
# -> the best rotation for all of them; None -> the parent's alignment (leaves whose direction is unknown).
ALIGN_CHILDREN: Final = {
    0: (1, 2, 3), 1: (4,), 2: (5,), 3: (6,), 4: (7,), 5: (8,), 6: (9,), 7: (10,), 8: (11,), 9: (12, 13, 14),
    10: None, 11: None, 12: (15,), 13: (16,), 14: (17,), 15: None, 16: (18,), 17: (19,), 18: (20,), 19: (21,),
}  # fmt: skip


def _unit(vectors: np.ndarray) -> np.ndarray:
    """Directions (K, 3): every child bone weighs the same in the best rotation, whatever its length."""
    return vectors / np.linalg.norm(vectors, axis=-1, keepdims=True)


def rest_alignment(rest_joints: np.ndarray, hand_dirs: np.ndarray | None = None) -> np.ndarray:
    """(J, 3, 3) per-joint rotations turning a body's rest pose (J, 3) onto SMPL's T-pose directions.

    hand_dirs (2, 3): wrist -> middle knuckle of the left and right hand in the rest pose; the wrists are
    aligned so that this points along the forearm of the T-pose. Without it a wrist takes its elbow's."""
    smpl = REST_JOINTS_M
    align = np.empty((NUM_JOINTS, 3, 3))
    for j in range(NUM_JOINTS):
        children = ALIGN_CHILDREN.get(j)
        if j in (20, 21):
            if hand_dirs is None:
                align[j] = align[PARENTS[j]]
                continue
            forearm = smpl[j] - smpl[PARENTS[j]]
            align[j] = smallest_rotations(hand_dirs[j - 20][None], forearm[None])[0]
        elif children is None:
            align[j] = align[PARENTS[j]]
        elif len(children) == 1:
            c = children[0]
            align[j] = smallest_rotations((rest_joints[c] - rest_joints[j])[None], (smpl[c] - smpl[j])[None])[
                0
            ]
        else:
            c = list(children)
            align[j] = best_rotations(
                _unit(rest_joints[c] - rest_joints[j])[None], _unit(smpl[c] - smpl[j])[None]
            )[0]
    return align


def fit_motion_to_body(motion: Motion, rest_joints: np.ndarray) -> Motion:
    """The motion on this body's bones: bone lengths from rest_joints (J, 3), the pelvis path scaled by the
    ratio of leg lengths (so steps keep their proportion and the feet stay near the floor), then grounded."""
    scale = body_bone_scale(rest_joints)
    leg_old = _leg_length_m(motion.bone_scale)
    leg_new = _leg_length_m(scale)
    start = motion.root_pos_m[:1]
    root = start + (motion.root_pos_m - start) * (leg_new / leg_old)
    root[:, 1] = motion.root_pos_m[:, 1] * (leg_new / leg_old)
    return ground(motion.replace(bone_scale=scale, root_pos_m=root))


def _leg_length_m(bone_scale: np.ndarray) -> float:
    offsets = rest_offsets(bone_scale)
    return float(sum(np.linalg.norm(offsets[j]) for j in LEG_CHAIN[1:]) + ANKLE_JOINT_HEIGHT_M)


def joint_transforms(
    bank: BodyBank, body: int, global_rot: np.ndarray, joints_m: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Skinning transforms of one pose: rot (J, 3, 3) = R_j A_j and shift (J, 3) = p_j - R_j A_j q_j, so that
    a rest vertex x skinned to j goes to rot_j x + shift_j. global_rot (J, 3, 3), joints_m (J, 3) from FK."""
    rot = global_rot @ bank.align[body]
    shift = joints_m - np.einsum("jab,jb->ja", rot, bank.rest_joints[body])
    return rot, shift


@njit(cache=True, parallel=True, fastmath=True)
def _skin(rest, skin_joint, skin_weight, rot, shift, out):
    for v in prange(rest.shape[0]):
        x, y, z = rest[v, 0], rest[v, 1], rest[v, 2]
        ox = oy = oz = 0.0
        for k in range(skin_joint.shape[1]):
            w = skin_weight[v, k]
            if w == 0.0:
                continue
            j = skin_joint[v, k]
            ox += w * (rot[j, 0, 0] * x + rot[j, 0, 1] * y + rot[j, 0, 2] * z + shift[j, 0])
            oy += w * (rot[j, 1, 0] * x + rot[j, 1, 1] * y + rot[j, 1, 2] * z + shift[j, 1])
            oz += w * (rot[j, 2, 0] * x + rot[j, 2, 1] * y + rot[j, 2, 2] * z + shift[j, 2])
        out[v, 0], out[v, 1], out[v, 2] = ox, oy, oz


def pose_vertices(bank: BodyBank, body: int, global_rot: np.ndarray, joints_m: np.ndarray) -> np.ndarray:
    """(V, 3) float64 world vertices of body ``body`` in the pose (global_rot (J, 3, 3), joints_m (J, 3))."""
    rot, shift = joint_transforms(bank, body, global_rot, joints_m)
    out = np.empty((bank.rest_vertices.shape[1], 3))
    _skin(bank.rest_vertices[body], bank.skin_joint, bank.skin_weight, rot, shift, out)
    return out
