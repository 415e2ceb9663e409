"""The mock headset against a real loopback server: pacing, loops, the report and its JSON, failures."""

from __future__ import annotations

import json

import numpy as np
from loopback import RECORDINGS, Client, running_server

from egoposevr.cli.main import main
from egoposevr.clients.replay import REPORT_KEYS, Recording
from egoposevr.model.skeleton import joint_bone_lengths

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


def test_a_returning_wearer_keeps_the_measured_body_and_is_given_it_next_time(tmp_path, capsys):
    """--body FILE (PROTOCOL.md §4.2): the first run keeps the body the server measured, the second gives it
    before its first sample, and every pose of that session has the kept bones; a damaged file fails clearly."""
    body_file = tmp_path / "wearer.json"
    with running_server() as server:
        assert main(["replay", str(WALK), "--url", server.url, "--session", "first", "--body", str(body_file),
                     "--quiet"]) == 0  # fmt: skip
        assert f"body kept in {body_file}" in capsys.readouterr().out
        kept = json.loads(body_file.read_text())["bone_lengths_m"]
        assert len(kept) == 21
        with Client(server.url, "second") as viewer:
            viewer.hello("render", "second")
            viewer.collect()
            assert main(["replay", str(WALK), "--url", server.url, "--session", "second", "--body",
                         str(body_file), "--quiet"]) == 0  # fmt: skip
            assert capsys.readouterr().out.rstrip().endswith("body given")
            viewer.wait_for(lambda: len(viewer.poses()) > 300, timeout=30)
            bodies = [m for _, m in viewer.received if m.type == "body"]
            assert bodies[0].given and np.allclose(bodies[0].bone_lengths_m, kept, atol=1e-6)
            served = [joint_bone_lengths(np.reshape(p.joints, (22, 3))) for p in viewer.poses()]
            assert np.abs(np.array(served) - kept).max() < 2e-3  # from the first pose on
    body_file.write_text('{"bone_lengths_m": [0.1, 0.2]}')
    assert main(["replay", str(WALK), "--body", str(body_file), "--quiet"]) == 2
    assert "not a kept body" in capsys.readouterr().err
