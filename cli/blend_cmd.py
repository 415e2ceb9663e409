"""Blend fusion nets in weight space: one net whose every weight is the weighted mean of several nets'.

For a net and a fine-tune of it (`train --init-from`): the blend keeps part of what the fine-tune learnt and
part of what it unlearnt (WiSE-FT). Nets trained from different random draws do not blend; serve them as an
ensemble instead (`export --runs A B`). Each fusion-<model>.pt that every --runs folder holds is blended with its
namesakes and written to --out, a runs folder for `egoposevr export` like any other. The nets
must be of one kind and config, read one encoder's keypoints and normalise their inputs alike.
See model/training/blend.py.

Example (half the bundled pair's start, half its fine-tune):
  egoposevr blend --runs runs/start-m0 runs/tuned-m0 --weights 0.5 0.5 --out runs/half-m0
A bundled member as a runs folder (the ONNX net loaded as it is, no step taken):
  egoposevr train --data D --model hmd-rgbd --out runs/start-m0 --encoders model/weights --init-from model/weights --init-member 0 --fusion-steps 0
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--runs",
        type=Path,
        nargs="+",
        required=True,
        metavar="DIR",
        help="runs folders whose fusion checkpoints are blended (two or more)",
    )
    parser.add_argument(
        "--weights",
        type=float,
        nargs="+",
        required=True,
        metavar="W",
        help="one weight per runs folder, >= 0; normalised to sum to 1",
    )
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="the blend's runs folder")


def run(args: argparse.Namespace) -> int:
    from ..model.training.blend import blend_runs

    try:
        written = blend_runs(args.runs, args.weights, args.out, args.command_line)
    except (FileNotFoundError, ValueError) as error:  # CheckpointError is a ValueError
        print(f"egoposevr blend: {error}", file=sys.stderr)
        return 2
    for path in written:
        print(f"{path}: blended from {len(args.runs)} nets")
    return 0
