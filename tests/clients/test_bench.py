"""`egoposevr bench`, small: one short run per feature; the JSON keys, the plot, the sweep's bookkeeping."""

from __future__ import annotations

import json

from egoposevr.cli.main import main
from egoposevr.clients.bench import STAGES


def test_bench_reports_latency_stages_fps_and_a_plot(tmp_path, capsys):
    out, png = tmp_path / "bench.json", tmp_path / "bench.png"
    args = ["bench", "--models", "hmd", "--seconds", "1.5", "--sessions", "2", "--flat-out", "--sweep",
            "--max-sessions", "2", "--json", str(out), "--plot", str(png)]  # fmt: skip
    assert main(args) == 0
    report = json.loads(out.read_text())
    result = report["models"]["hmd"]
    assert {"latency_ms", "stages_ms", "sessions", "skipped", "fps"} <= set(result)
    assert set(result["latency_ms"]) >= {"p50", "p95", "p99", "max"}
    assert 0 < result["latency_ms"]["p50"] <= result["latency_ms"]["p99"] <= result["latency_ms"]["max"]
    assert set(result["stages_ms"]) <= set(STAGES) and {"fusion", "total", "queue"} <= set(
        result["stages_ms"]
    )
    assert result["sessions"] == 2 and result["answered"] > 150 and result["fps"] > 0
    assert result["server_cpu_percent"] > 0
    steps = result["sweep"]["steps"]
    assert [s["sessions"] for s in steps][:1] == [1] and result["sweep"]["max_sessions_p99_within_frame"] <= 2
    assert png.stat().st_size > 10_000
    assert "| hmd | 2 |" in capsys.readouterr().out


def test_bench_compares_against_the_naive_cache(tmp_path):
    out = tmp_path / "naive.json"
    assert main(["bench", "--models", "hmd-rgbd", "--seconds", "1.5", "--naive", "--json", str(out)]) == 0
    models = json.loads(out.read_text())["models"]
    assert set(models) == {"hmd-rgbd", "hmd-rgbd (naive)"}
    assert models["hmd-rgbd"]["naive_visual_ratio"] > 1  # re-encoding 8 frames costs more than one


def test_bench_refuses_bad_arguments(capsys):
    assert main(["bench", "--sessions", "0"]) == 2
    assert main(["bench", "--flat-out", "--models", "nope"]) == 2
    assert "nope" in capsys.readouterr().err
