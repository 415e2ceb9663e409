"""Check message files against protocol v1 and print them as JSON.

Each FILE holds one msgpack message exactly as sent in one WebSocket binary frame ('-' reads standard input).
Binary fields print as their size and first bytes. Exit status 1 if any file is not a valid v1 message; the
error code and message are the ones the server would send back.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from ..protocol import ProtocolError, decode


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("files", nargs="+", metavar="FILE", help="file with one msgpack message, or -")
    parser.add_argument("--max-bytes", type=int, default=None, help="size limit to check against")


def run(args: argparse.Namespace) -> int:
    failures = 0
    for name in args.files:
        data = sys.stdin.buffer.read() if name == "-" else Path(name).read_bytes()
        try:
            msg = decode(data) if args.max_bytes is None else decode(data, max_bytes=args.max_bytes)
        except ProtocolError as exc:
            failures += 1
            print(json.dumps({"file": name, "error": {"code": str(exc.code), "message": exc.message}}))
            continue
        print(json.dumps({"file": name, "bytes": len(data), "message": _printable(msg.model_dump())}))
    return 1 if failures else 0


def _printable(value: Any) -> Any:
    """JSON-able copy: bytes become a short description."""
    if isinstance(value, bytes):
        return {"bin_bytes": len(value), "starts": value[:8].hex()}
    if isinstance(value, dict):
        return {k: _printable(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_printable(v) for v in value]
    return value
