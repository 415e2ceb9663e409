"""The protocol logic of every connection: handshake, roles, limits and routing into sessions. No sockets.

The app's glue calls ``connect`` when a WebSocket opens, ``receive`` for each frame it reads, ``disconnect``
when it closes, and ``shutdown`` when stopping. A message with work for the model goes into its session and
the session goes to the :class:`~egoposevr.server.scheduler.Scheduler` (``wake``); the scheduler delivers
the results itself, so nothing calls back into the hub. Everything a client should get is put in its
:class:`~egoposevr.server.broadcast.Outbox`; a fatal error also asks the outbox to close with the WebSocket
code PROTOCOL.md §6 gives. All methods run on the event loop.

Errors never escape ``receive``: a message that cannot be used gets an ``error`` reply (with its ``seq`` when
it had one) and is counted; the connection stays up unless the error is fatal.
"""

from __future__ import annotations

import dataclasses
import hmac
import time
from collections.abc import Callable

from ..protocol import (
    Calibrate,
    ErrorCode,
    GetBody,
    Hello,
    Hmd,
    ListModels,
    Message,
    Models,
    Ping,
    Pong,
    ProtocolError,
    Rgbd,
    SelectModel,
    SessionStatus,
    SetBody,
    Welcome,
    decode,
    encode,
)
from .broadcast import Outbox
from .config import ServerConfig
from .metrics import Metrics
from .recorder import Recorder
from .registry import ModelRegistry
from .scheduler import Scheduler
from .session import Received, Session, TokenBucket, check_set_body, error_about

CLOSE_NORMAL, CLOSE_GOING_AWAY, CLOSE_POLICY, CLOSE_TOO_BIG, CLOSE_INTERNAL, CLOSE_TRY_LATER = (
    1000, 1001, 1008, 1009, 1011, 1013,
)  # fmt: skip
CLOSE_CODES = {
    ErrorCode.TOO_LARGE: CLOSE_TOO_BIG,
    ErrorCode.HANDSHAKE_REQUIRED: CLOSE_POLICY,
    ErrorCode.AUTH_FAILED: CLOSE_POLICY,
    ErrorCode.SESSION_BUSY: CLOSE_POLICY,
    ErrorCode.INVALID_FIELD: CLOSE_POLICY,  # only fatal for a hello whose session disagrees with the URL
    ErrorCode.SERVER_FULL: CLOSE_TRY_LATER,
    ErrorCode.INTERNAL: CLOSE_INTERNAL,
    ErrorCode.SHUTTING_DOWN: CLOSE_GOING_AWAY,
}
RATE_ERROR_INTERVAL_NS = 1_000_000_000  # one rate_limited reply per second per client; all drops counted


@dataclasses.dataclass(eq=False)
class Client:
    """One connection as the hub sees it."""

    id: int
    remote: str
    outbox: Outbox
    role: str | None = None
    session: Session | None = None
    label: str = ""  # hello.client, for logs
    last_rate_error_ns: int = -RATE_ERROR_INTERVAL_NS

    def __str__(self) -> str:
        who = f"#{self.id} {self.remote}"
        return f"{who} {self.role}@{self.session.id}" if self.session else who


class Hub:
    """All sessions and clients of one server."""

    def __init__(
        self,
        config: ServerConfig,
        registry: ModelRegistry,
        metrics: Metrics,
        scheduler: Scheduler,
        recorder: Recorder | None = None,
        server_name: str = "egoposevr/0",
    ) -> None:
        self.config, self.registry, self.metrics, self.recorder = config, registry, metrics, recorder
        self.scheduler, self.server_name = scheduler, server_name
        self.sessions: dict[str, Session] = {}
        self.clients: set[Client] = set()
        self.ready = False  # models loaded
        self.accepting = True  # False once shutting down
        self._next_id = 0

    # ------------------------------------------------------------------------------ connections
    def connect(self, remote: str, wake: Callable[[], None] = lambda: None) -> Client:
        self._next_id += 1
        client = Client(self._next_id, remote, Outbox(self.config.pose_queue, wake))
        self.clients.add(client)
        self.metrics.connections.inc()
        return client

    def disconnect(self, client: Client) -> None:
        self.clients.discard(client)
        session, client.session = client.session, None
        if session is None:
            return
        self.metrics.clients.labels(client.role).dec()
        if self.recorder is not None:
            self.recorder.close(client)
        if session.input is client:
            session.input = None
            session.restart_stream()
            self._tell_renders(session, "input_left")
        elif client in session.renders:
            session.renders.remove(client)
        if not session.clients:
            del self.sessions[session.id]
            self.metrics.sessions.set(len(self.sessions))
            self.scheduler.forget(session)

    def shutdown(self) -> None:
        """Tell every client the server is stopping (fatal, close 1001); refuse new hellos."""
        self.accepting = False
        for client in list(self.clients):
            self.fail(client, ErrorCode.SHUTTING_DOWN, "the server is shutting down", fatal=True)

    def describe_sessions(self) -> list[dict[str, object]]:
        """For /api/sessions and the viewer's session picker."""
        return [
            {"session": s.id, "model": s.model_name, "input": s.input is not None, "viewers": len(s.renders)}
            for s in sorted(self.sessions.values(), key=lambda s: s.id)
        ]

    def fail(
        self,
        client: Client,
        code: ErrorCode,
        message: str,
        *,
        fatal: bool = False,
        about: tuple[str | None, int | None] = (None, None),
    ) -> None:
        """Send an ``error``; a fatal one closes the connection after it. ``about``: the (type, seq) of the
        client message that caused it, where known (PROTOCOL.md §6: ``ref``)."""
        client.outbox.put_control(encode(error_about(code, message, about, fatal)))
        self.metrics.errors.labels(code.value).inc()
        if fatal:
            client.outbox.close(CLOSE_CODES.get(code, CLOSE_POLICY), f"{code.value}: {message}")

    # ------------------------------------------------------------------------------ messages
    def receive(
        self, client: Client, data: bytes | str, recv_ns: int, url_session: str | None = None
    ) -> None:
        """One WebSocket frame from ``client``, read at ``recv_ns`` (perf_counter ns)."""
        if client.outbox.close_code is not None:
            return  # closing: what still arrives is not answered
        greeted = client.session is not None
        try:
            if isinstance(data, str):
                raise ProtocolError(ErrorCode.MALFORMED, "text frame: protocol messages are binary msgpack")
            msg = decode(data, max_bytes=self.config.max_message_bytes)
        except ProtocolError as exc:
            self.metrics.messages.labels("invalid").inc()
            about = (exc.ref_type, exc.ref_seq)
            if exc.code is ErrorCode.TOO_LARGE:
                self.fail(client, exc.code, exc.message, fatal=True)
            elif not greeted and exc.ref_type == "hello":  # a bad hello says what is wrong with it
                self.fail(client, exc.code, exc.message, fatal=True, about=about)
            elif not greeted:
                self.fail(
                    client,
                    ErrorCode.HANDSHAKE_REQUIRED,
                    f"the first message must be a valid hello; this one was refused ({exc.code.value}: "
                    f"{exc.message})",
                    fatal=True,
                    about=about,
                )
            else:
                self.fail(client, exc.code, exc.message, about=about)
            return
        decode_ns = time.perf_counter_ns() - recv_ns
        self.metrics.messages.labels(msg.type).inc()
        if not greeted:
            if isinstance(msg, Hello):
                self._hello(client, msg, url_session, data)
            else:
                self.fail(
                    client,
                    ErrorCode.HANDSHAKE_REQUIRED,
                    f"the first message must be hello, got {msg.type}",
                    fatal=True,
                    about=_about(msg),
                )
            return
        if not client.session.rate.allow(recv_ns):
            self._rate_limited(client, recv_ns, msg)
            return
        self._dispatch(client, msg, Received(msg, recv_ns, decode_ns), data)

    def _dispatch(self, client: Client, msg: Message, received: Received, data: bytes | str) -> None:
        session = client.session
        if isinstance(msg, Hmd | Rgbd) and client is not session.input:
            self.fail(
                client,
                ErrorCode.WRONG_ROLE,
                f"{msg.type} is for the input role; this client is {client.role}",
                about=_about(msg),
            )
        elif isinstance(msg, Hmd):
            self._record(client, data, received.recv_ns)
            if session.offer_hmd(received):
                self.metrics.skipped_samples.inc()
            self.scheduler.wake(session)
        elif isinstance(msg, Rgbd):
            self._record(client, data, received.recv_ns)
            if not session.offer_rgbd(received):
                self.metrics.replaced_frames.inc()
            self.scheduler.wake(session)
        elif isinstance(msg, SelectModel):
            self._record(client, data, received.recv_ns)
            self._select(client, msg.model, msg)
        elif isinstance(msg, Calibrate):
            self._record(client, data, received.recv_ns)
            session.request_calibration(msg)
            self.scheduler.wake(session)
        elif isinstance(msg, SetBody | GetBody):
            refusal = check_set_body(msg) if isinstance(msg, SetBody) else None
            if refusal is not None:
                self.fail(client, ErrorCode.OUT_OF_RANGE, refusal, about=_about(msg))
                return
            if isinstance(msg, SetBody):  # it changes what is served; a get_body does not
                self._record(client, data, received.recv_ns)
            session.request_body(msg)
            self.scheduler.wake(session)
        elif isinstance(msg, ListModels):
            client.outbox.put_control(encode(self._models(session)))
        elif isinstance(msg, Ping):
            pong = Pong(nonce=msg.nonce, t_us=msg.t_us, server_t_us=time.monotonic_ns() // 1000)
            client.outbox.put_control(encode(pong))
        elif isinstance(msg, Hello):
            self.fail(
                client,
                ErrorCode.ALREADY_GREETED,
                f"this connection already joined session {session.id}",
                about=_about(msg),
            )
        else:
            self.fail(
                client,
                ErrorCode.UNEXPECTED_MESSAGE,
                f"{msg.type} is a server-to-client message",
                about=_about(msg),
            )

    def _rate_limited(self, client: Client, now_ns: int, msg: Message) -> None:
        self.metrics.rate_limited.inc()
        if now_ns - client.last_rate_error_ns >= RATE_ERROR_INTERVAL_NS:
            client.last_rate_error_ns = now_ns
            cfg = self.config
            self.fail(
                client,
                ErrorCode.RATE_LIMITED,
                f"session {client.session.id} is over {cfg.rate_limit_hz:g} messages/s (burst {cfg.rate_burst}); "
                "excess messages are dropped (this one among them); one such error per second",
                about=_about(msg),
            )

    # ------------------------------------------------------------------------------ handshake
    def _hello(self, client: Client, hello: Hello, url_session: str | None, data: bytes | str) -> None:
        about = _about(hello)
        refusal = self._refuse_hello(hello, url_session)
        if refusal is not None:
            self.fail(client, *refusal, fatal=True, about=about)
            return
        session = self.sessions.get(hello.session) or self._new_session(hello)
        if session is None:
            return self.fail(
                client,
                ErrorCode.SERVER_FULL,
                f"{self.config.max_sessions} sessions are open; try again later",
                fatal=True,
                about=about,
            )
        if hello.role == "input":
            if session.input is not None:
                return self.fail(
                    client,
                    ErrorCode.SESSION_BUSY,
                    f"session {hello.session} already has an input client",
                    fatal=True,
                    about=about,
                )
            session.input = client
            session.restart_stream()
        else:
            if len(session.renders) >= self.config.max_renders_per_session:
                return self.fail(
                    client,
                    ErrorCode.SERVER_FULL,
                    f"session {hello.session} has {len(session.renders)} render clients, the limit",
                    fatal=True,
                    about=about,
                )
            session.renders.append(client)
        client.role, client.session, client.label = hello.role, session, hello.client or ""
        self.metrics.clients.labels(hello.role).inc()
        if hello.role == "input" and self.recorder is not None:
            self.recorder.open(client, session.id)
            self._record(client, data, time.perf_counter_ns())
        requested = hello.model if hello.role == "input" else None  # viewers do not choose the model
        if requested is not None and requested != session.model_name and self.registry.get(requested):
            session.select(requested, self.registry.get(requested))
        welcome = Welcome(
            session=session.id,
            role=hello.role,
            server=self.server_name,
            model=session.model_name,
            models=self.registry.names(),
            provider=getattr(self.registry.get(session.model_name), "provider", None),
        )
        client.outbox.put_control(encode(welcome))
        if requested is not None and self.registry.get(requested) is None:
            self._unknown_model(client, requested, about)
        client.outbox.put_control(encode(self._models(session)))
        if hello.role == "render":
            client.outbox.put_control(encode(self._status(session, "joined")))
        else:
            self._tell_renders(session, "input_joined")

    def _status(self, session: Session, event: str) -> SessionStatus:
        return SessionStatus(
            session=session.id,
            event=event,
            input=session.input is not None,
            model=session.model_name,
            renders=len(session.renders),
        )

    def _tell_renders(self, session: Session, event: str) -> None:
        """A ``session`` message to every render client of ``session`` (the input client joined or left)."""
        status = encode(self._status(session, event))
        for render in session.renders:
            render.outbox.put_control(status)

    def _refuse_hello(self, hello: Hello, url_session: str | None) -> tuple[ErrorCode, str] | None:
        if not self.accepting:
            return ErrorCode.SHUTTING_DOWN, "the server is shutting down"
        if not self.ready:
            return ErrorCode.SERVER_FULL, "models are still loading; try again shortly"
        if not self.registry.names():
            return ErrorCode.SERVER_FULL, "no model is loaded (all were removed from the models folder)"
        token = self.config.token
        if token is not None and not hmac.compare_digest(
            (hello.token or "").encode(), token.get_secret_value().encode()
        ):
            return ErrorCode.AUTH_FAILED, "missing or wrong token"
        if url_session is not None and url_session != hello.session:
            return (
                ErrorCode.INVALID_FIELD,
                f"hello.session {hello.session!r} differs from the URL's session {url_session!r}",
            )
        return None

    def _new_session(self, hello: Hello) -> Session | None:
        if len(self.sessions) >= self.config.max_sessions:
            return None
        name = self.default_model_name()
        cfg = self.config
        bucket = TokenBucket(cfg.rate_limit_hz, cfg.rate_burst)
        session = Session(
            hello.session, name, self.registry.get(name), bucket, frame_lane=cfg.frame_lane,
            first_frame_wait_ns=round(cfg.first_frame_wait_ms * 1e6),
            low_head_wait_ns=round(cfg.low_head_wait_ms * 1e6),
        )  # fmt: skip
        self.sessions[session.id] = session
        self.metrics.sessions.set(len(self.sessions))
        return session

    def default_model_name(self) -> str:
        names = self.registry.names()
        return self.config.default_model if self.config.default_model in names else names[0]

    def _select(self, client: Client, name: str, msg: Message) -> None:
        """select_model: swap the session's model and tell every client of the session (an unknown name:
        ``unknown_model`` to the sender, then ``models`` to every client, unchanged)."""
        session = client.session
        model = self.registry.get(name)
        if model is None:
            self._unknown_model(client, name, _about(msg))
        elif name != session.model_name:
            session.select(name, model)
        models = encode(self._models(session))
        for member in session.clients:
            member.outbox.put_control(models)

    def _unknown_model(self, client: Client, name: str, about: tuple[str | None, int | None]) -> None:
        known = ", ".join(self.registry.names())
        message = f"no model {name!r}; the session keeps {client.session.model_name} (models: {known})"
        self.fail(client, ErrorCode.UNKNOWN_MODEL, message, about=about)

    def _models(self, session: Session) -> Models:
        return Models(active=session.model_name, models=self.registry.wire_infos())

    def _record(self, client: Client, data: bytes | str, recv_ns: int) -> None:
        if self.recorder is not None and isinstance(data, bytes):
            self.recorder.record(client, data, recv_ns)

    def internal_error(self, client: Client, what: str) -> None:
        self.fail(client, ErrorCode.INTERNAL, f"server error while {what}; the connection closes", fatal=True)


def _about(msg: Message) -> tuple[str | None, int | None]:
    """(type, seq) of a client message, for an error's ``ref``."""
    return msg.type, getattr(msg, "seq", None)
