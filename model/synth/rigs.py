"""Rig detection for any humanoid BVH: which joints are the SMPL-22 body, the units, the up axis and facing.

A rig is read in three steps, each from what every humanoid file has:

1. **Anchors** (head, both hands, both feet) by joint name. Names are normalised first: namespaces
   (``mixamorig:``) go, CamelCase and ``_ . - space`` split words, a side is ``Left``/``Right``, ``L``/``R``,
   ``l_``/``_l`` or a letter glued to the front (``LThigh``, ``lShldr``, ``lfemur``), digits are dropped,
   and the rest is looked up in :data:`PART_WORDS`. Where a name is missing the **structure** finds the
   anchors instead: the pelvis's three branches (two legs, the spine), up from the legs to the spine, the
   ankles where the leg chains turn forward, left = up × forward, the hands at the spine's most lateral
   leaves, the chest where their chains meet, and the head below the leaves of the chest's third branch
   (eyes, jaw or an end site).
2. **Chains** between anchors by topology: the pelvis is the lowest common ancestor of the feet and the
   head, the chest (SMPL's spine3) that of the hands and the head. Knees and elbows by name on their chain,
   or by arc length where no name says; the hip and shoulder are the nearest joints above them that sit
   elsewhere (twist or roll bones and zero-length spacers skipped); the clavicle is what holds the shoulder,
   and SMPL's collar sits on it where it is medial, else on the chest -> shoulder line.
3. **Frame and units** from the rest pose (the OFFSETs): up is the snapped feet→head axis, left the snapped
   right→left hip axis; units are whichever of m, cm, mm, inches and CMU units gives an adult height; a file
   in none of them (a rescaled rig) is scaled to a 1.70 m body, and the report says so.

The result is a :class:`DetectedRig`: a :class:`RigMapping` the retargeting uses, the rotation from the
file's world to ours (y up, +z forward, +x left) and a report for ``egoposevr motion inspect``.

Shape legend: ``S`` source joints (end sites included).
"""

from __future__ import annotations

import dataclasses
import itertools
import re
from typing import Final

import numpy as np

from ..skeleton import JOINT_INDEX, REST_JOINTS_M
from .bvh import CMU_LICENCE, BvhClip, BvhError, JointSource, RigMapping, rest_positions


class RigError(BvhError):
    """A skeleton that cannot be mapped onto SMPL-22; the message names the chains that were not found."""


# Normalised name (side and digits removed) -> body part. "shoulder" is deliberately absent: it is the
# clavicle in CMU/Mixamo/Rokoko and the upper arm in H-Anim or CMU's 3ds Max rig; the chain decides.
PART_WORDS: Final = {
    "head": ("head", "skullbase", "skull"),
    "neck": ("neck", "lowerneck", "upperneck"),
    "hand": ("hand", "wrist", "palm"),
    "forearm": ("forearm", "lowerarm", "elbow", "farm", "larm", "radius"),
    "foot": ("foot", "ankle", "talus"),
    "thigh": ("upleg", "upperleg", "thigh", "uleg", "femur"),
    "shin": ("leg", "lowerleg", "shin", "calf", "knee", "lleg", "tibia", "crus"),
    "toe": ("toe", "toes", "toebase", "ball", "metatarsal", "midtarsal", "toe0"),
    "hips": ("hips", "hip", "pelvis", "humanoidroot", "root"),
}
_PART_OF: Final = {word: part for part, words in PART_WORDS.items() for word in words}
_GLUED_PARTS: Final = {
    "femur", "tibia", "foot", "toes", "humerus", "radius", "wrist", "hand", "clavicle", "hipjoint", "fingers",
    "thumb", "shoulder", "elbow", "knee", "ankle", "hip", "thigh", "shin", "arm", "forearm", "leg", "upleg",
}  # fmt: skip
_TWIST: Final = re.compile(r"twist|roll|bend|share|helper|adjust|scale|end", re.IGNORECASE)
_SIDE_WORDS: Final = {"left": "L", "l": "L", "lft": "L", "right": "R", "r": "R", "rt": "R", "rgt": "R"}
_NOISE_WORDS: Final = {"mixamorig", "bip", "biped", "j", "c", "def", "org", "mch", "character", "skeleton"}
_WORD: Final = re.compile(r"[A-Z]+(?=[A-Z][a-z])|[A-Z]?[a-z]+|[A-Z]+|\d+")

# Families recognised by their names, for the report (the mapping itself never depends on the family).
FAMILIES: Final = (
    ("mixamo", lambda ns: any(n.lower().startswith("mixamorig") for n in ns)),
    ("3ds-max-biped", lambda ns: any(re.match(r"bip0*\d", n, re.IGNORECASE) for n in ns)),
    ("vrm", lambda ns: any(n.startswith("J_Bip_") for n in ns)),
    ("cmu", lambda ns: {"LHipJoint", "LeftUpLeg", "LowerBack"} <= set(ns)),
    ("cmu-daz", lambda ns: {"abdomen", "lShldr", "lThigh"} <= set(ns)),
    ("cmu-max", lambda ns: {"LeftHip", "LeftKnee", "lowerback"} <= set(ns)),
    ("optitrack-motive", lambda ns: any(n.endswith(("LUArm", "LFArm")) for n in ns)),
    ("xsens-mvn", lambda ns: {"T8", "L5"} <= {n.split(":")[-1] for n in ns}),
    ("rokoko", lambda ns: {"LeftThigh", "LeftShin"} <= set(ns) or "Spine4" in ns),
    ("perception-neuron", lambda ns: any("InHand" in n for n in ns) or "Spine3" in ns),
    ("unity-humanoid", lambda ns: {"LeftUpperArm", "LeftLowerArm"} <= set(ns)),
    ("unreal", lambda ns: {"upperarm_l", "calf_l"} <= {n.lower() for n in ns}),
    ("h-anim", lambda ns: {"l_hip", "l_knee"} <= {n.lower() for n in ns}),
    ("suffix _L/_R", lambda ns: any(re.search(r"[_.][LR]$", n) for n in ns)),
    ("prefix l_/r_", lambda ns: any(re.match(r"[lr]_", n) for n in ns)),
    ("left/right words", lambda ns: any("Left" in n for n in ns)),
)

# SMPL's spine joints along its pelvis -> spine3 polyline, as arc-length fractions (from the rest skeleton).
_SPINE_POLYLINE: Final = REST_JOINTS_M[[0, 3, 6, 9]]
_SPINE_ARC: Final = np.cumsum([0.0, *np.linalg.norm(np.diff(_SPINE_POLYLINE, axis=0), axis=1)])
SPINE1_FRACTION: Final = float(_SPINE_ARC[1] / _SPINE_ARC[-1])
SPINE2_FRACTION: Final = float(_SPINE_ARC[2] / _SPINE_ARC[-1])
KNEE_FRACTION: Final = 0.53  # the knee along pelvis -> ankle by arc length (SMPL 0.53, CMU 0.56)
ELBOW_FRACTION: Final = 0.66  # the elbow along chest -> wrist by arc length (SMPL)
THIGH_MIN: Final = 0.3  # of pelvis -> ankle: the thigh is longer (0.39-0.42), a mid-thigh twist bone shorter
UPPER_ARM_MIN: Final = 0.2  # of chest -> wrist: the upper arm is longer (0.32-0.35), a mid-arm twist shorter
SNAP_FRACTION: Final = 0.15  # of the spine's length: see _point_along
COLLAR_WEIGHT: Final = 0.45  # the SMPL collar, this far from the chest joint towards the shoulder...
COLLAR_AWAY: Final = 0.25  # ...unless the clavicle joint is this far (of chest -> shoulder) from both ends
BALL_FRACTION: Final = 0.7  # the ball of the foot along ankle -> toe tip, for feet without a toe joint

# Units by the rest pose's head-joint height above the lowest foot joint (SMPL: 1.61 m for a 1.70 m person).
UNITS: Final = (("m", 1.0), ("cm", 0.01), ("mm", 0.001), ("inch", 0.0254), ("cmu", 0.056444))
HEAD_HEIGHT_RANGE_M: Final = (1.2, 2.0)  # adults (and tall children); the ranges of the units do not overlap
NOMINAL_HEAD_HEIGHT_M: Final = 1.60  # a 1.70 m body, for files in no known unit


@dataclasses.dataclass(frozen=True)
class NameInfo:
    """What a joint's name says: ``side`` 'L', 'R' or '', ``part`` a key of PART_WORDS or '' , ``word``
    the normalised rest (for reports), ``twist`` an in-between helper bone."""

    side: str
    part: str
    word: str
    twist: bool


def _side_prefix(base: str) -> tuple[str, str]:
    """(side, rest) for a side glued to the front of a name: LEFTARM, LThigh, lShldr, lfemur."""
    for prefix, letter in (("LEFT", "L"), ("RIGHT", "R")):
        if base.isupper() and base.startswith(prefix):
            return letter, base[len(prefix) :]
    if glued := re.match(r"^([LlRr])(?=[A-Z])", base):
        return glued.group(1).upper(), base[1:]
    if (glued := re.match(r"^([lr])([a-z]{3,})$", base)) and glued.group(2) in _GLUED_PARTS:
        return glued.group(1).upper(), glued.group(2)  # CMU's ASF names: lfemur, ltibia, lwrist
    return "", base


def read_name(name: str) -> NameInfo:
    """Normalise one joint name (see the module docstring)."""
    side, base = _side_prefix(re.split(r"[:|]", name)[-1])
    words = [w.lower() for chunk in re.split(r"[\s_.\-]+", base) for w in _WORD.findall(chunk)]
    rest = []
    for word in words:
        if word in _SIDE_WORDS and not side:
            side = _SIDE_WORDS[word]
        elif not (word in _SIDE_WORDS or word in _NOISE_WORDS or word.isdigit()):
            rest.append(word)
    word = "".join(rest)
    part = _PART_OF.get(word, "")
    if part == "hips" and side:
        part = "thigh"  # l_hip, LeftHip: the hip joint of a leg
    return NameInfo(side=side, part=part, word=word, twist=bool(_TWIST.search(word)))


@dataclasses.dataclass(frozen=True)
class DetectedRig:
    """A rig read from a BVH file.

    mapping:          where each SMPL joint comes from (metres_per_unit filled in, tpose_frame None).
    world_from_file:  (3, 3) rotation from the file's axes to ours (y up, +z forward, +x left).
    family:           the name family recognised ('' if none), for the report.
    units:            'm', 'cm', 'mm', 'inch', 'cmu', or 'unknown' (then scaled to a 1.70 m body).
    up_axis:          the file's up axis, e.g. '+Y' or '+Z'; forward_axis likewise.
    anchors_from:     'names' or 'structure'.
    roles:            SMPL-side role -> source joint name (head, hands, feet, knees, elbows, ...).
    notes:            anything the user should know (mirrored names, no toe joint, ...).
    """

    mapping: RigMapping
    world_from_file: np.ndarray
    family: str
    units: str
    up_axis: str
    forward_axis: str
    anchors_from: str
    roles: dict[str, str]
    notes: tuple[str, ...]


# ------------------------------------------------------------------------------------------- topology
class _Tree:
    """Parent/child queries over a clip's joints, with their rest positions (S, 3), file units."""

    def __init__(self, clip: BvhClip) -> None:
        self.names = clip.names
        self.parents = clip.parents
        self.end_site = clip.end_site or (False,) * len(clip.names)
        self.rest = rest_positions(clip)
        self.children: list[list[int]] = [[] for _ in clip.names]
        for j, parent in enumerate(clip.parents):
            if parent >= 0:
                self.children[parent].append(j)
        self.info = [read_name(n) for n in clip.names]

    def ancestors(self, j: int) -> list[int]:
        """j and its ancestors, j first."""
        out = []
        while j >= 0:
            out.append(j)
            j = int(self.parents[j])
        return out

    def common_ancestor(self, joints: list[int]) -> int:
        chains = [self.ancestors(j)[::-1] for j in joints]
        common = -1
        for level in zip(*chains, strict=False):
            if len(set(level)) != 1:
                break
            common = level[0]
        return common

    def path(self, top: int, bottom: int) -> list[int]:
        """Joints from ``top`` down to ``bottom`` (both included); ``top`` must be an ancestor."""
        chain = self.ancestors(bottom)
        if top not in chain:
            raise RigError(f"{self.names[top]!r} is not above {self.names[bottom]!r}")
        return chain[: chain.index(top) + 1][::-1]

    def descendants(self, j: int) -> list[int]:
        out, todo = [], [j]
        while todo:
            k = todo.pop()
            out.append(k)
            todo += self.children[k]
        return out

    def leaves(self, j: int) -> list[int]:
        return [k for k in self.descendants(j) if not self.children[k]]

    def arc(self, path: list[int]) -> np.ndarray:
        """Cumulative rest length along a path, (len(path),)."""
        steps = np.linalg.norm(np.diff(self.rest[path], axis=0), axis=1)
        return np.concatenate([[0.0], np.cumsum(steps)])


# -------------------------------------------------------------------------------------------- anchors
def _named(tree: _Tree, part: str, side: str) -> int | None:
    """The shallowest joint whose name says ``part`` on ``side`` (None if no name says so)."""
    hits = [j for j, info in enumerate(tree.info) if info.part == part and info.side == side]
    hits = [j for j in hits if not tree.end_site[j]]
    return min(hits, key=lambda j: len(tree.ancestors(j))) if hits else None


def _anchors_by_name(tree: _Tree) -> dict[str, int] | None:
    anchors = {
        "head": _named(tree, "head", ""),
        "hand_L": _named(tree, "hand", "L"),
        "hand_R": _named(tree, "hand", "R"),
        "foot_L": _named(tree, "foot", "L"),
        "foot_R": _named(tree, "foot", "R"),
    }
    if None in anchors.values():
        return None
    return {k: v for k, v in anchors.items() if v is not None}


def _snap(vector: np.ndarray) -> np.ndarray:
    """The signed coordinate axis nearest to a direction."""
    axis = int(np.argmax(np.abs(vector)))
    out = np.zeros(3)
    out[axis] = np.sign(vector[axis]) or 1.0
    return out


def _pelvis_guess(tree: _Tree) -> int:
    """The root, or below it while it has one child (a 'root'/'Bip01' wrapper above the pelvis)."""
    j = 0
    while len(tree.children[j]) == 1 and tree.children[tree.children[j][0]]:
        j = tree.children[j][0]
    return j


def _anchors_by_structure(tree: _Tree) -> dict[str, int]:
    """Head, hands and feet from topology and rest geometry alone (names unknown)."""
    pelvis, spine, legs = _trunk(tree)
    up, left, (foot_l, foot_r) = _feet_and_frame(tree, pelvis, spine, legs)
    head, (hand_l, hand_r) = _head_and_hands(tree, spine, up, left)
    return {"head": head, "hand_L": hand_l, "hand_R": hand_r, "foot_L": foot_l, "foot_R": foot_r}


def _trunk(tree: _Tree) -> tuple[int, int, list[int]]:
    """(pelvis, the spine's first joint, the two legs' first joints): the pelvis's three largest branches."""
    pelvis = _pelvis_guess(tree)
    branches = sorted(tree.children[pelvis], key=lambda c: len(tree.descendants(c)), reverse=True)
    if len(branches) < 3:
        raise RigError(
            f"cannot find the legs and spine: the pelvis {tree.names[pelvis]!r} has "
            f"{len(branches)} branches (legs and spine need 3), and the joint names are not recognised"
        )
    return pelvis, branches[0], branches[1:3]


def _feet_and_frame(
    tree: _Tree, pelvis: int, spine: int, legs: list[int]
) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """(up, left, (left ankle, right ankle)): up from the legs' tips to the spine, forward where the toes
    point, left = up × forward."""
    rest = tree.rest - tree.rest[pelvis]
    tips = [max(tree.leaves(b), key=lambda k: np.linalg.norm(rest[k])) for b in legs]
    up = _snap(rest[tree.descendants(spine)].mean(axis=0) - rest[tips].mean(axis=0))
    feet = [_ankle_on_path(tree, tree.path(pelvis, tip), up) for tip in tips]
    forward = sum(rest[tip] - rest[foot] for tip, foot in zip(tips, feet, strict=True))
    left = np.cross(up, _snap(forward - (forward @ up) * up))
    foot_l, foot_r = sorted(feet, key=lambda k: -(rest[k] @ left))
    return up, left, (foot_l, foot_r)


def _head_and_hands(tree: _Tree, spine: int, up: np.ndarray, left: np.ndarray) -> tuple[int, tuple[int, int]]:
    """The hands end the spine's most lateral leaf chains; the chest is where those chains meet; the head
    sits below the leaves (eyes, jaw, an end site) of the chest's branch that holds the highest leaf."""
    upper = tree.leaves(spine)
    tips = (max(upper, key=lambda k: tree.rest[k] @ left), min(upper, key=lambda k: tree.rest[k] @ left))
    chest = tree.common_ancestor(list(tips))
    top = max(upper, key=lambda k: tree.rest[k] @ up)
    neck = next((c for c in tree.children[chest] if top in tree.descendants(c)), None)
    if neck is None or tips[0] == tips[1] or chest in tips:
        raise RigError(
            "cannot find the left and right arm chains and the head: the spine branch does not split into "
            "two arms and a neck, and the joint names are not recognised"
        )
    head = tree.common_ancestor(tree.leaves(neck))
    head = int(tree.parents[head]) if tree.end_site[head] else head
    hand_l, hand_r = (_hand_on_path(tree, tree.path(spine, tip)) for tip in tips)
    return head, (hand_l, hand_r)


def _ankle_on_path(tree: _Tree, path: list[int], up: np.ndarray) -> int:
    """The ankle: where a leg chain, after its long descent, first runs more forward than down."""
    descended = False
    for a, b in itertools.pairwise(path):
        step = tree.rest[b] - tree.rest[a]
        length = np.linalg.norm(step)
        if length < 1e-9:
            continue
        vertical = abs(step @ up)
        if vertical > 0.7 * length:
            descended = True
        elif descended:
            return a
    return path[-2] if len(path) > 1 else path[-1]


def _hand_on_path(tree: _Tree, path: list[int]) -> int:
    """The wrist: the first joint past mid-arm that branches (fingers), else the last real joint."""
    arc = tree.arc(path)
    for j, s in zip(path, arc, strict=True):
        if s > 0.6 * arc[-1] and len([c for c in tree.children[j] if not tree.info[c].twist]) >= 2:
            return j
    real = [j for j in path if not tree.end_site[j]]
    return real[-1]


# --------------------------------------------------------------------------------------------- chains
def _distinct_above(tree: _Tree, path: list[int], joint: int, min_length: float) -> int:
    """The nearest joint above ``joint`` on ``path`` that sits elsewhere and is no twist/roll helper."""
    index = path.index(joint)
    for k in range(index - 1, -1, -1):
        j = path[k]
        far = np.linalg.norm(tree.rest[j] - tree.rest[joint]) > min_length
        if far and not tree.info[j].twist:
            return j
    return path[0]


def _by_fraction(tree: _Tree, path: list[int], fraction: float, exclude: tuple[int, ...]) -> int:
    arc = tree.arc(path)
    candidates = [k for k, j in enumerate(path) if j not in exclude]
    best = min(candidates, key=lambda k: abs(arc[k] - fraction * arc[-1]))
    return path[best]


def _on_path(tree: _Tree, path: list[int], part: str) -> int | None:
    hits = [j for j in path if tree.info[j].part == part]
    return hits[0] if hits else None


def _limb(
    tree: _Tree, top: int, end: int, what: str, middle: tuple[str, float], upper_min: float
) -> tuple[int, int]:
    """The upper and middle joints of a limb chain ``top`` -> ``end`` (hip and knee, shoulder and elbow).

    middle:    (the part its name says, its arc-length fraction along the chain where no name says).
    upper_min: the upper joint is the nearest one above the middle joint at least this fraction of the
               chain's length away (twist bones and zero-length spacers in between are skipped).
    """
    path = tree.path(top, end)
    if len(path) < 3:
        raise RigError(f"the {what} chain {[tree.names[j] for j in path]} has no middle joint")
    part, fraction = middle
    named = _on_path(tree, path[1:-1], part)
    mid = named if named is not None else _by_fraction(tree, path, fraction, (top, end))
    upper = _distinct_above(tree, path, mid, upper_min * tree.arc(path)[-1])
    if upper == top:
        upper = path[1] if path[1] != mid else mid
    return upper, mid


def _leg(tree: _Tree, pelvis: int, foot: int, side: str) -> dict[str, int]:
    hip, knee = _limb(tree, pelvis, foot, f"{side} leg", ("shin", KNEE_FRACTION), THIGH_MIN)
    return {"hip": hip, "knee": knee, "ankle": foot, "toe": _toe_below(tree, foot)}


def _toe_below(tree: _Tree, foot: int) -> int:
    """The toe (SMPL's foot joint, the ball): a toe-named joint below the ankle, else the first joint or end
    site below it that sits elsewhere."""
    below = tree.descendants(foot)[1:]
    named = [j for j in below if tree.info[j].part == "toe" and not tree.end_site[j]]
    if named:
        return min(named, key=lambda j: len(tree.ancestors(j)))
    far = [j for j in below if np.linalg.norm(tree.rest[j] - tree.rest[foot]) > 1e-6]
    if not far:
        raise RigError(f"nothing below the ankle {tree.names[foot]!r} to place the toes")
    return min(far, key=lambda j: len(tree.ancestors(j)))


def _toe_source(tree: _Tree, leg: dict[str, int]) -> JointSource:
    """SMPL's foot joint (the ball of the foot): the toe joint, or, where the foot ends in its tip (no toe
    joint), that far along the ankle -> tip line, turned by the ankle."""
    ankle, toe = tree.names[leg["ankle"]], tree.names[leg["toe"]]
    if tree.end_site[leg["toe"]]:
        return JointSource(ankle, ankle, toe, BALL_FRACTION)
    return JointSource(toe, toe)


def _collar_source(tree: _Tree, chest: int, arm: dict[str, int]) -> JointSource:
    """SMPL's collar: the clavicle joint where it sits away from the chest joint (its medial end, as most rigs
    place it), else a point on the chest -> shoulder line (CMU's clavicles start at the chest joint)."""
    chest_name, clavicle, shoulder = tree.names[chest], arm["clavicle"], arm["shoulder"]
    span = np.linalg.norm(tree.rest[shoulder] - tree.rest[chest])
    from_chest = np.linalg.norm(tree.rest[clavicle] - tree.rest[chest])
    to_shoulder = np.linalg.norm(tree.rest[shoulder] - tree.rest[clavicle])
    if clavicle != chest and min(from_chest, to_shoulder) > COLLAR_AWAY * span:
        return JointSource(tree.names[clavicle], tree.names[clavicle])
    return JointSource(chest_name, tree.names[clavicle], tree.names[shoulder], COLLAR_WEIGHT)


def _arm(tree: _Tree, chest: int, hand: int, side: str) -> dict[str, int]:
    shoulder, elbow = _limb(tree, chest, hand, f"{side} arm", ("forearm", ELBOW_FRACTION), UPPER_ARM_MIN)
    clavicle = int(tree.parents[shoulder]) if shoulder != chest else chest
    return {"clavicle": clavicle, "shoulder": shoulder, "elbow": elbow, "wrist": hand}


def _point_along(tree: _Tree, path: list[int], fraction: float) -> JointSource:
    """A point ``fraction`` of the way along a chain (by rest arc length), driven by its segment's joint.

    A joint of the chain within :data:`SNAP_FRACTION` of that point is used itself: SMPL's chain bends only
    at its joints, so a point between two source pivots misses by centimetres whenever the source bends.
    """
    arc = tree.arc(path)
    target = fraction * arc[-1]
    inner = range(1, len(path) - 1)
    near = [k for k in inner if abs(arc[k] - target) <= SNAP_FRACTION * arc[-1]]
    if near:
        k = min(near, key=lambda k: abs(arc[k] - target))
        return JointSource(tree.names[path[k]], tree.names[path[k]])
    k = int(np.clip(np.searchsorted(arc, target, side="right") - 1, 0, len(path) - 2))
    span = arc[k + 1] - arc[k]
    weight = float((target - arc[k]) / span) if span > 0 else 0.0
    return JointSource(tree.names[path[k]], tree.names[path[k]], tree.names[path[k + 1]], weight)


# ------------------------------------------------------------------------------------- frame and units
def _axis_label(vector: np.ndarray) -> str:
    axis = int(np.argmax(np.abs(vector)))
    return ("+" if vector[axis] > 0 else "-") + "XYZ"[axis]


def _units(head_height: float) -> tuple[str, float]:
    low, high = HEAD_HEIGHT_RANGE_M
    for name, metres in UNITS:
        if low <= head_height * metres <= high:
            return name, metres
    return "unknown", NOMINAL_HEAD_HEIGHT_M / head_height


def _family(names: tuple[str, ...]) -> str:
    return next((name for name, test in FAMILIES if test(names)), "")


# -------------------------------------------------------------------------------------------- detect
def detect_rig(clip: BvhClip) -> DetectedRig:
    """Read a clip's rig (see the module docstring). Raises :class:`RigError` naming what was not found."""
    tree = _Tree(clip)
    anchors = _anchors_by_name(tree)
    anchors_from = "names" if anchors is not None else "structure"
    if anchors is None:
        anchors = _anchors_by_structure(tree)
    pelvis = tree.common_ancestor([anchors["foot_L"], anchors["foot_R"], anchors["head"]])
    chest = tree.common_ancestor([anchors["hand_L"], anchors["hand_R"], anchors["head"]])
    _check_chains(tree, anchors, pelvis, chest)
    swapped = False
    while True:
        legs = {s: _leg(tree, pelvis, anchors[f"foot_{s}"], s) for s in "LR"}
        arms = {s: _arm(tree, chest, anchors[f"hand_{s}"], s) for s in "LR"}
        world_from_file = _world_from_file(tree, anchors, legs)
        rest_ours = tree.rest @ world_from_file.T  # file units, our axes
        if swapped or _toes_forward(rest_ours, legs):
            break
        # Toes pointing backwards: the names call the actor's left side right. Trust the body.
        anchors = {
            k.replace("_L", "_X").replace("_R", "_L").replace("_X", "_R"): v for k, v in anchors.items()
        }
        swapped = True
    units, metres = _units(_head_height(rest_ours, anchors["head"], legs))
    roles = {
        "pelvis": tree.names[pelvis],
        "chest": tree.names[chest],
        "head": tree.names[anchors["head"]],
        **{f"{s}_{k}": tree.names[j] for s in "LR" for k, j in legs[s].items()},
        **{f"{s}_{k}": tree.names[j] for s in "LR" for k, j in arms[s].items()},
    }
    return DetectedRig(
        mapping=_mapping(tree, pelvis, chest, anchors["head"], legs, arms, metres),
        world_from_file=world_from_file,
        family=_family(clip.names),
        units=units,
        up_axis=_axis_label(world_from_file[1]),
        forward_axis=_axis_label(world_from_file[2]),
        anchors_from=anchors_from,
        roles=roles,
        notes=_notes(tree, legs, units)
        + (("left and right are swapped in the joint names: swapped back",) if swapped else ()),
    )


def _head_height(rest_ours: np.ndarray, head: int, legs: dict[str, dict[str, int]]) -> float:
    """The head joint's height above the lowest foot joint in the rest pose, file units (refused if <= 0)."""
    feet_y = min(rest_ours[legs[s][k], 1] for s in "LR" for k in ("ankle", "toe"))
    height = float(rest_ours[head, 1] - feet_y)
    if not height > 1e-6 * float(np.abs(rest_ours).max(initial=1.0)):
        raise RigError(
            "cannot map the rig: its rest pose (OFFSETs) does not stand: the head is not above the feet"
        )
    return height


def _toes_forward(rest_ours: np.ndarray, legs: dict[str, dict[str, int]]) -> bool:
    """False only when the feet clearly point backwards (a foot pointing down says nothing)."""
    feet = [rest_ours[legs[s]["toe"]] - rest_ours[legs[s]["ankle"]] for s in "LR"]
    return sum(f[2] for f in feet) > -0.3 * sum(np.linalg.norm(f) for f in feet)


def _notes(tree: _Tree, legs: dict[str, dict[str, int]], units: str) -> tuple[str, ...]:
    """What the user should know about how the rig was read."""
    notes = []
    if any(tree.end_site[legs[s]["toe"]] for s in "LR"):
        notes.append(
            f"no toe joints: SMPL's feet placed {BALL_FRACTION:.0%} of the way from ankle to toe tip"
        )
    if units == "unknown":
        notes.append(f"units unknown: scaled to a {NOMINAL_HEAD_HEIGHT_M / 0.94:.2f} m body")
    return tuple(notes)


def _check_chains(tree: _Tree, anchors: dict[str, int], pelvis: int, chest: int) -> None:
    """Refuse rigs whose anchors do not hang together like a body, naming the chains that fail."""
    missing = []
    for side in "LR":
        if pelvis not in tree.ancestors(anchors[f"foot_{side}"]) or anchors[f"foot_{side}"] == pelvis:
            missing.append(f"{side} leg")
        if chest not in tree.ancestors(anchors[f"hand_{side}"]) or anchors[f"hand_{side}"] == chest:
            missing.append(f"{side} arm")
    if chest == anchors["head"] or pelvis not in tree.ancestors(chest):
        missing.append("spine to the head")
    if chest == pelvis:
        missing.append("spine (the arms branch off at the pelvis)")
    if missing:
        raise RigError(f"cannot map the rig: no {', '.join(missing)} chain")


def _world_from_file(tree: _Tree, anchors: dict[str, int], legs: dict) -> np.ndarray:
    """(3, 3) rows: the file's left, up and forward axes (snapped), so ours = this @ the file's."""
    rest = tree.rest
    feet = rest[[anchors["foot_L"], anchors["foot_R"]]].mean(axis=0)
    up = _snap(rest[anchors["head"]] - feet)
    across = rest[legs["L"]["hip"]] - rest[legs["R"]["hip"]]
    if np.linalg.norm(across - (across @ up) * up) < 1e-9:
        across = rest[anchors["hand_L"]] - rest[anchors["hand_R"]]
    left = _snap(across - (across @ up) * up)
    forward = np.cross(left, up)
    if not np.any(forward):
        raise RigError("cannot map the rig: its rest pose has no left-right extent (hips and hands coincide)")
    return np.stack([left, up, forward])


def _mapping(
    tree: _Tree, pelvis: int, chest: int, head: int, legs: dict, arms: dict, metres: float
) -> RigMapping:
    n = tree.names
    spine = tree.path(pelvis, chest)
    neck_path = tree.path(chest, head)
    if len(neck_path) > 2:
        neck = JointSource(n[neck_path[1]], n[neck_path[-2]])
    else:
        neck = JointSource(n[chest], n[chest], n[head], 0.5)
    joints = {
        "pelvis": JointSource(n[pelvis], n[pelvis], hub=True),
        "spine1": _point_along(tree, spine, SPINE1_FRACTION),
        "spine2": _point_along(tree, spine, SPINE2_FRACTION),
        "spine3": JointSource(n[chest], n[chest], hub=True),
        "neck": neck,
        "head": JointSource(n[head], n[head]),
    }
    for side, word in (("L", "left"), ("R", "right")):
        leg, arm = legs[side], arms[side]
        joints[f"{word}_hip"] = JointSource(n[leg["hip"]], n[leg["hip"]])
        joints[f"{word}_knee"] = JointSource(n[leg["knee"]], n[leg["knee"]])
        joints[f"{word}_ankle"] = JointSource(n[leg["ankle"]], n[leg["ankle"]])
        joints[f"{word}_foot"] = _toe_source(tree, leg)
        joints[f"{word}_collar"] = _collar_source(tree, chest, arm)
        joints[f"{word}_shoulder"] = JointSource(n[arm["shoulder"]], n[arm["shoulder"]])
        joints[f"{word}_elbow"] = JointSource(n[arm["elbow"]], n[arm["elbow"]])
        joints[f"{word}_wrist"] = JointSource(n[arm["wrist"]], n[arm["wrist"]])
    assert set(joints) == set(JOINT_INDEX)
    return RigMapping(name="auto", metres_per_unit=metres, tpose_frame=None, joints=joints, licence="")


__all__ = ["CMU_LICENCE", "DetectedRig", "RigError", "detect_rig", "read_name"]
