"""``egoposevr`` entry point. Subcommands register here; each imports its heavy modules only when run.

Only subcommands that work are listed.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from ..model.provenance import package_version, remember_code
from . import (
    bench_cmd,
    blend_cmd,
    bodies_cmd,
    bridge_cmd,
    decode_cmd,
    demo_cmd,
    eval_cmd,
    export_cmd,
    fitbody_cmd,
    models_cmd,
    motion_cmd,
    render_cmd,
    replay_cmd,
    serve_cmd,
    synth_cmd,
    train_cmd,
)

# Subcommands whose files or reports record the code that made them (model/provenance.py).
RECORDING = frozenset({"synth", "train", "export", "blend", "fit-body", "eval"})
# (name, module): each module has `add_arguments(parser)`, `run(args) -> int` and a docstring for --help.
SUBCOMMANDS = (
    ("demo", demo_cmd),
    ("serve", serve_cmd),
    ("models", models_cmd),
    ("replay", replay_cmd),
    ("render", render_cmd),
    ("bridge", bridge_cmd),
    ("bench", bench_cmd),
    ("decode", decode_cmd),
    ("motion", motion_cmd),
    ("bodies", bodies_cmd),
    ("synth", synth_cmd),
    ("train", train_cmd),
    ("export", export_cmd),
    ("blend", blend_cmd),
    ("fit-body", fitbody_cmd),
    ("eval", eval_cmd),
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="egoposevr", description="EgoPoseVR: real-time full-body pose server for VR headsets."
    )
    parser.add_argument("--version", action="version", version=f"egoposevr {package_version()}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, module in SUBCOMMANDS:
        summary = (module.__doc__ or "").strip().splitlines()[0]
        sub = subparsers.add_parser(
            name,
            help=summary,
            description=module.__doc__,
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        module.add_arguments(sub)
        sub.set_defaults(run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    # the command line as typed, and the code as imported, for what records how a file was made
    # (model/provenance.py)
    args.command_line = ["egoposevr", *(sys.argv[1:] if argv is None else argv)]
    if args.command in RECORDING:
        remember_code()
    return args.run(args)


if __name__ == "__main__":
    sys.exit(main())
