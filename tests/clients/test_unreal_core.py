"""The C++ client core (clients/unreal/EgoPoseProtocol.h) compiled with g++ against msgpack-cxx: checked against
the golden fixtures and PROTOCOL.md's worked examples (clients/unreal/tests/core_test.cpp), and as a scripted
input client of a real server on loopback (clients/unreal/tests/live_client.cpp; this test is its socket).
Skipped, saying so, without g++ or msgpack-cxx (Debian: apt-get install libmsgpack-cxx-dev; .ci/run installs
it)."""

from __future__ import annotations

import shutil
import subprocess
import threading
from pathlib import Path
from typing import IO

import pytest
from cameraimages import camera_images
from loopback import running_server
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import ClientConnection, connect

ROOT = Path(__file__).resolve().parents[2]
UNREAL = ROOT / "clients" / "unreal"
GXX = shutil.which("g++")
MSGPACK_HEADER = Path("/usr/include/msgpack.hpp")
pytestmark = pytest.mark.skipif(
    GXX is None or not MSGPACK_HEADER.exists(),
    reason="needs g++ and msgpack-cxx (apt-get install libmsgpack-cxx-dev)",
)


def _build(source: Path, exe: Path) -> Path:
    """``source`` built with warnings as errors."""
    assert GXX is not None
    build = [GXX, "-std=c++17", "-Wall", "-Wextra", "-Werror", "-O1", "-pthread", "-o", str(exe), str(source)]
    built = subprocess.run(build, capture_output=True, text=True, timeout=300)
    assert built.returncode == 0, built.stdout + built.stderr
    return exe


def test_cpp_core_matches_golden_fixtures_and_worked_examples(tmp_path: Path) -> None:
    exe = _build(UNREAL / "tests" / "core_test.cpp", tmp_path / "core_test")
    golden, openxr = ROOT / "tests" / "protocol" / "golden", ROOT / "tests" / "protocol" / "openxr"
    result = subprocess.run([str(exe), str(golden), str(openxr)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and result.stdout.startswith("ok: "), result.stdout + result.stderr


def _server_to_child(ws: ClientConnection, child_in: IO[bytes]) -> None:
    """Each server message to the child as a 4-byte big-endian length and its bytes, until either side closes."""
    try:
        for message in ws:
            assert isinstance(message, bytes), "the server sends binary frames only"
            child_in.write(len(message).to_bytes(4, "big") + message)
            child_in.flush()
    except (ConnectionClosed, BrokenPipeError, ValueError):
        pass  # the child finished (its stdin closed) or the server went away: the child's exit code tells


def _child_to_server(child_out: IO[bytes], ws: ClientConnection) -> None:
    """Each framed message the child writes, sent to the server as one binary WebSocket message."""
    while len(header := child_out.read(4)) == 4:
        ws.send(child_out.read(int.from_bytes(header, "big")))


def test_cpp_core_drives_a_real_server_session(tmp_path: Path) -> None:
    """Welcome, models with their digests, ping, camera frames and poses, select_model, list_models, get_body, a
    calibration measured and cleared, and a refused sample: each encoded and read by the C++ core."""
    exe = _build(UNREAL / "tests" / "live_client.cpp", tmp_path / "live_client")
    rgb, depth = camera_images(tmp_path)
    with running_server() as server, connect(server.url + "?session=cpp-live", compression=None) as ws:
        with subprocess.Popen(
            [str(exe), str(rgb), str(depth)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        ) as child:
            assert child.stdin is not None and child.stdout is not None and child.stderr is not None
            relay = threading.Thread(target=_server_to_child, args=(ws, child.stdin), daemon=True)
            relay.start()
            watchdog = threading.Timer(120, child.kill)  # a child waiting for a message that never comes
            watchdog.start()
            try:
                _child_to_server(child.stdout, ws)
                child.stdin.close()
                report = child.stderr.read().decode()
                code = child.wait(timeout=60)
            finally:
                watchdog.cancel()
        ws.close()
        relay.join(10)
    assert code == 0 and report.startswith("ok: "), f"exit {code}: {report}"
