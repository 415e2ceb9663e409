"""Recorded sessions: the ``.egrec`` format and the demo recordings bundled with the package.

The bundled recordings are synthesised from procedural motion only (no third-party motion capture inside
the package), by ``egoposevr synth --sessions``; DATA.md gives the exact command.
"""

from __future__ import annotations

from pathlib import Path

from .egrec import EgrecError, EgrecWriter, Record, read_header, read_records

BUNDLED_DIR = Path(__file__).resolve().parent


def bundled() -> list[Path]:
    """Paths of the bundled demo recordings, sorted by name."""
    return sorted(BUNDLED_DIR.glob("*.egrec"))


__all__ = ["BUNDLED_DIR", "EgrecError", "EgrecWriter", "Record", "bundled", "read_header", "read_records"]
