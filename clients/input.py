"""Input library for real rigs: stream a headset and an RGB-D camera to an EgoPoseVR server, get poses back.

Untested on real hardware: it was developed and tested against the project's own server with recorded and
synthetic data only. The sketch below shows where a real capture loop plugs in::

    import asyncio
    from egoposevr.clients.input import HeadsetClient
    from egoposevr.protocol.openxr import hmd_from_openxr

    async def main():
        async with HeadsetClient("ws://server:8765/ws", session="player-1") as headset:
            asyncio.create_task(camera_loop(headset))
            asyncio.create_task(pose_consumer(headset))
            while True:  # one sample per display frame (OpenXR: after xrWaitFrame / xrLocateSpace)
                t_us, view, left_grip, right_grip = read_openxr_poses()  # each ([px,py,pz,qx,qy,qz,qw], flags)
                msg = hmd_from_openxr(0, t_us, view, left_grip, right_grip)  # PROTOCOL.md §3.3
                await headset.send_hmd(t_us, msg.head, msg.left, msg.right, msg.valid)

    async def camera_loop(headset):  # e.g. a RealSense D4xx: aligned color + depth frames at 30 Hz
        while True:
            t_us, rgb, depth_mm, intrinsics = await grab_aligned_frame()  # uint8 (H,W,3) RGB, uint16 mm
            await headset.send_rgbd(t_us, rgb, depth_mm, intrinsics)  # encodes JPEG + 16-bit PNG for you

    async def pose_consumer(headset):
        async for pose in headset.poses():
            drive_avatar(pose.global_orient, pose.body_pose, pose.transl)

Timestamps are the rig's own monotonic clock in µs, the same clock for both streams (PROTOCOL.md §3).
On a Quest, use OpenXR's STAGE reference space (floor at y = 0) and locate the VIEW space and the two
``grip`` poses in it; ``hmd_from_openxr`` turns the grips' orientations the quarter turn the models expect
and maps the location flags to ``valid`` (PROTOCOL.md §3.3). A RealSense needs depth aligned to color
(`rs.align`) and the color intrinsics; `cam_from_head` is the camera's pose in the headset's frame from your
mount's calibration (omit it to use the training camera's).

Connection handling: the client says ``hello`` as ``input``, and if the connection drops it reconnects with
exponential backoff and resumes the same session (same id, model and sequence counters). Samples sent while
offline are dropped and counted (``dropped_offline``): for a real-time stream, stale data is worth nothing.
A fatal refusal that retrying cannot fix (``auth_failed``, ``session_busy``) stops the client and is raised.
A server message that breaks the protocol is logged, counted (``counts["unreadable"]``) and skipped; the stream
goes on.

A returning wearer (PROTOCOL.md §4.2): pass the body kept from their last session as ``body=`` (or give it
with :meth:`HeadsetClient.set_body`); the client gives it first after every welcome, reconnects included, so no
sample is served without it. At the session's end, ``await headset.get_body()`` and keep its
``bone_lengths_m`` with the user's profile if it is ``measured``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import deque
from collections.abc import AsyncIterator, Sequence
from typing import Any

import cv2
import numpy as np
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidURI

from ..protocol import (
    Body,
    Calibrate,
    Calibration,
    Error,
    GetBody,
    Hello,
    Hmd,
    Message,
    Models,
    Pose,
    ProtocolError,
    Rgbd,
    SelectModel,
    SetBody,
    Welcome,
    decode_from_server,
    encode,
)
from . import body_lengths, read_server_message, session_url

log = logging.getLogger("egoposevr.input")
# Fatal refusals that retrying cannot fix: a wrong token, a session taken, or a hello the server refuses for
# its content (it answers the broken rule's own code, PROTOCOL.md §4).
PERMANENT_REFUSALS = frozenset(
    {"auth_failed", "session_busy", "invalid_field", "wrong_length", "missing_field", "unsupported_version"}
)


class InputClientError(RuntimeError):
    """The server refused the session for good, or the client was used after closing."""


class BodyRefused(ValueError):
    """The server refused a body this client gave (``out_of_range``: not a body's proportions, PROTOCOL.md §4.2);
    the session's body stayed as it was, and the client no longer gives it at a reconnect."""


class HeadsetClient:
    """One headset's connection; use ``async with`` or ``connect`` / ``close``."""

    def __init__(
        self,
        url: str,
        session: str,
        *,
        model: str | None = None,
        token: str | None = None,
        label: str = "egoposevr-input",
        reconnect: bool = True,
        backoff_s: tuple[float, float] = (0.25, 5.0),
        jpeg_quality: int = 90,
        pose_buffer: int = 64,
        body: Sequence[float] | None = None,
    ) -> None:
        self.url, self.session, self.model, self.token, self.label = url, session, model, token, label
        self.reconnect, self.backoff_s, self.jpeg_quality = reconnect, backoff_s, jpeg_quality
        self.welcome: Welcome | None = None
        self.models: Models | None = None
        self.calibration: Calibration | None = None  # the newest calibration message
        self._calibration_changed = asyncio.Event()
        self.body: Body | None = None  # the newest body message
        self._body_changed = asyncio.Event()
        self._body_refusal: Error | None = None  # the server's refusal of the last body given, until read
        # The wearer's body given after every welcome (set_body, PROTOCOL.md §4.2), or None: the server estimates it.
        self.given_body: list[float] | None = None if body is None else body_lengths(body)
        self.errors: deque[Error] = deque(maxlen=100)  # the newest error replies
        self.dropped_offline = 0  # samples and frames sent while disconnected
        self.dropped_poses = 0  # poses the reader did not take in time (the buffer keeps the newest)
        self.reconnects = 0
        self.counts: dict[str, int] = {}  # "unreadable": server messages that broke the protocol, skipped
        self._poses: asyncio.Queue[Pose] = asyncio.Queue(pose_buffer)
        self._ws: ClientConnection | None = None
        self._online = asyncio.Event()
        self._reader: asyncio.Task[None] | None = None
        self._closed = False
        self._failure: InputClientError | None = None
        self._hmd_seq = 0
        self._rgbd_seq = 0

    # ------------------------------------------------------------------------------ connection
    async def __aenter__(self) -> HeadsetClient:
        await self.connect()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def connect(self) -> Welcome:
        """Connect and say hello; returns the server's welcome. Raises InputClientError if refused."""
        welcome = await self._open()
        self._reader = asyncio.create_task(self._read_forever())
        return welcome

    async def _open(self) -> Welcome:
        ws = await connect(session_url(self.url, self.session), compression=None, max_size=None)
        hello = Hello(
            role="input", session=self.session, model=self.model, token=self.token, client=self.label
        )
        await ws.send(encode(hello))
        try:
            first = decode_from_server(await ws.recv())
        except ProtocolError as exc:
            await ws.close()
            raise InputClientError(f"the server's answer to hello is unreadable: {exc}") from exc
        if not isinstance(first, Welcome | Error):
            await ws.close()
            raise InputClientError(
                f"the server answered hello with {getattr(first, 'type', 'an unknown type')}"
            )
        if isinstance(first, Error):
            await ws.close()
            raise InputClientError(f"the server refused the session: {first.code}: {first.message}")
        # Before anything else this connection sends, so that every sample is served with the body.
        if self.given_body is not None:
            await ws.send(encode(SetBody(bone_lengths_m=self.given_body)))
        self.welcome, self._ws = first, ws
        self._online.set()
        return first

    async def close(self) -> None:
        self._closed = True
        self._online.clear()
        if self._reader is not None:
            self._reader.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._reader
        if self._ws is not None:
            await self._ws.close()

    @property
    def online(self) -> bool:
        return self._online.is_set()

    async def wait_online(self, timeout: float | None = None) -> None:
        await asyncio.wait_for(self._online.wait(), timeout)

    async def _read_forever(self) -> None:
        delay = self.backoff_s[0]
        while not self._closed:
            try:
                async for data in self._ws:
                    msg = read_server_message(data, self.counts)
                    if msg is not None:
                        self._on_message(msg)
                    delay = self.backoff_s[0]
            except ConnectionClosed:
                pass
            self._online.clear()
            if self._closed or self._failure is not None or not self.reconnect:
                return
            while not self._closed:  # reconnect with exponential backoff, same session
                await asyncio.sleep(delay)
                delay = min(delay * 2, self.backoff_s[1])
                try:
                    await self._open()
                    self.reconnects += 1
                    log.info("reconnected to %s (session %s)", self.url, self.session)
                    break
                except InputClientError as exc:
                    if any(code in str(exc) for code in PERMANENT_REFUSALS):
                        self._failure = exc
                        return
                except (OSError, TimeoutError, InvalidHandshake, InvalidURI, ConnectionClosed):
                    continue

    def _on_message(self, msg: Message) -> None:
        if isinstance(msg, Pose):
            if self._poses.full():
                self._poses.get_nowait()
                self.dropped_poses += 1
            self._poses.put_nowait(msg)
        elif isinstance(msg, Models):
            self.models = msg
        elif isinstance(msg, Calibration):
            self.calibration = msg
            self._calibration_changed.set()
        elif isinstance(msg, Body):
            self.body = msg
            self._body_changed.set()
        elif isinstance(msg, Error):
            self.errors.append(msg)
            if msg.ref is not None and msg.ref.type == "set_body":
                self.given_body = None  # refused: giving it again at a reconnect would be refused again
                self._body_refusal = msg
                self._body_changed.set()
            if msg.fatal and msg.code in PERMANENT_REFUSALS:
                self._failure = InputClientError(f"the server ended the session: {msg.code}: {msg.message}")

    # ------------------------------------------------------------------------------ sending
    async def _send(self, msg: Message) -> bool:
        if self._failure is not None:
            raise self._failure
        if self._closed:
            raise InputClientError("the client is closed")
        if not self.online:
            self.dropped_offline += 1
            return False
        try:
            await self._ws.send(encode(msg))
            return True
        except ConnectionClosed:
            self.dropped_offline += 1
            return False

    async def send_hmd(
        self,
        t_us: int,
        head: Sequence[float],
        left: Sequence[float],
        right: Sequence[float],
        valid: Sequence[bool] = (True, True, True),
    ) -> int:
        """One headset sample (poses ``[px, py, pz, qx, qy, qz, qw]``, metres); returns its seq."""
        self._hmd_seq += 1
        msg = Hmd(seq=self._hmd_seq, t_us=int(t_us), head=_floats(head), left=_floats(left),
                  right=_floats(right), valid=[bool(v) for v in valid])  # fmt: skip
        await self._send(msg)
        return self._hmd_seq

    async def send_rgbd(
        self,
        t_us: int,
        rgb: np.ndarray,
        depth_mm: np.ndarray,
        intrinsics: Sequence[float],
        cam_from_head: np.ndarray | None = None,
    ) -> int:
        """One camera frame: rgb (H, W, 3) uint8 RGB, depth (H, W) uint16 mm, intrinsics (fx, fy, cx, cy) px,
        cam_from_head (4, 4) or None. Encodes JPEG and 16-bit PNG off the event loop; returns its seq."""
        rgb_jpeg, depth_png = await asyncio.to_thread(encode_frame, rgb, depth_mm, self.jpeg_quality)
        self._rgbd_seq += 1
        msg = Rgbd(
            seq=self._rgbd_seq, t_us=int(t_us), width=rgb.shape[1], height=rgb.shape[0],
            intrinsics=_floats(intrinsics), rgb=rgb_jpeg, depth=depth_png,
            cam_from_head=None if cam_from_head is None else _floats(np.asarray(cam_from_head).reshape(16)),
        )  # fmt: skip
        await self._send(msg)
        return self._rgbd_seq

    async def select_model(self, name: str) -> None:
        self.model = name  # also the model a reconnect asks for
        await self._send(SelectModel(model=name))

    async def calibrate(
        self, pose: str = "tpose", seconds: float = 2.0, timeout_s: float = 30.0
    ) -> Calibration:
        """Ask the server to measure the wearer (PROTOCOL.md §4.1); keep sending ``hmd`` meanwhile. Returns
        the final ``calibration`` message (``done`` or ``failed``; read its ``status``)."""
        return await self._calibration_request(Calibrate(pose=pose, seconds=seconds), timeout_s)

    async def clear_calibration(self, timeout_s: float = 10.0) -> Calibration:
        return await self._calibration_request(Calibrate(clear=True), timeout_s)

    async def _calibration_request(self, msg: Calibrate, timeout_s: float) -> Calibration:
        self.calibration = None
        self._calibration_changed.clear()
        await self._send(msg)
        async with asyncio.timeout(timeout_s):
            while True:
                await self._calibration_changed.wait()
                self._calibration_changed.clear()
                if self.calibration is not None and self.calibration.status != "started":
                    return self.calibration

    async def get_body(self, timeout_s: float = 10.0) -> Body:
        """The wearer's body as the session knows it (PROTOCOL.md §4.2). Keep the ``bone_lengths_m`` of a ``measured``
        one with the wearer's profile, and give them back with :meth:`set_body` at their next session."""
        return await self._body_request(GetBody(), timeout_s)

    async def set_body(self, bone_lengths_m: Sequence[float] | None, timeout_s: float = 10.0) -> Body:
        """Serve a known wearer's body (21 bone lengths, m, as ``body`` gave them) from the next sample on, and
        give it again after every reconnect; with None, estimate it again (PROTOCOL.md §4.2). Returns the server's
        ``body``. Raises :class:`BodyRefused` for a body the server refuses (not a body's proportions; the
        session's body stays as it was) and ValueError for one the wire does not take (clients.body_lengths)."""
        lengths = None if bone_lengths_m is None else body_lengths(bone_lengths_m)
        self.given_body = lengths
        msg = SetBody(clear=True) if lengths is None else SetBody(bone_lengths_m=lengths)
        return await self._body_request(msg, timeout_s)

    async def _body_request(self, msg: SetBody | GetBody, timeout_s: float) -> Body:
        self.body, self._body_refusal = None, None
        self._body_changed.clear()
        await self._send(msg)
        async with asyncio.timeout(timeout_s):
            await self._body_changed.wait()
        if self._body_refusal is not None:
            raise BodyRefused(f"{self._body_refusal.code}: {self._body_refusal.message}")
        assert self.body is not None
        return self.body

    # ------------------------------------------------------------------------------ receiving
    async def poses(self) -> AsyncIterator[Pose]:
        """Poses as they come, across reconnects; ends when the client closes or is refused for good."""
        while not self._closed:
            if self._failure is not None:
                raise self._failure
            try:
                # asyncio.timeout, not wait_for: in Python 3.11 wait_for can swallow a cancellation that
                # arrives as the queue hands over a pose, leaving a cancelled consumer looping forever.
                async with asyncio.timeout(0.5):
                    pose = await self._poses.get()
            except TimeoutError:
                continue
            yield pose


def encode_frame(rgb: np.ndarray, depth_mm: np.ndarray, jpeg_quality: int = 90) -> tuple[bytes, bytes]:
    """RGB (H, W, 3) uint8 and depth (H, W) uint16 mm -> (JPEG, 16-bit PNG) as the protocol wants them."""
    rgb, depth_mm = np.asarray(rgb), np.asarray(depth_mm)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"rgb must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    if depth_mm.dtype != np.uint16 or depth_mm.shape != rgb.shape[:2]:
        raise ValueError(
            f"depth must be {rgb.shape[:2]} uint16 millimetres, got {depth_mm.shape} {depth_mm.dtype}"
        )
    ok_rgb, jpeg = cv2.imencode(
        ".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality]
    )
    ok_depth, png = cv2.imencode(".png", depth_mm, [cv2.IMWRITE_PNG_COMPRESSION, 1])  # speed over size
    if not (ok_rgb and ok_depth):
        raise ValueError("OpenCV could not encode the frame")
    return jpeg.tobytes(), png.tobytes()


def _floats(values: Any) -> list[float]:
    return [float(v) for v in values]
