"""The server's added latency for one headset session at real rate (90 Hz headset + 30 Hz camera).

Usage: python benchmarks/server_latency.py [--model egoposevr] [--seconds 20] [--runs 3] [--recording walk-0000]

Starts `egoposevr serve` in its own process (so the client does not share its GIL), replays a bundled
recording at its recorded pace over a loopback WebSocket and prints, per run and as the median over runs:
- end-to-end latency: hmd sent -> its pose received, one clock (the client's), p50 / p99 / max;
- the server's own `total` stage (arrival -> pose ready to send), p50 / p99 — the added latency without the
  loopback hops and the client's own decoding;
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
import time
from pathlib import Path

import numpy as np
from websockets.asyncio.client import connect

from egoposevr.protocol import Hello, decode, encode
from egoposevr.recordings.egrec import KIND_CLIENT, read_records

RECORDINGS = Path(__file__).resolve().parents[1] / "recordings"


def start_server(model: str) -> tuple[subprocess.Popen, str]:
    cmd = [sys.executable, "-m", "egoposevr.cli.main", "serve", "--port", "0", "--default-model", model]
    process = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
    for line in process.stderr:
        if match := re.search(r"on (ws://\S+)", line):
            return process, match.group(1)
    raise RuntimeError("the server did not start")


def client_messages(name: str) -> list[tuple[int, str, bytes]]:
    out = []
    for record in read_records(RECORDINGS / f"{name}.egrec"):
        if record.kind == KIND_CLIENT and (kind := decode(record.payload).type) != "hello":
            out.append((record.t_us, kind, record.payload))
    return out


async def one_run(url: str, messages: list[tuple[int, str, bytes]], seconds: float, session: str) -> dict:
    sent: dict[int, float] = {}
    e2e_ms, server_ms, skipped = [], [], 0
    stages: dict[str, list[int]] = {}
    async with connect(f"{url}?session={session}", compression=None) as ws:
        await ws.send(encode(Hello(role="input", session=session)))

        async def receive() -> None:
            nonlocal skipped
            async for data in ws:
                now = time.perf_counter()
                msg = decode(data)
                if msg.type == "pose":
                    e2e_ms.append((now - sent[msg.seq]) * 1e3)
                    server_ms.append(msg.timing_us["total"] * 1e-3)
                    skipped += msg.skipped or 0
                    for stage, us in msg.timing_us.items():
                        stages.setdefault(stage, []).append(us)

        reader = asyncio.create_task(receive())
        start, t0, seq_offset, loop_t_us = time.perf_counter(), messages[0][0], 0, messages[-1][0] + 11_111
        while time.perf_counter() - start < seconds:  # loop the recording, seqs and times kept increasing
            for t_us, kind, data in messages:
                delay = (t_us - t0 + seq_offset * loop_t_us) * 1e-6 - (time.perf_counter() - start)
                if delay > 0:
                    await asyncio.sleep(delay)
                msg = decode(data)
                shifted = msg.model_copy(update={"seq": msg.seq + seq_offset * 100_000,
                                                 "t_us": msg.t_us + seq_offset * loop_t_us})  # fmt: skip
                if kind == "hmd":
                    sent[shifted.seq] = time.perf_counter()
                await ws.send(encode(shifted) if seq_offset else data)
                if time.perf_counter() - start >= seconds:
                    break
            seq_offset += 1
        await asyncio.sleep(0.5)
        reader.cancel()
    return {
        "e2e": np.array(e2e_ms), "server": np.array(server_ms), "answered": len(e2e_ms), "skipped": skipped,
        "sent": len(sent), "stages": stages,
    }  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--model", default="egoposevr")
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--recording", default="walk-0000")
    args = parser.parse_args()
    messages = client_messages(args.recording)
    process, url = start_server(args.model)
    rows, stage_rows = [], []
    try:
        for i in range(args.runs):
            r = asyncio.run(one_run(url, messages, args.seconds, f"bench-{i}"))
            row = {
                "e2e_p50": np.percentile(r["e2e"], 50), "e2e_p99": np.percentile(r["e2e"], 99),
                "e2e_max": r["e2e"].max(), "srv_p50": np.percentile(r["server"], 50),
                "srv_p99": np.percentile(r["server"], 99), "answered": r["answered"], "skipped": r["skipped"],
            }  # fmt: skip
            rows.append(row)
            stage_rows.append(
                {k: (np.percentile(v, 50), np.percentile(v, 99)) for k, v in r["stages"].items()}
            )
            print(f"run {i + 1}: " + "  ".join(f"{k} {v:.2f}" if isinstance(v, float) else f"{k} {v}"
                                              for k, v in row.items()), flush=True)  # fmt: skip
    finally:
        process.terminate()
        process.wait(10)
    print(f"\nmodel {args.model}, {args.seconds:g} s x {args.runs} runs, medians over runs (ms):")
    print("| e2e p50 | e2e p99 | e2e max | server p50 | server p99 | answered | skipped |")
    print("|---|---|---|---|---|---|---|")
    med = {k: statistics.median(r[k] for r in rows) for k in rows[0]}
    print(f"| {med['e2e_p50']:.2f} | {med['e2e_p99']:.2f} | {med['e2e_max']:.2f} | {med['srv_p50']:.2f} | "
          f"{med['srv_p99']:.2f} | {med['answered']:.0f} | {med['skipped']:.0f} |")  # fmt: skip
    print("\nserver stages, µs (median over runs of each run's p50 / p99):")
    for stage in stage_rows[0]:
        p50 = statistics.median(r[stage][0] for r in stage_rows if stage in r)
        p99 = statistics.median(r[stage][1] for r in stage_rows if stage in r)
        print(f"  {stage:10s} {p50:8.0f} {p99:8.0f}")


if __name__ == "__main__":
    main()
