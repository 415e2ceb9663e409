"""The web viewer's default avatar: a mannequin written as a VRM 1.0 file (glTF 2.0 binary + ``VRMC_vrm``).

Made here, from the SMPL rest skeleton (``model/skeleton.py``), so the project can ship it under CC0: one bone
per SMPL joint (the humanoid bones of VRM), rigid capsules skinned to the bone they ride on (limbs left orange,
right blue, the rest grey, as the capsule view colours them), a head, hands and feet. It stands in a T-pose
facing +Z with every bone at rest identity rotation, the feet on y = 0, which is VRM 1.0's rest pose and SMPL's.

``python -m egoposevr.clients.avatar OUT.vrm`` writes it; the same code gives the same bytes every time
(``tests/clients/test_avatar.py`` checks the bundled file against a fresh one).
"""

from __future__ import annotations

import json
import struct
import sys
from pathlib import Path
from typing import Any, Final

import numpy as np

from egoposevr.model.skeleton import FOOT_JOINT_HEIGHT_M, PARENTS, REST_JOINTS_M

# VRM 1.0 humanoid bone of each SMPL joint (PROTOCOL.md §3 order).
VRM_BONES: Final = (
    "hips", "leftUpperLeg", "rightUpperLeg", "spine", "leftLowerLeg", "rightLowerLeg", "chest", "leftFoot",
    "rightFoot", "upperChest", "leftToes", "rightToes", "neck", "leftShoulder", "rightShoulder", "head",
    "leftUpperArm", "rightUpperArm", "leftLowerArm", "rightLowerArm", "leftHand", "rightHand",
)  # fmt: skip
HIPS_HEIGHT_M: Final = float(-REST_JOINTS_M[:, 1].min() + FOOT_JOINT_HEIGHT_M)  # feet on the floor
LEFT: Final = frozenset({1, 4, 7, 10, 13, 16, 18, 20})
RIGHT: Final = frozenset({2, 5, 8, 11, 14, 17, 19, 21})
COLOURS: Final = {"centre": (0.85, 0.85, 0.85), "left": (1.0, 0.55, 0.24), "right": (0.24, 0.63, 1.0)}
SIDES: Final = 12  # faces around a capsule

# (from joint, to joint, radius m): a capsule between two rest joints, riding on the bone of `from`.
SEGMENTS: Final = (
    (0, 3, 0.11), (0, 1, 0.075), (0, 2, 0.075), (3, 6, 0.12), (6, 9, 0.13), (9, 12, 0.07), (12, 15, 0.05),
    (9, 13, 0.06), (9, 14, 0.06), (13, 16, 0.05), (14, 17, 0.05), (1, 4, 0.07), (2, 5, 0.07),
    (4, 7, 0.05), (5, 8, 0.05), (7, 10, 0.04), (8, 11, 0.04), (16, 18, 0.045), (17, 19, 0.045),
    (18, 20, 0.036), (19, 21, 0.036),
)  # fmt: skip


def rest_positions_m() -> np.ndarray:
    """(22, 3) world positions of the joints in the avatar's rest pose (feet on y = 0)."""
    return REST_JOINTS_M + np.array([0.0, HIPS_HEIGHT_M, 0.0])


def _side(joint: int) -> str:
    return "left" if joint in LEFT else "right" if joint in RIGHT else "centre"


def _capsule(a: np.ndarray, b: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(positions (V, 3), normals (V, 3), triangles (T, 3)) of a closed tube from a to b with rounded ends."""
    axis = b - a
    length = float(np.linalg.norm(axis))
    w = axis / length
    u = np.cross(w, [0.0, 0.0, 1.0] if abs(w[2]) < 0.9 else [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(w, u)
    angles = np.linspace(0.0, 2 * np.pi, SIDES, endpoint=False)
    ring = np.cos(angles)[:, None] * u + np.sin(angles)[:, None] * v  # (SIDES, 3) unit directions
    # Rings (position along the axis in m, radius factor): two rounding rings at each end, the tube between.
    cap = ((0.7, 0.7), (0.35, 0.94))
    rows = [(-radius * d, f) for d, f in cap] + [(0.0, 1.0), (length, 1.0)]
    rows += [(length + radius * d, f) for d, f in reversed(cap)]
    positions, normals = [], []
    for along, factor in rows:
        bulge = min(along, 0.0) + max(along - length, 0.0)  # how far past an end, m
        positions.append(a + w * along + ring * radius * factor)
        normals.append(ring * factor + w * bulge / radius)
    positions.append([a - w * radius, b + w * radius])
    normals.append([-w, w])
    pos = np.concatenate(positions)
    nrm = np.concatenate(normals)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    triangles = []
    for r in range(len(rows) - 1):
        for k in range(SIDES):
            i0, i1 = r * SIDES + k, r * SIDES + (k + 1) % SIDES
            triangles += [(i0, i1, i1 + SIDES), (i0, i1 + SIDES, i0 + SIDES)]
    bottom, top, last = len(rows) * SIDES, len(rows) * SIDES + 1, (len(rows) - 1) * SIDES
    for k in range(SIDES):
        triangles += [(bottom, (k + 1) % SIDES, k), (top, last + k, last + (k + 1) % SIDES)]
    return pos, nrm, np.array(triangles)


def _parts() -> list[tuple[int, str, np.ndarray, np.ndarray, np.ndarray]]:
    """(bone, side, positions, normals, triangles) of every body part, in rest-pose world coordinates."""
    rest = rest_positions_m()
    parts = [(f, _side(t), *_capsule(rest[f], rest[t], r)) for f, t, r in SEGMENTS]
    head = rest[15] + [0.0, 0.09, 0.01]
    crown = np.array([0.0, 0.04, 0.0])
    parts.append((15, "centre", *_capsule(head - crown, head + crown, 0.1)))
    for wrist, elbow in ((20, 18), (21, 19)):
        direction = (rest[wrist] - rest[elbow]) / np.linalg.norm(rest[wrist] - rest[elbow])
        parts.append((wrist, _side(wrist), *_capsule(rest[wrist], rest[wrist] + 0.12 * direction, 0.035)))
    return parts


class _Buffer:
    """The GLB's binary chunk and the accessors/bufferViews that describe it."""

    def __init__(self) -> None:
        self.data = bytearray()
        self.views: list[dict[str, Any]] = []
        self.accessors: list[dict[str, Any]] = []

    def add(self, array: np.ndarray, kind: str, component: int, target: int | None = None) -> int:
        while len(self.data) % 4:
            self.data.append(0)
        view = {"buffer": 0, "byteOffset": len(self.data), "byteLength": array.nbytes}
        if target is not None:
            view["target"] = target
        self.data += array.tobytes()
        self.views.append(view)
        accessor: dict[str, Any] = {
            "bufferView": len(self.views) - 1, "componentType": component, "count": len(array), "type": kind,
        }  # fmt: skip
        if kind == "VEC3" and component == 5126:
            accessor["min"] = [float(x) for x in array.min(axis=0)]  # float32 values, exactly
            accessor["max"] = [float(x) for x in array.max(axis=0)]
        self.accessors.append(accessor)
        return len(self.accessors) - 1


def _primitive(buffer: _Buffer, parts: list, material: int) -> dict[str, Any]:
    positions, normals, joints, triangles = [], [], [], []
    offset = 0
    for bone, _, pos, nrm, tri in parts:
        positions.append(pos)
        normals.append(nrm)
        joints.append(np.full(len(pos), bone))
        triangles.append(tri + offset)
        offset += len(pos)
    count = offset
    joint_ids = np.zeros((count, 4), np.uint16)
    joint_ids[:, 0] = np.concatenate(joints)
    weights = np.zeros((count, 4), np.float32)
    weights[:, 0] = 1.0  # rigid: each vertex rides on one bone
    return {
        "attributes": {
            "POSITION": buffer.add(np.concatenate(positions).astype(np.float32), "VEC3", 5126, 34962),
            "NORMAL": buffer.add(np.concatenate(normals).astype(np.float32), "VEC3", 5126, 34962),
            "JOINTS_0": buffer.add(joint_ids, "VEC4", 5123, 34962),
            "WEIGHTS_0": buffer.add(weights, "VEC4", 5126, 34962),
        },
        "indices": buffer.add(np.concatenate(triangles).astype(np.uint16).ravel(), "SCALAR", 5123, 34963),
        "material": material,
    }


def _vrm_extension(bone_nodes: list[int]) -> dict[str, Any]:
    return {
        "specVersion": "1.0",
        "meta": {
            "name": "EgoPoseVR mannequin",
            "version": "1",
            "authors": ["EgoPoseVR"],
            # VRM 1.0 names its own licence here (every permission granted below); the file is CC0 besides.
            "licenseUrl": "https://vrm.dev/licenses/1.0/",
            "otherLicenseUrl": "https://creativecommons.org/publicdomain/zero/1.0/",
            "avatarPermission": "everyone",
            "commercialUsage": "corporation",
            "creditNotation": "unnecessary",
            "allowRedistribution": True,
            "modification": "allowModificationRedistribution",
        },
        "humanoid": {
            "humanBones": {name: {"node": node} for name, node in zip(VRM_BONES, bone_nodes, strict=True)}
        },
    }


def mannequin_vrm() -> bytes:
    """The default avatar as the bytes of a .vrm (GLB) file."""
    rest = rest_positions_m()
    first_bone = 1  # node 0: the skinned mesh (a root, as glTF wants), nodes 1..22: the bones
    bone_nodes = [first_bone + j for j in range(22)]
    nodes: list[dict[str, Any]] = [{"name": "Body", "mesh": 0, "skin": 0}]
    for j in range(22):
        parent = PARENTS[j]
        offset = rest[j] - (rest[parent] if parent >= 0 else 0.0)
        node: dict[str, Any] = {"name": VRM_BONES[j], "translation": [round(float(x), 6) for x in offset]}
        children = [first_bone + c for c in range(22) if PARENTS[c] == j]
        if children:
            node["children"] = children
        nodes.append(node)
    buffer = _Buffer()
    by_side = {side: [p for p in _parts() if p[1] == side] for side in COLOURS}
    primitives = [_primitive(buffer, by_side[side], k) for k, side in enumerate(COLOURS)]
    inverse_bind = np.tile(np.eye(4, dtype=np.float32), (22, 1, 1))
    inverse_bind[:, 3, :3] = -rest.astype(np.float32)  # column-major: the translation is the last column
    gltf = {
        "asset": {"version": "2.0", "generator": "egoposevr.clients.avatar"},
        "extensionsUsed": ["VRMC_vrm"],
        "extensions": {"VRMC_vrm": _vrm_extension(bone_nodes)},
        "scene": 0,
        "scenes": [{"nodes": [0, first_bone]}],
        "nodes": nodes,
        "meshes": [{"name": "Body", "primitives": primitives}],
        "skins": [
            {
                "joints": bone_nodes,
                "skeleton": first_bone,
                "inverseBindMatrices": buffer.add(inverse_bind, "MAT4", 5126),
            }
        ],
        "materials": [_material(side, rgb) for side, rgb in COLOURS.items()],
        "bufferViews": buffer.views,
        "accessors": buffer.accessors,
        "buffers": [{"byteLength": len(buffer.data)}],
    }
    return _glb(json.dumps(gltf, separators=(",", ":")).encode(), bytes(buffer.data))


def _material(name: str, rgb: tuple[float, float, float]) -> dict[str, Any]:
    return {
        "name": name,
        "pbrMetallicRoughness": {
            "baseColorFactor": [*rgb, 1.0],
            "metallicFactor": 0.0,
            "roughnessFactor": 0.6,
        },
    }


def _glb(json_chunk: bytes, bin_chunk: bytes) -> bytes:
    json_chunk += b" " * (-len(json_chunk) % 4)
    bin_chunk += b"\0" * (-len(bin_chunk) % 4)
    total = 12 + 8 + len(json_chunk) + 8 + len(bin_chunk)
    return b"".join([
        struct.pack("<4sII", b"glTF", 2, total),
        struct.pack("<I4s", len(json_chunk), b"JSON"), json_chunk,
        struct.pack("<I4s", len(bin_chunk), b"BIN\0"), bin_chunk,
    ])  # fmt: skip


if __name__ == "__main__":
    Path(sys.argv[1] if len(sys.argv) > 1 else "mannequin.vrm").write_bytes(mannequin_vrm())
