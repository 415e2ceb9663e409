"""Synthesis speed: camera frames per second of `egoposevr synth`, capsule bodies against mesh bodies, side by
side in one run, each the median over repeated runs of a fresh process (start-up, numba's cache load and
the encoders included, as a user runs it).

Usage: python benchmarks/synthesis.py --bodies data/bodies.npz [--repeats 3] [--clips 4] [--seconds 5]
       [--resolution 320x256] [--rig-pool train]
Prints a markdown table: setting, median frames/s, min, max.
"""

from __future__ import annotations

import argparse
import re
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

RATE = re.compile(r"([0-9.]+) frames/s")


def frames_per_second(extra: list[str], clips: int, seconds: float, resolution: str) -> float:
    with tempfile.TemporaryDirectory() as out:
        command = [sys.executable, "-m", "egoposevr.cli.main", "synth", "--procedural", str(clips), "--seconds",
                   str(seconds), "--resolution", resolution, "--out", out, "--seed", "1", "--no-progress", *extra]  # fmt: skip
        done = subprocess.run(command, capture_output=True, text=True, check=True)
    return float(RATE.search(done.stdout).group(1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bodies", type=Path, required=True, help="a body bank (egoposevr bodies)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--clips", type=int, default=4)
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--resolution", default="320x256")
    parser.add_argument("--rig-pool", default="train")
    args = parser.parse_args()
    settings = {
        "capsules, fixed rig": [],
        "mesh bodies, fixed rig": ["--bodies", str(args.bodies)],
        f"mesh bodies, rigs drawn ({args.rig_pool})": [
            "--bodies",
            str(args.bodies),
            "--rig-pool",
            args.rig_pool,
        ],
    }
    frames_per_second(settings["mesh bodies, fixed rig"], 1, 2.0, args.resolution)  # numba's cache, warm
    rates: dict[str, list[float]] = {name: [] for name in settings}
    for _ in range(args.repeats):  # interleaved, so that the machine's load falls on every setting alike
        for name, extra in settings.items():
            rates[name].append(frames_per_second(extra, args.clips, args.seconds, args.resolution))
    print(f"| {args.resolution}, {args.clips} clips of {args.seconds:g} s | frames/s (median) | min | max |")
    print("|---|---:|---:|---:|")
    for name, values in rates.items():
        print(f"| {name} | {statistics.median(values):.1f} | {min(values):.1f} | {max(values):.1f} |")


if __name__ == "__main__":
    main()
