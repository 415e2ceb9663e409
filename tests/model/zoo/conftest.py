"""A tiny zoo the tests make themselves: synthesize -> train (preset tiny) -> export. Seconds, not minutes."""

import dataclasses

import pytest

from egoposevr.cli.main import main
from egoposevr.model.training.train import PRESETS, train_zoo
from egoposevr.model.zoo import ZOO


@pytest.fixture(scope="session")
def tiny_data(tmp_path_factory):
    root = tmp_path_factory.mktemp("zoo-data")
    common = [
        "--resolution",
        "80x64",
        "--hmd-rate",
        "60",
        "--seconds",
        "2",
        "--no-progress",
        "--out",
        str(root),
    ]
    assert main(["synth", "--procedural", "2", "--families", "walk,squat", "--seed", "3", *common]) == 0
    assert (
        main(["synth", "--procedural", "1", "--families", "kick", "--split", "val", "--seed", "4", *common])
        == 0
    )
    return root


@pytest.fixture(scope="session")
def tiny_runs(tiny_data, tmp_path_factory):
    out = tmp_path_factory.mktemp("zoo-runs")
    config = dataclasses.replace(PRESETS["tiny"], visual_steps=4, fusion_steps=4)
    train_zoo(list(ZOO), tiny_data, out, config, progress=False)
    return out


@pytest.fixture(scope="session")
def tiny_weights(tiny_runs, tmp_path_factory):
    out = tmp_path_factory.mktemp("zoo-weights")
    assert main(["export", "--runs", str(tiny_runs), "--out", str(out)]) == 0
    return out
