"""From OpenXR space locations to an ``hmd`` message (PROTOCOL.md §3.3). Pure Python: no numpy, no I/O.

What the protocol's three device poses are, in OpenXR's terms:

- ``head``: the VIEW reference space (between the eyes, looking along −Z, +Y up) located in the app's STAGE or
  LOCAL_FLOOR space, as it is.
- ``left``/``right``: ``/user/hand/<hand>/input/grip/pose`` located in the same space, its orientation turned
  a quarter turn about its own Z axis (left +90°, right −90°), so that +Y leaves the back of the hand. The
  grip's own −Z (little finger to thumb) and its position (the palm) are kept.
- ``valid``: a device's POSITION_VALID and ORIENTATION_VALID bits both set (TRACKED is not needed: the
  runtime's inferred pose beats none). Orientation-only tracking (no POSITION_VALID) counts as untracked.

Quaternions are ``[x, y, z, w]``; poses ``[px, py, pz, qx, qy, qz, qw]``.
"""

from __future__ import annotations

import math
from typing import Final, Literal

from .messages import Hmd

# XrSpaceLocationFlagBits
ORIENTATION_VALID: Final = 0x1
POSITION_VALID: Final = 0x2
ORIENTATION_TRACKED: Final = 0x4
POSITION_TRACKED: Final = 0x8

_HALF: Final = math.sqrt(0.5)
# grip frame -> the protocol's controller frame: a quarter turn about the grip's Z axis. The grip's +X leaves
# the palm of the left hand and the back of the right (OpenXR, WebXR), so the turn takes -X (left) and +X
# (right) onto +Y: out of the back of the hand.
GRIP_TO_CONTROLLER: Final = {"left": (0.0, 0.0, _HALF, _HALF), "right": (0.0, 0.0, -_HALF, _HALF)}
UNTRACKED_POSE: Final = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)  # what to send for an untracked device (ignored)


def quat_multiply(a: tuple[float, ...] | list[float], b: tuple[float, ...] | list[float]) -> list[float]:
    """Hamilton product ``a ⊗ b`` of two [x, y, z, w] quaternions (b's rotation applied first, in a's frame)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return [
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ]


def is_valid(location_flags: int) -> bool:
    """The protocol's ``valid`` for one device from its XrSpaceLocation.locationFlags."""
    wanted = POSITION_VALID | ORIENTATION_VALID
    return location_flags & wanted == wanted


def controller_pose(grip_pose: list[float], hand: Literal["left", "right"]) -> list[float]:
    """The protocol's controller pose from the grip pose [px, py, pz, qx, qy, qz, qw] of ``hand``."""
    return [*grip_pose[:3], *quat_multiply(grip_pose[3:], GRIP_TO_CONTROLLER[hand])]


def hmd_from_openxr(
    seq: int,
    t_us: int,
    view: tuple[list[float], int],
    left_grip: tuple[list[float], int],
    right_grip: tuple[list[float], int],
) -> Hmd:
    """An ``hmd`` message from three (pose, locationFlags) pairs: the VIEW space and the two grip poses."""
    (head, head_flags), (left, left_flags), (right, right_flags) = view, left_grip, right_grip
    valid = [is_valid(head_flags), is_valid(left_flags), is_valid(right_flags)]
    return Hmd(
        seq=seq,
        t_us=t_us,
        head=list(head) if valid[0] else list(UNTRACKED_POSE),
        left=controller_pose(left, "left") if valid[1] else list(UNTRACKED_POSE),
        right=controller_pose(right, "right") if valid[2] else list(UNTRACKED_POSE),
        valid=valid,
    )
