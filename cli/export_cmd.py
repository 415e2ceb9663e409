"""Export trained checkpoints to the ONNX models the runtime serves.

Writes <name>.onnx per model and the visual encoders they share (visual-rgb.onnx, visual-rgbd.onnx) into
--out, each with its config, joint order and units in the ONNX metadata, and checks every graph against
torch (max |difference| must stay under 1e-4). The bundled weights are model/weights/.

Example:
  egoposevr export --runs runs/cpu16 --out model/weights
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--runs", type=Path, required=True, metavar="DIR", help="checkpoints from train")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR")
    parser.add_argument("--model", default="all", help="zoo names, comma-separated, or all (default)")


def run(args: argparse.Namespace) -> int:
    from ..model.training.export import PARITY_TOL, export_zoo
    from ..model.zoo import resolve

    try:
        names = resolve(args.model)
        errors = export_zoo(names, args.runs, args.out)
    except (ValueError, FileNotFoundError) as error:
        print(f"egoposevr export: {error}", file=sys.stderr)
        return 2
    worst = 0.0
    for name, err in errors.items():
        size_mb = (args.out / name).stat().st_size / 1e6
        print(f"{name:28s} {size_mb:6.2f} MB   max |torch - onnx| = {err:.2e}")
        worst = max(worst, err)
    if worst > PARITY_TOL:
        print(f"egoposevr export: parity {worst:.2e} exceeds {PARITY_TOL:.0e}", file=sys.stderr)
        return 1
    return 0
