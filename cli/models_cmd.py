"""List the models a server would serve: name, inputs and description, plus files that fail to load.

Examples:
  egoposevr models
  egoposevr models --models-dir ./models
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--models-dir", type=Path, default=None, metavar="DIR", help="extra ONNX models")
    parser.add_argument("--no-bundled", action="store_true", help="leave out the bundled models")


def run(args: argparse.Namespace) -> int:
    from ..server.registry import ModelRegistry

    registry = ModelRegistry(args.models_dir, bundled=not args.no_bundled)
    registry.rescan()
    for name, model in registry.models.items():
        print(f"{name:18s} {'+'.join(model.info.inputs):14s} {model.info.description}")
    for path, reason in registry.failures.items():
        print(f"FAILED {path}: {reason}")
    return 0 if registry.models and not registry.failures else 1
