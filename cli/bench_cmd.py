"""Measure latency: N mock headsets at real rate against a server, per model, with the server's stage times.

Starts a server in a subprocess unless --url is given. Reports end-to-end latency (hmd sent -> pose received,
one clock) p50/p95/p99/max, the server-reported stages, skipped samples and the server's CPU use.
--sweep finds the most sessions that keep p99 within one 90 Hz frame (11.1 ms) with no skipped sample, against
two servers side by side: cross-session batching on (--batch-window-ms) and off; --sweep-repeats N runs it N
times and reports the median. The load generator's own CPU is reported; on a machine with 4 or more cores
the servers and the load generator are pinned to separate cores (--no-pin keeps them together); --flat-out measures the
paper's full-pipeline FPS in-process (a new RGB-D frame every sample); --naive replays the first recording
in-process through the incremental keypoint cache and through the paper's baseline that re-encodes the whole
visual window per request, and reports how much the cache saves (the server has no such mode).
--soak SECONDS streams the sessions without a break against a server that records them (--record), samples
the server's memory, open files, threads and the latency every --soak-interval, and fails (exit 1) if its
memory grows more than --soak-growth-mib after --soak-warmup.

Examples:
  egoposevr bench                                   # egoposevr, 1 session, 20 s, 90 Hz + 30 Hz
  egoposevr bench --sessions 4 --models egoposevr,hmd --json bench.json --plot bench.png
  egoposevr bench --sweep --flat-out --naive --seconds 10
  egoposevr bench --sweep --sweep-repeats 3 --seconds 10 --json sweep.json     # PERFORMANCE.md
  egoposevr bench --soak 3600 --sessions 2 --json soak.json       # an hour; CI runs --soak 120
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..clients import url_argument


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--url", type=url_argument, default=None, help="an already running server (default: start one)"
    )
    parser.add_argument("--sessions", type=int, default=1, help="concurrent mock headsets (default 1)")
    parser.add_argument("--seconds", type=float, default=20.0, help="length of each run (default 20)")
    parser.add_argument("--hmd-rate", type=float, default=90.0, help="headset rate, Hz (default 90)")
    parser.add_argument(
        "--camera-rate", type=float, default=30.0, help="camera rate, Hz; 0 = none (default 30)"
    )
    parser.add_argument("--models", default="egoposevr", help="comma-separated models (default egoposevr)")
    parser.add_argument("--recordings", type=Path, nargs="*", default=None, metavar="FILE.egrec",
                        help="sessions to replay (default: the bundled ones, one per headset in turn)")  # fmt: skip
    parser.add_argument("--naive", action="store_true", help="also measure the re-encode-everything baseline")
    parser.add_argument("--sweep", action="store_true", help="find the most sessions with p99 <= 11.1 ms")
    parser.add_argument("--max-sessions", type=int, default=12, help="upper bound of the sweep (default 12)")
    parser.add_argument(
        "--sweep-repeats", type=int, default=1, help="sweeps to take the median of (default 1)"
    )
    parser.add_argument("--batch-window-ms", type=float, default=None,
                        help="the batching server's window (default: the server's own default)")  # fmt: skip
    parser.add_argument("--pin", action=argparse.BooleanOptionalAction, default=True,
                        help="pin servers and load generator apart when there are >= 4 cores (default on)")  # fmt: skip
    parser.add_argument("--flat-out", action="store_true", help="full-pipeline FPS, in-process")
    parser.add_argument("--soak", type=float, default=None, metavar="SECONDS", help="one long run, sampled")
    parser.add_argument("--soak-interval", type=float, default=60.0, metavar="S", help="sample period (60)")
    parser.add_argument(
        "--soak-warmup", type=float, default=120.0, metavar="S", help="before memory counts (120)"
    )
    parser.add_argument(
        "--soak-growth-mib", type=float, default=64.0, metavar="MIB", help="allowed growth after warm-up (64)"
    )
    parser.add_argument(
        "--providers",
        default="cpu",
        help="onnxruntime execution providers for the server it starts and --flat-out",
    )
    parser.add_argument("--json", type=Path, default=None, metavar="OUT")
    parser.add_argument("--plot", type=Path, default=None, metavar="OUT.png", help="needs matplotlib")


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def print_tables(results: dict[str, dict]) -> None:
    print(
        "| model | sessions | e2e p50 | p95 | p99 | max (ms) | server total p50 | p99 (ms) | skipped | server CPU | FPS |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name, r in results.items():
        lat, total = r["latency_ms"], r["stages_ms"].get("total", {})
        cpu = "-" if r.get("server_cpu_percent") is None else f"{r['server_cpu_percent']:.0f} %"
        fps = "-" if r.get("fps") is None else f"{r['fps']:.0f}"
        print(f"| {name} | {r['sessions']} | {_ms(lat['p50'])} | {_ms(lat['p95'])} | {_ms(lat['p99'])} | "
              f"{_ms(lat['max'])} | {_ms(total.get('p50'))} | {_ms(total.get('p99'))} | {r['skipped']} | {cpu} | {fps} |")  # fmt: skip
    print("\nserver stages, ms (p50 / p99 / mean):")
    for name, r in results.items():
        parts = [f"{k} {_ms(v['p50'])}/{_ms(v['p99'])}/{_ms(v['mean'])}" for k, v in r["stages_ms"].items()]
        print(f"  {name}: " + "  ".join(parts))
    for name, r in results.items():
        if "sweep" in r:
            print_sweep(name, r["sweep"])
        if "naive_visual_ratio" in r:
            ms = r["naive_visual_ms"]
            print(f"\n{name}: the incremental cache spends {r['naive_visual_ratio']:.1f}x less visual-encoder time "
                  f"per request than re-encoding the window ({ms['incremental']:.2f} against {ms['naive']:.2f} ms, "
                  "mean of the visual stage, in-process over the same recording)")  # fmt: skip


def print_sweep(model: str, result: dict) -> None:
    """Each sweep's steps per server, then the most sessions that held (median over the sweeps)."""
    for i, one in enumerate(result["sweeps"]):
        print(
            f"\n{model}, sweep {i + 1}: sessions | "
            + " | ".join(
                f"{server}: e2e p99 (server p99) skipped, server CPU, bench CPU"
                for server in result["servers"]
            )
        )
        for step in one["steps"]:
            cells = []
            for server in result["servers"]:
                r = step.get(server)
                cells.append(
                    "-"
                    if r is None
                    else f"{_ms(r['p99_ms'])} ({_ms(r['server_p99_ms'])}) "
                    f"{r['skipped']}, {_pct(r['server_cpu_percent'])}, {_pct(r['bench_cpu_percent'])}"
                )
            print(f"  {step['sessions']} | " + " | ".join(cells))  # fmt: skip
    for server, held in result["max_sessions"].items():
        runs = ", ".join(str(one["max_sessions"][server]) for one in result["sweeps"])
        print(f"{model}: {server}: {held} sessions hold e2e p99 <= 11.1 ms with no skipped sample "
              f"(median of {len(result['sweeps'])} sweeps: {runs})")  # fmt: skip
    print(f"pinned apart: {result['pinned'] or 'no (fewer than 4 cores, or --no-pin)'}")


def _pct(value: float | None) -> str:
    return "-" if value is None else f"{value:.0f} %"


def run_sweeps(args: argparse.Namespace, load, model: str) -> dict:
    """--sweep: a batching and a non-batching server side by side, --sweep-repeats times."""
    import contextlib
    import statistics

    from ..clients.bench import pinned_to, pinning, serving, sweep

    window = [] if args.batch_window_ms is None else ["--batch-window-ms", str(args.batch_window_ms)]
    variants = {"batched": window, "unbatched": ["--batch-window-ms", "0"]}
    server_cpus, bench_cpus = pinning() if args.pin and args.url is None else (None, None)
    with contextlib.ExitStack() as stack:
        servers = {name: stack.enter_context(serving(None, "--providers", args.providers, *flags,
                                                     cpus=server_cpus))
                   for name, flags in variants.items()}  # fmt: skip
        with pinned_to(bench_cpus):
            sweeps = [sweep(servers, load, model, args.max_sessions) for _ in range(args.sweep_repeats)]
    best = {name: statistics.median(s["max_sessions"][name] for s in sweeps) for name in variants}
    pinned = None if server_cpus is None else {"servers": sorted(server_cpus), "bench": sorted(bench_cpus)}
    return {"servers": list(variants), "max_sessions": best, "sweeps": sweeps, "pinned": pinned}


def run_soak(args: argparse.Namespace) -> int:
    """--soak: one long run against a recording server, sampled every interval; exit 1 if memory grows."""
    import dataclasses
    import tempfile

    from ..clients.bench import Load, serving, soak, soak_verdict
    from ..recordings import bundled

    model = args.models.split(",")[0].strip()
    load = Load(
        args.sessions, args.soak, args.hmd_rate, args.camera_rate, tuple(args.recordings or bundled())
    )
    print("| t (s) | server RSS (MiB) | open files | threads | e2e p50 | p99 (ms) | answered | skipped |")
    print("|---|---|---|---|---|---|---|---|")

    def show(s) -> None:
        print(f"| {s.t_s:.0f} | {_ms(s.rss_mib)} | {s.open_files} | {s.threads} | {_ms(s.p50_ms)} | "
              f"{_ms(s.p99_ms)} | {s.answered} | {s.skipped} |", flush=True)  # fmt: skip

    with tempfile.TemporaryDirectory(prefix="egoposevr-soak-") as folder:
        try:
            with serving(args.url, "--record", folder) as (url, pid):
                samples = soak(url, pid, load, model, args.soak_interval, show)
        except (OSError, RuntimeError) as exc:
            print(f"egoposevr bench: {exc}", file=sys.stderr)
            return 1
    verdict = soak_verdict(samples, args.soak_warmup, args.soak_growth_mib)
    print(json.dumps(verdict))
    if args.json is not None:
        args.json.write_text(json.dumps({"load": dataclasses.asdict(load) | {"recordings": None},
                                         "model": model, "samples": [dataclasses.asdict(s) for s in samples],
                                         "verdict": verdict}, indent=2, default=str))  # fmt: skip
    return 0 if verdict["passed"] else 1


def check_recordings(paths: list[Path] | None) -> bool:
    """Read the user's --recordings once before any server starts: False (said on stderr) when one cannot
    be replayed; a recording cut short is benchmarked on its good part, with a warning."""
    from ..clients.replay import Recording, ReplayError
    from ..recordings.egrec import EgrecError

    for path in paths or ():
        try:
            recording = Recording.load(path)
        except (OSError, EgrecError, ReplayError) as exc:
            print(f"egoposevr bench: {exc}", file=sys.stderr)
            return False
        if (warning := recording.cut_warning("replaying")) is not None:
            print(f"egoposevr bench: {warning}", file=sys.stderr)
    return True


def run(args: argparse.Namespace) -> int:
    if not check_recordings(args.recordings):
        return 2
    if args.soak is not None:
        if args.soak <= 0 or args.soak_interval <= 0:
            print("egoposevr bench: --soak and --soak-interval must be > 0", file=sys.stderr)
            return 2
        return run_soak(args)
    from ..clients.bench import Load, flat_out_fps, measure, plot, serving, visual_ms
    from ..clients.replay import Recording
    from ..model.runtime.loading import ProviderError, resolve_providers
    from ..model.weights import model_files
    from ..recordings import bundled

    try:
        providers = resolve_providers(args.providers)
    except ProviderError as error:
        print(f"egoposevr bench: {error}", file=sys.stderr)
        return 2
    models = [m.strip() for m in args.models.split(",") if m.strip()]
    files = model_files()
    if args.flat_out and (missing := [m for m in models if m not in files]):
        print(f"egoposevr bench: --flat-out needs bundled models; no {missing}", file=sys.stderr)
        return 2
    if args.sessions < 1 or args.seconds <= 0 or args.hmd_rate <= 0 or args.camera_rate < 0:
        print("egoposevr bench: sessions >= 1, seconds > 0, rates > 0 (camera may be 0)", file=sys.stderr)
        return 2
    load = Load(
        args.sessions, args.seconds, args.hmd_rate, args.camera_rate, tuple(args.recordings or bundled())
    )
    results: dict[str, dict] = {}
    try:
        with serving(args.url, "--providers", args.providers) as (url, pid):
            for model in models:
                results[model] = measure(url, pid, load, model, tag=f"bench-{model}")
        if args.sweep:
            if args.url is not None:
                print(
                    "egoposevr bench: --sweep starts its own servers; --url is ignored for it",
                    file=sys.stderr,
                )
            for model in models:
                results[model]["sweep"] = run_sweeps(args, load, model)
        if args.naive:  # in-process, side by side: the server has no naive mode
            recording = Recording.load(load.recordings[0])
            for model in models:
                if model not in files:
                    continue
                incremental = visual_ms(files[model], recording, naive=False, providers=providers)
                baseline = visual_ms(files[model], recording, naive=True, providers=providers)
                results[model]["naive_visual_ms"] = {"incremental": incremental, "naive": baseline}
                if incremental > 0:
                    results[model]["naive_visual_ratio"] = baseline / incremental
    except (OSError, RuntimeError) as exc:
        print(f"egoposevr bench: {exc}", file=sys.stderr)
        return 1
    if args.flat_out:
        recording = Recording.load(load.recordings[0])
        for name in list(results):
            results[name]["fps"] = flat_out_fps(files[name], recording, providers=providers)
    for r in results.values():
        r.setdefault("fps", None)
    print_tables(results)
    if args.plot is not None:
        try:
            plot(results, args.plot)
        except ImportError:
            print(
                "egoposevr bench: --plot needs matplotlib (pip install 'egoposevr[bench]')", file=sys.stderr
            )
            return 2
    if args.json is not None:
        clean = {n: {k: v for k, v in r.items() if k != "latency_samples_ms"} for n, r in results.items()}
        args.json.write_text(json.dumps({"load": {"sessions": load.sessions, "seconds": load.seconds,
                                                  "hmd_rate_hz": load.hmd_rate_hz, "camera_rate_hz": load.camera_rate_hz},
                                         "models": clean}, indent=2))  # fmt: skip
    return 0
