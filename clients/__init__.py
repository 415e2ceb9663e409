"""Clients of the EgoPoseVR server: mock headset, input library, renderer, VMC bridge, bench. No torch here."""

from __future__ import annotations

import argparse
import logging
import urllib.parse
from typing import Any

from ..protocol import Message, ProtocolError, SetBody, decode_from_server

log = logging.getLogger("egoposevr.clients")

WS_PATH = "/ws"


def server_url(url: str) -> str:
    """A server address as people type it -> the WebSocket URL: ``ws://host:port`` (no path) gets ``/ws``;
    ``http(s)://`` is refused with the scheme to use. Raises ``ValueError`` saying what to write instead."""
    parts = urllib.parse.urlsplit(url.strip())
    if parts.scheme in ("http", "https"):
        scheme = "wss" if parts.scheme == "https" else "ws"
        raise ValueError(
            f"{url}: the server speaks WebSocket, not HTTP; use {scheme}://{parts.netloc}{parts.path or WS_PATH}"
        )
    if parts.scheme not in ("ws", "wss") or not parts.netloc:
        raise ValueError(f"{url}: expected ws://HOST:PORT/ws (or wss:// for TLS)")
    path = parts.path if parts.path not in ("", "/") else WS_PATH
    return urllib.parse.urlunsplit((parts.scheme, parts.netloc, path, parts.query, ""))


def session_url(url: str, session: str) -> str:
    """The WebSocket URL with ``?session=`` added (PROTOCOL.md §1: balancers route on it)."""
    url = server_url(url)
    return f"{url}{'&' if '?' in url else '?'}session={urllib.parse.quote(session, safe='')}"


def url_argument(text: str) -> str:
    """``--url`` for argparse: normalised by :func:`server_url`, a clear usage error otherwise."""
    try:
        return server_url(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def body_lengths(values: Any) -> list[float]:
    """A kept body's 21 bone lengths (m) as ``set_body`` carries them, checked by the protocol's own message
    (PROTOCOL.md §4.2). ValueError for anything else: another count, or a length that is no number, not finite or
    outside the wire's 0.01-1 m."""
    try:
        if isinstance(values, str | bytes) or any(isinstance(v, bool | str | bytes) for v in values):
            raise TypeError("not numbers")
        return SetBody(bone_lengths_m=[float(v) for v in values]).bone_lengths_m
    except (TypeError, ValueError):  # pydantic's ValidationError is a ValueError
        raise ValueError(
            f"a body is 21 positive finite bone lengths in metres (0.01-1 m each), got {values!r}"
        ) from None


def read_server_message(
    data: bytes | bytearray | memoryview, counts: dict[str, int] | None = None
) -> Message | None:
    """A server message for a client's read loop, or None for one to skip: a type this version does not know
    (PROTOCOL.md §9) or bytes that are no v1 message, which are logged and, with ``counts``, counted under
    ``"unreadable"`` (§8: one bad message costs that message, not the stream)."""
    try:
        return decode_from_server(data)
    except ProtocolError as exc:
        log.warning("an unreadable server message was skipped: %s", exc)
        if counts is not None:
            counts["unreadable"] = counts.get("unreadable", 0) + 1
        return None
