"""The server: WebSocket and HTTP on one port, glued to the socket-free :class:`~egoposevr.server.hub.Hub`.

Reads as steps, like uvicorn: ``start`` (bind, load models, fail fast on a bad configuration, mark ready) →
serve (one task per connection, one sender task per connection, the scheduler's dispatch task, a model
rescan task) → ``stop`` (refuse new hellos and connections, tell every client ``shutting_down`` and close with
1001, wait a bounded time, abort what is left, flush recordings).

Threads: the event loop receives, decodes (microseconds), routes and sends; the sessions' inference runs in
the scheduler's worker pool and frame lane (server/scheduler.py: onnxruntime, OpenCV and the compiled kernels
release the GIL), one job at a time per session, several sessions' jobs batched, so the loop never waits for
a model. HTTP: ``/healthz`` (alive), ``/readyz`` (models loaded, not stopping), ``/metrics``
(Prometheus), ``/api/sessions`` (JSON), ``/viewer/`` (the web viewer); the WebSocket is ``/ws?session=ID``.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.resources
import json
import logging
import signal
import socket
import time
import urllib.parse
from collections.abc import AsyncIterator
from concurrent.futures import ThreadPoolExecutor
from http import HTTPStatus
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

from websockets.asyncio.server import Server as WsServer
from websockets.asyncio.server import ServerConnection, serve
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from ..model.runtime.loading import resolve_providers
from ..protocol import ErrorCode
from .config import ConfigError, ServerConfig
from .hub import CLOSE_NORMAL, Client, Hub
from .metrics import CONTENT_TYPE, Metrics
from .recorder import Recorder
from .registry import ModelRegistry
from .scheduler import Scheduler

log = logging.getLogger("egoposevr.server")
WS_PATH = "/ws"
# The web viewer's static files ship inside the clients package (data only: the server imports no client code).
VIEWER_DIR = Path(str(importlib.resources.files("egoposevr.clients") / "viewer"))
STATIC_TYPES = {
    ".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8", ".css": "text/css; charset=utf-8",
    ".md": "text/plain; charset=utf-8", ".png": "image/png", ".vrm": "model/gltf-binary",
}  # fmt: skip
# websockets refuses frames above max_size by closing with 1009 and no explanation; the headroom lets a
# message up to twice the protocol limit arrive so that the client gets a `too_large` error first.
FRAME_HEADROOM = 2


def server_name() -> str:
    try:
        return f"egoposevr/{version('egoposevr')}"
    except PackageNotFoundError:  # a source tree that was never installed
        return "egoposevr/0+unknown"


class Server:
    """One running server; use ``async with running(config) as server`` or ``start`` / ``stop``."""

    def __init__(self, config: ServerConfig) -> None:
        self.config = config
        self.metrics = Metrics()
        self.registry = ModelRegistry(
            config.models_dir, config.bundled_models, config.ort_threads, resolve_providers(config.providers)
        )
        self.recorder = (
            Recorder(config.record, server_name(), on_failure=self.metrics.recordings_failed.inc)
            if config.record
            else None
        )
        self.scheduler = Scheduler(
            self.metrics, config.workers, config.batch_window_ms * 1e-3, config.max_batch
        )
        self.hub = Hub(
            config, self.registry, self.metrics, self.scheduler, self.recorder, server_name=server_name()
        )
        self._loader = ThreadPoolExecutor(1, thread_name_prefix="egoposevr-models")
        self._connections: set[ServerConnection] = set()
        self._ws: WsServer | None = None
        self._rescan_task: asyncio.Task[None] | None = None
        self.stopping = False

    # ------------------------------------------------------------------------------ lifecycle
    async def start(self) -> None:
        """Bind, load the models, check the configuration against them, then accept hellos."""
        tls = self.config.ssl_context()  # a bad certificate fails before anything binds
        self._ws = await serve(
            self._connection,
            self.config.host,
            self.config.port,
            process_request=self._http,
            compression=None,
            max_size=self.config.max_message_bytes * FRAME_HEADROOM,
            max_queue=8,
            origins=self._origins(),
            open_timeout=self.config.hello_timeout_s,  # a TCP connection that never upgrades is dropped
            ping_interval=self.config.ping_interval_s,
            ping_timeout=self.config.ping_timeout_s,
            close_timeout=2,
            server_header=server_name(),
            ssl=tls,
        )
        try:
            await self._rescan()
            self._check_models()
        except BaseException:
            await self.stop()
            raise
        self.hub.ready = True
        if self.config.models_dir is not None and self.config.rescan_s > 0:
            self._rescan_task = asyncio.create_task(self._rescan_forever())
        scheme = "wss" if tls is not None else "ws"
        log.info(
            "serving %s on %s://%s:%d%s",
            ", ".join(self.registry.names()),
            scheme,
            self.config.host,
            self.port,
            WS_PATH,
        )

    def _check_models(self) -> None:
        names = self.registry.names()
        if not self.registry.file_names():
            problems = (
                "; ".join(f"{p}: {r}" for p, r in self.registry.failures.items()) or "no model files found"
            )
            raise ConfigError(f"no model could be loaded ({problems})")
        if self.config.default_model not in names:
            raise ConfigError(
                f"default_model {self.config.default_model!r} is not among the models: {', '.join(names)}"
            )

    def _origins(self) -> list[str | None] | None:
        # Browsers always send Origin; other clients (headsets, scripts) send none and are let through.
        return [*self.config.origins, None] if self.config.origins else None

    @property
    def port(self) -> int:
        return self._ws.sockets[0].getsockname()[1] if self._ws else self.config.port

    @property
    def url(self) -> str:
        host = "127.0.0.1" if self.config.host in ("0.0.0.0", "") else self.config.host
        scheme = "wss" if self.config.ssl_certfile is not None else "ws"
        return f"{scheme}://{host}:{self.port}{WS_PATH}"

    async def stop(self) -> None:
        """Graceful stop, bounded by ``shutdown_timeout_s``."""
        if self.stopping:
            return
        self.stopping = True
        self.hub.accepting = False
        if self._rescan_task is not None:
            self._rescan_task.cancel()
        if self._ws is not None:
            self._ws.close(close_connections=False)  # no new connections
            self.hub.shutdown()  # error + close 1001 through each client's outbox
            try:
                await asyncio.wait_for(asyncio.shield(self._ws.wait_closed()), self.config.shutdown_timeout_s)
            except TimeoutError:
                log.warning("%d connections did not close in time; aborting them", len(self._connections))
                for ws in list(self._connections):
                    ws.transport.abort()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._ws.wait_closed(), 1.0)
        self.scheduler.close()
        if self.recorder is not None:
            self.recorder.close_all()
        self._loader.shutdown(wait=False, cancel_futures=True)
        log.info("stopped")

    # ------------------------------------------------------------------------------ models
    async def _rescan(self) -> None:
        await asyncio.get_running_loop().run_in_executor(self._loader, self.registry.rescan)
        self.metrics.models_loaded.set(len(self.registry.models))
        for provider in self.registry.active_providers():
            self.metrics.execution_provider.labels(provider).set(1)
        self.metrics.model_failures.set(len(self.registry.failures))

    async def _rescan_forever(self) -> None:
        while True:
            await asyncio.sleep(self.config.rescan_s)
            try:
                await self._rescan()
            except Exception:  # a scan must never stop the server; the next one tries again
                log.exception("model rescan failed")

    # ------------------------------------------------------------------------------ HTTP
    def _http(self, connection: ServerConnection, request: Request) -> Response | None:
        path = urllib.parse.urlsplit(request.path).path
        if path == WS_PATH:
            return None  # the WebSocket handshake goes on
        if path == "/healthz":
            return connection.respond(HTTPStatus.OK, "ok\n")
        if path == "/readyz":
            ready = self.hub.ready and not self.stopping
            return connection.respond(HTTPStatus.OK if ready else HTTPStatus.SERVICE_UNAVAILABLE,
                                      "ready\n" if ready else "not ready\n")  # fmt: skip
        if path == "/metrics":
            return _response(HTTPStatus.OK, self.metrics.exposition(), CONTENT_TYPE)
        if path == "/api/sessions":
            return _response(
                HTTPStatus.OK, json.dumps(self.hub.describe_sessions()).encode(), "application/json"
            )
        if path == "/viewer":  # the page's relative links need the trailing slash
            query = urllib.parse.urlsplit(request.path).query
            return _response(
                HTTPStatus.FOUND,
                b"",
                "text/plain",
                [("Location", "/viewer/" + (f"?{query}" if query else ""))],
            )
        if path.startswith("/viewer/"):
            return _static_file(path.removeprefix("/viewer/") or "index.html")
        return connection.respond(HTTPStatus.NOT_FOUND, f"no such path {path}; the WebSocket is {WS_PATH}\n")

    # ------------------------------------------------------------------------------ connections
    async def _connection(self, ws: ServerConnection) -> None:
        wake = asyncio.Event()
        remote = "{}:{}".format(*ws.remote_address[:2]) if ws.remote_address else "?"
        client = self.hub.connect(remote, wake.set)
        self._connections.add(ws)
        self._limit_send_buffer(ws)
        query = urllib.parse.parse_qs(urllib.parse.urlsplit(ws.request.path).query)
        url_session = query.get("session", [None])[0]
        sender = asyncio.create_task(self._send(ws, client, wake))
        log.info("connect %s", client)
        try:
            await self._receive(ws, client, url_session)
        except ConnectionClosed:
            pass
        except Exception:  # a bug: logged once, the client gets `internal` and the connection closes 1011
            log.exception("connection %s failed", client)
            self.hub.internal_error(client, "handling a message")
        finally:
            self.hub.disconnect(client)
            client.outbox.close(CLOSE_NORMAL)  # lets the sender finish (a no-op after a fatal error's close)
            with contextlib.suppress(TimeoutError, ConnectionClosed, asyncio.CancelledError):
                await asyncio.wait_for(sender, 1.0)  # lets queued replies and the close frame go out
            sender.cancel()
            self._connections.discard(ws)
            log.info("close %s (code %s)", client, ws.close_code)

    def _limit_send_buffer(self, ws: ServerConnection) -> None:
        """Loopback and LAN sockets autotune their send buffers to megabytes: seconds of poses that a slow
        viewer would receive late. A small kernel buffer makes back-pressure reach the outbox, which drops
        the oldest pose instead."""
        sock = ws.transport.get_extra_info("socket")
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.config.send_buffer_bytes)

    async def _receive(self, ws: ServerConnection, client: Client, url_session: str | None) -> None:
        try:
            async with asyncio.timeout(self.config.hello_timeout_s):
                first = await ws.recv()
        except TimeoutError:
            message = f"no hello within {self.config.hello_timeout_s:g} s"
            self.hub.fail(client, ErrorCode.HANDSHAKE_REQUIRED, message, fatal=True)
            await ws.wait_closed()
            return
        self.hub.receive(client, first, time.perf_counter_ns(), url_session)
        async for data in ws:
            self.hub.receive(client, data, time.perf_counter_ns(), url_session)

    async def _send(self, ws: ServerConnection, client: Client, wake: asyncio.Event) -> None:
        outbox = client.outbox
        try:
            while True:
                data = outbox.take()
                if data is not None:
                    await ws.send(data)
                elif outbox.close_code is not None:
                    await ws.close(outbox.close_code, outbox.close_reason)
                    return
                else:
                    wake.clear()
                    await wake.wait()
        except ConnectionClosed:
            return


def _response(
    status: HTTPStatus, body: bytes, content_type: str, extra: list[tuple[str, str]] | None = None
) -> Response:
    headers = Headers([("Content-Type", content_type), ("Content-Length", str(len(body))), *(extra or [])])
    return Response(status, status.phrase, headers, body)


def _static_file(relative: str) -> Response:
    """A file of the web viewer (clients/viewer, package data); nothing outside that folder."""
    root = VIEWER_DIR.resolve()
    path = (root / urllib.parse.unquote(relative)).resolve()
    if root not in path.parents or not path.is_file():
        return _response(
            HTTPStatus.NOT_FOUND, f"no viewer file {relative}\n".encode(), "text/plain; charset=utf-8"
        )
    content_type = STATIC_TYPES.get(path.suffix, "text/plain; charset=utf-8")
    return _response(HTTPStatus.OK, path.read_bytes(), content_type, [("Cache-Control", "no-cache")])


@contextlib.asynccontextmanager
async def running(config: ServerConfig) -> AsyncIterator[Server]:
    """A started server for the duration of the block (tests use port 0)."""
    server = Server(config)
    await server.start()
    try:
        yield server
    finally:
        await server.stop()


async def serve_until_signalled(config: ServerConfig) -> None:
    """``egoposevr serve``: run until SIGINT or SIGTERM, then stop gracefully."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    async with running(config):
        await stop.wait()
        log.info("signal received; stopping")
