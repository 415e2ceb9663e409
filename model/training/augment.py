"""Training augmentation: mirrored people and rigs, other motion speeds, other camera crops and aspect ratios.

- :func:`mirror_sequence`: a whole shard sequence reflected through the world's x = 0 plane, left and right
  swapped (devices, joints, bones). Reflection keeps every frame proper: ``R' = M R M`` with
  ``M = diag(-1, 1, 1)``, i.e. quaternion ``(x, y, z, w) -> (x, -y, -z, w)``. The rig's grip offsets and
  device turns are mirror images of each other, so a mirrored left controller is a right one.
- :func:`retime_sequence`: the same motion played faster or slower (every clock scaled about its start).
- :func:`narrow_tracking_cone`: the same session as a headset that tracks its controllers over a narrower
  cone would report it: more, and longer, controller losses of the kind inside-out tracking has.
- :func:`lose_hanging_arms`: the same session as a headset that cannot see a hand hanging low at the side
  would report it: a controller lost while its wrist hangs well under its shoulder (a walking, swinging arm).
- :func:`swap_arms`: one person's legs, torso and head with another person's arm motion: the arms move while
  the legs do what they did (still legs stay still). The camera saw the first person's arms, so the copy's
  arm keypoints are marked unseen (``arms_unseen``).
- :func:`crop_and_flip`: for the keypoint net, a batch of frames cropped (other aspect ratios and fields of
  view than the renders': 16:9 sensors, zoomed lenses) and/or mirrored, with labels and intrinsics to match.

Shape legend: ``N`` headset samples, ``K`` camera frames, ``B`` batch, ``J`` = 22 joints, devices (head,
left, right); images (B, h, w, C).
"""

from __future__ import annotations

from typing import Any, Final

import cv2
import numpy as np

from ..inputs import X_MIRROR_SIGNS
from ..rig import TRACKED_JOINTS
from ..rotations import matrix_to_quat_xyzw, quat_xyzw_to_matrix
from ..skeleton import ARM_JOINTS, MIRROR_JOINTS, SHOULDERS, forward_kinematics, rest_offsets
from ..synth.headset import HeadsetRig, held_longer_than, hold_last_tracked, out_of_view

MIRROR_DEVICES: Final = np.array([0, 2, 1])
_QUAT_SIGNS: Final = np.array([1.0, -1.0, -1.0, 1.0])


def mirror_sequence(seq: dict[str, Any]) -> dict[str, Any]:
    """A shard sequence's motion, tracks and truth mirrored (a new dict; images and camera labels are the
    source's: ``mirror_of`` is it, ``images_key`` its key, and stage-2 mirrors the keypoints it predicts from them)."""
    out = dict(seq)
    poses = np.array(seq["hmd_poses"], dtype=np.float64)[:, MIRROR_DEVICES]
    poses[..., :3] *= X_MIRROR_SIGNS
    poses[..., 3:] *= _QUAT_SIGNS
    out["hmd_poses"] = poses.astype(seq["hmd_poses"].dtype)
    out["hmd_valid"] = np.asarray(seq["hmd_valid"])[:, MIRROR_DEVICES]
    out["gt_local_quat"] = (np.asarray(seq["gt_local_quat"])[:, MIRROR_JOINTS] * _QUAT_SIGNS).astype(
        seq["gt_local_quat"].dtype
    )
    out["gt_joints_m"] = (np.asarray(seq["gt_joints_m"])[:, MIRROR_JOINTS] * X_MIRROR_SIGNS).astype(
        seq["gt_joints_m"].dtype
    )
    if "gt_root_m" in seq:
        out["gt_root_m"] = (np.asarray(seq["gt_root_m"]) * X_MIRROR_SIGNS).astype(seq["gt_root_m"].dtype)
    out["bone_scale"] = np.asarray(seq["bone_scale"])[MIRROR_JOINTS]
    out["mirror_of"] = seq
    out["images_key"] = seq.get("images_key", seq["key"])
    out["key"] = f"{seq['key']}~mirrored"
    return out


def mirror_world_keypoints(kp_world: np.ndarray, confidence: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Stage-1 keypoints (K, J, 3) in the world and their confidence (K, J), as the mirrored body's."""
    return kp_world[:, MIRROR_JOINTS] * X_MIRROR_SIGNS, confidence[:, MIRROR_JOINTS]


def retime_sequence(seq: dict[str, Any], speed: float) -> dict[str, Any]:
    """The sequence played ``speed`` times as fast: every clock scaled by 1 / speed about the first sample."""
    out = dict(seq)
    t0 = int(seq["hmd_t_us"][0])
    for key in ("hmd_t_us", "cam_t_us"):
        out[key] = (t0 + (np.asarray(seq[key], dtype=np.int64) - t0) / speed).astype(np.int64)
    out["images_key"] = seq.get("images_key", seq["key"])
    out["key"] = f"{seq['key']}~x{speed:.3f}"
    return out


def _seconds(seq: dict[str, Any]) -> np.ndarray:
    """(N,) each headset sample's time since the sequence's first, s."""
    return (np.asarray(seq["hmd_t_us"], dtype=np.int64) - int(seq["hmd_t_us"][0])) * 1e-6


def _retracked(seq: dict[str, Any], poses: np.ndarray, valid: np.ndarray, tag: str) -> dict[str, Any]:
    """A new dict: ``seq`` with other device poses (N, 3, 7) and validity (N, 3), keyed ``<key>~<tag>``; its
    images are still ``seq``'s (``images_key``)."""
    out = dict(seq)
    out["hmd_poses"], out["hmd_valid"] = poses.astype(np.asarray(seq["hmd_poses"]).dtype), valid
    out["key"] = f"{seq['key']}~{tag}"
    out["images_key"] = seq.get("images_key", seq["key"])
    return out


def narrow_tracking_cone(seq: dict[str, Any], cone_deg: float, grace_s: float = 0.25) -> dict[str, Any]:
    """The sequence as a headset whose cameras track a controller only within ``cone_deg`` of its forward
    axis would report it (a new dict): a true wrist further off-axis than that for longer than ``grace_s``
    (the IMU's bridge) also loses its controller, which then reports its last tracked pose: the renders' own
    rules (synth.headset.out_of_view, hold_last_tracked). Losses the sequence already has are kept."""
    poses = np.array(seq["hmd_poses"], dtype=np.float64)  # (N, 3, 7)
    valid = np.array(seq["hmd_valid"], dtype=bool)  # (N, 3)
    at_wrists = poses.copy()  # the controllers where the true wrists are: what the cameras would have to see
    at_wrists[:, 1:, :3] = np.asarray(seq["gt_joints_m"], dtype=np.float64)[:, list(TRACKED_JOINTS[1:])]
    rig = HeadsetRig(tracking_cone_deg=cone_deg, tracking_grace_s=grace_s)
    unseen = out_of_view(at_wrists, _seconds(seq), rig)
    for device in (1, 2):
        valid[:, device] &= ~unseen[:, device - 1]
        poses[:, device] = hold_last_tracked(poses[:, device], valid[:, device])
    return _retracked(seq, poses, valid, f"cone{cone_deg:.0f}")


def lose_hanging_arms(seq: dict[str, Any], drop_m: float = 0.3, grace_s: float = 0.25) -> dict[str, Any]:
    """The sequence as a headset that loses a controller whose hand hangs at the side would report it (a new
    dict): a true wrist more than ``drop_m`` under its true shoulder (world y up) for longer than ``grace_s``
    also loses its controller, which then reports its last tracked pose (synth.headset.hold_last_tracked).
    Inside-out cameras look forward and down: a hand hanging at the side, or swinging behind the body in a
    walk, is where they lose it. Losses the sequence already has are kept."""
    poses = np.array(seq["hmd_poses"], dtype=np.float64)  # (N, 3, 7)
    valid = np.array(seq["hmd_valid"], dtype=bool)  # (N, 3)
    joints = np.asarray(seq["gt_joints_m"], dtype=np.float64)  # (N, J, 3)
    t_s = _seconds(seq)
    for device, wrist, shoulder in zip((1, 2), TRACKED_JOINTS[1:], SHOULDERS, strict=True):
        hanging = joints[:, wrist, 1] < joints[:, shoulder, 1] - drop_m
        valid[:, device] &= ~held_longer_than(hanging, t_s, grace_s)
        poses[:, device] = hold_last_tracked(poses[:, device], valid[:, device])
    return _retracked(seq, poses, valid, "hanging")


def _grip(device_poses: np.ndarray, valid: np.ndarray, wrist_m: np.ndarray, wrist_rot: np.ndarray):
    """How a controller sits on its wrist: its position (3,) in the wrist's frame (mean over tracked samples)
    and its rotation (3, 3) against the wrist's (at the first tracked sample; the identity if never)."""
    tracked = np.flatnonzero(valid)
    if not len(tracked):
        return np.zeros(3), np.eye(3)
    rel = np.einsum("nji,nj->ni", wrist_rot[tracked], device_poses[tracked, :3] - wrist_m[tracked])
    first = tracked[0]
    turn = wrist_rot[first].T @ quat_xyzw_to_matrix(device_poses[first, 3:])
    return rel.mean(0), turn


def swap_arms(
    seq: dict[str, Any], donor: dict[str, Any], start: int, cone_deg: float, grace_s: float = 0.25
) -> dict[str, Any]:
    """``seq``'s person with ``donor``'s arms (a new dict): the arm joints' local rotations (ARM_JOINTS) from
    donor's samples ``start``, ``start + 1``, ... (wrapping), the rest as recorded. The joints are the forward
    kinematics of that on ``seq``'s skeleton, the controllers sit on the new wrists as ``seq``'s sat on its
    own (same grip), and a controller outside a tracking cone of ``cone_deg`` (after ``grace_s``) is lost,
    reporting its last tracked pose, as the renders' rule has it. The images are ``seq``'s, whose arms are
    not these: ``arms_unseen`` tells stage 2 to treat the arm keypoints as not seen."""
    n = len(seq["hmd_t_us"])
    local = quat_xyzw_to_matrix(np.asarray(seq["gt_local_quat"], dtype=np.float64))  # (N, J, 3, 3)
    donor_local = quat_xyzw_to_matrix(np.asarray(donor["gt_local_quat"], dtype=np.float64))
    picks = (start + np.arange(n)) % len(donor_local)
    offsets = rest_offsets(seq["bone_scale"])
    old_joints, old_glob = forward_kinematics(local, seq["gt_root_m"], offsets)
    local[:, ARM_JOINTS] = donor_local[picks][:, ARM_JOINTS]
    joints, glob = forward_kinematics(local, seq["gt_root_m"], offsets)
    poses = np.array(seq["hmd_poses"], dtype=np.float64)  # (N, 3, 7)
    valid = np.array(seq["hmd_valid"], dtype=bool)
    for device in (1, 2):
        wrist = TRACKED_JOINTS[device]
        offset, turn = _grip(poses[:, device], valid[:, device], old_joints[:, wrist], old_glob[:, wrist])
        # The tracking's own noise and drift, kept: where the controller was against where its grip puts it.
        noise = (
            poses[:, device, :3] - old_joints[:, wrist] - np.einsum("nij,j->ni", old_glob[:, wrist], offset)
        )
        noise[~valid[:, device]] = 0.0
        poses[:, device, :3] = joints[:, wrist] + np.einsum("nij,j->ni", glob[:, wrist], offset) + noise
        poses[:, device, 3:] = matrix_to_quat_xyzw(glob[:, wrist] @ turn)
    rig = HeadsetRig(tracking_cone_deg=cone_deg, tracking_grace_s=grace_s)
    valid[:, 1:] = ~out_of_view(poses, _seconds(seq), rig)
    for device in (1, 2):
        poses[:, device] = hold_last_tracked(poses[:, device], valid[:, device])
    out = _retracked(seq, poses, valid, f"arms:{donor['key']}@{start}")
    out["gt_local_quat"] = matrix_to_quat_xyzw(local).astype(np.asarray(seq["gt_local_quat"]).dtype)
    out["gt_joints_m"] = joints.astype(np.asarray(seq["gt_joints_m"]).dtype)
    out["arms_unseen"] = True
    return out


def crop_and_flip(
    rng: np.random.Generator,
    rgb: np.ndarray,
    depth: np.ndarray,
    uv: np.ndarray,
    visible: np.ndarray,
    intrinsics: np.ndarray,
    size_wh: np.ndarray,
    joints_cam_m: np.ndarray,
    crop_p: float = 0.5,
    flip_p: float = 0.5,
    keep_x: tuple[float, float] = (0.7, 1.0),
    keep_y: tuple[float, float] = (0.5, 1.0),
) -> tuple[np.ndarray, ...]:
    """A batch of resized frames with labels -> the same, some cropped (then resized back) and some mirrored.

    rgb (B, h, w, 3), depth (B, h, w); uv (B, J, 2) normalised to the camera's image; visible (B, J);
    intrinsics (B, 4) and size_wh (B, 2) of each frame's camera, pixels; joints_cam_m (B, J, 3). Returns new
    arrays in that order. A cropped frame is a camera with the crop's size and shifted principal point; a
    joint the crop leaves out is no longer visible. Vertical keeps go lower than horizontal ones: that is
    how a 5:4 render becomes a 16:9 sensor's view.
    """
    rgb, depth = rgb.copy(), depth.copy()
    uv, visible = uv.astype(np.float64, copy=True), visible.copy()
    intrinsics, size_wh = intrinsics.astype(np.float64, copy=True), size_wh.astype(np.float64, copy=True)
    joints_cam_m = joints_cam_m.copy()
    h, w = rgb.shape[1:3]
    for b in np.flatnonzero(rng.random(len(rgb)) < crop_p):
        keep = np.array([rng.uniform(*keep_x), rng.uniform(*keep_y)])
        crop_wh = np.maximum(np.round(keep * (w, h)).astype(int), 8)
        corner = np.array([rng.integers(0, w - crop_wh[0] + 1), rng.integers(0, h - crop_wh[1] + 1)])
        (x0, y0), (cw, ch) = corner, crop_wh
        rgb[b] = cv2.resize(rgb[b, y0 : y0 + ch, x0 : x0 + cw], (w, h), interpolation=cv2.INTER_AREA)
        depth[b] = cv2.resize(depth[b, y0 : y0 + ch, x0 : x0 + cw], (w, h), interpolation=cv2.INTER_NEAREST)
        pixel = size_wh[b] / (w, h)  # camera pixels per stored pixel
        corner_px, crop_px = corner * pixel, crop_wh * pixel
        uv[b] = (uv[b] * size_wh[b] - corner_px) / crop_px
        intrinsics[b, 2:] -= corner_px
        size_wh[b] = crop_px
        visible[b] &= ((uv[b] >= 0.0) & (uv[b] <= 1.0)).all(-1)
    for b in np.flatnonzero(rng.random(len(rgb)) < flip_p):
        rgb[b], depth[b] = rgb[b, :, ::-1], depth[b, :, ::-1]
        uv[b] = uv[b, MIRROR_JOINTS] * (-1.0, 1.0) + (1.0, 0.0)
        visible[b] = visible[b, MIRROR_JOINTS]
        joints_cam_m[b] = joints_cam_m[b, MIRROR_JOINTS] * X_MIRROR_SIGNS
        intrinsics[b, 2] = size_wh[b, 0] - 1.0 - intrinsics[b, 2]
    return rgb, depth, uv.astype(np.float32), visible, intrinsics, size_wh, joints_cam_m
