"""Render a third-person skeleton video (MP4) from a recorded session or a live server session.

From a recording, the model runs in-process (no server needed) and the recorded ground truth, if any, is drawn
as a grey ghost with the running MPJPE. From a live server, the command joins --session as a viewer.

Examples:
  egoposevr render recordings/walk-0000.egrec --out walk.mp4
  egoposevr render recordings/kick-0002.egrec --model hmd --out kick-hmd.mp4
  egoposevr render --url ws://127.0.0.1:8765/ws --session demo --seconds 10 --out live.mp4
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..clients import url_argument


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("recording", type=Path, nargs="?", metavar="FILE.egrec", help="recorded session")
    parser.add_argument(
        "--url", type=url_argument, default=None, help="live server WebSocket URL instead of a recording"
    )
    parser.add_argument("--session", default="demo", help="live session to watch (default demo)")
    parser.add_argument("--seconds", type=float, default=10.0, help="live: how long to watch (default 10)")
    parser.add_argument(
        "--model", default="egoposevr", help="recording: bundled model to run (default egoposevr)"
    )
    parser.add_argument(
        "--models-dir", type=Path, default=None, metavar="DIR", help="recording: model folder"
    )
    parser.add_argument("--out", type=Path, required=True, metavar="VIDEO.mp4")
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--size", default="640x480", metavar="WxH")
    parser.add_argument(
        "--strict", action="store_true", help="refuse a recording cut short (default: render its good part)"
    )


def run(args: argparse.Namespace) -> int:
    from ..clients.render import frames_from_recording, frames_from_server, write_video
    from ..clients.replay import Recording, ReplayError
    from ..model.runtime.loading import LoadedModel, ModelError
    from ..model.weights import WEIGHTS_DIR, model_files
    from ..recordings.egrec import EgrecError

    if (args.recording is None) == (args.url is None):
        print("egoposevr render: give a recording or --url, not both", file=sys.stderr)
        return 2
    try:
        size = tuple(int(v) for v in args.size.lower().split("x"))
        assert len(size) == 2 and min(size) >= 16
    except (ValueError, AssertionError):
        print(f"egoposevr render: --size must be WxH, got {args.size!r}", file=sys.stderr)
        return 2
    try:
        if args.url is not None:
            frames = frames_from_server(args.url, args.session, args.seconds, args.fps)
        else:
            files = model_files(args.models_dir or WEIGHTS_DIR)
            if args.model not in files:
                print(f"egoposevr render: no model {args.model!r}; have {', '.join(files)}", file=sys.stderr)
                return 2
            recording = Recording.load(args.recording, strict=args.strict)
            if (warning := recording.cut_warning("rendering")) is not None:
                print(f"egoposevr render: {warning} (--strict refuses such files)", file=sys.stderr)
            frames = frames_from_recording(
                recording, LoadedModel.load(files[args.model]), args.model, args.fps
            )
        count = write_video(frames, args.out, args.fps, size)
    except (OSError, EgrecError, ReplayError, ModelError) as exc:
        print(f"egoposevr render: {exc}", file=sys.stderr)
        return 1
    if count == 0:
        print("egoposevr render: no poses to draw", file=sys.stderr)
        return 1
    print(f"wrote {args.out} ({count} frames, {count / args.fps:.1f} s at {args.fps:g} fps)")
    return 0
