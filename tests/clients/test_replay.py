"""The mock headset against a real loopback server: pacing, loops, the report and its JSON, failures."""

from __future__ import annotations

import json

from loopback import RECORDINGS, running_server

from egoposevr.cli.main import main
from egoposevr.clients.replay import REPORT_KEYS, Recording

WALK = RECORDINGS / "walk-0000.egrec"


def test_replay_reports_latency_counts_and_accuracy(tmp_path, capsys):
    out = tmp_path / "report.json"
    with running_server() as server:
        code = main(
            [
                "replay",
                str(WALK),
                "--url",
                server.url,
                "--model",
                "hmd",
                "--seconds",
                "2",
                "--json",
                str(out),
                "--quiet",
            ]
        )
    assert code == 0
    report = json.loads(out.read_text())
    assert set(REPORT_KEYS) <= set(report)
    assert set(report["latency_ms"]) == {"p50", "p95", "p99", "max"}
    assert 0 < report["latency_ms"]["p50"] <= report["latency_ms"]["p99"] <= report["latency_ms"]["max"]
    assert report["answered"] + report["skipped"] == report["sent"] > 150  # 2 s at 90 Hz
    assert 0 < report["mpjpe_u_cm"] < 20 and 0 < report["mpjpe_l_cm"] < 40
    assert report["models"] == ["hmd"]
    assert "MPJPE upper" in capsys.readouterr().out


def test_loop_keeps_seq_and_time_increasing_past_the_recordings_end(tmp_path):
    recording = Recording.load(WALK)
    seconds = recording.duration_us * 1e-6 * 1.5
    out = tmp_path / "loop.json"
    with running_server() as server:
        args = ["replay", str(WALK), "--url", server.url, "--model", "hmd", "--loop", "--seconds", f"{seconds:.2f}",
                "--speed", "2", "--json", str(out), "--quiet"]  # fmt: skip
        assert main(args) == 0
    report = json.loads(out.read_text())
    samples = sum(m.type == "hmd" for _, m, _ in recording.messages)
    assert report["sent"] > 1.3 * samples  # went round once and more
    assert report["errors"] == {} and report["mpjpe_u_cm"] is not None  # truth matched across loops


def test_unreachable_server_and_bad_files_fail_clearly(tmp_path, capsys):
    assert main(["replay", str(WALK), "--url", "ws://127.0.0.1:1/ws", "--quiet"]) == 1
    assert "cannot reach" in capsys.readouterr().err
    bad = tmp_path / "bad.egrec"
    bad.write_bytes(b"\x00\x01garbage")
    assert main(["replay", str(bad)]) == 2
    assert "egrec" in capsys.readouterr().err


def test_a_fatal_server_error_ends_the_replay_with_its_reason(capsys):
    with running_server(token="s3cret") as server:
        assert main(["replay", str(WALK), "--url", server.url, "--quiet"]) == 1
    assert "auth_failed" in capsys.readouterr().err
