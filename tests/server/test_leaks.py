"""Connections that misbehave leave nothing behind: no task, no file, no memory, no client or session.

Connections that open and never say hello, TCP connections that never upgrade, clients that stop answering
(half-open: the peer is gone without a FIN), and a thousand quick connect/hello/close cycles.
"""

from __future__ import annotations

import asyncio
import os
import socket
import time

import psutil
import pytest
from loopback import Client, ServerThread, address, close_code, raw_client, running_server

pytestmark = pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="counts open files through /proc")


def _footprint(server: ServerThread) -> dict[str, int]:
    """What the server holds: its loop's tasks, the hub's clients and sessions, open connections, and this
    process's open files and resident memory (the server runs in a thread of it)."""

    async def tasks() -> int:
        return len(asyncio.all_tasks())

    return {
        "tasks": asyncio.run_coroutine_threadsafe(tasks(), server.loop).result(5),
        "clients": len(server.server.hub.clients),
        "sessions": len(server.server.hub.sessions),
        "connections": len(server.server._connections),
        "files": len(os.listdir("/proc/self/fd")),
        "rss_mib": psutil.Process().memory_info().rss // 2**20,
    }


def _assert_nothing_left(after: dict[str, int], baseline: dict[str, int]) -> None:
    """No more tasks or files than before (a session worker of the baseline may have ended meanwhile), and
    no client, session or connection at all."""
    assert (after["clients"], after["sessions"], after["connections"]) == (0, 0, 0), after
    assert after["tasks"] <= baseline["tasks"] and after["files"] <= baseline["files"], (baseline, after)


def _settled(server: ServerThread, baseline: dict[str, int], timeout: float = 10.0) -> dict[str, int]:
    """The footprint once it is back at the baseline (or the last one seen when the timeout passes)."""
    deadline = time.monotonic() + timeout
    while True:
        now = _footprint(server)
        same = all(now[k] <= baseline[k] for k in ("tasks", "clients", "sessions", "connections", "files"))
        if same or time.monotonic() > deadline:
            return now
        time.sleep(0.1)


@pytest.mark.protocol("hello-first")
def test_silent_connections_and_tcp_that_never_upgrades_are_dropped_without_a_trace():
    with running_server(hello_timeout_s=0.5) as server:
        baseline = _footprint(server)
        silent = [Client(server.url, f"quiet-{k}") for k in range(20)]  # upgraded, never say hello
        raw = [socket.create_connection(address(server.url)) for _ in range(20)]  # TCP only
        time.sleep(1.5)
        for client in silent:
            assert close_code(client) == 1008
            client.close()
        for sock in raw:
            sock.settimeout(5)
            assert sock.recv(1024) == b""  # the server closed it
            sock.close()
        _assert_nothing_left(_settled(server, baseline), baseline)


def test_half_open_peers_are_dropped_by_the_keepalive_and_their_sessions_end():
    with running_server(ping_interval_s=0.2, ping_timeout_s=0.3) as server:
        baseline = _footprint(server)
        gone = [raw_client(server.url, f"gone-{k}", role="input") for k in range(10)]
        time.sleep(0.3)
        assert len(server.server.hub.sessions) == 10
        after = _settled(server, baseline, timeout=10)
        assert (after["clients"], after["sessions"], after["connections"]) == (0, 0, 0)
        assert after["tasks"] <= baseline["tasks"]
        for sock in gone:
            sock.close()


def test_a_thousand_quick_connections_leave_no_task_file_or_memory(server):
    for warm in range(20):  # first connections allocate caches that stay: not a leak
        with Client(server.url, f"warm-{warm}") as client:
            client.hello("render", f"warm-{warm}")
    baseline = _settled(server, _footprint(server))
    for k in range(1000):
        with Client(server.url, f"cycle-{k % 50}") as client:
            client.hello("input" if k % 2 else "render", f"cycle-{k % 50}")
    after = _settled(server, baseline)
    _assert_nothing_left(after, baseline)
    assert after["rss_mib"] - baseline["rss_mib"] < 40, (baseline, after)
