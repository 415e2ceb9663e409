"""Network inputs, shared by training and the runtime so that both see exactly the same numbers.

- **Heading frame.** Windows are expressed relative to the newest headset sample: origin on the floor under
  the headset, axes turned by the headset's yaw (its twist about world +y). Height, pitch and roll stay
  absolute, so crouching still reads as crouching, but walking north or east looks the same to the nets.
- **Images.** RGB-D frames are resized to the visual encoder's input (any client resolution works; keypoints
  come back as normalised image coordinates and are lifted with the frame's own intrinsics).
- **Visual tokens.** Cached keypoints (world frame, one row per camera frame) become per-frame tokens in the
  heading frame of the newest headset sample: ``[joints 22x3, confidence 22, present 1, age_s 1]``.
- **Mirrored inputs.** The world reflected through the heading frame's x = 0 plane, left and right swapped,
  is a person too (training mirrors whole sequences, training/augment.py): ``hmd[..., HMD_MIRROR_ORDER] *
  HMD_MIRROR_SIGNS`` and ``tokens[..., VISUAL_MIRROR_ORDER] * VISUAL_MIRROR_SIGNS`` are that person's inputs,
  and ``sixd[..., MIRROR_JOINTS, :] * SIXD_MIRROR_SIGNS`` turns their joints' rotations back into this one's.
  A reflection M = diag(-1, 1, 1) turns a rotation R into M R M; the two 6D columns of M R M are the
  columns' of R with SIXD_MIRROR_SIGNS, whichever frame the rotation is in.

Shape legend: ``T`` HMD window, ``Tv`` visual window, ``J`` = 22 joints, ``K`` camera frames, ``...`` batch.
"""

from __future__ import annotations

from typing import Final

import cv2
import numpy as np

from ..protocol.errors import InputError
from .hmd import FEATURE_DIM, VALIDITY_DIM
from .rotations import quat_xyzw_to_matrix
from .runtime.filters import OneEuroFilter
from .skeleton import MIRROR_JOINTS, NUM_JOINTS

VISUAL_TOKEN_DIM: Final = NUM_JOINTS * 4 + 2
X_MIRROR_SIGNS: Final = np.array([-1.0, 1.0, 1.0])  # a vector reflected through x = 0
SIXD_MIRROR_SIGNS: Final = np.array([1.0, -1.0, -1.0, -1.0, 1.0, 1.0])  # rot6d of M R M from R's
DEPTH_SCALE_M: Final = 2.0  # depth channel = metres / 2: the body sits 0.3-2 m from the camera
MAX_FRAME_AGE_S: Final = 0.5  # camera frames older than this leave the visual window
VISIBILITY_THRESHOLD: Final = 0.5
# Alg. 1's One Euro filter on ζ (a probability per joint, ~30 Hz): steady unless ζ moves fast.
ZETA_MIN_CUTOFF_HZ: Final = 1.5
ZETA_BETA: Final = 1.0


def heading_frame(head_pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Headset poses (..., 7) -> yaw rotation (..., 3, 3) world-from-heading and origin (..., 3) on the floor.

    Yaw is the twist of the orientation about +y (2·atan2(qy, qw)), which stays defined when looking down.
    """
    head_pose = np.asarray(head_pose, dtype=np.float64)
    yaw = 2.0 * np.arctan2(head_pose[..., 4], head_pose[..., 6])
    c, s = np.cos(yaw), np.sin(yaw)
    zero, one = np.zeros_like(c), np.ones_like(c)
    rot = np.stack([c, zero, s, zero, one, zero, -s, zero, c], axis=-1).reshape(*yaw.shape, 3, 3)
    origin = np.stack([head_pose[..., 0], zero, head_pose[..., 2]], axis=-1)
    return rot, origin


def to_heading(points: np.ndarray, rot: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """World points (..., N, 3) -> heading frame, for frames rot (..., 3, 3), origin (..., 3)."""
    return (points - origin[..., None, :]) @ rot


def canonicalize_hmd(window: np.ndarray, rot: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """HMD features (..., T, 72 [+ tracking state]) in the world -> heading frame (rot (..., 3, 3), origin
    (..., 3)); float32.

    Per device the first 12 numbers are four world vectors — position, the two 6D columns, linear velocity —
    so they turn together; the position also moves to the origin. Angular velocity (body frame), the
    controllers' head-relative descriptors and the tracking state after x_t do not depend on the world frame.
    """
    if window.shape[-1] not in (FEATURE_DIM, FEATURE_DIM + VALIDITY_DIM):
        raise ValueError(f"window must be (..., T, {FEATURE_DIM} [+ {VALIDITY_DIM}]), got {window.shape}")
    out = np.array(window, dtype=np.float64)
    for base in (0, 18, 36):
        vectors = out[..., base : base + 12].reshape(*out.shape[:-1], 4, 3)
        vectors[..., 0, :] -= origin[..., None, :]
        out[..., base : base + 12] = (vectors @ rot[..., None, :, :]).reshape(*out.shape[:-1], 12)
    return out.astype(np.float32)


def encoded_image_size(data: bytes) -> tuple[int, int]:
    """(width, height) from a JPEG's frame header or a PNG's IHDR, without decoding the pixels.

    Decoding first would let a few bytes claiming 60 000 × 60 000 pixels allocate gigabytes. Raises ValueError
    for data that is neither or whose header is cut short.
    """
    if data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR" and len(data) >= 24:
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    if data[:2] == b"\xff\xd8":
        return _jpeg_size(data)
    raise InputError("image is neither a PNG with an IHDR header nor a JPEG")


# JPEG start-of-frame markers carry the size; C4 (Huffman), C8 (reserved) and CC (arithmetic) do not.
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def _jpeg_size(data: bytes) -> tuple[int, int]:
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            raise InputError(f"JPEG marker expected at byte {i}")
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        length = int.from_bytes(data[i + 2 : i + 4], "big")
        if marker in _JPEG_SOF and i + 9 <= len(data):
            return int.from_bytes(data[i + 7 : i + 9], "big"), int.from_bytes(data[i + 5 : i + 7], "big")
        i += 2 + length
    raise InputError("JPEG has no frame header")


def decode_rgbd(
    rgb_jpeg: bytes, depth_png: bytes, expected_wh: tuple[int, int] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Encoded frame -> RGB (H, W, 3) uint8 and depth (H, W) uint16 mm. Raises ValueError if undecodable.

    With ``expected_wh`` the headers' sizes are checked before any pixel is decoded.
    """
    if expected_wh is not None:
        for name, data in (("rgb", rgb_jpeg), ("depth", depth_png)):
            size = encoded_image_size(data)
            if size != tuple(expected_wh):
                raise InputError(
                    f"{name} image is {size[0]}x{size[1]}, the message says {expected_wh[0]}x{expected_wh[1]}"
                )
    bgr = cv2.imdecode(np.frombuffer(rgb_jpeg, np.uint8), cv2.IMREAD_COLOR)
    depth = cv2.imdecode(np.frombuffer(depth_png, np.uint8), cv2.IMREAD_UNCHANGED)
    if bgr is None or depth is None:
        raise InputError("rgb or depth image does not decode")
    if depth.dtype != np.uint16 or depth.ndim != 2:
        raise InputError(f"depth must be a 16-bit single-channel PNG, got {depth.dtype} {depth.shape}")
    if depth.shape != bgr.shape[:2]:
        raise InputError(f"rgb {bgr.shape[:2]} and depth {depth.shape} sizes differ")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), depth


def resize_frame(
    rgb: np.ndarray, depth_mm: np.ndarray, size_wh: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """RGB (H, W, 3) uint8 and depth (H, W) uint16 mm -> the same at size_wh (w, h).

    RGB is area-averaged; depth is resized by nearest neighbour (averaging would invent depths at edges and
    holes).
    """
    rgb_small = cv2.resize(rgb, size_wh, interpolation=cv2.INTER_AREA)
    depth_small = cv2.resize(depth_mm, size_wh, interpolation=cv2.INTER_NEAREST)
    return rgb_small, depth_small


def network_input(rgb: np.ndarray, depth_mm: np.ndarray, channels: int) -> np.ndarray:
    """Resized frames RGB (..., h, w, 3) uint8 and depth (..., h, w) uint16 -> (..., C, h, w) float32.

    RGB is centred on 0; depth becomes metres / DEPTH_SCALE_M (~[0, 1]), holes staying 0. C = 3 drops depth.
    """
    x = np.moveaxis(rgb.astype(np.float32) / 255.0 - 0.5, -1, -3)
    if channels == 3:
        return np.ascontiguousarray(x)
    d = depth_mm.astype(np.float32)[..., None, :, :] / (1000.0 * DEPTH_SCALE_M)
    # C order explicitly: concatenate keeps moveaxis' channels-last layout, which onnxruntime would copy and
    # which crashes torch's CPU convolution backward (seen with torch 2.13).
    return np.ascontiguousarray(np.concatenate([x, d], axis=-3))


def lift_keypoints(
    uv_norm: np.ndarray, depth_m: np.ndarray, intrinsics: np.ndarray, size_wh: tuple[int, int]
) -> np.ndarray:
    """Normalised image coordinates (..., J, 2) in [0, 1] and depths (..., J) m -> camera-frame points (..., J, 3).

    ``u_px = u_norm * W - 0.5`` (pixel centres at integers); intrinsics (fx, fy, cx, cy) of a W×H image.
    """
    fx, fy, cx, cy = np.asarray(intrinsics, dtype=np.float64)
    u = uv_norm[..., 0] * size_wh[0] - 0.5
    v = uv_norm[..., 1] * size_wh[1] - 0.5
    return np.stack([(u - cx) / fx * depth_m, (v - cy) / fy * depth_m, depth_m], axis=-1)


def normalise_uv(uv_px: np.ndarray, size_wh: tuple[int, int]) -> np.ndarray:
    """Pixel coordinates (..., 2) -> normalised [0, 1] image coordinates (inverse of lift's mapping)."""
    return (uv_px + 0.5) / np.asarray(size_wh, dtype=np.float64)


def camera_to_world(
    points_cam: np.ndarray,
    head_pose: np.ndarray,
    cam_from_head: np.ndarray,
    head_from_cam: np.ndarray | None = None,
) -> np.ndarray:
    """Camera-frame points (..., J, 3) -> world, given the headset pose (..., 7) at capture and the (4, 4)
    headset-device -> camera transform (or its inverse ``head_from_cam``, if the caller has it)."""
    head_from_cam = np.linalg.inv(cam_from_head) if head_from_cam is None else head_from_cam
    in_head = points_cam @ head_from_cam[:3, :3].T + head_from_cam[:3, 3]
    world_from_head = quat_xyzw_to_matrix(head_pose[..., 3:])
    return in_head @ np.swapaxes(world_from_head, -1, -2) + head_pose[..., None, :3]


def nearest_sample(t_query_us: np.ndarray | int, t_us: np.ndarray) -> np.ndarray:
    """Index of the sample in sorted t_us (N >= 1,) nearest to each query time."""
    if len(t_us) == 1:
        return np.zeros(np.shape(t_query_us), dtype=np.int64)
    idx = np.clip(np.searchsorted(t_us, t_query_us), 1, len(t_us) - 1)
    earlier = np.abs(t_us[idx - 1] - t_query_us) <= np.abs(t_us[idx] - t_query_us)
    return np.where(earlier, idx - 1, idx)


class VisibilityFilter:
    """Alg. 1: One Euro on each joint's ζ over the camera stream, then the mask ζ̃ >= 0.5.

    Only new frames are filtered (earlier frames keep their smoothed values: the incremental cache). The
    returned confidence ``2·ReLU(ζ̃ - 0.5)`` is the paper's η rescaled to [0, 1]; it is 0 exactly where a joint
    is masked out.
    """

    def __init__(self) -> None:
        self._filter = OneEuroFilter(ZETA_MIN_CUTOFF_HZ, ZETA_BETA)

    def reset(self) -> None:
        self._filter.reset()

    def __call__(self, t_us: int, zeta: np.ndarray) -> np.ndarray:
        """ζ (J,) in [0, 1] of a new frame -> confidence (J,) in [0, 1]."""
        smoothed = self._filter(t_us, np.asarray(zeta, dtype=np.float64))
        return np.clip(2.0 * (smoothed - VISIBILITY_THRESHOLD), 0.0, 1.0)


def visual_window(
    frame_t_us: np.ndarray, now_us: int, window: int, max_age_s: float = MAX_FRAME_AGE_S
) -> np.ndarray:
    """Indices into frames (K,) sorted by time for the visual window at ``now_us``: the newest ``window``
    frames captured no later than now and no older than ``max_age_s``, oldest first (may be fewer)."""
    end = int(np.searchsorted(frame_t_us, now_us, side="right"))
    start = max(0, end - window)
    idx = np.arange(start, end)
    return idx[(now_us - frame_t_us[idx]) * 1e-6 <= max_age_s]


def visual_tokens(
    kp_world: np.ndarray,
    confidence: np.ndarray,
    age_s: np.ndarray,
    window: int,
    rot: np.ndarray,
    origin: np.ndarray,
) -> np.ndarray:
    """The frames of one window -> tokens (window, VISUAL_TOKEN_DIM) float32, newest in the last slot.

    kp_world (k, J, 3), confidence (k, J), age_s (k,) with k <= window; missing slots stay zero with
    present = 0. Masked joints (confidence 0) have zero coordinates. rot (3, 3), origin (3,): heading frame.
    """
    k = len(age_s)
    tokens = np.zeros((window, VISUAL_TOKEN_DIM), dtype=np.float32)
    if k == 0:
        return tokens
    kp = to_heading(kp_world, rot, origin) * (confidence[..., None] > 0)
    tokens[window - k :, : NUM_JOINTS * 3] = kp.reshape(k, -1)
    tokens[window - k :, NUM_JOINTS * 3 : NUM_JOINTS * 4] = confidence
    tokens[window - k :, -2] = 1.0
    tokens[window - k :, -1] = age_s
    return tokens


def _hmd_mirror() -> tuple[np.ndarray, np.ndarray]:
    """HMD_MIRROR_ORDER, HMD_MIRROR_SIGNS over x_t and the tracking state (FEATURE_DIM + VALIDITY_DIM,)."""
    order = np.arange(FEATURE_DIM + VALIDITY_DIM)
    signs = np.ones(FEATURE_DIM + VALIDITY_DIM)
    vector, sixd = X_MIRROR_SIGNS, SIXD_MIRROR_SIGNS
    for base in (0, 18, 36):  # position, rotation, velocity, angular velocity of head, left, right
        signs[base : base + 18] = np.concatenate([vector, sixd, vector, sixd])
    for base in (54, 63):  # each controller in the head's frame: position, rotation
        signs[base : base + 9] = np.concatenate([vector, sixd])
    swaps = [(slice(18, 36), slice(36, 54)), (slice(54, 63), slice(63, 72))]  # left <-> right
    swaps += [(slice(FEATURE_DIM + 1, FEATURE_DIM + 2), slice(FEATURE_DIM + 2, FEATURE_DIM + 3))]  # valid
    swaps += [(slice(FEATURE_DIM + 4, FEATURE_DIM + 5), slice(FEATURE_DIM + 5, FEATURE_DIM + 6))]  # age
    for left, right in swaps:
        order[left], order[right] = order[right].copy(), order[left].copy()
    return order, signs


def _visual_mirror() -> tuple[np.ndarray, np.ndarray]:
    """VISUAL_MIRROR_ORDER, VISUAL_MIRROR_SIGNS over a visual token (VISUAL_TOKEN_DIM,)."""
    joints = NUM_JOINTS * 3
    order = np.concatenate(
        [
            (3 * MIRROR_JOINTS[:, None] + np.arange(3)).ravel(),
            joints + MIRROR_JOINTS,
            np.arange(joints + NUM_JOINTS, VISUAL_TOKEN_DIM),
        ]
    )
    signs = np.ones(VISUAL_TOKEN_DIM)
    signs[:joints] = np.tile(X_MIRROR_SIGNS, NUM_JOINTS)
    return order, signs


# The mirrored person's inputs from this one's: x[..., ORDER] * SIGNS (see the module docstring). A net
# without the tracking state reads the first FEATURE_DIM of the HMD pair.
HMD_MIRROR_ORDER, HMD_MIRROR_SIGNS = _hmd_mirror()
VISUAL_MIRROR_ORDER, VISUAL_MIRROR_SIGNS = _visual_mirror()
