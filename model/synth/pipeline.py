"""Motion -> headset tracks -> rendered RGB-D frames -> datasets and recorded sessions.

Everything is drawn from one ``numpy.random.Generator`` per sequence, seeded from the run's seed and the
sequence's index, so the same seed gives the same bytes (shards are written as zip files with fixed
timestamps for that reason).

Shape legend: ``N`` headset samples, ``K`` camera frames, ``J`` = 22 joints, ``H``×``W`` image.
"""

from __future__ import annotations

import dataclasses
import functools
import json
from pathlib import Path
from typing import Any, Final

import cv2
import numpy as np

from ...protocol import Hmd, Rgbd, encode
from ...recordings.egrec import EgrecWriter
from ..rotations import matrix_to_quat_xyzw
from ..skeleton import PARENTS, forward_kinematics, local_rot_to_smpl
from ..training.dataset import iter_shard_sequences, load_shard  # noqa: F401  (re-exported: the format's readers)
from .archive import write_npz
from .bodies import BodyBank, fit_motion_to_body, pose_vertices
from .headset import CameraModel, HeadsetRig, HeadsetTrack, device_poses, simulate_headset
from .motion import Motion, sample_at
from .render import (
    FLOOR_PATTERNS,
    JOINT_RADIUS_M,
    Appearance,
    MeshBody,
    Renderer,
    SensorNoise,
    body_capsules,
    controller_capsules,
    prepare_mesh_body,
    random_appearance,
)
from .variation import RigPool, pool_bodies, random_rig, record

FORMAT_VERSION = 1
TORSO: Final = (0, 3, 6, 9, 12, 13, 14)


def _own_surface() -> np.ndarray:
    """(J, J) bool: joint a's own surface includes the body moved by joint b (itself, its parent, its
    children; the whole torso for torso joints): seeing it there means the joint is not occluded."""
    own = np.eye(22, dtype=bool)
    for child in range(1, 22):
        own[child, PARENTS[child]] = own[PARENTS[child], child] = True
    own[np.ix_(TORSO, TORSO)] = True
    return own


OWN_SURFACE: Final = _own_surface()


@dataclasses.dataclass(frozen=True)
class SynthConfig:
    hmd_rate_hz: float = 60.0
    camera_rate_hz: float = 30.0
    camera: CameraModel = dataclasses.field(default_factory=CameraModel)
    rig: HeadsetRig = dataclasses.field(default_factory=HeadsetRig)
    noise: SensorNoise = dataclasses.field(default_factory=SensorNoise)
    blur_samples: int = 1  # > 1: average that many renders over the exposure (motion blur)
    exposure_s: float = 0.012
    jpeg_quality: int = 90
    camera_latency_us: int = 25_000  # capture -> sent, for recorded sessions
    hmd_latency_us: int = 1_000
    bodies: BodyBank | None = None  # mesh bodies (bodies.py); None: capsule bodies
    rig_pool: RigPool | None = None  # draw camera, headset, sensor and rate per sequence (variation.POOLS)


@dataclasses.dataclass
class CameraFrames:
    """Rendered frames of one sequence with their labels.

    t_us (K,) capture times on the headset clock; head_pose (K, 7) the true headset pose at capture;
    rgb_jpeg / depth_png: K encoded images; joints_cam_m (K, J, 3); joints_uv_px (K, J, 2);
    visible (K, J) inside the field of view; occluded (K, J) visible but hidden behind something.
    """

    t_us: np.ndarray
    head_pose: np.ndarray
    rgb_jpeg: list[bytes]
    depth_png: list[bytes]
    joints_cam_m: np.ndarray
    joints_uv_px: np.ndarray
    visible: np.ndarray
    occluded: np.ndarray


@dataclasses.dataclass
class Sequence:
    name: str
    motion: Motion
    track: HeadsetTrack
    frames: CameraFrames
    appearance: Appearance
    body: int = -1  # the body bank's body, -1 for a capsule body
    config: SynthConfig | None = None  # this sequence's camera, rig, sensor and rates (drawn or fixed)
    rig: dict[str, Any] | None = None  # what was drawn (variation.record), None for the fixed rig


def encode_images(rgb: np.ndarray, depth_mm: np.ndarray, jpeg_quality: int) -> tuple[bytes, bytes]:
    """(H, W, 3) uint8 RGB and (H, W) uint16 mm -> (JPEG bytes, 16-bit PNG bytes)."""
    ok_rgb, jpeg = cv2.imencode(
        ".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality]
    )
    ok_depth, png = cv2.imencode(".png", depth_mm, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not (ok_rgb and ok_depth):
        raise RuntimeError("OpenCV failed to encode a frame")
    return jpeg.tobytes(), png.tobytes()


def nearest_pixel(uv: np.ndarray, width: int, height: int) -> np.ndarray:
    """(..., 2) int pixel (column, row) inside a width x height image nearest each projection (..., 2) px.
    A joint near the lens plane projects far off the image, beyond what an int holds, and a degenerate one to
    NaN: neither is in view, so the pixel it is given is only there to keep the lookup in bounds."""
    uv_finite = np.nan_to_num(uv, nan=0.0, posinf=0.0, neginf=0.0)
    return np.clip(np.round(uv_finite), 0, [width - 1, height - 1]).astype(int)


def render_frames(
    motion: Motion,
    track: HeadsetTrack,
    look: Appearance,
    cfg: SynthConfig,
    renderer: Renderer,
    rng: np.random.Generator,
    body: MeshBody | None = None,
) -> CameraFrames:
    """Render the camera frames of one sequence at ``cfg.camera_rate_hz`` with their labels; a mesh body
    when ``body`` is given (posed by the motion, which must be on that body's bones), capsules otherwise."""
    cam = cfg.camera
    count = max(1, int(np.floor(motion.duration_s * cfg.camera_rate_hz)))
    t_s = np.arange(count) / cfg.camera_rate_hz
    blur = max(1, cfg.blur_samples)
    shifts = (np.linspace(-0.5, 0.5, blur) if blur > 1 else np.zeros(1)) * cfg.exposure_s
    all_t = (t_s[:, None] + shifts[None]).ravel()
    local_rot, root = sample_at(motion, all_t)
    joints, global_rot = forward_kinematics(local_rot, root, motion.offsets_m())
    devices = device_poses(joints, global_rot, cfg.rig)
    joints = joints.reshape(count, blur, 22, 3)
    devices = devices.reshape(count, blur, 3, 7)
    global_rot = global_rot.reshape(count, blur, 22, 3, 3)
    centre = blur // 2

    out_t = track.t_us[0] + np.round((t_s - track.motion_t_s[0]) * 1e6).astype(np.int64)
    head_pose = devices[:, centre, 0]
    frames = CameraFrames(
        t_us=out_t,
        head_pose=head_pose,
        rgb_jpeg=[],
        depth_png=[],
        joints_cam_m=np.empty((count, 22, 3)),
        joints_uv_px=np.empty((count, 22, 2)),
        visible=np.empty((count, 22), dtype=bool),
        occluded=np.zeros((count, 22), dtype=bool),
    )
    for k in range(count):
        rgb_sum, depth = None, None
        for b in range(blur):
            world_from_cam = cam.world_from_camera(devices[k, b, 0])
            if body is None:
                caps = body_capsules(joints[k, b], motion.bone_scale, look.girth, devices[k, b, 1:])
                rgb, d = renderer.render_clean(world_from_cam, caps, look)
            else:
                vertices = pose_vertices(body.bank, body.index, global_rot[k, b], joints[k, b])
                props = controller_capsules(devices[k, b, 1:])
                rgb, d = renderer.render_mesh_clean(world_from_cam, body, vertices, props, look)
            rgb_sum = rgb if rgb_sum is None else rgb_sum + rgb
            if b == centre:
                depth = d
                cam_from_world = np.linalg.inv(world_from_cam)
                body_face = renderer.last_body_face if body is not None else None
        if body_face is not None:
            rgb_mean, depth, body_face = renderer.distort(rgb_sum / blur, depth, body_face)
        else:
            rgb_mean, depth = renderer.distort(rgb_sum / blur, depth)
        rgb8, depth_mm = renderer.add_noise(rgb_mean, depth, rng, cfg.noise)
        jpeg, png = encode_images(rgb8, depth_mm, cfg.jpeg_quality)
        frames.rgb_jpeg.append(jpeg)
        frames.depth_png.append(png)
        joints_cam = joints[k, centre] @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
        uv = cam.project(joints_cam)
        visible = cam.in_view(joints_cam)
        frames.joints_cam_m[k], frames.joints_uv_px[k], frames.visible[k] = joints_cam, uv, visible
        px = nearest_pixel(uv, cam.width, cam.height)
        surface = depth[px[:, 1], px[:, 0]]
        if body_face is None:  # capsules: something lies in front of the joint's own (radius + 3 cm of slack)
            hidden = surface < joints_cam[:, 2] - JOINT_RADIUS_M * look.girth * 1.3 - 0.03
        else:  # mesh: what is seen there is not the joint's own part of the body (nor next to it)
            face = body_face[px[:, 1], px[:, 0]]
            seen = np.where(face >= 0, body.bank.skin_joint[body.faces[np.maximum(face, 0), 0], 0], -1)
            own = (face >= 0) & OWN_SURFACE[np.arange(22), np.maximum(seen, 0)]
            hidden = ~own & (surface < joints_cam[:, 2] - 0.03)
        frames.occluded[k] = visible & hidden
    return frames


def synthesize_sequence(
    motion: Motion,
    cfg: SynthConfig,
    rng: np.random.Generator,
    renderer: Renderer | None = None,
    name: str | None = None,
    body: int | None = None,
) -> Sequence:
    """One sequence. With a body bank in ``cfg``, a mesh body (``body``, or a random one of the pool's) that
    the motion is fitted to unless it is on that body's bones already (procedural motion made for it);
    capsules without. With ``cfg.rig_pool``, this sequence's camera, headset, sensor and rate are drawn from
    that pool; otherwise ``cfg``'s are used (and ``renderer``, when given, must be for ``cfg.camera``)."""
    mesh, head_offset = None, cfg.rig.head_offset_m
    pool = cfg.rig_pool
    if cfg.bodies is not None:
        if body is None:
            choices = pool_bodies(cfg.bodies.count, pool) if pool else range(cfg.bodies.count)
            body = int(rng.choice(list(choices)))
        mesh = prepare_mesh_body(cfg.bodies, body)
        if not np.allclose(motion.bone_scale, cfg.bodies.bone_scale(body)):
            motion = fit_motion_to_body(motion, cfg.bodies.rest_joints[body])
        head_offset = cfg.bodies.head_offset_m(body)
    drawn = random_rig(rng, pool, head_offset) if pool else None
    if drawn is not None:
        cfg = dataclasses.replace(
            cfg, camera=drawn.camera, rig=drawn.headset, noise=drawn.sensor, hmd_rate_hz=drawn.hmd_rate_hz,
            jpeg_quality=drawn.jpeg_quality,
        )  # fmt: skip
        renderer = None
    else:
        cfg = dataclasses.replace(cfg, rig=dataclasses.replace(cfg.rig, head_offset_m=head_offset))
    renderer = renderer or renderer_for(cfg.camera)
    track = simulate_headset(motion, cfg.hmd_rate_hz, rng, cfg.rig)
    if pool is None:
        look = random_appearance(rng, motion.root_pos_m[0, [0, 2]], FLOOR_PATTERNS[:3])
    else:
        look = random_appearance(
            rng, motion.root_pos_m[0, [0, 2]], pool.floors, pool.top_patterns, pool.two_lights_p
        )
    frames = render_frames(motion, track, look, cfg, renderer, rng, mesh)
    rig = record(drawn) if drawn is not None else None
    return Sequence(name or motion.name, motion, track, frames, look, -1 if mesh is None else body, cfg, rig)


@functools.lru_cache(maxsize=16)
def renderer_for(camera: CameraModel) -> Renderer:
    """A renderer (its ray grid) per camera model, kept for the cameras a run draws again."""
    return Renderer(camera)


# ------------------------------------------------------------------------------------------ datasets
def _blob(chunks: list[bytes]) -> tuple[np.ndarray, np.ndarray]:
    offsets = np.zeros(len(chunks) + 1, dtype=np.int64)
    offsets[1:] = np.cumsum([len(c) for c in chunks])
    return np.frombuffer(b"".join(chunks), dtype=np.uint8), offsets


def _camera(seq: Sequence) -> CameraModel:
    if seq.config is None:
        raise ValueError(f"sequence {seq.name} has no configuration (made outside synthesize_sequence)")
    return seq.config.camera


def sequence_arrays(seqs: list[Sequence]) -> dict[str, np.ndarray]:
    """The arrays of one shard (several sequences concatenated; ``*_start`` index them)."""
    hmd_start = np.cumsum([0] + [len(s.track.t_us) for s in seqs])
    cam_start = np.cumsum([0] + [len(s.frames.t_us) for s in seqs])
    cat = np.concatenate
    rgb, rgb_offsets = _blob([b for s in seqs for b in s.frames.rgb_jpeg])
    depth, depth_offsets = _blob([b for s in seqs for b in s.frames.depth_png])
    return {
        "seq_name": np.array([s.name for s in seqs]),
        "seq_source": np.array([s.motion.source for s in seqs]),
        "bone_scale": np.stack([s.motion.bone_scale for s in seqs]).astype(np.float32),
        "body": np.array([s.body for s in seqs], dtype=np.int32),
        "cam_size": np.array([_camera(s).width_height for s in seqs], dtype=np.int32).reshape(-1, 2),
        "cam_intrinsics": np.array([_camera(s).intrinsics() for s in seqs], dtype=np.float64).reshape(-1, 4),
        "cam_from_head": np.array([_camera(s).cam_from_head().ravel() for s in seqs]).reshape(-1, 16),
        "hmd_start": hmd_start.astype(np.int64),
        "cam_start": cam_start.astype(np.int64),
        "hmd_t_us": cat([s.track.t_us for s in seqs]),
        "hmd_poses": cat([s.track.poses for s in seqs]).astype(np.float32),
        "hmd_valid": cat([s.track.valid for s in seqs]),
        "gt_local_quat": cat([matrix_to_quat_xyzw(s.track.local_rot) for s in seqs]).astype(np.float32),
        "gt_root_m": cat([s.track.root_pos_m for s in seqs]).astype(np.float32),
        "gt_joints_m": cat([s.track.joints_m for s in seqs]).astype(np.float32),
        "cam_t_us": cat([s.frames.t_us for s in seqs]),
        "cam_head_pose": cat([s.frames.head_pose for s in seqs]).astype(np.float32),
        "rgb_jpeg": rgb,
        "rgb_offsets": rgb_offsets,
        "depth_png": depth,
        "depth_offsets": depth_offsets,
        "joints_cam_m": cat([s.frames.joints_cam_m for s in seqs]).astype(np.float32),
        "joints_uv_px": cat([s.frames.joints_uv_px for s in seqs]).astype(np.float32),
        "visible": cat([s.frames.visible for s in seqs]),
        "occluded": cat([s.frames.occluded for s in seqs]),
    }


class DatasetWriter:
    """Writes sequences into ``DIR/<split>/shard-NNNNN.npz`` files of about ``shard_frames`` camera frames."""

    def __init__(self, out_dir: Path, split: str, shard_frames: int = 1500) -> None:
        self.split_dir = Path(out_dir) / split
        self.split_dir.mkdir(parents=True, exist_ok=True)
        self.shard_frames = shard_frames
        self._pending: list[Sequence] = []
        self.shards: list[str] = []
        self.counts = {"sequences": 0, "hmd_samples": 0, "camera_frames": 0}

    def add(self, seq: Sequence) -> None:
        self._pending.append(seq)
        self.counts["sequences"] += 1
        self.counts["hmd_samples"] += len(seq.track.t_us)
        self.counts["camera_frames"] += len(seq.frames.t_us)
        if sum(len(s.frames.t_us) for s in self._pending) >= self.shard_frames:
            self.flush()

    def flush(self) -> None:
        if not self._pending:
            return
        name = f"shard-{len(self.shards):05d}.npz"
        write_npz(self.split_dir / name, sequence_arrays(self._pending))
        self.shards.append(name)
        self._pending = []


def camera_manifest(cam: CameraModel) -> dict[str, Any]:
    fx, fy, cx, cy = cam.intrinsics()
    return {
        "width": cam.width,
        "height": cam.height,
        "intrinsics": [fx, fy, cx, cy],
        "hfov_deg": cam.hfov_deg,
        "pitch_down_deg": cam.pitch_down_deg,
        "cam_from_head": np.round(cam.cam_from_head(), 9).ravel().tolist(),
        "depth_units": "uint16 millimetres, 0 = no reading",
        "min_depth_m": cam.min_depth_m,
        "max_depth_m": cam.max_depth_m,
    }


def update_manifest(out_dir: Path, split: str, entry: dict[str, Any]) -> Path:
    """Merge one split's entry into ``DIR/manifest.json`` (other splits are kept)."""
    path = Path(out_dir) / "manifest.json"
    manifest = json.loads(path.read_text()) if path.exists() else {}
    manifest.setdefault("format", "egoposevr-dataset")
    manifest["version"] = FORMAT_VERSION
    manifest.setdefault("splits", {})[split] = entry
    path.write_text(json.dumps(manifest, indent=2, sort_keys=True) + "\n")
    return path


# ---------------------------------------------------------------------------------- recorded sessions
def smpl_truths(track: HeadsetTrack) -> list[dict[str, Any]]:
    """The ``gt`` record of every headset sample (one batched SMPL conversion for the whole track)."""
    global_orient, body_pose = local_rot_to_smpl(track.local_rot)
    return [
        {
            "seq": i,
            "t_us": int(track.t_us[i]),
            "global_orient": global_orient[i].astype(np.float32).tolist(),
            "body_pose": body_pose[i].astype(np.float32).tolist(),
            "transl": track.root_pos_m[i].astype(np.float32).tolist(),
            "joints": track.joints_m[i].astype(np.float32).ravel().tolist(),
        }
        for i in range(len(track.t_us))
    ]


def write_session(seq: Sequence, path: Path, cfg: SynthConfig) -> int:
    """Write one sequence as an .egrec recording (hmd + rgbd messages, ground truth per hmd); -> bytes.
    The sequence's own camera and rates (drawn per sequence with a rig pool) win over ``cfg``'s."""
    cfg = seq.config or cfg
    cam = cfg.camera
    track, frames = seq.track, seq.frames
    start = int(min(track.t_us[0], frames.t_us[0]))
    events: list[tuple[int, int, str, Any]] = []  # (send time, order, kind, payload)
    truths = smpl_truths(track)
    for i in range(len(track.t_us)):
        msg = Hmd(
            seq=i,
            t_us=int(track.t_us[i]),
            head=track.poses[i, 0].astype(np.float32).tolist(),
            left=track.poses[i, 1].astype(np.float32).tolist(),
            right=track.poses[i, 2].astype(np.float32).tolist(),
            valid=track.valid[i].tolist(),
        )
        sent = int(track.t_us[i]) - start + cfg.hmd_latency_us
        events.append((sent, 0, "c2s", encode(msg)))
        events.append((sent, 1, "gt", truths[i]))
    intrinsics = list(cam.intrinsics())
    cam_from_head = cam.cam_from_head().ravel().tolist()
    for k in range(len(frames.t_us)):
        msg = Rgbd(
            seq=k,
            t_us=int(frames.t_us[k]),
            width=cam.width,
            height=cam.height,
            intrinsics=intrinsics,
            rgb=frames.rgb_jpeg[k],
            depth=frames.depth_png[k],
            cam_from_head=cam_from_head,
        )
        events.append((int(frames.t_us[k]) - start + cfg.camera_latency_us, 2, "c2s", encode(msg)))
    events.sort(key=lambda e: (e[0], e[1]))
    with EgrecWriter(
        path,
        session=seq.name,
        created_by="egoposevr synth",
        source=seq.motion.source,
        licence=seq.motion.licence,
        hmd_rate_hz=cfg.hmd_rate_hz,
        camera_rate_hz=cfg.camera_rate_hz,
        has_ground_truth=True,
        camera=camera_manifest(cam),
        bone_scale=seq.motion.bone_scale.astype(np.float32).tolist(),
    ) as writer:
        for sent, _, kind, payload in events:
            writer.write(sent, kind, payload)
    return path.stat().st_size


# ------------------------------------------------------------------------------------------- preview
PREVIEW_WH: Final = (320, 256)


def _letterbox(image: np.ndarray, size_wh: tuple[int, int] = PREVIEW_WH) -> np.ndarray:
    """Scale an image to fit size_wh, keeping its aspect, on black (cameras of several sizes in one sheet)."""
    h, w = image.shape[:2]
    scale = min(size_wh[0] / w, size_wh[1] / h)
    resized = cv2.resize(image, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_AREA)
    out = np.zeros((size_wh[1], size_wh[0], 3), dtype=np.uint8)
    y0, x0 = (size_wh[1] - resized.shape[0]) // 2, (size_wh[0] - resized.shape[1]) // 2
    out[y0 : y0 + resized.shape[0], x0 : x0 + resized.shape[1]] = resized
    return out


def contact_sheet(seqs: list[dict[str, Any]], path: Path, tiles: int = 12, columns: int = 4) -> None:
    """A PNG grid of RGB frames with their 2D labels (green: visible, red: occluded) and depth beside."""
    picks = []
    total = sum(len(s["rgb_jpeg"]) for s in seqs)
    wanted = set(np.linspace(0, max(total - 1, 0), min(tiles, total)).astype(int).tolist())
    index = 0
    for s in seqs:
        for k in range(len(s["rgb_jpeg"])):
            if index in wanted:
                picks.append((s, k))
            index += 1
    images = []
    for s, k in picks:
        bgr = cv2.imdecode(np.frombuffer(s["rgb_jpeg"][k], np.uint8), cv2.IMREAD_COLOR)
        depth = cv2.imdecode(np.frombuffer(s["depth_png"][k], np.uint8), cv2.IMREAD_UNCHANGED)
        colour = cv2.applyColorMap(np.clip(depth / 3000.0 * 255, 0, 255).astype(np.uint8), cv2.COLORMAP_TURBO)
        colour[depth == 0] = 0
        for (u, v), vis, occ in zip(s["joints_uv_px"][k], s["visible"][k], s["occluded"][k], strict=True):
            if vis:
                cv2.circle(bgr, (round(u), round(v)), 3, (0, 0, 255) if occ else (0, 255, 0), -1)
        tile = np.concatenate([_letterbox(bgr), _letterbox(colour)], axis=1)
        cv2.putText(
            tile, s["name"][:40], (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA
        )
        images.append(tile)
    if not images:
        return
    blank = np.zeros_like(images[0])
    while len(images) % columns:
        images.append(blank)
    rows = [np.concatenate(images[i : i + columns], axis=1) for i in range(0, len(images), columns)]
    cv2.imwrite(str(path), np.concatenate(rows, axis=0))
