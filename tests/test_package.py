"""Package-wide invariants: import boundaries, the console script, and the layout an install produces."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# Folders that serving runs from: never torch. model/ is serving code too, except its training-only parts.
SERVING = ["protocol", "server", "clients", "cli", "model"]
TRAINING_ONLY = {"nets", "train", "export"}  # under model/: the nets/ package, train.py, export.py
PROTOCOL_FORBIDDEN = {
    "asyncio",
    "socket",
    "websockets",
    "numpy",
    "cv2",
    "torch",
    "os",
    "io",
    "pathlib",
    "open",
}


def imported_modules(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


def serving_files():
    for folder in SERVING:
        for path in (ROOT / folder).rglob("*.py"):
            parts = path.relative_to(ROOT / "model").with_suffix("").parts if folder == "model" else ()
            if TRAINING_ONLY & set(parts):
                continue
            yield path


def test_serving_code_never_imports_torch():
    offenders = [str(p.relative_to(ROOT)) for p in serving_files() if {"torch", "roma"} & imported_modules(p)]
    assert offenders == []


def test_protocol_does_no_io():
    for path in (ROOT / "protocol").rglob("*.py"):
        tree = ast.parse(path.read_text())
        calls = {
            n.func.id for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)
        }
        assert not (imported_modules(path) | calls) & PROTOCOL_FORBIDDEN, path.name


@pytest.mark.parametrize(
    "module",
    ["egoposevr.protocol", "egoposevr.model.skeleton", "egoposevr.model.hmd", "egoposevr.model.filters",
     "egoposevr.model.runtime", "egoposevr.model.evaluate", "egoposevr.model.kpo", "egoposevr.model.weights",
     "egoposevr.cli.main", "egoposevr.server.app", "egoposevr.server.hub", "egoposevr.cli.serve_cmd"],
)  # fmt: skip
def test_importing_serving_modules_does_not_load_torch(module):
    code = f"import sys, {module}; assert 'torch' not in sys.modules, 'torch was imported'"
    subprocess.run([sys.executable, "-c", code], check=True)


def run_cli(*args, stdin=b""):
    return subprocess.run(
        [sys.executable, "-m", "egoposevr.cli.main", *args], input=stdin, capture_output=True
    )


def test_help_lists_only_working_subcommands():
    from egoposevr.cli.main import SUBCOMMANDS

    out = run_cli("--help").stdout.decode()
    assert "decode" in out
    for name, _ in SUBCOMMANDS:
        assert run_cli(name, "--help").returncode == 0


def test_decode_command_checks_files(tmp_path):
    good = ROOT / "tests" / "protocol" / "golden" / "hmd.msgpack"
    ok = run_cli("decode", str(good))
    assert ok.returncode == 0 and b'"type": "hmd"' in ok.stdout
    bad = run_cli("decode", "-", stdin=b"\x81\xa4type\xa3hmd")
    assert bad.returncode == 1 and b"unsupported_version" in bad.stdout


def test_console_script_is_installed():
    script = Path(sys.executable).parent / "egoposevr"
    assert script.exists(), "pip install -e . creates the console script"
    assert b"usage: egoposevr" in subprocess.run([script, "--help"], capture_output=True).stdout


def test_a_regular_install_carries_every_subpackage(tmp_path):
    """Not only the editable install: a plain `pip install .` maps each folder to egoposevr.<name>."""
    target = tmp_path / "site"
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
         "--target", str(target), str(ROOT)],
        check=True, capture_output=True,
    )  # fmt: skip
    installed = {p.relative_to(target).as_posix() for p in (target / "egoposevr").rglob("*.py")}
    expected = {f"egoposevr/{p.relative_to(ROOT).as_posix()}" for f in ("protocol", "model", "cli")
                for p in (ROOT / f).rglob("*.py")}  # fmt: skip
    assert expected <= installed
    weights = ROOT / "model" / "weights"
    bundled = {
        p.name for p in weights.iterdir() if p.suffix in (".onnx", ".json") or p.name == "MODEL_CARD.md"
    }
    assert bundled <= {
        p.name for p in (target / "egoposevr" / "model" / "weights").iterdir()
    }  # models, regressors
    code = "import egoposevr.protocol as p, egoposevr.model.hmd; print(p.__file__)"
    out = subprocess.run(
        [sys.executable, "-c", code], env={"PYTHONPATH": str(target)}, capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr
    assert str(target) in out.stdout
