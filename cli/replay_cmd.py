"""Replay a recorded session (.egrec) against a server as a mock headset, and report latency and accuracy.

Paces hmd and rgbd by the recording's send times, receives the poses, and prints end-to-end latency
percentiles, answered and skipped samples and, when the recording has ground truth, MPJPE upper/lower.

Examples:
  egoposevr replay recordings/walk-0000.egrec
  egoposevr replay session.egrec --url ws://host:8765/ws --model hmd --speed 2 --json report.json
  egoposevr replay recordings/squat-0001.egrec --loop --seconds 60
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
from pathlib import Path

from ..clients import url_argument

DEFAULT_URL = "ws://127.0.0.1:8765/ws"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("recording", type=Path, metavar="FILE.egrec")
    parser.add_argument(
        "--url", type=url_argument, default=DEFAULT_URL, help=f"server WebSocket URL (default {DEFAULT_URL})"
    )
    parser.add_argument("--session", default=None, help="session id (default: the recording's)")
    parser.add_argument("--model", default=None, help="model to ask for (default: the server's default)")
    parser.add_argument("--speed", type=float, default=1.0, help="playback speed factor (default 1)")
    parser.add_argument("--loop", action="store_true", help="repeat the recording until --seconds or Ctrl-C")
    parser.add_argument("--seconds", type=float, default=None, help="stop after this much playback time")
    parser.add_argument("--token", default=None, help="shared token, if the server requires one")
    parser.add_argument("--json", type=Path, default=None, metavar="OUT", help="write the report as JSON")
    parser.add_argument("--quiet", action="store_true", help="no live line each second")
    parser.add_argument(
        "--strict", action="store_true", help="refuse a recording cut short (default: replay its good part)"
    )
    parser.add_argument(
        "--body",
        type=Path,
        default=None,
        metavar="FILE.json",
        help="a returning wearer (PROTOCOL.md §4.2): give the body kept in FILE before the first sample, and at "
        "the end keep the body the server measured there (the file is made if missing)",
    )


def run(args: argparse.Namespace) -> int:
    from ..clients.replay import Recording, Replayer, ReplayError, summary_line
    from ..recordings.egrec import EgrecError

    if args.speed <= 0:
        print("egoposevr replay: --speed must be > 0", file=sys.stderr)
        return 2
    try:
        recording = Recording.load(args.recording, strict=args.strict)
    except (OSError, EgrecError, ReplayError) as exc:
        print(f"egoposevr replay: {exc}", file=sys.stderr)
        return 2
    if (warning := recording.cut_warning("replaying")) is not None:
        print(f"egoposevr replay: {warning} (--strict refuses such files)", file=sys.stderr)
    try:
        replayer = Replayer(
            recording, args.url, args.session, args.model, args.speed, args.loop, args.seconds, args.token,
            body_file=args.body,
        )  # fmt: skip
    except ReplayError as exc:
        print(f"egoposevr replay: {exc}", file=sys.stderr)
        return 2
    live = (
        None
        if args.quiet
        else (lambda stats: print(summary_line(stats.report()), file=sys.stderr, flush=True))
    )
    try:
        stats = asyncio.run(replayer.run(on_second=live))
    except ReplayError as exc:
        print(f"egoposevr replay: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        stats = replayer.stats
    report = stats.report()
    report["recording_cut"] = None if recording.cut is None else {
        "records_read": recording.cut.records,
        "bytes_read": recording.cut.bytes_read,
        "bytes_total": recording.cut.bytes_total,
        "reason": recording.cut.reason,
    }  # fmt: skip
    print(summary_line(report) + ("  (recording cut short)" if recording.cut is not None else ""))
    if args.json is not None:
        args.json.write_text(json.dumps(report, indent=2))
    return 0 if report["answered"] else 1
