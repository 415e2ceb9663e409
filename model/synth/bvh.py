"""BVH motion files: parsing, forward kinematics, and retargeting to the SMPL-22 skeleton.

Retargeting keeps rotations, not only positions: each SMPL joint's global rotation starts as its driving
source joint's rotation relative to the rig's T-pose frame (CMU files add one as frame 0), and is then
corrected by the smallest rotation that points its bones at the mapped source joints (Kabsch over several
children). Bone lengths come from the source, as per-bone scales of the SMPL rest skeleton, so FK of the
result lands on the source joints (the test holds it to 2 cm) and twist about a bone follows the source.

Shape legend: ``F`` frames, ``S`` source joints, ``J`` = 22 SMPL joints.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Final

import numpy as np
from scipy.spatial.transform import Rotation

from ..skeleton import JOINT_NAMES, NUM_JOINTS, PARENTS, global_to_local, rest_offsets
from .motion import Motion, ground, resample

CMU_LICENCE: Final = (
    "CMU Graphics Lab Motion Capture Database (mocap.cs.cmu.edu): free for all uses, including inside "
    "commercially sold products, but may not be resold directly, even in converted form. The database was "
    "created with funding from NSF EIA-0196217."
)


class BvhError(ValueError):
    """A BVH file that cannot be read; the message names the file and what is wrong."""


@dataclasses.dataclass(frozen=True)
class BvhClip:
    """A parsed BVH file.

    names/parents: (S,) joint names and parent indices (-1 for the root); end sites are dropped.
    offsets:       (S, 3) offsets from the parent, file units.
    channels:      per joint, the channel names in file order.
    values:        (F, C) the MOTION table, all channels of a frame in joint order.
    frame_time_s:  seconds per frame.
    """

    names: tuple[str, ...]
    parents: np.ndarray
    offsets: np.ndarray
    channels: tuple[tuple[str, ...], ...]
    values: np.ndarray
    frame_time_s: float


@dataclasses.dataclass(frozen=True)
class JointSource:
    """Where an SMPL joint comes from: a point ``weight`` of the way from ``a`` to ``b`` (b None: at a), and
    the source joint whose rotation drives the SMPL joint's bones (its twist, and the rotation of leaves).

    A ``hub`` (an SMPL joint with several children: pelvis, spine3) has no single source joint in most rigs;
    it becomes the point, fixed in its driver's frame, from which its children lie in SMPL's rest directions.
    Without that the rigid SMPL hub cannot reach all children and they miss by 4-7 cm on CMU data.
    """

    a: str
    rotation: str
    b: str | None = None
    weight: float = 0.0
    hub: bool = False  # placed by :func:`_place_hubs` instead (a and b unused)
    fit_weight: float = 1.0  # this joint's weight when its parent hub's rotation is fitted to its children


@dataclasses.dataclass(frozen=True)
class RigMapping:
    """How one rig maps onto SMPL-22: units, its T-pose frame and a source per SMPL joint.

    A rig other than CMU's needs one of these (and a y-up, +z-forward, +x-left world, or a converted file).
    """

    name: str
    metres_per_unit: float
    tpose_frame: int | None  # a frame that holds the rig's T-pose (dropped from the motion); None: rest pose
    joints: dict[str, JointSource]
    licence: str = ""

    def __post_init__(self) -> None:
        missing = set(JOINT_NAMES) - set(self.joints)
        if missing:
            raise ValueError(f"rig mapping {self.name!r} lacks SMPL joints {sorted(missing)}")


def _side(side: str) -> dict[str, JointSource]:
    S = side.capitalize()
    return {
        f"{side}_hip": JointSource(f"{S}UpLeg", f"{S}UpLeg"),
        f"{side}_knee": JointSource(f"{S}Leg", f"{S}Leg"),
        f"{side}_ankle": JointSource(f"{S}Foot", f"{S}Foot"),
        f"{side}_foot": JointSource(f"{S}ToeBase", f"{S}ToeBase"),
        f"{side}_collar": JointSource("Spine1", f"{S}Shoulder", f"{S}Arm", 0.45),
        f"{side}_shoulder": JointSource(f"{S}Arm", f"{S}Arm"),
        f"{side}_elbow": JointSource(f"{S}ForeArm", f"{S}ForeArm"),
        f"{side}_wrist": JointSource(f"{S}Hand", f"{S}Hand"),
    }


# The CMU BVH conversion: Hips/LowerBack/Spine/Spine1/Neck/Neck1/Head and Left*/Right* limbs. The pelvis and
# spine3 are hubs; spine2 and the collars are points along source bones; the SMPL neck sits on CMU's neck
# pivot, which is rigid with Spine1 like the shoulders, so spine3's children stay rigid. Measured over all 83
# clips in ../shared/mocap/cmu: mean FK error per joint 0.0-1.9 cm (arms and head <= 0.8 cm), median
# per-clip 99th percentile <= 2.7 cm. The rest comes from CMU's LowerBack, which bends the spine about the
# hip centre where SMPL has no joint; weighting the legs at the pelvis fit traded hip error for spine error.
CMU_MAPPING: Final = RigMapping(
    name="cmu",
    metres_per_unit=0.056444,
    tpose_frame=0,
    licence=CMU_LICENCE,
    joints={
        "pelvis": JointSource("Hips", "Hips", hub=True),
        "spine1": JointSource("Spine", "Spine"),
        "spine2": JointSource("Spine", "Spine", "Spine1", 0.5),
        "spine3": JointSource("Spine1", "Spine1", hub=True),
        "neck": JointSource("Neck", "Neck1"),  # CMU's neck pivot, which is rigid with Spine1 like the collars
        "head": JointSource("Head", "Head"),
        **_side("left"),
        **_side("right"),
    },
)


# ----------------------------------------------------------------------------------------------- parsing
def parse_bvh(text: str, name: str = "<bvh>") -> BvhClip:
    """Parse BVH text. Raises :class:`BvhError` naming what is wrong."""
    tokens = text.split()
    pos = 0

    def take() -> str:
        nonlocal pos
        if pos >= len(tokens):
            raise BvhError(f"{name}: unexpected end of file")
        pos += 1
        return tokens[pos - 1]

    def expect(word: str) -> None:
        got = take()
        if got != word:
            raise BvhError(f"{name}: expected {word!r}, got {got!r}")

    def number() -> float:
        word = take()
        try:
            return float(word)
        except ValueError:
            raise BvhError(f"{name}: expected a number, got {word!r}") from None

    names: list[str] = []
    parents: list[int] = []
    offsets: list[tuple[float, float, float]] = []
    channels: list[tuple[str, ...]] = []

    def joint(parent: int) -> None:
        index = len(names)
        names.append(take())
        parents.append(parent)
        expect("{")
        expect("OFFSET")
        offsets.append((number(), number(), number()))
        expect("CHANNELS")
        count = int(number())
        channels.append(tuple(take() for _ in range(count)))
        while True:
            word = take()
            if word == "}":
                return
            if word == "JOINT":
                joint(index)
            elif word == "End":
                take()  # "Site"
                expect("{")
                expect("OFFSET")
                for _ in range(3):
                    number()
                expect("}")
            else:
                raise BvhError(f"{name}: unexpected {word!r} in joint {names[index]!r}")

    expect("HIERARCHY")
    expect("ROOT")
    joint(-1)
    expect("MOTION")
    expect("Frames:")
    frames = int(number())
    expect("Frame")
    expect("Time:")
    frame_time_s = number()
    if frame_time_s <= 0 or frames <= 0:
        raise BvhError(f"{name}: needs frames > 0 and Frame Time > 0 (got {frames}, {frame_time_s})")
    width = sum(len(c) for c in channels)
    body = tokens[pos:]
    if len(body) < frames * width:
        raise BvhError(
            f"{name}: MOTION holds {len(body)} numbers, {frames} frames × {width} channels need more"
        )
    try:
        values = np.asarray(body[: frames * width], dtype=np.float64).reshape(frames, width)
    except ValueError as error:
        raise BvhError(f"{name}: bad number in MOTION ({error})") from None
    if not np.isfinite(values).all():
        raise BvhError(f"{name}: MOTION holds non-finite numbers")
    return BvhClip(
        names=tuple(names),
        parents=np.array(parents),
        offsets=np.array(offsets),
        channels=tuple(channels),
        values=values,
        frame_time_s=frame_time_s,
    )


def load_bvh(path: str | Path) -> BvhClip:
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="strict")
    except (OSError, UnicodeDecodeError) as error:
        raise BvhError(f"{path}: cannot read ({error})") from None
    return parse_bvh(text, name=str(path))


# ------------------------------------------------------------------------------------------ kinematics
def bvh_fk(clip: BvhClip) -> tuple[np.ndarray, np.ndarray]:
    """World positions (F, S, 3) in file units and global rotations (F, S, 3, 3) of every joint."""
    frames = len(clip.values)
    count = len(clip.names)
    local_rot = np.empty((frames, count, 3, 3))
    local_pos = np.broadcast_to(clip.offsets, (frames, count, 3)).copy()
    column = 0
    for j, chans in enumerate(clip.channels):
        block = clip.values[:, column : column + len(chans)]
        column += len(chans)
        rot_axes = "".join(c[0].upper() for c in chans if c.endswith("rotation"))
        rot_cols = [k for k, c in enumerate(chans) if c.endswith("rotation")]
        # BVH: rotation channels listed Z Y X mean R = Rz·Ry·Rx (intrinsic, scipy's upper-case order).
        local_rot[:, j] = (
            Rotation.from_euler(rot_axes, block[:, rot_cols], degrees=True).as_matrix()
            if rot_axes
            else np.eye(3)
        )
        for k, axis in enumerate("XYZ"):
            if f"{axis}position" in chans:
                local_pos[:, j, k] = block[:, chans.index(f"{axis}position")]
    global_rot = np.empty_like(local_rot)
    pos = np.empty((frames, count, 3))
    for j, parent in enumerate(clip.parents):
        if parent < 0:
            global_rot[:, j] = local_rot[:, j]
            pos[:, j] = local_pos[:, j]
        else:
            global_rot[:, j] = global_rot[:, parent] @ local_rot[:, j]
            pos[:, j] = pos[:, parent] + (global_rot[:, parent] @ local_pos[:, j, :, None])[..., 0]
    return pos, global_rot


# ------------------------------------------------------------------------------------------ retargeting
def _align(vectors_from: np.ndarray, vectors_to: np.ndarray) -> np.ndarray:
    """Smallest rotations (F, 3, 3) turning directions (F, 3) onto directions (F, 3)."""
    a = vectors_from / np.linalg.norm(vectors_from, axis=-1, keepdims=True)
    b = vectors_to / np.linalg.norm(vectors_to, axis=-1, keepdims=True)
    axis = np.cross(a, b)
    sin = np.linalg.norm(axis, axis=-1)
    cos = np.einsum("fi,fi->f", a, b)
    angle = np.arctan2(sin, cos)
    safe = np.where(sin[:, None] > 1e-12, axis / np.maximum(sin, 1e-12)[:, None], 0.0)
    return Rotation.from_rotvec(safe * angle[:, None]).as_matrix()


def _kabsch(vectors_from: np.ndarray, vectors_to: np.ndarray) -> np.ndarray:
    """Best rotations (F, 3, 3) mapping vector sets (F, K, 3) onto (F, K, 3) (least squares)."""
    h = np.swapaxes(vectors_from, -1, -2) @ vectors_to
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(np.swapaxes(vt, -1, -2) @ np.swapaxes(u, -1, -2)))
    fix = np.ones((len(d), 3))
    fix[:, 2] = d
    return np.swapaxes(vt, -1, -2) @ (fix[:, :, None] * np.swapaxes(u, -1, -2))


def mapped_positions(pos: np.ndarray, names: tuple[str, ...], mapping: RigMapping) -> np.ndarray:
    """(F, S, 3) source positions -> (F, J, 3) positions of the SMPL joints under ``mapping`` (same units)."""
    index = {n: i for i, n in enumerate(names)}
    try:
        out = np.empty((len(pos), NUM_JOINTS, 3))
        for j, joint in enumerate(JOINT_NAMES):
            src = mapping.joints[joint]
            out[:, j] = pos[:, index[src.a]]
            if src.b is not None:
                out[:, j] += src.weight * (pos[:, index[src.b]] - pos[:, index[src.a]])
    except KeyError as error:
        raise BvhError(
            f"rig {mapping.name!r} needs source joint {error.args[0]!r}, not in the file"
        ) from None
    return out


def _place_hubs(
    target_m: np.ndarray, driver_pos_m: np.ndarray, driver_rot: np.ndarray, tpose: int, mapping: RigMapping
) -> None:
    """Fill in the hub joints of ``target_m`` (F, J, 3) in place (see :class:`JointSource`).

    At the T-pose frame a hub's children should lie along SMPL's rest directions from it (all global
    rotations are identity there), so the hub is the least-squares meeting point of those lines; it then
    moves rigidly with its rotation driver (driver_pos_m (F, J, 3), driver_rot (F, J, 3, 3)).
    """
    rest = rest_offsets()
    for j, joint in enumerate(JOINT_NAMES):
        if not mapping.joints[joint].hub:
            continue
        kids = np.flatnonzero(j == PARENTS)
        normal_sum, point_sum = np.zeros((3, 3)), np.zeros(3)
        for kid in kids:
            direction = rest[kid] / np.linalg.norm(rest[kid])
            projector = np.eye(3) - np.outer(direction, direction)
            normal_sum += projector
            point_sum += projector @ target_m[tpose, kid]
        hub_t = np.linalg.solve(normal_sum, point_sum)
        local = driver_rot[tpose, j].T @ (hub_t - driver_pos_m[tpose, j])
        target_m[:, j] = driver_pos_m[:, j] + driver_rot[:, j] @ local


def retarget(
    target_pos_m: np.ndarray,
    driver_rot: np.ndarray,
    tpose_rot: np.ndarray,
    fit_weight: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Solve SMPL-22 rotations whose FK reproduces mapped source positions.

    target_pos_m: (F, J, 3) mapped source joint positions, metres.
    driver_rot:   (F, J, 3, 3) world rotation of each SMPL joint's driving source joint.
    tpose_rot:    (J, 3, 3) the same in the rig's T-pose (SMPL's rest pose is a T-pose).
    fit_weight:   (J,) each joint's weight in its parent's multi-child fit; None = 1.
    Returns (local_rot (F, J, 3, 3), root_pos_m (F, 3), bone_scale (J,)).
    """
    rest = rest_offsets()
    bone_len = np.linalg.norm(target_pos_m[:, 1:] - target_pos_m[:, PARENTS[1:]], axis=-1)
    bone_scale = np.ones(NUM_JOINTS)
    bone_scale[1:] = np.median(bone_len, axis=0) / np.linalg.norm(rest[1:], axis=-1)
    offsets = rest_offsets(bone_scale)
    children = [np.flatnonzero(j == PARENTS) for j in range(NUM_JOINTS)]
    weight = np.ones(NUM_JOINTS) if fit_weight is None else np.asarray(fit_weight, dtype=np.float64)

    global_rot = driver_rot @ np.swapaxes(tpose_rot, -1, -2)[None]  # rotation since the T-pose
    pos = np.empty_like(target_pos_m)
    pos[:, 0] = target_pos_m[:, 0]
    for j in range(NUM_JOINTS):  # parents come before children in SMPL order
        if j > 0:
            pos[:, j] = pos[:, PARENTS[j]] + (global_rot[:, PARENTS[j]] @ offsets[j])
        kids = children[j]
        if len(kids) == 1:
            have = global_rot[:, j] @ offsets[kids[0]]
            want = target_pos_m[:, kids[0]] - pos[:, j]
            global_rot[:, j] = _align(have, want) @ global_rot[:, j]
        elif len(kids) > 1:
            want = (target_pos_m[:, kids] - pos[:, j, None]) * weight[kids, None]
            have = np.broadcast_to(offsets[kids] * weight[kids, None], want.shape)
            global_rot[:, j] = _kabsch(have, want)
    return global_to_local(global_rot), pos[:, 0].copy(), bone_scale


def bvh_to_motion(
    clip: BvhClip, mapping: RigMapping = CMU_MAPPING, name: str = "bvh", fps: float | None = None
) -> Motion:
    """Retarget a parsed BVH clip to an SMPL-22 :class:`Motion`, grounded, optionally resampled to ``fps``."""
    pos, rot = bvh_fk(clip)
    index = {n: i for i, n in enumerate(clip.names)}
    drivers = [index.get(mapping.joints[j].rotation) for j in JOINT_NAMES]
    if None in drivers:
        missing = [mapping.joints[j].rotation for j, d in zip(JOINT_NAMES, drivers, strict=True) if d is None]
        raise BvhError(f"rig {mapping.name!r} needs source joints {missing}, not in the file")
    target = mapped_positions(pos, clip.names, mapping) * mapping.metres_per_unit
    driver_rot = rot[:, drivers]
    tpose = 0 if mapping.tpose_frame is None else mapping.tpose_frame
    _place_hubs(target, pos[:, drivers] * mapping.metres_per_unit, driver_rot, tpose, mapping)
    if mapping.tpose_frame is None:
        tpose_rot = np.broadcast_to(np.eye(3), (NUM_JOINTS, 3, 3))
    else:
        tpose_rot = driver_rot[mapping.tpose_frame]
        keep = np.arange(len(target)) != mapping.tpose_frame
        target, driver_rot = target[keep], driver_rot[keep]
    if len(target) == 0:
        raise BvhError(f"{name}: no frames besides the T-pose")
    fit_weight = np.array([mapping.joints[j].fit_weight for j in JOINT_NAMES])
    local_rot, root, scale = retarget(target, driver_rot, tpose_rot, fit_weight)
    motion = Motion(
        name=name,
        fps=1.0 / clip.frame_time_s,
        local_rot=local_rot,
        root_pos_m=root,
        bone_scale=scale,
        source=f"{mapping.name}:{name}",
        licence=mapping.licence,
    )
    motion = ground(motion)
    return motion if fps is None else resample(motion, fps)


def load_bvh_motion(path: str | Path, mapping: RigMapping = CMU_MAPPING, fps: float | None = None) -> Motion:
    path = Path(path)
    return bvh_to_motion(load_bvh(path), mapping, name=path.stem, fps=fps)
