"""Fit each visual encoder's body regressor: bone lengths from the height and what the camera measures.

Run after `egoposevr export`. For every RGB-D visual encoder the folder's models use, feeds each sequence of
--split (of every --data folder, fitted together) through the serving code's body calibrator (camera frames
through the encoder and Alg. 1, head heights from the headset), fits a regressor from the height and the
measured hip, spine and leg lengths to every bone's length (one ridge expert per body family the training
bodies show), and writes it beside the encoder (visual-rgbd.onnx -> visual-rgbd.body.json).
With --check-split it reports the summed bone-length error there, in each --data folder that has that split.
Models load it with their encoder; a regressor fitted on another encoder is refused. See
model/runtime/body.py.

Example:
  egoposevr fit-body --data data/dev --weights model/weights
  egoposevr fit-body --data data/v3g data/sit-train --weights model/weights --check-split ''
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--data", type=Path, nargs="+", required=True, metavar="DIR",
        help="dataset root; several: their --split sequences fitted together",
    )  # fmt: skip
    parser.add_argument("--weights", type=Path, required=True, metavar="DIR", help="exported models")
    parser.add_argument("--split", default="train", help="split to fit on (default train)")
    parser.add_argument(
        "--check-split",
        default="val",
        help="split to report on, in each --data folder that has it; '' for none (default val)",
    )
    parser.add_argument("--ridge", type=float, default=None, help="ridge penalty (default 1.0)")
    parser.add_argument("--no-progress", action="store_true")


def run(args: argparse.Namespace) -> int:
    from ..model.runtime.loading import ModelError
    from ..model.training.bodyfit import DEFAULT_RIDGE, fit_body_regressors
    from ..model.training.dataset import DatasetError

    def progress(name: str, done: int, total: int) -> None:
        if not args.no_progress:
            print(f"\r{name}: {done}/{total} sequences", end="" if done < total else "\n", file=sys.stderr)

    ridge = DEFAULT_RIDGE if args.ridge is None else args.ridge
    try:
        written = fit_body_regressors(
            args.weights, args.data, args.split, args.check_split or None, ridge, progress, args.command_line
        )
    except (DatasetError, ModelError, ValueError) as error:
        print(f"egoposevr fit-body: {error}", file=sys.stderr)
        return 2
    if not written:
        print(f"egoposevr fit-body: no model in {args.weights} reads a depth camera", file=sys.stderr)
        return 2
    for path, regressor in written.items():
        errors = regressor.record.get("summed_bone_error_cm")
        report = ", ".join(f"{k} {v:.1f}" for k, v in errors.items()) if errors else "no check split"
        print(f"{path.name}: {regressor.record['sequences']} sequences; summed bone error cm: {report}")
    return 0
