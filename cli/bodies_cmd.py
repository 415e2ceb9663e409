"""Make a body bank: random adult mesh bodies for `egoposevr synth --bodies`.

The bodies come from anny (NAVER's parametric body model, Apache-2.0, built on MakeHuman's CC0 assets; it
needs the training extras: torch and anny). Each body's shape parameters are drawn from the seed and
recorded in the bank; its SMPL-22 joints, skinning and body-part regions are derived from anny's rig and
segmentation. The bank is a plain .npz: rendering from it needs neither torch nor anny. --preview writes a
picture of every body with its joints.

Example:
  egoposevr bodies --count 64 --seed 0 --out data/bodies.npz --preview data/bodies.png
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--count", type=int, default=64, metavar="N", help="bodies in the bank (default 64)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, required=True, metavar="FILE", help="the bank (.npz)")
    parser.add_argument("--preview", type=Path, metavar="PNG", help="a picture of the bodies")


def run(args: argparse.Namespace) -> int:
    if not 1 <= args.count <= 10_000:
        print("egoposevr bodies: --count must be within 1..10000", file=sys.stderr)
        return 2
    try:
        from ..model.synth.anny_bodies import build_bank
    except ImportError as error:
        print(f"egoposevr bodies: needs the training extras (torch, anny): {error}", file=sys.stderr)
        return 2
    started = time.perf_counter()
    bank = build_bank(args.count, args.seed)
    bank.save(args.out)
    heights = [bank.height_m(b) for b in range(bank.count)]
    print(
        f"{bank.count} bodies ({bank.rest_vertices.shape[1]} vertices, {len(bank.faces)} triangles), heights "
        f"{min(heights):.2f}-{max(heights):.2f} m, in {time.perf_counter() - started:.1f} s: wrote {args.out}"
    )
    if args.preview:
        from ..model.synth.render import bank_preview

        bank_preview(bank, args.preview)
        print(f"wrote {args.preview}")
    return 0
