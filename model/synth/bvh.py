"""BVH motion files: parsing, forward kinematics, and retargeting to the SMPL-22 skeleton.

Which source joint becomes which SMPL joint, the file's axes and its units come from ``rigs.detect_rig``
(any humanoid rig), or from a hand-written :class:`RigMapping` (``CMU_MAPPING``). The rig's T-pose is its
rest pose (the OFFSETs) with the limbs turned onto SMPL's T-pose directions (:func:`tpose_reference`), or a
frame of the file that a mapping names.

Retargeting keeps rotations, not only positions: each SMPL joint's global rotation starts as its driving
source joint's rotation relative to the rig's T-pose, and is then corrected by the smallest rotation that
points its bones at the mapped source joints (Kabsch over several children). Bone lengths come from the
source, as per-bone scales of the SMPL rest skeleton, so FK of the result lands on the source joints and
twist about a bone follows the source.

``rigs`` builds on this module's types, so :func:`retarget_bvh` imports it when called.

Shape legend: ``F`` frames, ``S`` source joints, ``J`` = 22 SMPL joints.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING, Final

import numpy as np
from scipy.spatial.transform import Rotation

from ..skeleton import (
    JOINT_NAMES,
    NUM_JOINTS,
    PARENTS,
    REST_JOINTS_M,
    bone_scale_of,
    global_to_local,
    joint_bone_lengths,
    rest_offsets,
)
from .motion import Motion, fix_feet, ground, resample

if TYPE_CHECKING:
    from .rigs import DetectedRig

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

    names/parents: (S,) joint names and parent indices (-1 for the root), parents before children. End
                   sites are joints too (no channels, ``end_site`` True, named ``<parent>_EndSite``): some
                   rigs end a limb there (a foot without a toe joint).
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
    end_site: tuple[bool, ...] = ()


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
CHANNEL_NAMES: Final = frozenset(f"{axis}{kind}" for axis in "XYZ" for kind in ("position", "rotation"))
MAX_JOINTS: Final = 2048  # far beyond any body rig (fingers, face and props included)
MAX_FRAMES: Final = 10_000_000


class _Tokens:
    """Whitespace tokens of a BVH file with the reads the grammar needs; errors name the file."""

    def __init__(self, text: str, name: str) -> None:
        self.words = text.split()
        self.pos = 0
        self.name = name

    def take(self) -> str:
        if self.pos >= len(self.words):
            raise BvhError(f"{self.name}: unexpected end of file")
        self.pos += 1
        return self.words[self.pos - 1]

    def expect(self, word: str) -> None:
        got = self.take()
        if got != word:
            raise BvhError(f"{self.name}: expected {word!r}, got {got!r}")

    def number(self) -> float:
        word = self.take()
        try:
            value = float(word)
        except ValueError:
            raise BvhError(f"{self.name}: expected a number, got {word!r}") from None
        if not np.isfinite(value):
            raise BvhError(f"{self.name}: expected a finite number, got {word!r}")
        return value

    def count(self, what: str, low: int, high: int) -> int:
        value = self.number()
        if value != int(value) or not low <= value <= high:
            raise BvhError(f"{self.name}: {what} must be a whole number in {low}..{high}, got {value:g}")
        return int(value)

    def joint_name(self) -> str:
        """A joint name runs to the next ``{`` (3ds Max writes names with spaces: ``Bip01 L Thigh``)."""
        parts = []
        while (word := self.take()) != "{":
            parts.append(word)
        if not parts:
            raise BvhError(f"{self.name}: a joint without a name")
        return " ".join(parts)


def _read_hierarchy(tokens: _Tokens) -> tuple[list[str], list[int], list[tuple], list[tuple], list[bool]]:
    """The HIERARCHY block, read without recursion (a hostile file cannot exhaust the stack)."""
    names: list[str] = []
    parents: list[int] = []
    offsets: list[tuple[float, float, float]] = []
    channels: list[tuple[str, ...]] = []
    end_site: list[bool] = []

    def open_joint(parent: int, is_end: bool) -> int:
        if len(names) >= MAX_JOINTS:
            raise BvhError(f"{tokens.name}: more than {MAX_JOINTS} joints")
        if is_end:
            tokens.expect("Site")
            tokens.expect("{")
            name = f"{names[parent]}_EndSite"
        else:
            name = tokens.joint_name()
            if name in names:
                raise BvhError(f"{tokens.name}: joint name {name!r} appears twice")
        tokens.expect("OFFSET")
        offsets.append((tokens.number(), tokens.number(), tokens.number()))
        chans: tuple[str, ...] = ()
        if not is_end:
            tokens.expect("CHANNELS")
            chans = tuple(tokens.take() for _ in range(tokens.count("CHANNELS", 0, 6)))
            unknown = [c for c in chans if c not in CHANNEL_NAMES]
            if unknown or len(set(chans)) != len(chans):
                raise BvhError(f"{tokens.name}: joint {name!r} has bad channels {list(chans)}")
        names.append(name)
        parents.append(parent)
        channels.append(chans)
        end_site.append(is_end)
        return len(names) - 1

    tokens.expect("HIERARCHY")
    tokens.expect("ROOT")
    stack = [open_joint(-1, False)]
    while stack:
        word = tokens.take()
        if word == "}":
            stack.pop()
        elif word in ("JOINT", "End") and not end_site[stack[-1]]:
            stack.append(open_joint(stack[-1], word == "End"))
        else:
            raise BvhError(f"{tokens.name}: unexpected {word!r} in joint {names[stack[-1]]!r}")
    return names, parents, offsets, channels, end_site


def parse_bvh(text: str, name: str = "<bvh>") -> BvhClip:
    """Parse BVH text. Raises :class:`BvhError` naming what is wrong; nothing else escapes."""
    tokens = _Tokens(text, name)
    names, parents, offsets, channels, end_site = _read_hierarchy(tokens)
    tokens.expect("MOTION")
    tokens.expect("Frames:")
    frames = tokens.count("Frames", 1, MAX_FRAMES)
    tokens.expect("Frame")
    tokens.expect("Time:")
    frame_time_s = tokens.number()
    if frame_time_s <= 0:
        raise BvhError(f"{name}: needs Frame Time > 0 (got {frame_time_s})")
    width = sum(len(c) for c in channels)
    body = tokens.words[tokens.pos :]
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
        parents=np.array(parents, dtype=np.int64),
        offsets=np.array(offsets, dtype=np.float64).reshape(-1, 3),
        channels=tuple(channels),
        values=values,
        frame_time_s=frame_time_s,
        end_site=tuple(end_site),
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
def smallest_rotations(vectors_from: np.ndarray, vectors_to: np.ndarray) -> np.ndarray:
    """Smallest rotations (F, 3, 3) turning directions (F, 3) onto directions (F, 3); opposite directions
    get a half turn about an axis perpendicular to them."""
    a = vectors_from / np.linalg.norm(vectors_from, axis=-1, keepdims=True)
    b = vectors_to / np.linalg.norm(vectors_to, axis=-1, keepdims=True)
    axis = np.cross(a, b)
    sin = np.linalg.norm(axis, axis=-1)
    cos = np.einsum("fi,fi->f", a, b)
    angle = np.arctan2(sin, cos)
    safe = np.where(sin[:, None] > 1e-12, axis / np.maximum(sin, 1e-12)[:, None], 0.0)
    opposite = (sin <= 1e-12) & (cos < 0)
    if opposite.any():
        helper = np.where(np.abs(a[opposite, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        perpendicular = np.cross(a[opposite], helper)
        safe[opposite] = perpendicular / np.linalg.norm(perpendicular, axis=-1, keepdims=True)
    return Rotation.from_rotvec(safe * angle[:, None]).as_matrix()


def best_rotations(vectors_from: np.ndarray, vectors_to: np.ndarray) -> np.ndarray:
    """Best rotations (F, 3, 3) mapping vector sets (F, K, 3) onto (F, K, 3) (least squares, Kabsch)."""
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
        _ride_with_driver(
            target_m, driver_pos_m, driver_rot, tpose, j, np.linalg.solve(normal_sum, point_sum)
        )


def _ride_with_driver(
    target_m: np.ndarray,
    driver_pos_m: np.ndarray,
    driver_rot: np.ndarray,
    tpose: int,
    j: int,
    at_tpose: np.ndarray,
) -> None:
    """Set joint j of ``target_m`` (F, J, 3) to the point that is ``at_tpose`` at the T-pose frame and moves
    rigidly with j's rotation driver (driver_pos_m (F, J, 3), driver_rot (F, J, 3, 3)) in every other frame."""
    local = driver_rot[tpose, j].T @ (at_tpose - driver_pos_m[tpose, j])
    target_m[:, j] = driver_pos_m[:, j] + driver_rot[:, j] @ local


SPINE_CHAIN: Final = (3, 6, 9)  # spine1, spine2, spine3
# Where SMPL's spine2 sits between spine1 and spine3, measured along the line joining them (about 0.71).
SPINE2_FRACTION: Final = float(
    np.dot(REST_JOINTS_M[6] - REST_JOINTS_M[3], REST_JOINTS_M[9] - REST_JOINTS_M[3])
    / np.sum((REST_JOINTS_M[9] - REST_JOINTS_M[3]) ** 2)
)


def _keep_spine_in_order(
    target_m: np.ndarray, driver_pos_m: np.ndarray, driver_rot: np.ndarray, tpose: int
) -> None:
    """Put spine3 and spine2 of ``target_m`` (F, J, 3) back in order, in place, when the rig's trunk is short.

    A short trunk (CMU's BVH conversions: shoulders 29 cm above the hips, where SMPL has 56) makes the spine3
    hub, fitted to the neck and collars, land below the point that spine2 takes from the source's spine joints.
    Retargeted as is, spine2 folds back on itself (140-180° bends, undone by spine3: the positions still fit,
    the rotations are nonsense, and a longer trunk driven by them hunches). Then spine3 sits at its rotation
    driver (the source's chest joint: a hub far from its driver would swing with every turn of it), and spine2
    where SMPL has it on the line spine1 -> spine3, riding with its own driver.
    """
    s1, s2, s3 = (target_m[tpose, j] for j in SPINE_CHAIN)
    axis = s3 - s1
    length_sq = float(axis @ axis)
    if length_sq > 1e-12 and 0.2 < float((s2 - s1) @ axis) / length_sq < 0.95:
        return
    _, spine2, spine3 = SPINE_CHAIN
    target_m[:, spine3] = driver_pos_m[:, spine3]
    moved = s1 + SPINE2_FRACTION * (target_m[tpose, spine3] - s1)
    _ride_with_driver(target_m, driver_pos_m, driver_rot, tpose, spine2, moved)


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
    bone_scale = bone_scale_of(np.median(joint_bone_lengths(target_pos_m), axis=0))
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
            global_rot[:, j] = smallest_rotations(have, want) @ global_rot[:, j]
        elif len(kids) > 1:
            want = (target_pos_m[:, kids] - pos[:, j, None]) * weight[kids, None]
            have = np.broadcast_to(offsets[kids] * weight[kids, None], want.shape)
            global_rot[:, j] = best_rotations(have, want)
    return global_to_local(global_rot), pos[:, 0].copy(), bone_scale


# ---------------------------------------------------------------------------------- any rig, end to end
TPOSE_BONES: Final = tuple(
    (f"{side}_{a}", f"{side}_{b}")
    for side in ("left", "right")
    for a, b in (
        ("hip", "knee"),
        ("knee", "ankle"),
        ("ankle", "foot"),
        ("shoulder", "elbow"),
        ("elbow", "wrist"),
    )
)
MAX_BLEND_S: Final = 0.25  # the longest blend out of a reference frame that is dropped with it


def rest_positions(clip: BvhClip) -> np.ndarray:
    """(S, 3) joint positions of the rest pose (every channel zero, the root at its OFFSET), file units."""
    pos = np.zeros((len(clip.names), 3))
    for j, parent in enumerate(clip.parents):  # parents come before children in a BVH file
        pos[j] = clip.offsets[j] + (pos[parent] if parent >= 0 else 0.0)
    return pos


def _subtree(parents: np.ndarray, root: int) -> np.ndarray:
    inside = np.zeros(len(parents), dtype=bool)
    inside[root] = True
    for j in range(root + 1, len(parents)):  # parents come first, so one pass finds every descendant
        inside[j] = parents[j] >= 0 and inside[parents[j]]
    return np.flatnonzero(inside)


def tpose_reference(
    rest_pos_m: np.ndarray, rest_rot: np.ndarray, clip: BvhClip, mapping: RigMapping
) -> tuple[np.ndarray, np.ndarray]:
    """The rig's rest pose with its limbs turned onto SMPL's T-pose directions.

    rest_pos_m (S, 3), rest_rot (S, 3, 3): the rest pose in our axes. Each limb bone (thigh, shin, foot,
    upper arm, forearm) is turned by the smallest rotation that points it along SMPL's rest bone, so an A-pose,
    an I-pose or a T-pose rest all become SMPL's T-pose; twist about the bone stays the rig's.
    Returns (pos_m (S, 3), global_rot (S, 3, 3)).
    """
    pos, rot = rest_pos_m.copy(), rest_rot.copy()
    index = {n: i for i, n in enumerate(clip.names)}
    rest = rest_offsets()
    for parent, child in TPOSE_BONES:
        mapped = mapped_positions(pos[None], clip.names, mapping)[0]
        have = mapped[JOINT_NAMES.index(child)] - mapped[JOINT_NAMES.index(parent)]
        if np.linalg.norm(have) < 1e-9:
            continue
        turn = smallest_rotations(have[None], rest[JOINT_NAMES.index(child)][None])[0]
        driver = index[mapping.joints[parent].rotation]
        moved = _subtree(clip.parents, driver)
        pos[moved] = pos[driver] + (pos[moved] - pos[driver]) @ turn.T
        rot[moved] = turn @ rot[moved]
    return pos, rot


def _rotation_columns(clip: BvhClip, joints: list[int]) -> list[int]:
    """Columns of clip.values that hold the rotation channels of ``joints``."""
    starts = np.concatenate([[0], np.cumsum([len(c) for c in clip.channels])])
    return [
        int(starts[j]) + k
        for j in joints
        for k, name in enumerate(clip.channels[j])
        if name.endswith("rotation")
    ]


def leading_reference_frames(clip: BvhClip, pos_m: np.ndarray, body: list[int]) -> int:
    """How many leading frames are no motion: a reference pose at frame 0 and any blend out of it.

    pos_m: (F, S, 3) joint positions, metres; body: the source joints the body is read from (fingers, eyes
    and props say nothing). Frame 0 is a reference pose when every body rotation below the root is within 5°
    of zero and frame 1 turns some joint 10° further (a rest-pose frame, as Daz-style exports add, with
    crumbs of a few degrees; an actor who starts near the rig's rest pose does not turn 10° in one frame),
    or when the body jumps from it to
    frame 1 (an added T-pose, as CMU's BVH conversion has, or a glitch). Converters often blend out of such a
    frame: the frames after it that still move much faster than the clip ever does again go with it.
    """
    frames = len(pos_m)
    if frames < 3:
        return 0
    rel = pos_m[:, body] - pos_m[:, :1]
    step = np.linalg.norm(np.diff(rel, axis=0), axis=-1).max(axis=-1)  # (F-1,) largest joint step
    typical = float(np.percentile(step[1:], 95))
    angles = clip.values[:2, _rotation_columns(clip, [j for j in body if j > 0])]
    near_rest = angles.size > 0 and np.abs(angles[0]).max() < 5.0
    zero_first = near_rest and np.abs(angles[1] - angles[0]).max() > 10.0
    jump_first = step[0] > max(0.10, 4.0 * typical)
    if not (zero_first or jump_first):
        return 0
    drop = 1
    limit = min(frames - 2, 1 + int(MAX_BLEND_S / clip.frame_time_s))
    while drop < limit and step[drop] > 2.0 * typical:
        drop += 1
    return drop


@dataclasses.dataclass(frozen=True)
class Retargeted:
    """One BVH clip on SMPL-22, with what it took to get there.

    motion:   grounded, at the file's frame rate.
    rig:      the detected rig (None when a :class:`RigMapping` was given).
    dropped:  leading frames dropped as a reference pose (and the blend out of it).
    error_m:  (F, J) distance between the result's joints and the mapped source joints, metres; NaN for the
              hubs (pelvis, spine3), which are placed by the retargeting itself.
    """

    motion: Motion
    rig: DetectedRig | None
    dropped: int
    error_m: np.ndarray


def retarget_bvh(clip: BvhClip, mapping: RigMapping | None = None, name: str = "bvh") -> Retargeted:
    """Retarget a parsed clip to SMPL-22. ``mapping`` None: detect the rig (``rigs.detect_rig``)."""
    rig = None
    world = np.eye(3)
    if mapping is None:
        from .rigs import detect_rig  # rigs builds on this module's types

        rig = detect_rig(clip)
        mapping, world = rig.mapping, rig.world_from_file
    pos_m, rot, tpose, dropped = _posed(clip, mapping, world)
    index = {n: i for i, n in enumerate(clip.names)}
    drivers = [index.get(mapping.joints[j].rotation) for j in JOINT_NAMES]
    if None in drivers:
        missing = [mapping.joints[j].rotation for j, d in zip(JOINT_NAMES, drivers, strict=True) if d is None]
        raise BvhError(f"rig {mapping.name!r} needs source joints {missing}, not in the file")
    target = mapped_positions(pos_m, clip.names, mapping)
    driver_rot = rot[:, drivers]
    _place_hubs(target, pos_m[:, drivers], driver_rot, tpose, mapping)
    _keep_spine_in_order(target, pos_m[:, drivers], driver_rot, tpose)
    tpose_rot = driver_rot[tpose]
    keep = np.arange(len(target)) != tpose
    target, driver_rot = target[keep], driver_rot[keep]
    if len(target) == 0:
        raise BvhError(f"{name}: no frames besides the T-pose")
    fit_weight = np.array([mapping.joints[j].fit_weight for j in JOINT_NAMES])
    local_rot, root, scale = retarget(target, driver_rot, tpose_rot, fit_weight)
    family = rig.family if rig is not None and rig.family else mapping.name
    motion = Motion(
        name, 1.0 / clip.frame_time_s, local_rot, root, scale, f"{family}:{name}", mapping.licence
    )
    error_m = np.linalg.norm(motion.joints() - target, axis=-1)
    error_m[:, [i for i, j in enumerate(JOINT_NAMES) if mapping.joints[j].hub]] = np.nan
    return Retargeted(motion=ground(motion), rig=rig, dropped=dropped, error_m=error_m)


def _posed(clip: BvhClip, mapping: RigMapping, world: np.ndarray) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Every source joint in our axes, metres: (pos_m (F', S, 3), global rotations (F', S, 3, 3), the index of
    the T-pose frame among them, leading frames dropped). A detected rig gets its rest pose turned into a
    T-pose as frame 0 and its reference frames dropped; a pinned mapping names its own T-pose frame."""
    pos, rot = bvh_fk(clip)
    unit = mapping.metres_per_unit
    pos_m, rot = pos @ world.T * unit, world @ rot
    if mapping.tpose_frame is not None:
        return pos_m, rot, mapping.tpose_frame, 1
    index = {n: i for i, n in enumerate(clip.names)}
    body = sorted({index[n] for src in mapping.joints.values() for n in (src.a, src.rotation, src.b) if n})
    dropped = leading_reference_frames(clip, pos_m, body)
    rest_rot = np.broadcast_to(world, rot.shape[1:])
    tpose_pos, tpose_rot = tpose_reference(rest_positions(clip) @ world.T * unit, rest_rot, clip, mapping)
    return (
        np.concatenate([tpose_pos[None], pos_m[dropped:]]),
        np.concatenate([tpose_rot[None], rot[dropped:]]),
        0,
        dropped,
    )


def bvh_to_motion(
    clip: BvhClip, mapping: RigMapping | None = None, name: str = "bvh", fps: float | None = None
) -> Motion:
    """Retarget a parsed BVH clip to an SMPL-22 :class:`Motion`, grounded, optionally resampled to ``fps``.

    ``mapping`` None detects the rig from the file (any humanoid); a :class:`RigMapping` pins it. The feet
    are then fixed (:func:`~.motion.fix_feet`: levelled, since a rig whose rest foot is not a flat-standing
    one tilts every foot alike; held, where the feet slide; grounded again): the motion is what training
    sees, where :func:`retarget_bvh` is faithful to the file.
    """
    motion = fix_feet(retarget_bvh(clip, mapping, name).motion)
    return motion if fps is None else resample(motion, fps)


def load_bvh_motion(path: str | Path, mapping: RigMapping | None = None, fps: float | None = None) -> Motion:
    path = Path(path)
    return bvh_to_motion(load_bvh(path), mapping, name=path.stem, fps=fps)
