"""List the models a server would serve: name, inputs and description, plus files that fail to load.

With --training, each model's file and encoder also say how they were made: their digests, and for each net
its data (and the data's digest), steps, seed, start and the command, code and machine that ran it, and how
each file it started from was made, as the files record them (model/provenance.py; files made before those
were recorded say so). With --recipe, the commands that made each named model's file, in the order they ran.

Examples:
  egoposevr models
  egoposevr models --models-dir ./models
  egoposevr models --training egoposevr
  egoposevr models --recipe egoposevr
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--models-dir", type=Path, default=None, metavar="DIR", help="extra ONNX models")
    parser.add_argument("--no-bundled", action="store_true", help="leave out the bundled models")
    parser.add_argument(
        "--training", nargs="*", default=None, metavar="NAME",
        help="also say how each named model (every model without names) and its encoder were made",
    )  # fmt: skip
    parser.add_argument(
        "--recipe", nargs="+", default=None, metavar="NAME",
        help="print the commands that made each named model's file, in the order they ran",
    )  # fmt: skip


def run(args: argparse.Namespace) -> int:
    from ..server.registry import ModelRegistry

    registry = ModelRegistry(args.models_dir, bundled=not args.no_bundled)
    registry.rescan()
    unknown = sorted((set(args.training or ()) | set(args.recipe or ())) - set(registry.models))
    if args.recipe is not None:
        return _print_recipes(registry.models, args.recipe, unknown)
    unreadable: list[str] = []
    for name, model in registry.models.items():
        if args.training is not None and args.training and name not in args.training:
            continue
        print(f"{name:18s} {'+'.join(model.info.inputs):14s} {model.info.description}")
        if args.training is not None and not _print_training(model.info):
            unreadable.append(name)
    for path, reason in registry.failures.items():
        print(f"FAILED {path}: {reason}")
    for name in unknown:
        print(f"UNKNOWN {name}: no such model (egoposevr models lists them)")
    return 0 if registry.models and not registry.failures and not unknown and not unreadable else 1


def _print_recipes(models: dict[str, Any], names: list[str], unknown: list[str]) -> int:
    """Each named model's recipe (provenance.recipe), as shell lines under a comment naming the file."""
    from ..model.provenance import RecordError, file_digest, recipe

    unreadable = False
    for name in names:
        info = models[name].info if name in models else None
        if info is None or getattr(info, "path", None) is None:
            print(f"# {name}: {'no such model' if info is None else 'no file: the model is code'}")
            continue
        print(f"# {info.path.name}, sha256 {file_digest(info.path)[:16]}")
        try:
            print("\n".join(recipe(info.metadata.training)))
        except RecordError as error:
            print(f"# {error}")
            unreadable = True
    return 1 if unknown or unreadable else 0


def _print_training(info: Any) -> bool:
    """A model's file and its encoder's, each with its digest and its training record described; False when a
    record cannot be read (said in its place)."""
    from ..model.provenance import RecordError, describe, describe_fit, file_digest
    from ..model.runtime.body import regressor_path

    if getattr(info, "path", None) is None:
        print("  no file: the model is code, trained on nothing")
        return True
    files = [(info.path, info.metadata.training)]
    if info.visual_path is not None and info.encoder is not None:
        files.append((info.visual_path, info.encoder.training))
    if info.body_regressor is not None:
        files.append((regressor_path(info.visual_path), info.body_regressor.record))
    readable = True
    for path, record in files:
        fitted = path.suffix == ".json"
        what = "the encoder's body regressor" if fitted else f"sha256 {file_digest(path)[:16]}"
        print(f"  {path.name}, {what}:")
        try:
            lines = describe_fit(record) if fitted else describe(record, "  ")
        except RecordError as error:
            lines, readable = [str(error)], False
        for line in lines:
            print(f"    {line}")
    return readable
