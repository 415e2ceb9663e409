"""The viewer's default avatar: the bundled file is what clients/avatar.py writes, and it is a VRM 1.0 humanoid
whose bones rest where the SMPL rest skeleton's joints are, feet on the floor."""

from __future__ import annotations

import json
import struct

import numpy as np

from egoposevr.clients.avatar import VRM_BONES, mannequin_vrm, rest_positions_m
from egoposevr.model.skeleton import PARENTS
from egoposevr.server.app import VIEWER_DIR


def _gltf(glb: bytes) -> tuple[dict, bytes]:
    magic, version, total = struct.unpack("<4sII", glb[:12])
    assert (magic, version, total) == (b"glTF", 2, len(glb))
    json_length = struct.unpack("<I", glb[12:16])[0]
    return json.loads(glb[20 : 20 + json_length]), glb[28 + json_length :]


def test_bundled_mannequin_is_what_the_generator_writes() -> None:
    assert (VIEWER_DIR / "avatar" / "mannequin.vrm").read_bytes() == mannequin_vrm()


def test_mannequin_is_a_vrm_humanoid_on_the_smpl_rest_skeleton() -> None:
    gltf, _ = _gltf(mannequin_vrm())
    humanoid = gltf["extensions"]["VRMC_vrm"]["humanoid"]["humanBones"]
    assert list(humanoid) == list(VRM_BONES)
    nodes = gltf["nodes"]
    world = {}
    for j, bone in enumerate(VRM_BONES):  # parents come first in SMPL order
        offset = np.array(nodes[humanoid[bone]["node"]]["translation"])
        world[j] = offset + (world[PARENTS[j]] if PARENTS[j] >= 0 else 0.0)
        assert "rotation" not in nodes[humanoid[bone]["node"]]  # VRM 1.0 rest: identity rotations
    np.testing.assert_allclose(np.array([world[j] for j in range(22)]), rest_positions_m(), atol=1e-6)
    assert 0.02 < min(world[j][1] for j in (10, 11)) < 0.05  # the balls of the feet just above the floor
    skin = gltf["skins"][0]
    assert skin["joints"] == [humanoid[bone]["node"] for bone in VRM_BONES]
