"""The server's added latency for one headset session at real rate (90 Hz headset + 30 Hz camera).

Usage: python benchmarks/server_latency.py [--model egoposevr] [--seconds 15] [--runs 3] [--recording walk-0000]

Starts `egoposevr serve` in its own process (so the client does not share its GIL), replays a bundled
recording on loop at its recorded pace with the mock headset (`clients/replay.py`) and prints, per run and as
the median over runs:
- end-to-end latency: hmd sent -> its pose received, one clock (the client's), p50 / p99 / max;
- the server's own `total` stage (arrival -> pose ready to send), p50 / p99 — the added latency without the
  loopback hops and the client's decoding — and every other stage the poses report;
- answered and skipped samples.
The full `egoposevr bench` command (many sessions, sweeps, plots) arrives with the benchmark issue.
"""

from __future__ import annotations

import argparse
import asyncio
import re
import statistics
import subprocess
import sys

import numpy as np

from egoposevr.clients.replay import Recording, Replayer
from egoposevr.recordings import BUNDLED_DIR


def start_server(model: str) -> tuple[subprocess.Popen, str]:
    cmd = [sys.executable, "-m", "egoposevr.cli.main", "serve", "--port", "0", "--default-model", model]
    process = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
    for line in process.stderr:
        if match := re.search(r"on (ws://\S+)", line):
            return process, match.group(1)
    raise RuntimeError("the server did not start")


def one_run(recording: Recording, url: str, seconds: float, session: str) -> dict[str, float]:
    stats = asyncio.run(Replayer(recording, url, session, loop=True, seconds=seconds).run())
    e2e, server = np.asarray(stats.latency_ms), np.asarray(stats.stages_us["total"]) * 1e-3
    row = {
        "e2e_p50": np.percentile(e2e, 50), "e2e_p99": np.percentile(e2e, 99), "e2e_max": e2e.max(),
        "srv_p50": np.percentile(server, 50), "srv_p99": np.percentile(server, 99),
        "answered": stats.answered, "skipped": stats.skipped,
    }  # fmt: skip
    stages = {k: (np.percentile(v, 50), np.percentile(v, 99)) for k, v in stats.stages_us.items()}
    return row | {f"stage:{k}": v for k, v in stages.items()}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--model", default="egoposevr")
    parser.add_argument("--seconds", type=float, default=15.0)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--recording", default="walk-0000")
    args = parser.parse_args()
    recording = Recording.load(BUNDLED_DIR / f"{args.recording}.egrec")
    process, url = start_server(args.model)
    try:
        rows = [one_run(recording, url, args.seconds, f"bench-{i}") for i in range(args.runs)]
    finally:
        process.terminate()
        process.wait(10)
    med = {k: statistics.median(r[k] for r in rows) for k in rows[0] if not k.startswith("stage:")}
    print(f"model {args.model}, {args.seconds:g} s x {args.runs} runs, medians over runs (ms):")
    print("| e2e p50 | e2e p99 | e2e max | server p50 | server p99 | answered | skipped |")
    print("|---|---|---|---|---|---|---|")
    print(f"| {med['e2e_p50']:.2f} | {med['e2e_p99']:.2f} | {med['e2e_max']:.2f} | {med['srv_p50']:.2f} | "
          f"{med['srv_p99']:.2f} | {med['answered']:.0f} | {med['skipped']:.0f} |")  # fmt: skip
    print("\nserver stages, µs (median over runs of each run's p50 / p99):")
    for key in (k for k in rows[0] if k.startswith("stage:")):
        p50 = statistics.median(r[key][0] for r in rows if key in r)
        p99 = statistics.median(r[key][1] for r in rows if key in r)
        print(f"  {key[6:]:10s} {p50:8.0f} {p99:8.0f}")


if __name__ == "__main__":
    main()
