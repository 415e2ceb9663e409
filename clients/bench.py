"""The latency benchmark: N mock headsets at real rate against a server, per model; sweeps, flat-out
throughput and the incremental-vs-naive comparison.

Latency is end to end on one clock (the bench's): ``hmd`` sent → its ``pose`` received. The server's own
stage times come back in every pose (``timing_us``); CPU use is the server process' CPU time over the wall
time of the run (100 % = one core). The bench drives all sessions from one asyncio loop in its own process;
the server runs in another (``start_server``) unless a URL is given.

Shape legend: none (scalars and per-stage dicts).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import os
import re
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from ..model.inputs import decode_rgbd
from ..model.runtime.loading import DEFAULT_PROVIDERS, LoadedModel
from ..model.runtime.pipeline import Pipeline
from .replay import Recording, Replayer, ReplayStats

FRAME_BUDGET_MS = 11.1  # one display frame at 90 Hz
# Every stage a pose reports (PROTOCOL.md, pose.timing_us), in pipeline order.
STAGES = ("decode", "queue", "image", "features", "visual", "fusion", "fk_filter", "kpo", "rotations", "encode",
          "total")  # fmt: skip


@contextlib.contextmanager
def server_process(*args: str, cpus: set[int] | None = None) -> Iterator[tuple[str, int]]:
    """``egoposevr serve --port 0 ARGS`` in a subprocess (on ``cpus`` if given) -> (WebSocket URL, pid),
    stopped on exit."""
    cmd = [sys.executable, "-m", "egoposevr.cli.main", "serve", "--port", "0", *args]
    pin = None if cpus is None else (lambda: os.sched_setaffinity(0, cpus))
    process = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True, preexec_fn=pin)
    try:
        url = None
        for line in process.stderr:  # the startup line names the port
            if match := re.search(r"on (ws://\S+)", line):
                url = match.group(1)
                break
        if url is None:
            raise RuntimeError(f"the server did not start (exit {process.wait()})")
        # Keep reading its log (connects and closes), or a full pipe would stall the server.
        threading.Thread(target=lambda: [None for _ in process.stderr], daemon=True).start()
        yield url, process.pid
    finally:
        process.terminate()
        try:
            process.wait(15)
        except subprocess.TimeoutExpired:
            process.kill()
        process.stderr.close()


def serving(
    url: str | None, *args: str, cpus: set[int] | None = None
) -> contextlib.AbstractContextManager[tuple[str, int | None]]:
    """The given server (no pid: its CPU use is not measured), or a fresh one with the bench's limits."""
    if url is not None:
        return contextlib.nullcontext((url, None))
    limits = ("--max-sessions", "64", "--rate-limit-hz", "2000", "--rate-burst", "1000")
    return server_process(*limits, *args, cpus=cpus)


def pinning(min_cores: int = 4) -> tuple[set[int] | None, set[int] | None]:
    """(server cores, load-generator cores): a quarter of the cores (at least one) for the load generator,
    the rest for the servers, on machines with ``min_cores`` or more; (None, None) elsewhere (splitting two
    cores would halve the server)."""
    if not hasattr(os, "sched_getaffinity"):
        return None, None
    cores = sorted(os.sched_getaffinity(0))
    if len(cores) < min_cores:
        return None, None
    split = len(cores) - max(len(cores) // 4, 1)
    return set(cores[:split]), set(cores[split:])


@contextlib.contextmanager
def pinned_to(cpus: set[int] | None) -> Iterator[None]:
    """This process on ``cpus`` for the block (None: unchanged)."""
    if cpus is None:
        yield
        return
    before = os.sched_getaffinity(0)
    os.sched_setaffinity(0, cpus)
    try:
        yield
    finally:
        os.sched_setaffinity(0, before)


def _cpu_seconds(pid: int | None) -> float | None:
    if pid is None:
        return None
    try:
        import psutil

        times = psutil.Process(pid).cpu_times()
        return times.user + times.system
    except (ImportError, OSError):
        return None


def _percentiles(values: list[float] | np.ndarray) -> dict[str, float | None]:
    v = np.asarray(values, dtype=np.float64)
    if not len(v):
        return {"p50": None, "p95": None, "p99": None, "max": None, "mean": None}
    return {"p50": float(np.percentile(v, 50)), "p95": float(np.percentile(v, 95)),
            "p99": float(np.percentile(v, 99)), "max": float(v.max()), "mean": float(v.mean())}  # fmt: skip


@dataclasses.dataclass(frozen=True)
class Load:
    """What to drive: sessions, how long, at which rates, from which recordings."""

    sessions: int = 1
    seconds: float = 20.0
    hmd_rate_hz: float = 90.0
    camera_rate_hz: float = 30.0
    recordings: tuple[Path, ...] = ()


async def _drive(
    url: str, recordings: list[Recording], load: Load, model: str, tag: str
) -> list[ReplayStats]:
    async def session(i: int) -> ReplayStats:
        # Real headsets are not in phase: spread the sessions' samples over one headset period.
        await asyncio.sleep(i / (load.hmd_rate_hz * load.sessions))
        recording = recordings[i % len(recordings)]
        return await Replayer(recording, url, f"{tag}-{i}", model, loop=True, seconds=load.seconds).run()

    return list(await asyncio.gather(*(session(i) for i in range(load.sessions))))


def measure(url: str, pid: int | None, load: Load, model: str, tag: str = "bench") -> dict[str, Any]:
    """One run of ``load`` against a server: latency, stages, skipped, CPU."""
    recordings = [Recording.load(p).retimed(load.hmd_rate_hz, load.camera_rate_hz) for p in load.recordings]
    cpu_before, wall_before = _cpu_seconds(pid), time.perf_counter()
    bench_before = time.process_time()
    stats = asyncio.run(_drive(url, recordings, load, model, tag))
    cpu_after, wall = _cpu_seconds(pid), time.perf_counter() - wall_before
    bench_cpu = 100 * (time.process_time() - bench_before) / wall
    latency = [v for s in stats for v in s.latency_ms]
    stages = {k: [v * 1e-3 for s in stats for v in s.stages_us.get(k, [])] for k in STAGES}
    cpu = None if cpu_before is None or cpu_after is None else 100 * (cpu_after - cpu_before) / wall
    return {
        "sessions": load.sessions,
        "latency_ms": _percentiles(latency),
        "stages_ms": {k: _percentiles(v) for k, v in stages.items() if v},
        "answered": sum(s.answered for s in stats),
        "skipped": sum(s.skipped for s in stats),
        "sent": sum(s.sent for s in stats),
        "errors": {k: sum(s.errors.get(k, 0) for s in stats) for k in {c for s in stats for c in s.errors}},
        "server_cpu_percent": cpu,
        "bench_cpu_percent": bench_cpu,  # the load generator's own (mock headsets, decoding)
        "latency_samples_ms": latency,  # for the plot; dropped from the JSON
    }


def holds(result: dict[str, Any]) -> bool:
    """A load held: end-to-end p99 within one 90 Hz frame and no headset sample skipped."""
    p99 = result["latency_ms"]["p99"]
    return p99 is not None and p99 <= FRAME_BUDGET_MS and result["skipped"] == 0


def sweep(
    servers: dict[str, tuple[str, int | None]], load: Load, model: str, max_sessions: int = 16
) -> dict[str, Any]:
    """Add sessions until a load no longer :func:`holds`, against several servers side by side (each step
    measured on every server still holding, one after the other). -> the most sessions each held, and
    every step."""
    steps: list[dict[str, Any]] = []
    best = dict.fromkeys(servers, 0)
    holding = set(servers)
    for n in range(1, max_sessions + 1):
        step: dict[str, Any] = {"sessions": n}
        for name, (url, pid) in servers.items():
            if name not in holding:
                continue
            result = measure(url, pid, dataclasses.replace(load, sessions=n), model, tag=f"sweep-{name}-{n}")
            server_p99 = (result["stages_ms"].get("total") or {}).get("p99")
            step[name] = {"p99_ms": result["latency_ms"]["p99"], "server_p99_ms": server_p99,
                          "skipped": result["skipped"], "server_cpu_percent": result["server_cpu_percent"],
                          "bench_cpu_percent": result["bench_cpu_percent"]}  # fmt: skip
            if holds(result):
                best[name] = n
            else:
                holding.discard(name)
        steps.append(step)
        if not holding:
            break
    return {"max_sessions": best, "steps": steps}


def flat_out_fps(
    model_path: Path,
    recording: Recording,
    samples: int = 300,
    repeats: int = 3,
    naive: bool = False,
    providers: tuple[str, ...] = DEFAULT_PROVIDERS,
) -> float:
    """The paper's FPS: one stream, batch 1, a NEW RGB-D frame before every headset sample (image decode and
    visual encoder included), as fast as it goes, in-process. Median over ``repeats``."""
    hmd = [m for _, m, _ in recording.messages if m.type == "hmd"]
    frames = [m for _, m, _ in recording.messages if m.type == "rgbd"]
    pipeline = Pipeline(LoadedModel.load(model_path, providers=providers), naive=naive)
    rates = []
    for _ in range(repeats):
        pipeline.reset()
        started = time.perf_counter()
        for i in range(samples):
            sample = hmd[i % len(hmd)]
            t_us = sample.t_us + (i // len(hmd)) * (recording.duration_us + 11_111)
            if pipeline.model.visual is not None and frames:
                frame = frames[i % len(frames)]
                rgb, depth = decode_rgbd(frame.rgb, frame.depth)
                pipeline.push_rgbd(t_us - 1, rgb, depth, np.asarray(frame.intrinsics))
            pipeline.push_hmd(t_us, np.asarray(sample.poses()), np.asarray(sample.valid))
        rates.append(samples / (time.perf_counter() - started))
    return statistics.median(rates)


def visual_ms(
    model_path: Path, recording: Recording, naive: bool, providers: tuple[str, ...] = DEFAULT_PROVIDERS
) -> float:
    """Mean visual-stage time per pose (ms) over a recording replayed in arrival order, in-process: the
    incremental keypoint cache, or with ``naive`` the paper's baseline that re-encodes the whole window for
    every request. The baseline lives here, not in the server."""
    pipeline = Pipeline(LoadedModel.load(model_path, providers=providers), naive=naive)
    if pipeline.model.visual is None:
        return 0.0
    spent = []
    for _, message, _ in recording.messages:
        if message.type == "rgbd":
            rgb, depth = decode_rgbd(message.rgb, message.depth)
            pipeline.push_rgbd(message.t_us, rgb, depth, np.asarray(message.intrinsics))
        elif message.type == "hmd":
            pose = pipeline.push_hmd(message.t_us, np.asarray(message.poses()), np.asarray(message.valid))
            spent.append(pose.timing_us.get("visual", 0) * 1e-3)
    return float(np.mean(spent)) if spent else 0.0


def plot(results: dict[str, dict[str, Any]], path: Path) -> None:
    """Latency distribution (CDF per model) and the median stage times (stacked bars)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4.5))
    for name, result in results.items():
        latency = np.sort(result.get("latency_samples_ms", []))
        if len(latency):
            left.plot(latency, np.linspace(0, 1, len(latency)), label=f"{name} ({result['sessions']} sess.)")
    left.axvline(FRAME_BUDGET_MS, color="grey", linestyle="--", label="one 90 Hz frame")
    left.set(xlabel="end-to-end latency (ms)", ylabel="fraction of poses", title="Latency distribution")
    left.legend()
    stages = [s for s in STAGES if s != "total"]
    bottom = np.zeros(len(results))
    names = list(results)
    for stage in stages:
        heights = [((results[n]["stages_ms"].get(stage) or {}).get("p50") or 0.0) for n in names]
        right.bar(names, heights, bottom=bottom, label=stage)
        bottom += heights
    right.set(ylabel="server time, p50 per stage (ms)", title="Where the server's time goes")
    right.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# ------------------------------------------------------------------------------------------------ soak
@dataclasses.dataclass(frozen=True)
class SoakSample:
    """One interval of a soak: the server's resident memory, open files and threads at its end, and the
    interval's end-to-end latency, answered and skipped samples over all sessions."""

    t_s: float
    rss_mib: float | None
    open_files: int | None
    threads: int | None
    p50_ms: float | None
    p99_ms: float | None
    answered: int
    skipped: int


def _server_usage(pid: int | None) -> tuple[float | None, int | None, int | None]:
    """(resident MiB, open file descriptors, threads) of the server process, or Nones."""
    if pid is None:
        return None, None, None
    try:
        import psutil

        process = psutil.Process(pid)
        return process.memory_info().rss / 2**20, process.num_fds(), process.num_threads()
    except (ImportError, OSError):
        return None, None, None


def soak(
    url: str,
    pid: int | None,
    load: Load,
    model: str,
    interval_s: float = 60.0,
    on_sample: Callable[[SoakSample], None] = lambda sample: None,
) -> list[SoakSample]:
    """``load.sessions`` headsets streaming without a break for ``load.seconds``; a sample every
    ``interval_s`` (memory, files, threads of the server; latency of the interval)."""
    recordings = [Recording.load(p).retimed(load.hmd_rate_hz, load.camera_rate_hz) for p in load.recordings]
    return asyncio.run(_soak(url, pid, recordings, load, model, interval_s, on_sample))


async def _soak(
    url: str,
    pid: int | None,
    recordings: list[Recording],
    load: Load,
    model: str,
    interval_s: float,
    on_sample: Callable[[SoakSample], None],
) -> list[SoakSample]:
    replayers = [
        Replayer(recordings[i % len(recordings)], url, f"soak-{i}", model, loop=True, seconds=load.seconds)
        for i in range(load.sessions)
    ]

    async def run(i: int) -> ReplayStats:
        await asyncio.sleep(i / (load.hmd_rate_hz * load.sessions))
        return await replayers[i].run()

    tasks = [asyncio.create_task(run(i)) for i in range(load.sessions)]
    started, samples = time.perf_counter(), []
    answered, skipped = [0] * load.sessions, [0] * load.sessions
    while not all(t.done() for t in tasks):
        await asyncio.wait(tasks, timeout=interval_s)
        latencies: list[float] = []
        new_answered = new_skipped = 0
        for i, replayer in enumerate(replayers):
            stats = replayer.stats
            fresh = stats.answered - answered[i]
            latencies += list(stats.latency_ms)[-fresh:] if fresh > 0 else []
            new_answered, new_skipped = new_answered + fresh, new_skipped + stats.skipped - skipped[i]
            answered[i], skipped[i] = stats.answered, stats.skipped
        if not new_answered and all(t.done() for t in tasks):
            break  # the sessions ended inside this interval: nothing new to report
        rss, files, threads = _server_usage(pid)
        spread = _percentiles(latencies)
        sample = SoakSample(
            round(time.perf_counter() - started, 1), rss, files, threads, spread["p50"], spread["p99"],
            new_answered, new_skipped,
        )  # fmt: skip
        samples.append(sample)
        on_sample(sample)
    for task in tasks:
        task.result()  # a replay that failed fails the soak
    return samples


def soak_verdict(samples: list[SoakSample], warmup_s: float, growth_limit_mib: float) -> dict[str, Any]:
    """Memory at the first sample, after warm-up and at the end; growth past warm-up against the limit."""
    measured = [s for s in samples if s.rss_mib is not None]
    if not measured:
        return {"memory_checked": False, "passed": True, "reason": "the server's memory was not measured"}
    warm = next((s for s in measured if s.t_s >= warmup_s), measured[-1])
    after = [s for s in measured if s.t_s >= warm.t_s]
    growth = max(s.rss_mib for s in after) - warm.rss_mib
    files = [s.open_files for s in after if s.open_files is not None]
    return {
        "memory_checked": True,
        "rss_start_mib": measured[0].rss_mib,
        "rss_after_warmup_mib": warm.rss_mib,
        "rss_end_mib": measured[-1].rss_mib,
        "rss_growth_after_warmup_mib": growth,
        "growth_limit_mib": growth_limit_mib,
        "open_files_after_warmup": [min(files), max(files)] if files else None,
        "passed": growth <= growth_limit_mib,
    }
