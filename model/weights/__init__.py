"""The bundled model zoo: ONNX files made by ``egoposevr train`` + ``egoposevr export`` (MODEL_CARD.md)."""

from __future__ import annotations

from pathlib import Path

WEIGHTS_DIR = Path(__file__).resolve().parent


def model_files(folder: str | Path = WEIGHTS_DIR) -> dict[str, Path]:
    """{model name: path} for every model file in a folder (visual encoders are not models), zoo order first."""
    from ..zoo import ZOO

    found = {p.stem: p for p in Path(folder).glob("*.onnx") if not p.stem.startswith("visual-")}
    order = list(ZOO) + sorted(set(found) - set(ZOO))
    return {name: found[name] for name in order if name in found}
