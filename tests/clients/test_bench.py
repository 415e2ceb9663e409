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
    assert result["sessions"] == 2 and result["answered"] > 0 and result["fps"] > 0  # the rate is the bench's
    assert result["server_cpu_percent"] > 0
    sweep = result["sweep"]
    assert sweep["servers"] == ["batched", "unbatched"] and len(sweep["sweeps"]) == 1
    [steps] = [s["steps"] for s in sweep["sweeps"]]
    assert steps[0]["sessions"] == 1 and {"batched", "unbatched"} <= set(steps[0])
    assert steps[0]["batched"]["bench_cpu_percent"] > 0 and steps[0]["unbatched"]["server_cpu_percent"] > 0
    assert all(0 <= held <= 2 for held in sweep["max_sessions"].values())
    assert png.stat().st_size > 10_000
    printed = capsys.readouterr().out
    assert "| hmd | 2 |" in printed and "hmd: batched:" in printed and "hmd: unbatched:" in printed


def test_bench_compares_against_the_naive_cache(tmp_path):
    out = tmp_path / "naive.json"
    assert main(["bench", "--models", "hmd-rgbd", "--seconds", "1.5", "--naive", "--json", str(out)]) == 0
    models = json.loads(out.read_text())["models"]
    assert set(models) == {"hmd-rgbd"}  # the baseline runs in-process, not as a server mode
    assert models["hmd-rgbd"]["naive_visual_ratio"] > 1  # re-encoding 8 frames costs more than one
    ms = models["hmd-rgbd"]["naive_visual_ms"]
    assert 0 < ms["incremental"] < ms["naive"]


def test_bench_refuses_bad_arguments(capsys):
    assert main(["bench", "--sessions", "0"]) == 2
    assert main(["bench", "--flat-out", "--models", "nope"]) == 2
    assert "nope" in capsys.readouterr().err


def test_a_two_minute_soak_keeps_memory_files_and_answers_steady(tmp_path, capsys):
    """CI's short version of the hour-long soak (PERFORMANCE.md): two recorded sessions without a break."""
    out = tmp_path / "soak.json"
    args = ["bench", "--soak", "120", "--soak-interval", "20", "--soak-warmup", "40", "--soak-growth-mib", "32",
            "--sessions", "2", "--json", str(out)]  # fmt: skip
    assert main(args) == 0
    report = json.loads(out.read_text())
    samples, verdict = report["samples"], report["verdict"]
    assert len(samples) >= 5 and verdict["passed"] and verdict["memory_checked"]
    # Every headset sample of an interval is accounted for: answered by a pose or counted in a pose's `skipped`
    # (newest-wins). How many were answered is a speed, read by the benchmark (PERFORMANCE.md), not here.
    sent_per_interval = 2 * 90 * 20
    for s in samples[:-1]:
        assert s["answered"] > 0 and s["answered"] + s["skipped"] >= 0.8 * sent_per_interval, s
    answered = [s["answered"] for s in samples[:-1]]
    assert min(answered) >= 0.5 * max(answered)  # steady: no interval starves while another is served
    files = [s["open_files"] for s in samples]
    assert max(files) <= files[0] + 2  # no file leaks (the last sample may come after the sessions closed)
    assert "| t (s) | server RSS (MiB)" in capsys.readouterr().out


def test_a_soak_whose_memory_grows_fails():
    from egoposevr.clients.bench import SoakSample, soak_verdict

    growing = [SoakSample(60.0 * k, 300.0 + 10 * k, 12, 9, 3.0, 6.0, 10_000, 0) for k in range(10)]
    assert not soak_verdict(growing, warmup_s=120, growth_limit_mib=32)["passed"]
    assert soak_verdict(growing[:4], warmup_s=120, growth_limit_mib=32)["passed"]
