"""Per-client outgoing queues (small, bounded, drop-oldest, so a slow reader never slows anyone else) and
the fan-out of a session's results to them.

Each connection owns one :class:`Outbox`. Poses go to a queue of ``pose_capacity`` (a handful): when a viewer
falls behind, its oldest poses are dropped and counted, and the headset's inference never waits on it.
Replies (welcome, models, errors, pongs) go to a separate bounded queue and are sent first. ``close`` asks
the sender to finish the replies already queued (a fatal error's message included) and then close with the
given code. No sockets and no asyncio here: the app's sender task drains the outbox when ``wake`` fires.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING

from ..protocol import encode
from .metrics import Metrics

if TYPE_CHECKING:
    from .session import RunResult, Session

CONTROL_CAPACITY = 64


class Outbox:
    """Encoded messages waiting for one client's sender. Every method runs on the event loop."""

    def __init__(self, pose_capacity: int, wake: Callable[[], None] = lambda: None) -> None:
        self.poses: deque[bytes] = deque(maxlen=pose_capacity)
        self.control: deque[bytes] = deque(maxlen=CONTROL_CAPACITY)
        self.dropped_poses = 0
        self.dropped_control = 0
        self.close_code: int | None = None
        self.close_reason = ""
        self._wake = wake

    def put_pose(self, data: bytes) -> bool:
        """Queue a pose; returns False when the oldest queued pose was dropped to make room."""
        if self.close_code is not None:
            return True
        dropped = len(self.poses) == self.poses.maxlen
        self.dropped_poses += dropped
        self.poses.append(data)
        self._wake()
        return not dropped

    def put_control(self, data: bytes) -> None:
        """Queue a reply; a client that does not read its replies loses the oldest ones."""
        if self.close_code is not None:
            return
        self.dropped_control += len(self.control) == self.control.maxlen
        self.control.append(data)
        self._wake()

    def close(self, code: int, reason: str = "") -> None:
        """After the queued replies, close with ``code``; queued poses are dropped, nothing more is queued."""
        if self.close_code is None:
            self.close_code, self.close_reason = code, reason[:120]  # a close frame carries <= 123 bytes
            self.poses.clear()
            self._wake()

    def take(self) -> bytes | None:
        """The next message to send: replies first, then poses; None when empty."""
        if self.control:
            return self.control.popleft()
        if self.poses:
            return self.poses.popleft()
        return None


def publish(session: Session, result: RunResult, metrics: Metrics) -> None:
    """Deliver one run's pose to every client of the session, its notices to every client and its errors
    to the input client; counted. Never blocks: a full outbox drops its oldest pose."""
    for error in result.errors:
        if session.input is not None:
            session.input.outbox.put_control(encode(error))
        metrics.errors.labels(error.code).inc()
    if result.stale_frame:
        metrics.stale_frames.inc()
    for notice in result.notices:
        encoded = encode(notice)
        for member in session.clients:
            member.outbox.put_control(encoded)
    if result.pose is None:
        return
    metrics.poses.labels(result.model).inc()
    metrics.observe_timing(result.timing_us)
    for member in session.clients:
        if not member.outbox.put_pose(result.pose):
            metrics.dropped_poses.labels(member.role).inc()
