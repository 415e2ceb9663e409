"""`egoposevr serve` as users run it: a separate process, fail-fast configuration, graceful SIGTERM."""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from loopback import Client, recorded_messages, replay
from websockets.exceptions import ConnectionClosed

from egoposevr.protocol import decode
from egoposevr.recordings.egrec import KIND_CLIENT, read_records

SERVE = [sys.executable, "-m", "egoposevr.cli.main", "serve", "--port", "0"]


def start_server(*args: str) -> tuple[subprocess.Popen, str]:
    """The process and its WebSocket URL, read from its startup log line."""
    process = subprocess.Popen([*SERVE, *args], stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    for line in process.stderr:
        if match := re.search(r"on (ws://\S+)", line):
            return process, match.group(1)
        assert time.monotonic() < deadline, "server did not start"
    raise AssertionError(f"server exited with {process.wait()} before listening")


def close_code(client: Client) -> int:
    """Read until the server closes the connection; its close code."""
    try:
        while True:
            client.recv(timeout=10)
    except ConnectionClosed as closed:
        return closed.rcvd.code


def test_sigterm_drains_sessions_closes_1001_and_flushes_recordings(tmp_path):
    process, url = start_server("--record", str(tmp_path), "--default-model", "hmd")
    try:
        with Client(url, "live") as headset:
            headset.hello("input", "live")
            replay(headset, recorded_messages("walk-0000", limit=40))
            started = time.monotonic()
            process.send_signal(signal.SIGTERM)
            error = headset.recv_type("error", timeout=10)
            assert (error.code, error.fatal) == ("shutting_down", True)
            assert close_code(headset) == 1001
        assert process.wait(timeout=15) == 0
        assert time.monotonic() - started < 10
    finally:
        process.kill()
        log = process.stderr.read()
        process.stderr.close()
    assert "signal received" in log and "stopped" in log
    assert len(log.splitlines()) < 20  # connects, closes, model loads: never a line per message
    (recording,) = tmp_path.glob("live-*.egrec")
    kinds = [decode(r.payload).type for r in read_records(recording) if r.kind == KIND_CLIENT]
    assert kinds[0] == "hello" and kinds.count("hmd") == 30


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--default-model", "nope"], "default_model 'nope'"),
        (["--max-sessions", "0"], "max_sessions"),
        (["--no-bundled-models"], "no model could be loaded"),
    ],
)
def test_a_bad_configuration_fails_fast(args, message):
    result = subprocess.run([*SERVE, *args], capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert message in result.stderr


def test_a_config_file_with_an_unknown_key_fails_fast(tmp_path):
    config = tmp_path / "server.toml"
    config.write_text("port = 0\nmax_sesions = 3\n")
    result = subprocess.run([*SERVE, "--config", str(config)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "max_sesions" in result.stderr


def test_the_serving_process_never_imports_torch():
    script = textwrap.dedent(
        """
        import asyncio, sys
        from websockets.asyncio.client import connect
        from egoposevr.protocol import Hello, decode, encode
        from egoposevr.recordings.egrec import read_records
        from egoposevr.server.app import running
        from egoposevr.server.config import ServerConfig

        async def main():
            async with running(ServerConfig(port=0)) as server:
                async with connect(server.url) as ws:
                    await ws.send(encode(Hello(role="input", session="t")))
                    for record in read_records(sys.argv[1]):
                        if record.kind == "c2s" and decode(record.payload).type in ("hmd", "rgbd"):
                            await ws.send(record.payload)
                            if decode(record.payload).type == "hmd":
                                break
                    while decode(await ws.recv()).type != "pose":
                        pass
            assert "torch" not in sys.modules, "the server imported torch"

        asyncio.run(main())
        """
    )
    recording = Path(__file__).resolve().parents[2] / "recordings" / "walk-0000.egrec"
    subprocess.run([sys.executable, "-c", script, str(recording)], check=True, timeout=120)
