"""Evaluate served models on a dataset split: the paper's Tables 2-3 as a markdown table.

Runs the serving runtime (ONNX models, the same code the server uses) over every sequence of --split,
pushing camera frames as they would arrive, and reports MPJPE / PA-MPJPE / MPJRE (upper and lower body),
H-PE, jitter and full-pipeline FPS (one stream, a new RGB-D frame every headset sample).

Example:
  egoposevr eval --data data/dev --split val --json eval.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, required=True, metavar="DIR", help="dataset root")
    parser.add_argument("--split", default="val", help="split to evaluate (default val)")
    parser.add_argument("--models", default="all", help="comma-separated model names (default all)")
    parser.add_argument("--models-dir", type=Path, default=None, metavar="DIR", help="default: bundled")
    parser.add_argument("--limit", type=int, default=None, metavar="N", help="at most N sequences")
    parser.add_argument("--json", type=Path, default=None, metavar="OUT")
    parser.add_argument("--no-progress", action="store_true")


def run(args: argparse.Namespace) -> int:
    from ..model.runtime.loading import ModelError
    from ..model.training.dataset import DatasetError
    from ..model.training.evaluate import evaluate, markdown_table
    from ..model.weights import WEIGHTS_DIR, model_files

    available = model_files(args.models_dir or WEIGHTS_DIR)
    wanted = list(available) if args.models in ("", "all") else [m.strip() for m in args.models.split(",")]
    missing = [m for m in wanted if m not in available]
    if missing or not wanted:
        print(
            f"egoposevr eval: no model file for {missing or 'any model'}; have {sorted(available)}",
            file=sys.stderr,
        )
        return 2

    def progress(name: str, done: int, total: int) -> None:
        if not args.no_progress:
            print(f"\r{name}: {done}/{total} sequences", end="" if done < total else "\n", file=sys.stderr)

    try:
        results = evaluate(args.data, args.split, {m: available[m] for m in wanted}, args.limit, progress)
    except (DatasetError, ModelError) as error:
        print(f"egoposevr eval: {error}", file=sys.stderr)
        return 2
    print(markdown_table(results))
    if args.json:
        args.json.write_text(json.dumps({"split": args.split, "models": results}, indent=2) + "\n")
    return 0
