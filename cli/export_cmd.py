"""Export trained checkpoints to the ONNX models the runtime serves.

Writes <name>.onnx per model and the visual encoders they share (visual-rgb.onnx, visual-rgbd.onnx) into
--out, each with its config, joint order and units in the ONNX metadata, and checks every graph against
torch (max |difference| must stay under 1e-4). The bundled weights are model/weights/.

--encoders DIR takes the visual encoders (and their body regressors) from DIR as they are, for fusion nets
trained on them with `egoposevr train --encoders DIR`.

--runs with several folders (the same training with other seeds) serves each model as the mean of their
nets: one graph, the members' rotations (made orthonormal) and contact probabilities averaged.

--lean-gate writes into the files of models with KPO (egoposevr) that the runtime serves them with the lean
gate (model/runtime/stance.py): for nets that were chosen served with it (MODEL_CARD). --quiet-lift writes
into every model file that the runtime lifts a body estimate shorter than the wearer's quiet head
(model/runtime/body.py, QuietHead): for nets that hang the body from the eyes' head joint (MODEL_CARD).

--add-batch-axis rewrites model files exported for batch 1 (before the server batched sessions) in place
so that their fusion net takes a batch axis, checked against the original row by row.

--reexport rewrites model files in place in today's graph form (the exporter's opset, the nets' current
forward pass) from the weights they hold, without their checkpoints; metadata is kept, and the new graph
must agree with the old one within 1e-4. The bundled models were last rewritten so (MODEL_CARD).

--mirror-average rewrites model files in place so that each also answers for the mirrored person (the world
reflected, left and right swapped: a person its nets were trained on too) and serves the mean of its
answer and that one reflected back; twice the fusion net's work per sample (MODEL_CARD, "Each answer
averaged with the mirrored person's").

Examples:
  egoposevr export --runs runs/cpu16 --out model/weights
  egoposevr export --runs runs/temporal --out runs/temporal-weights --model egoposevr --encoders model/weights
  egoposevr export --runs runs/lock runs/lock2 --out runs/pair-weights --model egoposevr --encoders model/weights
  egoposevr export --add-batch-axis model/weights/egoposevr.onnx model/weights/hmd.onnx
  egoposevr export --reexport model/weights/hmd*.onnx model/weights/egoposevr*.onnx
  egoposevr export --mirror-average runs/pair-weights/egoposevr.onnx
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--runs", type=Path, nargs="+", metavar="DIR",
                        help="checkpoints from train; several: each model is the mean of their nets "
                             "(a seed ensemble; needs --encoders)")  # fmt: skip
    parser.add_argument("--out", type=Path, metavar="DIR")
    parser.add_argument("--model", default="all", help="zoo names, comma-separated, or all (default)")
    parser.add_argument("--encoders", type=Path, metavar="DIR",
                        help="copy the visual encoders from DIR (fusion nets trained with train --encoders)")  # fmt: skip
    parser.add_argument("--lean-gate", action="store_true",
                        help="the files of models with KPO ask the runtime for the lean gate "
                             "(model/runtime/stance.py): for nets chosen served with it")  # fmt: skip
    parser.add_argument("--quiet-lift", action="store_true",
                        help="the model files ask the runtime to lift a body estimate shorter than the "
                             "wearer's quiet head (model/runtime/body.py): for nets anchored at the eyes")  # fmt: skip
    parser.add_argument("--add-batch-axis", type=Path, nargs="+", metavar="ONNX",
                        help="give these fusion graphs a batch axis, in place (no --runs/--out)")  # fmt: skip
    parser.add_argument("--reexport", type=Path, nargs="+", metavar="ONNX",
                        help="rewrite these model files in today's graph form, in place (no --runs/--out)")  # fmt: skip
    parser.add_argument("--mirror-average", type=Path, nargs="+", metavar="ONNX",
                        help="rewrite these model files to average each answer with the mirrored person's, "
                             "in place (no --runs/--out)")  # fmt: skip


def run(args: argparse.Namespace) -> int:
    from ..model.training.export import PARITY_TOL, export_zoo
    from ..model.zoo import resolve

    if args.add_batch_axis:
        from ..model.training.export import add_batch_axis

        return _rewrite_in_place(
            args.add_batch_axis, add_batch_axis, "batch axis; batch of 8 against rows one by one"
        )
    if args.reexport:
        from ..model.training.export import reexport_model

        return _rewrite_in_place(
            args.reexport, reexport_model, "re-exported; against the old graph (batches of 1 and 8)"
        )
    if args.mirror_average:
        from ..model.training.export import export_mirror_averaged

        return _rewrite_in_place(
            args.mirror_average,
            lambda path: export_mirror_averaged(path, path, args.command_line),
            "mirror-averaged; against torch (batches of 1 and 8)",
        )
    if args.runs is None or args.out is None:
        print("egoposevr export: --runs and --out are required", file=sys.stderr)
        return 2
    try:
        names = resolve(args.model)
        errors = export_zoo(
            names, args.runs, args.out, args.encoders,
            lean_gate=args.lean_gate, command=args.command_line, quiet_lift=args.quiet_lift,
        )  # fmt: skip
    except (ValueError, FileNotFoundError) as error:
        print(f"egoposevr export: {error}", file=sys.stderr)
        return 2
    worst = 0.0
    for name, err in errors.items():
        size_mb = (args.out / name).stat().st_size / 1e6
        check = f"copied from {args.encoders}" if err is None else f"max |torch - onnx| = {err:.2e}"
        print(f"{name:28s} {size_mb:6.2f} MB   {check}")
        worst = max(worst, err or 0.0)
    if worst > PARITY_TOL:
        print(f"egoposevr export: parity {worst:.2e} exceeds {PARITY_TOL:.0e}", file=sys.stderr)
        return 1
    return 0


def _rewrite_in_place(paths: list[Path], rewrite: Callable[[Path], float], done: str) -> int:
    """Each file through ``rewrite`` (returns the largest difference it checked); stops at the first refusal."""
    for path in paths:
        try:
            worst = rewrite(path)
        except (ValueError, FileNotFoundError) as error:
            print(f"egoposevr export: {error}", file=sys.stderr)
            return 2
        print(f"{path}: {done}: max |difference| = {worst:.2e}")
    return 0
