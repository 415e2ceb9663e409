"""One known SMPL-22 motion written as BVH files of many rig families (names, axes, units, rest poses).

Every family's skeleton puts its body joints where SMPL's are, so every file shows the same motion: a
retargeter that reads them all right returns the same SMPL-22 joints. What differs is what real files differ
in: joint names (CMU, Mixamo, Unity, VRM, Unreal, 3ds Max Biped, Rokoko, Perception Neuron, Xsens, Motive,
H-Anim, Daz...), extra joints (finger chains, twist bones, zero-length spacers, a wrapper above the pelvis),
a foot without a toe joint, an A-pose rest, Z-up axes, centimetres or inches, and the rotation channel order.

Shape legend: ``F`` frames, ``J`` = 22 SMPL joints, ``R`` rig joints.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation

from egoposevr.model.skeleton import JOINT_INDEX, REST_JOINTS_M, forward_kinematics, rest_offsets

# SMPL joint of each role (the joint whose position the role's rig joint takes and whose rotation drives it).
ROLE_JOINT = {
    "pelvis": "pelvis", "spine_a": "spine1", "spine_b": "spine2", "chest": "spine3", "neck": "neck",
    "head": "head", "L_thigh": "left_hip", "L_shin": "left_knee", "L_foot": "left_ankle", "L_toe": "left_foot",
    "R_thigh": "right_hip", "R_shin": "right_knee", "R_foot": "right_ankle", "R_toe": "right_foot",
    "L_clavicle": "left_collar", "L_upperarm": "left_shoulder", "L_forearm": "left_elbow", "L_hand": "left_wrist",
    "R_clavicle": "right_collar", "R_upperarm": "right_shoulder", "R_forearm": "right_elbow",
    "R_hand": "right_wrist",
}  # fmt: skip


@dataclasses.dataclass(frozen=True)
class Family:
    """How one rig family names and builds the body.

    names:      role -> joint name ('{s}' is replaced by the family's side word); a role left out is absent
                (spine_b, L_toe...: the chain is shorter, or the foot ends in an end site).
    sides:      (left, right) words put into '{s}'.
    spacers:    role -> name of a zero-length joint inserted above that role's joint (CMU's LHipJoint).
    wrapper:    name of a joint above the pelvis at the same place (Biped's Bip01), or ''.
    fingers:    add finger chains below the hands; twist: add an in-line forearm twist bone.
    neck_mid:   name of a joint half-way from the neck to the head (CMU's Neck1), or ''.
    head_top:   what ends the head chain: an End Site, a HeadTop_End joint, or two eyes (Daz).
    """

    name: str
    names: dict[str, str]
    sides: tuple[str, str] = ("Left", "Right")
    spacers: dict[str, str] = dataclasses.field(default_factory=dict)
    wrapper: str = ""
    fingers: bool = False
    twist: bool = False
    neck_mid: str = ""
    head_top: str = "end"  # 'end': an End Site; 'joint': a HeadTop_End joint (Mixamo); 'eyes': two eye joints
    clavicle_at_chest: bool = False  # the clavicle pivots at the chest joint (CMU's conversion), not medially


def _limbs(thigh, shin, foot, toe, clavicle, upper, fore, hand) -> dict[str, str]:
    names = {"thigh": thigh, "shin": shin, "foot": foot, "toe": toe}
    names |= {"clavicle": clavicle, "upperarm": upper, "forearm": fore, "hand": hand}
    return {f"{s}_{k}": v for s in "LR" for k, v in names.items() if v}


def _spine(pelvis, a, b, chest, neck, head) -> dict[str, str]:
    names = {"pelvis": pelvis, "spine_a": a, "spine_b": b, "chest": chest, "neck": neck, "head": head}
    return {k: v for k, v in names.items() if v}


FAMILIES = (
    Family(
        "cmu",
        _spine("Hips", "Spine", "", "Spine1", "Neck", "Head")
        | _limbs("{s}UpLeg", "{s}Leg", "{s}Foot", "{s}ToeBase", "{s}Shoulder", "{s}Arm", "{s}ForeArm", "{s}Hand"),
        spacers={"L_thigh": "LHipJoint", "R_thigh": "RHipJoint", "spine_a": "LowerBack"},
        neck_mid="Neck1",
        fingers=True,
    ),
    Family(
        "cmu-asf",
        _spine("root", "lowerback", "upperback", "thorax", "lowerneck", "head")
        | _limbs("{s}femur", "{s}tibia", "{s}foot", "{s}toes", "{s}clavicle", "{s}humerus", "{s}radius", "{s}wrist"),
        sides=("l", "r"),
        spacers={"L_thigh": "lhipjoint", "R_thigh": "rhipjoint"},
        neck_mid="upperneck",
    ),
    Family(
        "mixamo",
        _spine("mixamorig:Hips", "mixamorig:Spine", "mixamorig:Spine1", "mixamorig:Spine2", "mixamorig:Neck",
               "mixamorig:Head")
        | _limbs("mixamorig:{s}UpLeg", "mixamorig:{s}Leg", "mixamorig:{s}Foot", "mixamorig:{s}ToeBase",
                 "mixamorig:{s}Shoulder", "mixamorig:{s}Arm", "mixamorig:{s}ForeArm", "mixamorig:{s}Hand"),
        fingers=True,
        head_top="joint",
    ),
    Family(
        "unity-humanoid",
        _spine("Hips", "Spine", "Chest", "UpperChest", "Neck", "Head")
        | _limbs("{s}UpperLeg", "{s}LowerLeg", "{s}Foot", "{s}Toes", "{s}Shoulder", "{s}UpperArm",
                 "{s}LowerArm", "{s}Hand"),
    ),
    Family(
        "vrm",
        _spine("J_Bip_C_Hips", "J_Bip_C_Spine", "J_Bip_C_Chest", "J_Bip_C_UpperChest", "J_Bip_C_Neck",
               "J_Bip_C_Head")
        | _limbs("J_Bip_{s}_UpperLeg", "J_Bip_{s}_LowerLeg", "J_Bip_{s}_Foot", "J_Bip_{s}_ToeBase",
                 "J_Bip_{s}_Shoulder", "J_Bip_{s}_UpperArm", "J_Bip_{s}_LowerArm", "J_Bip_{s}_Hand"),
        sides=("L", "R"),
        fingers=True,
    ),
    Family(
        "unreal-suffix",
        _spine("pelvis", "spine_01", "spine_02", "spine_03", "neck_01", "head")
        | _limbs("thigh_{s}", "calf_{s}", "foot_{s}", "ball_{s}", "clavicle_{s}", "upperarm_{s}", "lowerarm_{s}",
                 "hand_{s}"),
        sides=("l", "r"),
        wrapper="root",
        twist=True,
        fingers=True,
    ),
    Family(
        "suffix-upper-L",
        _spine("Hips", "Spine", "Spine1", "Chest", "Neck", "Head")
        | _limbs("UpperLeg_{s}", "LowerLeg_{s}", "Foot_{s}", "Toe_{s}", "Clavicle_{s}", "UpperArm_{s}",
                 "ForeArm_{s}", "Hand_{s}"),
        sides=("L", "R"),
    ),
    Family(
        "h-anim-prefix",
        _spine("HumanoidRoot", "vl1", "vt6", "vt1", "vc4", "skullbase")
        | _limbs("{s}_hip", "{s}_knee", "{s}_ankle", "{s}_metatarsal", "{s}_sternoclavicular", "{s}_shoulder",
                 "{s}_elbow", "{s}_wrist"),
        sides=("l", "r"),
    ),
    Family(
        "rokoko",
        _spine("Hips", "Spine1", "Spine2", "Spine4", "Neck", "Head")
        | _limbs("{s}Thigh", "{s}Shin", "{s}Foot", "{s}Toe", "{s}Shoulder", "{s}Arm", "{s}ForeArm", "{s}Hand"),
        fingers=True,
    ),
    Family(
        "perception-neuron",
        _spine("Hips", "Spine", "Spine1", "Spine3", "Neck", "Head")
        | _limbs("{s}UpLeg", "{s}Leg", "{s}Foot", "", "{s}Shoulder", "{s}Arm", "{s}ForeArm", "{s}Hand"),
        fingers=True,
    ),
    Family(
        "3ds-max-biped",
        _spine("Bip01 Pelvis", "Bip01 Spine", "Bip01 Spine1", "Bip01 Spine2", "Bip01 Neck", "Bip01 Head")
        | _limbs("Bip01 {s} Thigh", "Bip01 {s} Calf", "Bip01 {s} Foot", "Bip01 {s} Toe0", "Bip01 {s} Clavicle",
                 "Bip01 {s} UpperArm", "Bip01 {s} Forearm", "Bip01 {s} Hand"),
        sides=("L", "R"),
        wrapper="Bip01",
        fingers=True,
    ),
    Family(
        "daz",
        _spine("hip", "abdomen", "", "chest", "neck", "head")
        | _limbs("{s}Thigh", "{s}Shin", "{s}Foot", "", "{s}Collar", "{s}Shldr", "{s}ForeArm", "{s}Hand"),
        sides=("l", "r"),
        spacers={"L_thigh": "lButtock", "R_thigh": "rButtock"},
        fingers=True,
        head_top="eyes",
    ),
    Family(
        "xsens-mvn",
        _spine("Pelvis", "L5", "T12", "T8", "Neck", "Head")
        | _limbs("{s}UpperLeg", "{s}LowerLeg", "{s}Foot", "{s}Toe", "{s}Shoulder", "{s}UpperArm", "{s}ForeArm",
                 "{s}Hand"),
    ),
    Family(
        "optitrack-motive",
        _spine("Skeleton_Hip", "Skeleton_Ab", "", "Skeleton_Chest", "Skeleton_Neck", "Skeleton_Head")
        | _limbs("Skeleton_{s}Thigh", "Skeleton_{s}Shin", "Skeleton_{s}Foot", "Skeleton_{s}Toe",
                 "Skeleton_{s}Shoulder", "Skeleton_{s}UArm", "Skeleton_{s}FArm", "Skeleton_{s}Hand"),
        sides=("L", "R"),
    ),
    Family(
        "unknown-names",
        {role: f"joint{i:02d}" for i, role in enumerate(ROLE_JOINT) if role != "spine_b"},
        fingers=True,
    ),
)  # fmt: skip
FAMILY = {f.name: f for f in FAMILIES}


@dataclasses.dataclass(frozen=True)
class Layout:
    """How a file is written: the rest pose, axes, units and channel order (all ours by default)."""

    a_pose_deg: float = 0.0  # arms lowered this much from the T-pose in the rest pose (OFFSETs)
    z_up: bool = False
    units_per_m: float = 1.0
    order: str = "ZXY"  # rotation channels as listed (BVH: intrinsic, in this order)
    root_order: str = "ZYX"
    six_channels: bool = False  # every joint with position channels too (holding its offset), as some exports


def reference_motion(frames: int = 150, fps: float = 60.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A smooth SMPL-22 motion: (local_rot (F, J, 3, 3), root_pos_m (F, 3)); spine2 stays straight, since
    some families have no joint there."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames)[:, None] / fps
    amplitude = np.full(22, 0.45)
    amplitude[[0, 3, 9, 12, 15]] = 0.2
    amplitude[6] = 0.0
    angles = np.zeros((frames, 22, 3))
    for j in range(22):
        freq, phase = rng.uniform(0.3, 1.0, 3), rng.uniform(0, 2 * np.pi, 3)
        angles[:, j] = amplitude[j] * np.sin(2 * np.pi * freq * t + phase)
    local_rot = Rotation.from_rotvec(angles.reshape(-1, 3)).as_matrix().reshape(frames, 22, 3, 3)
    root = np.stack([0.3 * t[:, 0], 0.95 + 0.03 * np.sin(3 * t[:, 0]), -0.2 * t[:, 0]], axis=-1)
    return local_rot, root


@dataclasses.dataclass
class _Joint:
    name: str
    parent: int
    rest_m: np.ndarray  # T-pose rest position, our axes
    driver: str  # SMPL joint whose global rotation this joint carries
    arm: str = ""  # 'L'/'R' when in an arm from the upper arm down (turned for an A-pose)


def _skeleton(family: Family) -> list[_Joint]:
    rest = REST_JOINTS_M
    joints: list[_Joint] = []

    def add(name: str, parent: int, at: np.ndarray, driver: str, arm: str = "") -> int:
        joints.append(_Joint(name, parent, np.asarray(at, dtype=float), driver, arm))
        return len(joints) - 1

    def side_name(role: str) -> str:
        side = family.sides[0] if role.startswith("L") else family.sides[1]
        return family.names[role].replace("{s}", side)

    def place(role: str, parent: int, arm: str = "") -> int:
        smpl = ROLE_JOINT[role]
        at = rest[JOINT_INDEX[smpl]]
        if family.clavicle_at_chest and role.endswith("_clavicle"):
            at = rest[JOINT_INDEX["spine3"]]
        if role in family.spacers:
            driver = joints[parent].driver
            parent = add(family.spacers[role], parent, joints[parent].rest_m, driver)
        return add(side_name(role) if role[:2] in ("L_", "R_") else family.names[role], parent, at, smpl, arm)

    top = add(family.wrapper, -1, rest[0], "pelvis") if family.wrapper else -1
    pelvis = place("pelvis", top)
    below = place("spine_a", pelvis)
    if "spine_b" in family.names:
        below = place("spine_b", below)
    chest = place("chest", below)
    neck = place("neck", chest)
    if family.neck_mid:
        neck = add(family.neck_mid, neck, (rest[12] + rest[15]) / 2, "neck")
    head = place("head", neck)
    if family.head_top == "eyes":
        for side, x in (("left", 0.035), ("right", -0.035)):
            eye = add(f"{side}Eye", head, rest[15] + [x, 0.06, 0.08], "head")
            joints.append(_Joint("", eye, rest[15] + [x, 0.06, 0.09], "end"))
    else:
        joints.append(
            _Joint(
                "HeadTop_End", head, rest[15] + [0, 0.12, 0], "head" if family.head_top == "joint" else "end"
            )
        )
    for s in "LR":
        k = place(f"{s}_thigh", pelvis)
        k = place(f"{s}_shin", k)
        foot = place(f"{s}_foot", k)
        if f"{s}_toe" in family.names:
            place(f"{s}_toe", foot)
        else:
            ball, ankle = (
                rest[JOINT_INDEX[ROLE_JOINT[f"{s}_toe"]]],
                rest[JOINT_INDEX[ROLE_JOINT[f"{s}_foot"]]],
            )
            tip = ankle + (ball - ankle) / 0.7  # the foot's end site is the toe tip, the ball 70 % of the way
            joints.append(_Joint("", foot, tip, "end"))
        k = place(f"{s}_clavicle", chest)
        k = place(f"{s}_upperarm", k, arm=s)
        k = place(f"{s}_forearm", k, arm=s)
        wrist = rest[JOINT_INDEX[ROLE_JOINT[f"{s}_hand"]]]
        if family.twist:
            elbow = joints[k].rest_m
            k = add(
                f"lowerarm_twist_01_{family.sides['LR'.index(s)]}",
                k,
                (elbow + wrist) / 2,
                joints[k].driver,
                s,
            )
        hand = place(f"{s}_hand", k, arm=s)
        if family.fingers:
            out = np.sign(wrist[0])
            for _f, (dz, name) in enumerate(((0.03, "Thumb"), (0.0, "Index"), (-0.02, "Ring"))):
                base = add(
                    f"{side_name(f'{s}_hand')}{name}1",
                    hand,
                    wrist + np.array([out * 0.08, 0, dz]),
                    f"{s}_finger",
                    s,
                )
                add(
                    f"{side_name(f'{s}_hand')}{name}2",
                    base,
                    wrist + np.array([out * 0.11, 0, dz]),
                    f"{s}_finger",
                    s,
                )
    for joint in joints:
        if joint.driver == "end":
            joint.name, joint.driver = "", joints[joint.parent].driver
        elif joint.driver.endswith("_finger"):
            joint.driver = "left_wrist" if joint.driver[0] == "L" else "right_wrist"
    return joints


def _a_pose_turn(side: str, degrees: float) -> np.ndarray:
    sign = -1.0 if side == "L" else 1.0  # the left arm (+x) turns down about -z
    return Rotation.from_rotvec([0, 0, sign * np.radians(degrees)]).as_matrix()


def write_family_bvh(
    family: Family, layout: Layout, local_rot: np.ndarray, root_m: np.ndarray, fps: float
) -> str:
    """BVH text of the reference motion on ``family``'s rig written as ``layout`` says."""
    joints = _skeleton(family)
    pos_m, global_rot = forward_kinematics(local_rot, root_m, rest_offsets())
    shoulder = {s: REST_JOINTS_M[JOINT_INDEX[f"{w}_shoulder"]] for s, w in (("L", "left"), ("R", "right"))}
    turn = {s: _a_pose_turn(s, layout.a_pose_deg) for s in "LR"}
    rest_a = [
        j.rest_m if not j.arm else shoulder[j.arm] + turn[j.arm] @ (j.rest_m - shoulder[j.arm])
        for j in joints
    ]
    pre = [turn[j.arm] if j.arm else np.eye(3) for j in joints]  # each joint's rest frame against the T-pose
    world = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]) if layout.z_up else np.eye(3)  # file from ours
    frames = len(local_rot)
    g = np.stack([global_rot[:, JOINT_INDEX[j.driver]] @ pre[k].T for k, j in enumerate(joints)], axis=1)
    g = world @ g @ world.T
    lines = ["HIERARCHY"]
    columns: list[np.ndarray] = []
    children = [[k for k, c in enumerate(joints) if c.parent == p] for p in range(len(joints))]

    def emit(k: int, depth: int) -> None:
        j, pad = joints[k], "  " * depth
        offset = rest_a[k] - (rest_a[j.parent] if j.parent >= 0 else 0 * rest_a[k])
        offset = world @ offset * layout.units_per_m
        if j.parent < 0:
            offset = np.zeros(3)
        if not j.name:
            lines.extend(
                [
                    f"{pad}End Site",
                    pad + "{",
                    f"{pad}  OFFSET {offset[0]:.6f} {offset[1]:.6f} {offset[2]:.6f}",
                    pad + "}",
                ]
            )
            return
        lines.append(f"{pad}{'ROOT' if j.parent < 0 else 'JOINT'} {j.name}")
        lines.append(pad + "{")
        lines.append(f"{pad}  OFFSET {offset[0]:.6f} {offset[1]:.6f} {offset[2]:.6f}")
        local = g[:, k] if j.parent < 0 else np.swapaxes(g[:, j.parent], -1, -2) @ g[:, k]
        order = layout.root_order if j.parent < 0 else layout.order
        euler = Rotation.from_matrix(local).as_euler(order, degrees=True)
        rot_chans = " ".join(f"{axis}rotation" for axis in order)
        if j.parent < 0:
            lines.append(f"{pad}  CHANNELS 6 Xposition Yposition Zposition {rot_chans}")
            columns.append((pos_m[:, 0] @ world.T) * layout.units_per_m)
        elif layout.six_channels:
            lines.append(f"{pad}  CHANNELS 6 Xposition Yposition Zposition {rot_chans}")
            columns.append(np.broadcast_to(offset, (frames, 3)))
        else:
            lines.append(f"{pad}  CHANNELS 3 {rot_chans}")
        columns.append(euler)
        for child in children[k]:
            emit(child, depth + 1)
        lines.append(pad + "}")

    emit(0, 0)
    table = np.concatenate(columns, axis=1)
    lines += ["MOTION", f"Frames: {frames}", f"Frame Time: {1.0 / fps:.8f}"]
    lines += [" ".join(f"{v:.6f}" for v in row) for row in table]
    return "\n".join(lines) + "\n"
