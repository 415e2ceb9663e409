"""Test helpers: a real server on a loopback port (in a background thread with its own event loop) and a
blocking client. Blocking clients (websockets.sync) keep the tests linear and let hypothesis drive the socket.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import threading
import time
import urllib.parse
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgpack
from websockets.client import ClientProtocol
from websockets.exceptions import ConnectionClosed
from websockets.protocol import State
from websockets.sync.client import ClientConnection, connect
from websockets.uri import parse_uri

from egoposevr.protocol import Hello, Hmd, Message, decode, encode
from egoposevr.protocol.examples import example_messages
from egoposevr.recordings.egrec import KIND_CLIENT, read_records
from egoposevr.server.app import Server
from egoposevr.server.config import ServerConfig

RECORDINGS = Path(__file__).resolve().parents[1] / "recordings"


class ServerThread:
    """``Server`` running in a daemon thread; ``stop`` stops it gracefully."""

    def __init__(self, config: ServerConfig) -> None:
        self.config = config
        self.loop = asyncio.new_event_loop()
        self.server = Server(config)
        self._started = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._main, daemon=True)

    def _main(self) -> None:
        asyncio.set_event_loop(self.loop)
        try:
            self.loop.run_until_complete(self.server.start())
        except BaseException as exc:
            self._error = exc
            self._started.set()
            self.loop.close()
            return
        self._started.set()
        self.loop.run_forever()

    def start(self) -> ServerThread:
        self._thread.start()
        self._started.wait(30)
        if self._error is not None:
            raise self._error
        return self

    def stop(self) -> None:
        if self._thread.is_alive():
            asyncio.run_coroutine_threadsafe(self.server.stop(), self.loop).result(30)
            self.loop.call_soon_threadsafe(self.loop.stop)
            self._thread.join(10)
        if not self.loop.is_running():
            self.loop.close()

    @property
    def url(self) -> str:
        return self.server.url

    @property
    def http(self) -> str:
        return f"http://127.0.0.1:{self.server.port}"

    def get(self, path: str) -> tuple[int, str]:
        try:
            with urllib.request.urlopen(self.http + path, timeout=5) as reply:
                return reply.status, reply.read().decode()
        except urllib.error.HTTPError as exc:
            return exc.code, exc.read().decode()

    def metric(self, name: str, **labels: str) -> float:
        """The value of one sample in /metrics (0 when absent)."""
        want = name + (
            "{" + ",".join(f'{k}="{v}"' for k, v in sorted(labels.items())) + "}" if labels else ""
        )
        for line in self.get("/metrics")[1].splitlines():
            if line.startswith(want + " "):
                return float(line.rsplit(" ", 1)[1])
        return 0.0


def server_config(**overrides: Any) -> ServerConfig:
    defaults = {"port": 0, "workers": 2, "rescan_s": 0.2, "shutdown_timeout_s": 3.0}
    return ServerConfig(**(defaults | overrides))


@contextlib.contextmanager
def running_server(**overrides: Any) -> Iterator[ServerThread]:
    thread = ServerThread(server_config(**overrides)).start()
    try:
        yield thread
    finally:
        thread.stop()


class Client:
    """A blocking protocol client with helpers for the tests."""

    def __init__(self, url: str, session: str | None = None, **kwargs: Any) -> None:
        query = f"?session={session}" if session else ""
        self.ws: ClientConnection = connect(
            url + query, compression=None, open_timeout=10, legacy=True, **kwargs
        )

    def send(self, msg: Message | bytes | str) -> None:
        self.ws.send(encode(msg) if isinstance(msg, Message) else msg)

    def recv(self, timeout: float = 5.0) -> Message:
        return decode(self.ws.recv(timeout=timeout))

    def recv_type(self, msg_type: str, timeout: float = 5.0) -> Message:
        """The next message of ``msg_type``, skipping others (poses, models) on the way."""
        deadline = time.monotonic() + timeout
        while True:
            msg = self.recv(max(deadline - time.monotonic(), 0.01))
            if msg.type == msg_type:
                return msg

    def hello(self, role: str, session: str, **fields: Any) -> Message:
        self.send(Hello(role=role, session=session, **fields))
        welcome = self.recv()
        if welcome.type == "welcome":
            self.recv_type("models")
        return welcome

    def collect(self) -> Client:
        """Read everything from now on in a background thread into ``received`` [(perf_counter, msg)]."""
        self.received: list[tuple[float, Message]] = []

        def reader() -> None:
            with contextlib.suppress(Exception):
                for data in self.ws:
                    self.received.append((time.perf_counter(), decode(data)))

        threading.Thread(target=reader, daemon=True).start()
        return self

    def poses(self) -> list[Message]:
        return [m for _, m in self.received if m.type == "pose"]

    def wait_for(self, predicate: Any, timeout: float = 5.0, poll_s: float = 0.01) -> None:
        deadline = time.monotonic() + timeout
        while not predicate():
            assert time.monotonic() < deadline, "timed out waiting"
            time.sleep(poll_s)

    def close(self) -> None:
        self.ws.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def recorded_messages(name: str = "walk-0000", limit: int | None = None) -> list[tuple[int, str, bytes]]:
    """(send time µs, type, message bytes) of a bundled recording's client messages, hello left out."""
    out = []
    for record in read_records(RECORDINGS / f"{name}.egrec"):
        if record.kind == KIND_CLIENT and (kind := decode(record.payload).type) != "hello":
            out.append((record.t_us, kind, record.payload))
    return out[:limit]


def _paced(messages: list[tuple[int, str, bytes]], speed: float) -> Iterator[tuple[str, bytes]]:
    """(type, message bytes) of each message, each at its time from the first's, divided by ``speed``."""
    start = time.perf_counter()
    t0 = messages[0][0]
    for t_us, kind, data in messages:
        delay = (t_us - t0) * 1e-6 / speed - (time.perf_counter() - start)
        if delay > 0:
            time.sleep(delay)
        yield kind, data


def replay(client: Client, messages: list[tuple[int, str, bytes]], speed: float = 1.0) -> dict[int, float]:
    """Send ``messages`` paced by their times -> {hmd seq: perf_counter send time}."""
    sent = {}
    for kind, data in _paced(messages, speed):
        if kind == "hmd":
            sent[decode(data).seq] = time.perf_counter()
        client.send(data)
    return sent


def replay_until(
    client: Client, messages: list[tuple[int, str, bytes]], done: Any, timeout: float, speed: float = 1.0
) -> bool:
    """Send ``messages`` paced by their times until ``done()`` holds (checked before each message) or
    ``timeout`` seconds pass -> whether it held. For what the server does some time after a message: a real
    headset keeps streaming meanwhile, so a test that stops sending could wait for a pose that never comes."""
    start = time.perf_counter()
    for _, data in _paced(messages, speed):
        if done():
            return True
        if time.perf_counter() - start > timeout:
            return False
        client.send(data)
    deadline = time.perf_counter() + 1.0  # the last messages' answers
    while not done() and time.perf_counter() < deadline:
        time.sleep(0.01)
    return done()


# ------------------------------------------------------------------------------------------ raw and odd clients
def stream_flowed(report: dict[str, Any]) -> bool:
    """A ``replay --json`` report of a second-long stream that reached the server and back: the recording's
    samples went out at its rate, answers came, and every sample was answered or reported skipped but the few
    still in flight at the cut. Not a speed bar: a loaded machine answers fewer and skips more (PROTOCOL.md),
    which the benchmark measures."""
    return report["sent"] > 50 and report["answered"] > 0 and report["unanswered"] <= 5


def hmd_messages(t_us: Any, poses: Any, valid: Any, first_seq: int = 0) -> list[Hmd]:
    """``hmd`` messages for samples at t_us (N,) with device poses (N, 3, 7) and valid (N, 3), numbered from
    ``first_seq``."""
    return [
        Hmd(seq=first_seq + k, t_us=int(t), head=p[0].tolist(), left=p[1].tolist(), right=p[2].tolist(),
            valid=[bool(x) for x in v])
        for k, (t, p, v) in enumerate(zip(t_us, poses, valid, strict=True))
    ]  # fmt: skip


def address(url: str) -> tuple[str, int]:
    """(host, port) of a ws:// URL."""
    parts = urllib.parse.urlsplit(url)
    return parts.hostname, parts.port


def raw_client(
    url: str, session: str, role: str = "render", receive_buffer: int | None = None
) -> socket.socket:
    """A client that joins (upgrade + hello) and then never reads its socket: it drains nothing and answers
    no ping, as a stalled viewer or a peer gone without closing (half-open TCP) does. The handshake is
    driven by websockets' sans-I/O protocol, so nothing reads in the background. ``receive_buffer`` sets the
    TCP window before connecting (a small one makes the server's sends back up quickly)."""
    protocol = ClientProtocol(parse_uri(url + f"?session={session}"))
    sock = socket.socket()
    if receive_buffer is not None:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, receive_buffer)
    sock.connect(address(url))
    protocol.send_request(protocol.connect())
    sock.sendall(b"".join(protocol.data_to_send()))
    while protocol.state is State.CONNECTING:
        protocol.receive_data(sock.recv(4096))
    protocol.send_binary(encode(Hello(role=role, session=session)))
    sock.sendall(b"".join(protocol.data_to_send()))
    return sock


def close_code(client: Client, timeout: float = 10.0) -> int:
    """Read until the server closes the connection (messages still queued are skipped): its close code."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            client.recv(timeout=timeout)
        except ConnectionClosed as closed:
            return closed.rcvd.code
    raise AssertionError("the connection stayed open")


def pack(obj: Any) -> bytes:
    """Any value as msgpack, unvalidated (for messages the server must refuse)."""
    return msgpack.packb(obj, use_bin_type=True)


def example_with(kind: str, **changes: Any) -> bytes:
    """The canonical example message of ``kind`` with fields changed (None deletes), packed unvalidated."""
    fields = example_messages()[kind].model_dump(exclude_none=True)
    for key, value in changes.items():
        if value is None:
            fields.pop(key)
        else:
            fields[key] = value
    return pack(fields)
