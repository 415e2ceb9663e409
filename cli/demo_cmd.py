"""Run the demo: the server with the bundled models, and a mock headset replaying a bundled recording on loop.

Prints the web viewer's URL (open it in a browser to watch the avatar) and one live line per second
(latency, answered samples, accuracy against the recording's ground truth). Ctrl-C stops everything cleanly.

Examples:
  egoposevr demo
  egoposevr demo --recording squat-0001 --model hmd --port 9000
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import signal
import sys
from pathlib import Path

SESSION = "demo"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default="127.0.0.1", help="interface to listen on (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=8765, help="port (default 8765; 0 picks a free one)")
    parser.add_argument("--recording", default="walk-0000", help="bundled recording name or an .egrec path")
    parser.add_argument("--model", default=None, help="model for the demo session (default: the server's)")
    parser.add_argument("--seconds", type=float, default=None, help="stop after this long (default: Ctrl-C)")


def _recording_path(name: str) -> Path:
    from ..recordings import BUNDLED_DIR, bundled

    path = Path(name)
    if path.suffix == ".egrec":
        return path
    if not (BUNDLED_DIR / f"{name}.egrec").exists():
        raise FileNotFoundError(f"no bundled recording {name!r}; have {', '.join(p.stem for p in bundled())}")
    return BUNDLED_DIR / f"{name}.egrec"


async def _demo(args: argparse.Namespace) -> int:
    from ..clients.replay import Recording, Replayer, summary_line
    from ..server.app import running
    from ..server.config import ServerConfig

    recording = Recording.load(_recording_path(args.recording))
    if (warning := recording.cut_warning("replaying")) is not None:
        print(f"egoposevr demo: {warning}", file=sys.stderr)
    print(
        "starting the server (its first start on a machine compiles the pose kernels: about 30 s)", flush=True
    )
    async with running(ServerConfig(host=args.host, port=args.port)) as server:
        http = f"http://{'127.0.0.1' if args.host in ('0.0.0.0', '') else args.host}:{server.port}"
        print(f"EgoPoseVR demo: server {server.url}  (health {http}/healthz, metrics {http}/metrics)")
        print(f"replaying {recording.path.name} on loop as session {SESSION!r}")
        print(f"viewer: {http}/viewer/?session={SESSION}")
        print("Ctrl-C stops", flush=True)
        replayer = Replayer(recording, server.url, SESSION, args.model, loop=True, seconds=args.seconds)
        task = asyncio.create_task(
            replayer.run(on_second=lambda s: print(summary_line(s.report()), flush=True))
        )
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, replayer.stop)
        stats = await task
        print("final: " + summary_line(stats.report()), flush=True)
        return 0 if stats.answered else 1


def run(args: argparse.Namespace) -> int:
    from ..clients.replay import ReplayError
    from ..recordings.egrec import EgrecError
    from ..server.config import ConfigError

    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return asyncio.run(_demo(args))
    except (ConfigError, ReplayError, EgrecError, FileNotFoundError) as exc:
        print(f"egoposevr demo: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"egoposevr demo: cannot listen on {args.host}:{args.port}: {exc}", file=sys.stderr)
        return 1
