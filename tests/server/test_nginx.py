"""Scale-out run for real: nginx (Debian's package) in front of three ``egoposevr serve`` processes on
loopback, configured from the repository's own docker/nginx.conf.template.

Shown: sticky routing by ``?session=`` (a headset and its viewer reach one replica) and spread over replicas;
``wss://`` terminated by nginx; a replica killed with SIGKILL (the headset reconnects through nginx and its
session resumes on a live replica, the viewer re-subscribes, another session is not disturbed); a replica
drained with SIGTERM (its clients are told and move). Skipped, saying so, where nginx is not installed.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest
import trustme
from loopback import Client, recorded_messages
from websockets.exceptions import ConnectionClosed

from egoposevr.clients.input import HeadsetClient
from egoposevr.protocol import Hello, Ping, decode, encode

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "docker"))
from nginx_config import TEMPLATE, render  # noqa: E402

NGINX = shutil.which("nginx") or next((p for p in ("/usr/sbin/nginx",) if Path(p).exists()), None)
pytestmark = pytest.mark.skipif(
    NGINX is None, reason="nginx is not installed (Debian: apt-get install nginx)"
)
WALK_HMD = [decode(d) for _, k, d in recorded_messages("walk-0000") if k == "hmd"]


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


class Replica:
    """One ``egoposevr serve`` process."""

    def __init__(self) -> None:
        self.process = subprocess.Popen(
            [sys.executable, "-m", "egoposevr.cli.main", "serve", "--port", "0", "--default-model", "hmd",
             "--workers", "1"],
            stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        deadline = time.monotonic() + 90
        for line in self.process.stderr:
            if match := re.search(r"on ws://127\.0\.0\.1:(\d+)", line):
                self.port = int(match.group(1))
                break
            assert time.monotonic() < deadline, "a replica did not start"
        else:
            raise AssertionError(f"a replica exited with {self.process.wait()}")

    def sessions(self) -> dict[str, dict]:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{self.port}/api/sessions", timeout=2) as reply:
                return {s["session"]: s for s in json.loads(reply.read())}
        except OSError:
            return {}

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait(10)
        self.process.stderr.close()


class Cluster:
    """Three replicas behind nginx: ``url`` (ws://) and ``tls_url`` (wss://, terminated by nginx)."""

    def __init__(self, folder: Path, ca: trustme.CA) -> None:
        self.replicas = [Replica() for _ in range(3)]
        cert = ca.issue_cert("127.0.0.1", "localhost")
        chain, key = folder / "chain.pem", folder / "key.pem"
        cert.private_key_pem.write_to_path(str(key))
        for k, pem in enumerate(cert.cert_chain_pems):
            pem.write_to_path(str(chain), append=k > 0)
        plain, secure = _free_port(), _free_port()
        config = folder / "nginx.conf"
        config.write_text(
            render(
                [f"127.0.0.1:{r.port}" for r in self.replicas],
                listen=f"127.0.0.1:{plain}",
                tls=(f"127.0.0.1:{secure}", str(chain), str(key)),
                prefix=str(folder),
            )
        )
        self.nginx = subprocess.Popen(
            [NGINX, "-p", str(folder), "-c", str(config), "-g", "daemon off; master_process off;"],
            stderr=subprocess.PIPE,
        )
        self.url, self.tls_url = f"ws://127.0.0.1:{plain}/ws", f"wss://127.0.0.1:{secure}/ws"
        deadline = time.monotonic() + 10
        while True:
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", plain), 0.2):
                break
            assert self.nginx.poll() is None, self.nginx.stderr.read().decode()
            assert time.monotonic() < deadline, "nginx did not start"
            time.sleep(0.05)

    def replica_of(self, session: str) -> Replica | None:
        holders = [r for r in self.replicas if session in r.sessions()]
        assert len(holders) <= 1, f"session {session} is on {len(holders)} replicas"
        return holders[0] if holders else None

    def close(self) -> None:
        self.nginx.terminate()
        self.nginx.wait(10)
        self.nginx.stderr.close()
        for replica in self.replicas:
            replica.stop()


@pytest.fixture
def cluster(tmp_path, monkeypatch) -> Iterator[Cluster]:
    ca = trustme.CA()
    ca_file = tmp_path / "ca.pem"
    ca.cert_pem.write_to_path(str(ca_file))
    monkeypatch.setenv("SSL_CERT_FILE", str(ca_file))
    cluster = Cluster(tmp_path, ca)
    try:
        yield cluster
    finally:
        cluster.close()


def test_the_compose_configuration_is_the_template_filled_in():
    """docker/nginx.conf (what compose mounts) is the template filled with compose's three replicas."""
    rendered = render([f"server-{k}:8765" for k in (1, 2, 3)], listen="8080")
    assert (ROOT / "docker" / "nginx.conf").read_text() == rendered
    assert "${" not in rendered and "$arg_session" in TEMPLATE.read_text()


def test_sessions_are_sticky_spread_and_wss_is_terminated_by_nginx(cluster):
    names = [f"room-{k}" for k in range(9)]
    clients = []
    try:
        for name in names:
            headset, viewer = Client(cluster.url, name), Client(cluster.url, name)
            clients += [headset, viewer]
            assert headset.hello("input", name).type == "welcome"
            assert viewer.hello("render", name).type == "welcome"
        placement = {name: cluster.replica_of(name) for name in names}
        for name, replica in placement.items():
            assert replica is not None, name
            assert replica.sessions()[name] | {"model": None} == {
                "session": name,
                "model": None,
                "input": True,
                "viewers": 1,
            }  # both clients of the session on that one replica
        assert len({id(r) for r in placement.values()}) >= 2  # spread over replicas
        with Client(cluster.tls_url, "secure") as secure:
            assert secure.hello("render", "secure").type == "welcome"
            secure.send(Ping(nonce=3))
            assert secure.recv_type("pong").nonce == 3
    finally:
        for client in clients:
            client.close()


async def _stream(headset: HeadsetClient, stop: asyncio.Event) -> None:
    """The walk recording's headset samples at 90 Hz, looping, re-stamped on this clock."""
    k = 0
    while not stop.is_set():
        sample = WALK_HMD[k % len(WALK_HMD)]
        await headset.send_hmd(
            time.monotonic_ns() // 1000, sample.head, sample.left, sample.right, sample.valid
        )
        k += 1
        await asyncio.sleep(1 / 90)


async def _collect(headset: HeadsetClient, times: list[float]) -> None:
    async for _ in headset.poses():
        times.append(time.monotonic())


async def _viewer(url: str, session: str, times: list[float], stop: asyncio.Event) -> None:
    """A render client that re-subscribes whenever its connection drops (as the web viewer does)."""
    from websockets.asyncio.client import connect

    while not stop.is_set():
        with contextlib.suppress(OSError, ConnectionClosed, TimeoutError):
            async with connect(f"{url}?session={session}", open_timeout=2) as ws:
                await ws.send(encode(Hello(role="render", session=session)))
                while not stop.is_set():
                    if decode(await asyncio.wait_for(ws.recv(), 1.0)).type == "pose":
                        times.append(time.monotonic())
        await asyncio.sleep(0.25)


def _two_sessions_on_two_replicas(cluster: Cluster) -> tuple[str, str]:
    """Session names that the hash puts on different replicas (checked by joining them)."""
    placed: dict[int, str] = {}
    for k in range(40):
        name = f"s{k}"
        with Client(cluster.url, name) as probe:
            probe.hello("render", name)
            replica = cluster.replica_of(name)
            placed.setdefault(replica.port, name)
        if len(placed) >= 2:
            return tuple(placed.values())[:2]
    raise AssertionError("every session hashed to one replica")


async def _failover(cluster: Cluster, how: signal.Signals) -> dict[str, float]:
    victim, bystander = _two_sessions_on_two_replicas(cluster)
    stop = asyncio.Event()
    poses = {"victim": [], "bystander": [], "viewer": []}
    async with (
        HeadsetClient(cluster.url, victim, model="hmd") as headset,
        HeadsetClient(cluster.url, bystander, model="hmd") as other,
    ):
        tasks = [
            asyncio.create_task(_stream(headset, stop)),
            asyncio.create_task(_stream(other, stop)),
            asyncio.create_task(_collect(headset, poses["victim"])),
            asyncio.create_task(_collect(other, poses["bystander"])),
            asyncio.create_task(_viewer(cluster.url, victim, poses["viewer"], stop)),
        ]
        await asyncio.sleep(1.5)
        doomed = cluster.replica_of(victim)
        survivor = cluster.replica_of(bystander)
        assert doomed is not None and survivor is not None and doomed is not survivor
        killed_at = time.monotonic()
        doomed.process.send_signal(how)
        while headset.online and time.monotonic() < killed_at + 5:  # poses in flight may still arrive
            await asyncio.sleep(0.001)
        dropped_at = time.monotonic()
        await asyncio.sleep(4.0)
        stop.set()
        for task in tasks:  # the collectors wait for poses that no longer come: cancel them
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        back = [t for t in poses["victim"] if t > dropped_at]  # from the new replica
        viewer_back = [t for t in poses["viewer"] if t > dropped_at]
        around = [t for t in poses["bystander"] if killed_at - 1 < t < killed_at + 3]
        gaps = [b - a for a, b in itertools.pairwise(around)]
        assert back, "the headset never got a pose again"
        assert viewer_back, "the viewer did not re-subscribe"
        moved_to = cluster.replica_of(victim)
        assert moved_to is not None and moved_to is not doomed
        return {
            "failover_s": back[0] - killed_at,
            "connection_lost_s": dropped_at - killed_at,
            "viewer_back_s": viewer_back[0] - killed_at,
            "bystander_max_gap_s": max(gaps),
            "reconnects": headset.reconnects,
            "errors": [e.code for e in headset.errors],
        }


def test_a_replica_killed_with_sigkill_fails_over_within_2s(cluster, capsys):
    result = asyncio.run(asyncio.wait_for(_failover(cluster, signal.SIGKILL), 60))
    with capsys.disabled():
        print(f"\nSIGKILL failover: {json.dumps({k: v for k, v in result.items() if k != 'errors'})}")
    assert result["reconnects"] >= 1
    assert result["failover_s"] < 2.0
    assert result["bystander_max_gap_s"] < 0.5  # the other session was not disturbed


def test_a_replica_drained_with_sigterm_tells_its_clients_and_they_move(cluster, capsys):
    result = asyncio.run(asyncio.wait_for(_failover(cluster, signal.SIGTERM), 60))
    with capsys.disabled():
        print(f"\nSIGTERM drain: {json.dumps(result)}")
    assert "shutting_down" in result["errors"]  # told, then moved
    assert result["failover_s"] < 2.0 and result["bystander_max_gap_s"] < 0.5
