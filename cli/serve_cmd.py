"""Run the inference server: WebSocket /ws, /healthz, /readyz and /metrics on one port.

Every flag is also an EGOPOSEVR_* environment variable and a key of the --config TOML file (flags win over
the environment, the environment over the file). Stops gracefully on SIGINT/SIGTERM.

Examples:
  egoposevr serve                                  # bundled models on 127.0.0.1:8765
  egoposevr serve --host 0.0.0.0 --models-dir ./models --record ./recordings
  EGOPOSEVR_TOKEN=secret egoposevr serve --config server.toml
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
from pathlib import Path
from typing import Any, get_args


def _flag_type(annotation: Any) -> Any:
    """argparse type for a config field: the first concrete type of its annotation (Path, int, float, str)."""
    for candidate in (Path, int, float):
        if annotation is candidate or candidate in get_args(annotation):
            return candidate
    return str


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ..server.config import ServerConfig

    parser.add_argument(
        "--config", type=Path, default=None, metavar="FILE", help="TOML file with the same keys"
    )
    for name, field in ServerConfig.model_fields.items():
        flag = "--" + name.replace("_", "-")
        help_text = f"{field.description or ''} (default {field.default!r})".strip()
        if field.annotation is bool:
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=None, help=help_text)
        else:
            parser.add_argument(flag, type=_flag_type(field.annotation), default=None, help=help_text)


def run(args: argparse.Namespace) -> int:
    from ..server.app import serve_until_signalled
    from ..server.config import ConfigError, ServerConfig, load_config

    flags = {name: getattr(args, name) for name in ServerConfig.model_fields}
    try:
        config = load_config(flags, args.config)
    except ConfigError as exc:
        print(f"egoposevr serve: {exc}", file=sys.stderr)
        return 2
    logging.basicConfig(
        level=config.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    logging.getLogger("websockets").setLevel(logging.WARNING)  # it logs every handshake at INFO
    try:
        asyncio.run(serve_until_signalled(config))
    except ConfigError as exc:
        print(f"egoposevr serve: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # the port is taken, the interface does not exist
        print(f"egoposevr serve: cannot listen on {config.host}:{config.port}: {exc}", file=sys.stderr)
        return 1
    return 0
