"""Package-wide invariants: import boundaries, the console script, and the layout an install produces."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# Folders that serving runs from: never torch. model/ is serving code too, except its training-only parts.
SERVING = ["protocol", "server", "clients", "cli", "model"]
TORCH_ALLOWED = [
    "model/training/nets",
    "model/training/train.py",
    "model/training/export.py",
    "model/training/blend.py",
    "model/synth/anny_bodies.py",  # builds body banks with the anny body model; rendering reads the bank
]
# Which parts of model/ the runtime and the shared modules beside it may import (absolute names under
# egoposevr.model): each other, never training/ or synth/.
_SERVING_LAYER = {
    "runtime",
    "config",
    "skeleton",
    "rotations",
    "hmd",
    "inputs",
    "rig",
    "zoo",
    "weights",
    "provenance",
}
MODEL_LAYERS = {"runtime": _SERVING_LAYER, "shared": _SERVING_LAYER}
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
    allowed = [ROOT / p for p in TORCH_ALLOWED]
    for folder in SERVING:
        for path in (ROOT / folder).rglob("*.py"):
            if not any(path == a or a in path.parents for a in allowed):
                yield path


def model_imports(path: Path) -> set[str]:
    """The egoposevr.model submodules (first level: runtime, training, synth, skeleton...) a file imports,
    relative imports resolved against the file's place in the package."""
    package = ["egoposevr", *path.relative_to(ROOT).parent.parts]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            module = [*base, *(node.module.split(".") if node.module else [])]
            targets = [[*module, a.name] for a in node.names] if not node.module else [module]
        elif isinstance(node, ast.Import):
            targets = [a.name.split(".") for a in node.names]
        else:
            continue
        for t in targets:
            if t[:2] == ["egoposevr", "model"] and len(t) > 2:
                found.add(t[2])
    return found


def test_serving_code_never_imports_torch():
    offenders = [str(p.relative_to(ROOT)) for p in serving_files() if {"torch", "roma"} & imported_modules(p)]
    assert offenders == []


def test_model_layers_point_one_way():
    """runtime/ and the shared modules beside it never reach into training/ or synth/; training/ may use
    the runtime (evaluation is what is served), never the other way round."""
    shared = [p for p in (ROOT / "model").glob("*.py")]
    runtime = list((ROOT / "model" / "runtime").rglob("*.py"))
    offenders = {
        str(p.relative_to(ROOT)): sorted(model_imports(p) - MODEL_LAYERS["runtime"]) for p in shared + runtime
    }
    assert {k: v for k, v in offenders.items() if v} == {}


def test_serving_never_imports_training_or_synthesis():
    for folder in ("server", "clients"):
        for path in (ROOT / folder).rglob("*.py"):
            assert not {"training", "synth"} & model_imports(path), path


def test_protocol_does_no_io():
    for path in (ROOT / "protocol").rglob("*.py"):
        tree = ast.parse(path.read_text())
        calls = {
            n.func.id for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)
        }
        assert not (imported_modules(path) | calls) & PROTOCOL_FORBIDDEN, path.name


@pytest.mark.parametrize(
    "module",
    ["egoposevr.protocol", "egoposevr.model.skeleton", "egoposevr.model.hmd", "egoposevr.model.config",
     "egoposevr.model.runtime.pipeline", "egoposevr.model.runtime.frames", "egoposevr.model.runtime.kpo",
     "egoposevr.model.training.evaluate", "egoposevr.model.training.bodyfit", "egoposevr.model.weights",
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
