"""A small body bank made of tubes, for tests that must not need anny: each bone is a hexagonal tube from its
joint to its child, skinned to the joint, standing in an A-pose (arms 40° down), so the rest alignment has
something to undo."""

import numpy as np
from scipy.spatial.transform import Rotation

from egoposevr.model.skeleton import NUM_JOINTS, PARENTS, REST_JOINTS_M
from egoposevr.model.synth import bodies
from egoposevr.model.synth.bodies import BodyBank

SIDES = 6
ARM_DROP_DEG = 40.0
JOINT_REGION = {
    0: bodies.REGION_HIPS, 1: bodies.REGION_THIGH, 2: bodies.REGION_THIGH, 3: bodies.REGION_TORSO,
    4: bodies.REGION_SHIN, 5: bodies.REGION_SHIN, 6: bodies.REGION_TORSO, 7: bodies.REGION_FOOT,
    8: bodies.REGION_FOOT, 9: bodies.REGION_TORSO, 12: bodies.REGION_NECK, 13: bodies.REGION_TORSO,
    14: bodies.REGION_TORSO, 16: bodies.REGION_UPPER_ARM, 17: bodies.REGION_UPPER_ARM,
    18: bodies.REGION_FOREARM, 19: bodies.REGION_FOREARM, 20: bodies.REGION_HAND, 21: bodies.REGION_HAND,
    15: bodies.REGION_SCALP,
}  # fmt: skip


def a_pose_joints(scale: float) -> np.ndarray:
    """(J, 3) SMPL's rest joints scaled, feet on the floor, arms turned down about the shoulders."""
    joints = REST_JOINTS_M * scale
    for shoulder, sign in ((16, 1.0), (17, -1.0)):
        turn = Rotation.from_euler("z", -sign * ARM_DROP_DEG, degrees=True).as_matrix()
        arm = [shoulder, shoulder + 2, shoulder + 4]
        joints[arm] = joints[shoulder] + (joints[arm] - joints[shoulder]) @ turn.T
    joints[:, 1] -= joints[:, 1].min() - 0.03
    return joints


def _tube(a: np.ndarray, b: np.ndarray, radius: float) -> np.ndarray:
    """(2 * SIDES, 3) ring vertices around segment a -> b."""
    axis = (b - a) / np.linalg.norm(b - a)
    side = np.cross(axis, [0.0, 0.0, 1.0] if abs(axis[2]) < 0.9 else [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    up = np.cross(axis, side)
    angles = np.arange(SIDES) * 2 * np.pi / SIDES
    ring = radius * (np.cos(angles)[:, None] * side + np.sin(angles)[:, None] * up)
    return np.concatenate([a + ring, b + ring])


def tube_bank(scales=(1.0, 1.1)) -> BodyBank:
    vertices, faces, skin, region = [], [], [], []
    rest = [a_pose_joints(s) for s in scales]
    for child in range(1, NUM_JOINTS):
        joint = int(PARENTS[child])
        start = len(vertices[0]) if vertices else 0
        for b, joints in enumerate(rest):
            ring = _tube(joints[joint], joints[child], 0.05 * scales[b])
            if b == len(vertices):
                vertices.append([])
            vertices[b].extend(ring)
        skin += [joint] * (2 * SIDES)
        for k in range(SIDES):
            n = (k + 1) % SIDES
            quad = (start + k, start + n, start + SIDES + n, start + SIDES + k)
            faces += [(quad[0], quad[1], quad[2]), (quad[0], quad[2], quad[3])]
            region += [JOINT_REGION.get(joint, bodies.REGION_TORSO)] * 2
    count = len(skin)
    skin_joint = np.zeros((count, bodies.SKIN_SLOTS), dtype=np.int32)
    skin_joint[:, 0] = skin
    skin_weight = np.zeros((count, bodies.SKIN_SLOTS), dtype=np.float32)
    skin_weight[:, 0] = 1.0
    eyes = [joints[15] + [0.0, 0.03 * s, 0.08 * s] for joints, s in zip(rest, scales, strict=True)]
    return BodyBank(
        faces=np.array(faces, dtype=np.int32), region=np.array(region, dtype=np.uint8), skin_joint=skin_joint,
        skin_weight=skin_weight, rest_vertices=np.array(vertices, dtype=np.float32), rest_joints=np.array(rest),
        align=np.stack([bodies.rest_alignment(j) for j in rest]), eyes_m=np.array(eyes),
        phenotype=np.array(scales)[:, None], phenotype_names=("scale",), source="tubes (tests)",
    )  # fmt: skip
