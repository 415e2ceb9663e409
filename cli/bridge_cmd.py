"""Bridge a session's poses to other software. `vmc`: VMC protocol (OSC over UDP) for VSeeFace, Warudo,
VNyan, EVMC4U and other VMC receivers: Unity HumanBodyBones names, local rotations in Unity's frame.

Examples:
  egoposevr bridge vmc --session demo --to 127.0.0.1:39539          # VSeeFace's default VMC port
  egoposevr bridge vmc --url ws://server:8765/ws --session room-1 --to 192.168.1.20:39540
"""

from __future__ import annotations

import argparse
import asyncio
import sys

from ..clients import url_argument

DEFAULT_URL = "ws://127.0.0.1:8765/ws"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("protocol", choices=["vmc"], help="output protocol")
    parser.add_argument(
        "--url", type=url_argument, default=DEFAULT_URL, help=f"server WebSocket URL (default {DEFAULT_URL})"
    )
    parser.add_argument("--session", required=True, help="session to follow")
    parser.add_argument("--to", required=True, metavar="HOST:PORT", help="where the VMC receiver listens")
    parser.add_argument("--seconds", type=float, default=None, help="stop after this long (default: Ctrl-C)")


def run(args: argparse.Namespace) -> int:
    from ..clients.vmc import bridge

    host, _, port = args.to.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        print(f"egoposevr bridge: --to must be HOST:PORT, got {args.to!r}", file=sys.stderr)
        return 2
    print(f"forwarding session {args.session!r} from {args.url} to VMC receiver {host}:{port}", flush=True)
    try:
        counts = asyncio.run(bridge(args.url, args.session, (host, int(port)), args.seconds))
    except KeyboardInterrupt:
        return 0
    except (OSError, RuntimeError) as exc:
        print(f"egoposevr bridge: {exc}", file=sys.stderr)
        return 1
    print(f"sent {counts['poses']} poses as {counts['bundles']} bundles ({counts['bytes']} bytes)")
    return 0
