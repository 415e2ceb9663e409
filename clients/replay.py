"""The mock headset: replay a recorded session (``.egrec``) against a server at the recorded pace.

``hmd`` and ``rgbd`` messages are sent when their recorded send times come (scaled by ``speed``); every pose
that comes back is matched to the sample it answers. The report gives end-to-end latency (sample sent → pose
received, one clock), answered and skipped samples, and, when the recording carries ground truth, MPJPE of
the upper and lower body. With ``loop`` the recording repeats, with ``seq`` and ``t_us`` shifted so they keep
increasing (the server sees one continuous stream). With ``body_file`` the mock headset is a returning wearer
(PROTOCOL.md §4.2): a body kept in that file is given before the first sample, and at the end the body the
server measured, if it did, is written there for the next run.

Shape legend: ``J`` = 22 joints.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from ..model.skeleton import LOWER_BODY, NUM_JOINTS, UPPER_BODY
from ..protocol import (
    GetBody,
    Hello,
    Message,
    ProtocolError,
    SetBody,
    decode,
    encode,
)
from ..recordings.egrec import KIND_CLIENT, KIND_TRUTH, Cut, read_header, read_records
from . import body_lengths, read_server_message, session_url

LOOP_SEQ_STRIDE = 1_000_000  # seq offset per loop: far above any recording's own seq range
KEEP_SAMPLES = 200_000  # per measured quantity: about 37 minutes of poses at 90 Hz
MAX_UNANSWERED = 10_000  # samples awaiting their pose
BODY_ANSWER_S = 5.0  # how long the end of a replay waits for the server's body
REPORT_KEYS = ("latency_ms", "answered", "skipped", "mpjpe_u_cm", "mpjpe_l_cm")


class ReplayError(RuntimeError):
    """The replay could not run: unreadable recording, unreachable server, or a fatal error from it."""


@dataclasses.dataclass(frozen=True)
class Recording:
    """A session's client messages and ground truth, ready to send."""

    path: Path
    header: dict[str, Any]
    messages: list[tuple[int, Message, bytes]]  # (send time µs from start, decoded, exact bytes), no hello
    hello: Hello | None
    truth: dict[int, np.ndarray]  # hmd seq -> (J, 3) true joints, m
    cut: Cut | None = None  # set when the file was cut short and only its good part was read

    @classmethod
    def load(cls, path: str | Path, strict: bool = False) -> Recording:
        """Read a recording. A file cut short (crash, full disk) loads up to its last complete record and
        says so in ``cut``; ``strict`` refuses it instead (:class:`EgrecError`)."""
        path = Path(path)
        header = read_header(path)
        messages, hello, truth = [], None, {}
        cut = Cut()
        for record in read_records(path, strict=strict, cut=cut):
            if record.kind == KIND_CLIENT:
                try:
                    msg = decode(record.payload)
                except ProtocolError as exc:
                    raise ReplayError(f"{path}: a recorded message is not protocol v1 ({exc})") from None
                if isinstance(msg, Hello):
                    hello = msg
                elif msg.type in ("hmd", "rgbd", "select_model", "calibrate"):
                    messages.append((record.t_us, msg, record.payload))
            elif record.kind == KIND_TRUTH:
                truth[int(record.payload["seq"])] = np.asarray(record.payload["joints"]).reshape(
                    NUM_JOINTS, 3
                )
        if not any(m.type == "hmd" for _, m, _ in messages):
            why = f" ({cut.describe()})" if cut.happened else ""
            raise ReplayError(f"{path}: no hmd messages to replay{why}")
        entries = [_with_truth(m, truth) for m in messages]
        return cls(path, header, entries, hello, truth, cut if cut.happened else None)

    def cut_warning(self, doing: str) -> str | None:
        """For a recording read only up to a cut: what was lost, for a command that is ``doing`` (e.g.
        "replaying") its good part; None for a whole recording."""
        if self.cut is None:
            return None
        return (
            f"warning: {self.path} was {self.cut.describe()}; {doing} the {len(self.messages)} messages "
            "before it"
        )

    @property
    def duration_us(self) -> int:
        return self.messages[-1][0] - self.messages[0][0]

    def retimed(self, hmd_rate_hz: float, camera_rate_hz: float) -> Recording:
        """The same session at other rates: a headset sample every 1/hmd_rate and a frame every 1/camera_rate
        (0: no camera), each the recorded one nearest its tick, re-stamped and renumbered."""
        if hmd_rate_hz <= 0 or camera_rate_hz < 0:
            raise ValueError(f"rates must be positive, got hmd {hmd_rate_hz} Hz, camera {camera_rate_hz} Hz")
        start, end = self.messages[0][1].t_us, self.messages[-1][1].t_us
        streams = []
        for kind, rate in (("hmd", hmd_rate_hz), ("rgbd", camera_rate_hz)):
            recorded = [m for _, m, _ in self.messages if m.type == kind]
            if rate == 0 or not recorded:
                continue
            times = np.array([m.t_us for m in recorded])
            ticks = start + np.arange(0, end - start + 1, 1e6 / rate).astype(np.int64)
            nearest = np.clip(np.searchsorted(times, ticks), 1, len(times) - 1)
            nearest -= np.abs(times[nearest - 1] - ticks) <= np.abs(times[nearest] - ticks)
            for seq, (tick, k) in enumerate(zip(ticks, nearest, strict=True), start=1):
                msg = recorded[k].model_copy(update={"seq": seq, "t_us": int(tick)})
                streams.append((int(tick) - start, msg, encode(msg)))
        streams.sort(key=lambda entry: entry[0])
        truth = {
            m.seq: np.reshape(m.truth, (NUM_JOINTS, 3)) for _, m, _ in streams if m.type == "hmd" and m.truth
        }
        return dataclasses.replace(self, messages=streams, truth=truth)


def _with_truth(
    entry: tuple[int, Message, bytes], truth: dict[int, np.ndarray]
) -> tuple[int, Message, bytes]:
    """An hmd message carrying its recorded ground truth (``hmd.truth``), so viewers can draw it."""
    t_us, msg, _ = entry
    if msg.type != "hmd" or msg.truth is not None or msg.seq not in truth:
        return entry
    msg = msg.model_copy(update={"truth": truth[msg.seq].reshape(-1).tolist()})
    return t_us, msg, encode(msg)


@dataclasses.dataclass
class ReplayStats:
    """What the replay measured so far; ``report`` turns it into the JSON the CLI writes."""

    sent: int = 0
    answered: int = 0
    skipped: int = 0
    errors: dict[str, int] = dataclasses.field(default_factory=dict)
    # Bounded, so a demo looping for days keeps its memory: percentiles cover the newest KEEP_SAMPLES poses.
    latency_ms: deque[float] = dataclasses.field(default_factory=lambda: deque(maxlen=KEEP_SAMPLES))
    error_u_m: deque[float] = dataclasses.field(default_factory=lambda: deque(maxlen=KEEP_SAMPLES))
    error_l_m: deque[float] = dataclasses.field(default_factory=lambda: deque(maxlen=KEEP_SAMPLES))
    models: set[str] = dataclasses.field(default_factory=set)
    stages_us: dict[str, deque[int]] = dataclasses.field(default_factory=dict)  # the server's timing_us
    body: str | None = None  # with a body file: "given", then "kept" or why not

    def report(self) -> dict[str, Any]:
        lat = np.asarray(self.latency_ms)
        percentiles = {f"p{q}": float(np.percentile(lat, q)) if len(lat) else None for q in (50, 95, 99)}
        return {
            "latency_ms": percentiles | {"max": float(lat.max()) if len(lat) else None},
            "answered": self.answered,
            "skipped": self.skipped,
            "sent": self.sent,
            "unanswered": max(self.sent - self.answered - self.skipped, 0),
            "mpjpe_u_cm": 100 * float(np.mean(self.error_u_m)) if self.error_u_m else None,
            "mpjpe_l_cm": 100 * float(np.mean(self.error_l_m)) if self.error_l_m else None,
            "errors": dict(self.errors),
            "models": sorted(self.models),
            "body": self.body,
        }


def summary_line(report: dict[str, Any]) -> str:
    """One human line: latency percentiles, counts, accuracy."""
    lat = report["latency_ms"]
    text = "no poses yet"
    if lat["p50"] is not None:
        text = f"latency p50 {lat['p50']:.1f} / p95 {lat['p95']:.1f} / p99 {lat['p99']:.1f} / max {lat['max']:.1f} ms"
    text += f"  answered {report['answered']}  skipped {report['skipped']}"
    if report["mpjpe_u_cm"] is not None:
        text += f"  MPJPE upper {report['mpjpe_u_cm']:.1f} cm  lower {report['mpjpe_l_cm']:.1f} cm"
    if report["errors"]:
        text += "  errors " + ", ".join(f"{k} {v}" for k, v in sorted(report["errors"].items()))
    if report.get("body"):
        text += f"  body {report['body']}"
    return text


def read_body_file(path: Path) -> list[float] | None:
    """The bone lengths (21, m) kept in a body file, None when there is no file; ReplayError for one that is
    not a kept body (damaged, or not written by a replay)."""
    try:
        kept = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ReplayError(f"{path}: not a kept body ({exc})") from None
    try:
        return body_lengths(kept["bone_lengths_m"] if isinstance(kept, dict) else None)
    except (KeyError, ValueError):
        raise ReplayError(
            f'{path}: not a kept body (expected {{"bone_lengths_m": 21 lengths in metres}})'
        ) from None


class Replayer:
    """One replay run against ``url``; ``run`` returns the stats (also readable while it runs)."""

    def __init__(
        self,
        recording: Recording,
        url: str,
        session: str | None = None,
        model: str | None = None,
        speed: float = 1.0,
        loop: bool = False,
        seconds: float | None = None,
        token: str | None = None,
        body_file: Path | None = None,
    ) -> None:
        if speed <= 0:
            raise ValueError(f"speed must be > 0, got {speed}")
        self.recording, self.url, self.speed, self.loop, self.seconds = recording, url, speed, loop, seconds
        recorded = recording.hello
        self.session = session or (
            recorded.session if recorded else recording.header.get("session", "replay")
        )
        self.model = model or (recorded.model if recorded else None)
        self.token = token
        self.body_file = body_file
        # Read now, so that a damaged file fails before connecting.
        self._kept_body = None if body_file is None else read_body_file(body_file)
        self._body_answer: asyncio.Queue[Any] = asyncio.Queue()  # body messages, for the end's get_body
        self.stats = ReplayStats()
        self.stopping = False  # set by stop(): the replay ends after the current message, cleanly
        self._sent_at: dict[int, float] = {}  # hmd seq -> perf_counter at send

    def stop(self) -> None:
        """Ask a running replay to finish (safe from another thread or a signal handler)."""
        self.stopping = True

    async def run(self, on_second: Callable[[ReplayStats], None] | None = None) -> ReplayStats:
        try:
            async with connect(session_url(self.url, self.session), compression=None,
                               max_size=None, open_timeout=10) as ws:  # fmt: skip
                await ws.send(encode(Hello(role="input", session=self.session, model=self.model,
                                           token=self.token, client="egoposevr replay")))  # fmt: skip
                # Before the first sample, so that every one is served with it.
                if self._kept_body is not None:
                    await ws.send(encode(SetBody(bone_lengths_m=self._kept_body)))
                    self.stats.body = "given"
                reader = asyncio.create_task(self._receive(ws))
                ticker = asyncio.create_task(self._tick(on_second)) if on_second else None
                try:
                    await self._send_all(ws, reader)
                    await asyncio.wait({reader}, timeout=1.0)  # the last poses
                    if self.body_file is not None and not reader.done():
                        await self._keep_body(ws)
                finally:
                    for task in (reader, ticker):
                        if task is not None:
                            task.cancel()
                if reader.done() and not reader.cancelled() and reader.exception():
                    raise reader.exception()
        except (OSError, TimeoutError) as exc:
            raise ReplayError(f"cannot reach {self.url}: {exc}") from None
        return self.stats

    async def _keep_body(self, ws: Any) -> None:
        """Ask for the body the session knows and write it to the body file if the server measured it."""
        while not self._body_answer.empty():  # the answer to the set_body at the start
            self._body_answer.get_nowait()
        await ws.send(encode(GetBody()))
        try:
            async with asyncio.timeout(BODY_ANSWER_S):
                body = await self._body_answer.get()
        except TimeoutError:
            self.stats.body = "not kept: the server did not answer get_body"
            return
        if body.given:
            return  # the session served the kept body: nothing new was measured
        if not body.measured:
            self.stats.body = "not kept: the server has not measured this wearer (camera and standing needed)"
            return
        record = {"bone_lengths_m": body.bone_lengths_m, "recording": str(self.recording.path)}
        self.body_file.write_text(json.dumps(record, indent=1))
        self.stats.body = f"kept in {self.body_file}"

    async def _send_all(self, ws: Any, reader: asyncio.Task) -> None:
        start = time.perf_counter()
        first_us = self.recording.messages[0][0]
        period_us = self.recording.duration_us + 11_111  # one headset interval between loops
        repeat = 0
        while True:
            for t_us, msg, data in self.recording.messages:
                due_s = (t_us - first_us + repeat * period_us) * 1e-6 / self.speed
                if self.seconds is not None and due_s >= self.seconds:
                    return
                delay = due_s - (time.perf_counter() - start)
                if delay > 0:
                    await asyncio.sleep(delay)
                if reader.done() or self.stopping:  # the server closed the connection, or stop()
                    return
                await ws.send(self._shifted(msg, data, repeat, period_us))
            repeat += 1
            if not self.loop:
                return

    def _shifted(self, msg: Message, data: bytes, repeat: int, period_us: int) -> bytes:
        """The message for this loop: seq and t_us moved on so the stream keeps increasing."""
        seq = getattr(msg, "seq", None)
        if repeat and seq is not None:
            msg = msg.model_copy(
                update={"seq": seq + repeat * LOOP_SEQ_STRIDE, "t_us": msg.t_us + repeat * period_us}
            )
            data = encode(msg)
        if msg.type == "hmd":
            self.stats.sent += 1
            self._sent_at[msg.seq] = time.perf_counter()
            if len(self._sent_at) > MAX_UNANSWERED:  # a server that stopped answering: forget the oldest
                del self._sent_at[next(iter(self._sent_at))]
        return data

    async def _receive(self, ws: Any) -> None:
        try:
            async for data in ws:
                received = time.perf_counter()
                msg = read_server_message(data, self.stats.errors)
                if msg is None:
                    continue
                if msg.type == "pose":
                    self._on_pose(msg, received)
                elif msg.type == "body":
                    self._body_answer.put_nowait(msg)
                elif msg.type == "error":
                    self.stats.errors[msg.code] = self.stats.errors.get(msg.code, 0) + 1
                    if msg.ref is not None and msg.ref.type == "set_body":
                        self.stats.body = f"refused: {msg.message}"
                    if msg.fatal:
                        raise ReplayError(f"the server refused the session: {msg.code}: {msg.message}")
        except ConnectionClosed:
            return

    def _on_pose(self, pose: Any, received: float) -> None:
        stats = self.stats
        sent = self._sent_at.pop(pose.seq, None)
        if sent is not None:
            stats.latency_ms.append((received - sent) * 1e3)
        for seq in [s for s in self._sent_at if s < pose.seq]:  # older samples will get no pose now
            del self._sent_at[seq]
        stats.answered += 1
        stats.skipped += pose.skipped or 0
        stats.models.add(pose.model)
        for stage, us in pose.timing_us.items():
            stats.stages_us.setdefault(stage, deque(maxlen=KEEP_SAMPLES)).append(us)
        truth = self.recording.truth.get(pose.seq % LOOP_SEQ_STRIDE)
        if truth is not None:
            error = np.linalg.norm(np.asarray(pose.joints).reshape(NUM_JOINTS, 3) - truth, axis=-1)
            stats.error_u_m.append(float(error[UPPER_BODY].mean()))
            stats.error_l_m.append(float(error[LOWER_BODY].mean()))

    async def _tick(self, on_second: Callable[[ReplayStats], None]) -> None:
        while True:
            await asyncio.sleep(1.0)
            on_second(self.stats)
