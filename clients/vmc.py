"""VMC protocol bridge: poses as OSC bundles that VSeeFace, Warudo, VNyan and EVMC4U avatars follow.

VMC (Virtual Motion Capture protocol) sends, over UDP/OSC:
- ``/VMC/Ext/OK 1`` (a model is loaded) and ``/VMC/Ext/T <s>`` (time);
- ``/VMC/Ext/Root/Pos "root" px py pz qx qy qz qw``: the avatar root, here the identity at the origin;
- ``/VMC/Ext/Bone/Pos <HumanBodyBones name> px py pz qx qy qz qw`` per bone: its **local** rotation (and
  local position) in Unity's frame, as the performer applications send them. ``Hips`` carries the pelvis'
  world position and rotation, so the avatar walks around the room.

Frames. Unity is left-handed: x right, y up, z forward. The world conversion mirrors z (PROTOCOL.md §3.1).
A bone's own frame converts differently: SMPL joint frames are x to the subject's left, y up, z forward,
Unity humanoid bones x to the subject's right, y up, z forward, so bone frames mirror x. A local rotation R
(parent frame <- joint frame) becomes ``P R P`` with P = diag(-1, 1, 1); the pelvis' global rotation
(world <- pelvis frame) becomes ``M R P`` with M = diag(1, 1, -1). Both are proper rotations. SMPL's rest
pose and a normalised humanoid's (VRM, Unity Humanoid) are both T-poses with identity local rotations, so
the converted rotations apply to the avatar's normalised bones directly.

Each UDP datagram is one OSC bundle of at most ``MAX_DATAGRAM_BYTES`` (1500, one Ethernet MTU), so nothing is
fragmented; a pose takes two bundles.

Shape legend: ``J`` = 22 joints.
"""

from __future__ import annotations

import asyncio
import socket
import time
from typing import Any, Final

import numpy as np
from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
from pythonosc.osc_message_builder import OscMessageBuilder
from scipy.spatial.transform import Rotation
from websockets.asyncio.client import connect

from ..model.skeleton import NUM_JOINTS, rest_offsets, smpl_to_local_rot
from ..protocol import Hello, encode
from . import read_server_message, session_url

# Unity HumanBodyBones names in SMPL joint order.
UNITY_BONES: Final = (
    "Hips", "LeftUpperLeg", "RightUpperLeg", "Spine", "LeftLowerLeg", "RightLowerLeg", "Chest", "LeftFoot",
    "RightFoot", "UpperChest", "LeftToes", "RightToes", "Neck", "LeftShoulder", "RightShoulder", "Head",
    "LeftUpperArm", "RightUpperArm", "LeftLowerArm", "RightLowerArm", "LeftHand", "RightHand",
)  # fmt: skip
MAX_DATAGRAM_BYTES: Final = 1500
WORLD_TO_UNITY: Final = np.diag([1.0, 1.0, -1.0])  # M: OpenXR world -> Unity world
JOINT_TO_UNITY: Final = np.diag([-1.0, 1.0, 1.0])  # P: SMPL joint frame -> Unity humanoid bone frame
_REST_LOCAL_POS: Final = rest_offsets() @ JOINT_TO_UNITY  # (J, 3) bone offsets in Unity bone frames


def unity_bones(
    global_orient: np.ndarray, body_pose: np.ndarray, transl: np.ndarray
) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """SMPL pose -> [(bone name, local position (3,), local rotation quaternion xyzw (4,))] in Unity frames.

    ``Hips`` gets the pelvis' world position and rotation (mirrored into Unity's world)."""
    local = smpl_to_local_rot(np.asarray(global_orient, float), np.asarray(body_pose, float))  # (J, 3, 3)
    unity = JOINT_TO_UNITY @ local @ JOINT_TO_UNITY
    unity[0] = WORLD_TO_UNITY @ local[0] @ JOINT_TO_UNITY
    quats = Rotation.from_matrix(unity).as_quat()  # (J, 4) xyzw
    positions = _REST_LOCAL_POS.copy()
    positions[0] = WORLD_TO_UNITY @ np.asarray(transl, float)
    return [(UNITY_BONES[j], positions[j], quats[j]) for j in range(NUM_JOINTS)]


def _message(address: str, *args: Any) -> Any:
    builder = OscMessageBuilder(address=address)
    for arg in args:
        builder.add_arg(arg, "s" if isinstance(arg, str) else "i" if isinstance(arg, int) else "f")
    return builder.build()


def vmc_bundles(
    global_orient: np.ndarray, body_pose: np.ndarray, transl: np.ndarray, t_s: float
) -> list[bytes]:
    """One pose -> OSC bundles (bytes), each at most MAX_DATAGRAM_BYTES."""
    messages = [_message("/VMC/Ext/OK", 1), _message("/VMC/Ext/T", float(t_s)),
                _message("/VMC/Ext/Root/Pos", "root", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)]  # fmt: skip
    for name, pos, quat in unity_bones(global_orient, body_pose, transl):
        messages.append(_message("/VMC/Ext/Bone/Pos", name, *map(float, pos), *map(float, quat)))
    bundles, current, size = [], [], 16  # "#bundle\0" + time tag
    for msg in messages:
        if current and size + 4 + msg.size > MAX_DATAGRAM_BYTES:
            bundles.append(_bundle(current))
            current, size = [], 16
        current.append(msg)
        size += 4 + msg.size  # each element is prefixed by its length
    bundles.append(_bundle(current))
    return bundles


def _bundle(messages: list[Any]) -> bytes:
    builder = OscBundleBuilder(IMMEDIATELY)
    for msg in messages:
        builder.add_content(msg)
    return builder.build().dgram


async def bridge(url: str, session: str, to: tuple[str, int], seconds: float | None = None) -> dict[str, int]:
    """Join ``session`` as a viewer and forward every pose to ``to`` (host, port) as VMC bundles."""
    counts = {"poses": 0, "bundles": 0, "bytes": 0}
    started = time.perf_counter()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
        async with connect(session_url(url, session), compression=None, max_size=None) as ws:
            await ws.send(encode(Hello(role="render", session=session, client="egoposevr bridge vmc")))
            while seconds is None or (left := seconds - (time.perf_counter() - started)) > 0:
                try:
                    data = await asyncio.wait_for(ws.recv(), None if seconds is None else left)
                except TimeoutError:
                    break
                msg = read_server_message(data, counts)
                if msg is None:
                    continue
                if msg.type == "error" and msg.fatal:
                    raise RuntimeError(f"the server refused the viewer: {msg.code}: {msg.message}")
                if msg.type != "pose":
                    continue
                for dgram in vmc_bundles(msg.global_orient, msg.body_pose, msg.transl, msg.t_us * 1e-6):
                    udp.sendto(dgram, to)
                    counts["bundles"] += 1
                    counts["bytes"] += len(dgram)
                counts["poses"] += 1
    return counts
