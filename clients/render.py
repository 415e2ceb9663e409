"""Third-person skeleton video with OpenCV: for headless machines, reports and quick looks.

Two sources of poses: a recorded session (``.egrec``) run through a model in-process (no server needed; the
ground truth, when recorded, is drawn as a grey ghost), or a live server joined as a ``render`` client. A
virtual camera 3.2 m away, 1.2 m up, looking at the body from its front-left and following the pelvis
horizontally, projects the skeleton, a floor grid, the headset and the controllers; each frame carries the
model, the time and the running MPJPE when the truth is known.

Shape legend: ``J`` = 22 joints.
"""

from __future__ import annotations

import asyncio
import dataclasses
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from websockets.asyncio.client import connect

from ..model.inputs import decode_rgbd
from ..model.runtime.loading import LoadedModel
from ..model.runtime.pipeline import Pipeline
from ..model.skeleton import JOINT_NAMES, LOWER_BODY, NUM_JOINTS, PARENTS, UPPER_BODY
from ..protocol import Hello, encode
from . import read_server_message, session_url
from .replay import Recording

# BGR colours: the predicted body warm on the left side, cool on the right, the truth grey.
LEFT_BGR, RIGHT_BGR, CENTRE_BGR, TRUTH_BGR = (60, 140, 255), (255, 160, 60), (230, 230, 230), (120, 120, 120)
SIDE = [1 if n.startswith("left") else 2 if n.startswith("right") else 0 for n in JOINT_NAMES]  # 0 centre


@dataclasses.dataclass
class Frame:
    """What one video frame shows: joints (J, 3) m, optional truth (J, 3), time and labels."""

    joints: np.ndarray
    t_s: float
    model: str
    truth: np.ndarray | None = None
    camera: bool | None = None


class SkeletonRenderer:
    """Projects world joints (y up, metres) with a pinhole camera that follows the pelvis."""

    def __init__(self, width: int = 640, height: int = 480, fov_deg: float = 50.0) -> None:
        self.width, self.height = width, height
        self.focal_px = 0.5 * width / np.tan(np.radians(fov_deg) / 2)
        self.centre = np.zeros(3)
        self.mpjpe_sum = np.zeros(2)
        self.mpjpe_count = 0

    def _view(self, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World -> camera rotation (3, 3) (OpenCV axes) and camera position (3,)."""
        eye = target + np.array([-2.2, 1.2 - target[1], -2.3])  # front-left of a body facing -z, 3.2 m away
        forward = (target - eye) / np.linalg.norm(target - eye)
        right = np.cross(forward, [0.0, 1.0, 0.0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        return np.stack([right, down, forward]), eye

    def project(self, points: np.ndarray, rot: np.ndarray, eye: np.ndarray) -> np.ndarray:
        """(N, 3) world -> (N, 2) pixels; points behind the camera come out far off-screen."""
        cam = (points - eye) @ rot.T
        z = np.maximum(cam[:, 2], 1e-3)
        return np.stack(
            [self.focal_px * cam[:, 0] / z + self.width / 2, self.focal_px * cam[:, 1] / z + self.height / 2],
            -1,
        )

    def draw(self, frame: Frame) -> np.ndarray:
        """One (H, W, 3) BGR image."""
        target = frame.joints[0].copy()
        self.centre = target if not self.centre.any() else 0.9 * self.centre + 0.1 * target  # a steady camera
        rot, eye = self._view(np.array([self.centre[0], 1.0, self.centre[2]]))
        image = np.full((self.height, self.width, 3), 32, np.uint8)
        self._grid(image, rot, eye)
        if frame.truth is not None:
            self._skeleton(image, frame.truth, rot, eye, truth=True)
        self._skeleton(image, frame.joints, rot, eye)
        self._devices(image, frame.joints, rot, eye)
        self._labels(image, frame)
        return image

    def _grid(self, image: np.ndarray, rot: np.ndarray, eye: np.ndarray) -> None:
        cx, cz = np.round(self.centre[[0, 2]])
        for k in np.arange(-4, 5):
            for a, b in (
                ((cx + k, 0, cz - 4), (cx + k, 0, cz + 4)),
                ((cx - 4, 0, cz + k), (cx + 4, 0, cz + k)),
            ):
                p = self.project(np.array([a, b], dtype=float), rot, eye)
                cv2.line(image, _pt(p[0]), _pt(p[1]), (70, 70, 70), 1, cv2.LINE_AA)

    def _skeleton(
        self, image: np.ndarray, joints: np.ndarray, rot: np.ndarray, eye: np.ndarray, truth: bool = False
    ) -> None:
        px = self.project(joints, rot, eye)
        for j in range(1, NUM_JOINTS):
            colour = TRUTH_BGR if truth else (CENTRE_BGR, LEFT_BGR, RIGHT_BGR)[SIDE[j]]
            cv2.line(image, _pt(px[PARENTS[j]]), _pt(px[j]), colour, 2 if truth else 4, cv2.LINE_AA)
        if not truth:
            for p in px:
                cv2.circle(image, _pt(p), 4, (250, 250, 250), -1, cv2.LINE_AA)

    def _devices(self, image: np.ndarray, joints: np.ndarray, rot: np.ndarray, eye: np.ndarray) -> None:
        """The headset (above the head joint) and the controllers (at the wrists) as small boxes."""
        for j, size, colour in ((15, 9, (80, 220, 80)), (20, 6, (80, 220, 80)), (21, 6, (80, 220, 80))):
            offset = np.array([0.0, 0.08, 0.0]) if j == 15 else np.zeros(3)
            c = _pt(self.project((joints[j] + offset)[None], rot, eye)[0])
            cv2.rectangle(image, (c[0] - size, c[1] - size // 2), (c[0] + size, c[1] + size // 2), colour, 2)

    def _labels(self, image: np.ndarray, frame: Frame) -> None:
        text = f"{frame.model}  t {frame.t_s:6.2f} s"
        if frame.camera is not None:
            text += "  camera " + ("on" if frame.camera else "off")
        if frame.truth is not None:
            error = np.linalg.norm(frame.joints - frame.truth, axis=-1)
            self.mpjpe_sum += [error[UPPER_BODY].mean(), error[LOWER_BODY].mean()]
            self.mpjpe_count += 1
            u, low = 100 * self.mpjpe_sum / self.mpjpe_count
            text += f"  MPJPE U {u:.1f} / L {low:.1f} cm (grey: truth)"
        cv2.putText(image, text, (10, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (240, 240, 240), 1, cv2.LINE_AA)


def _pt(p: np.ndarray) -> tuple[int, int]:
    return int(np.clip(p[0], -1e4, 1e4)), int(np.clip(p[1], -1e4, 1e4))


def frames_from_recording(recording: Recording, model: LoadedModel, name: str, fps: float) -> Iterator[Frame]:
    """Run the recording through the model in-process, in arrival order; one frame per 1/fps of its time."""
    pipeline = Pipeline(model)
    next_t_us = None
    for _, msg, _ in recording.messages:
        if msg.type == "rgbd":
            rgb, depth = decode_rgbd(msg.rgb, msg.depth)
            cam = None if msg.cam_from_head is None else np.reshape(msg.cam_from_head, (4, 4))
            pipeline.push_rgbd(msg.t_us, rgb, depth, np.asarray(msg.intrinsics), cam)
        elif msg.type == "hmd":
            pose = pipeline.push_hmd(msg.t_us, np.asarray(msg.poses()), np.asarray(msg.valid))
            next_t_us = msg.t_us if next_t_us is None else next_t_us
            if msg.t_us >= next_t_us:
                next_t_us += int(1e6 / fps)
                t_s = (msg.t_us - recording.messages[0][1].t_us) * 1e-6
                yield Frame(pose.joints, t_s, name, recording.truth.get(msg.seq), pose.camera)


async def _live_poses(url: str, session: str, seconds: float) -> list[tuple[float, Any]]:
    out: list[tuple[float, Any]] = []
    async with connect(session_url(url, session), compression=None, max_size=None) as ws:
        await ws.send(encode(Hello(role="render", session=session, client="egoposevr render")))
        start = time.perf_counter()
        while (left := seconds - (time.perf_counter() - start)) > 0:
            try:
                msg = read_server_message(await asyncio.wait_for(ws.recv(), left))
            except TimeoutError:
                break
            if msg is not None and msg.type == "pose":
                out.append((time.perf_counter() - start, msg))
    return out


def frames_from_server(url: str, session: str, seconds: float, fps: float) -> list[Frame]:
    """Join ``session`` as a viewer for ``seconds``; the poses resampled to ``fps`` by arrival time."""
    poses = asyncio.run(_live_poses(url, session, seconds))
    frames, next_s = [], 0.0
    for t_s, pose in poses:
        if t_s >= next_s:
            next_s += 1.0 / fps
            frames.append(Frame(np.reshape(pose.joints, (NUM_JOINTS, 3)), t_s, pose.model, None, pose.camera))
    return frames


def write_video(
    frames: Iterator[Frame] | list[Frame], out: Path, fps: float, size: tuple[int, int] = (640, 480)
) -> int:
    """Encode frames as MP4 (OpenCV's mp4v); returns the number of frames written."""
    renderer = SkeletonRenderer(*size)
    writer = cv2.VideoWriter(str(out), cv2.VideoWriter_fourcc(*"mp4v"), fps, size)
    if not writer.isOpened():
        raise OSError(f"OpenCV cannot write {out}")
    count = 0
    try:
        for frame in frames:
            writer.write(renderer.draw(frame))
            count += 1
    finally:
        writer.release()
    return count
