"""The C++ client core (clients/unreal/EgoPoseProtocol.h) compiled with g++ against msgpack-cxx and checked against
the golden fixtures and PROTOCOL.md's worked examples (clients/unreal/tests/core_test.cpp). Skipped, saying so,
without g++ or msgpack-cxx (Debian: apt-get install libmsgpack-cxx-dev; .ci/run installs it)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
UNREAL = ROOT / "clients" / "unreal"
GXX = shutil.which("g++")
MSGPACK_HEADER = Path("/usr/include/msgpack.hpp")
pytestmark = pytest.mark.skipif(
    GXX is None or not MSGPACK_HEADER.exists(),
    reason="needs g++ and msgpack-cxx (apt-get install libmsgpack-cxx-dev)",
)


def test_cpp_core_matches_golden_fixtures_and_worked_examples(tmp_path: Path) -> None:
    exe = tmp_path / "core_test"
    build = [
        GXX,
        "-std=c++17",
        "-Wall",
        "-Wextra",
        "-Werror",
        "-O1",
        "-o",
        str(exe),
        str(UNREAL / "tests" / "core_test.cpp"),
    ]
    built = subprocess.run(build, capture_output=True, text=True, timeout=300)
    assert built.returncode == 0, built.stdout + built.stderr
    golden, openxr = ROOT / "tests" / "protocol" / "golden", ROOT / "tests" / "protocol" / "openxr"
    result = subprocess.run([str(exe), str(golden), str(openxr)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and result.stdout.startswith("ok: "), result.stdout + result.stderr
