"""The model registry without a server: the digests it gives clients (PROTOCOL.md §model-digests) follow the
files, an encoder shared by several models is read and hashed once per version, and each model's head joint
(§model-head-joint) is the one its file records."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest

from egoposevr.model.provenance import file_digest
from egoposevr.model.weights import WEIGHTS_DIR
from egoposevr.server import registry as registry_module
from egoposevr.server.registry import ModelRegistry

SHARING = ("hmd-rgbd.onnx", "hmd-rgbd-concat.onnx")  # two models that read one encoder
ENCODER = ("visual-rgbd.onnx", "visual-rgbd.body.json")


@pytest.fixture
def models_dir(tmp_path: Path) -> Path:
    for name in (*SHARING, *ENCODER):
        shutil.copy(WEIGHTS_DIR / name, tmp_path / name)
    return tmp_path


def test_a_shared_encoder_is_hashed_once_per_version_and_its_digest_follows_the_file(models_dir, monkeypatch):
    hashed: list[str] = []

    def counting_digest(path: str | Path) -> str:
        hashed.append(Path(path).name)
        return file_digest(path)

    monkeypatch.setattr(registry_module, "file_digest", counting_digest)
    registry = ModelRegistry(models_dir, bundled=False)
    registry.rescan()
    infos = {info.name: info for info in registry.wire_infos()}
    encoder_sha256 = file_digest(models_dir / ENCODER[0])
    for name in SHARING:
        stem = name.removesuffix(".onnx")
        assert infos[stem].sha256 == file_digest(models_dir / name)
        assert infos[stem].encoder_sha256 == encoder_sha256
    assert infos["procedural"].sha256 is None and infos["procedural"].encoder_sha256 is None
    assert sorted(hashed) == sorted([*SHARING, ENCODER[0]])

    # The encoder written again (a new version by its time): both models reload, and it is hashed once again.
    hashed.clear()
    encoder = models_dir / ENCODER[0]
    encoder.write_bytes(encoder.read_bytes())
    stat = encoder.stat()
    os.utime(encoder, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
    events = registry.rescan()
    assert sorted(e.split()[1] for e in events) == sorted(n.removesuffix(".onnx") for n in SHARING)
    assert sorted(hashed) == sorted([*SHARING, ENCODER[0]])
    assert {info.encoder_sha256 for info in registry.wire_infos() if info.name != "procedural"} == {
        encoder_sha256
    }

    hashed.clear()
    assert registry.rescan() == [] and hashed == []  # nothing changed: nothing read


def test_a_model_file_says_where_it_hangs_the_head_joint_and_the_models_message_carries_it(models_dir):
    """§model-head-joint: a file that records another head offset (here the one every bundled model had until
    2026-11-27, 6 cm under and 11 cm behind the eyes) is listed with it; the bundled files with theirs."""
    onnx = pytest.importorskip("onnx")
    graph = onnx.load(models_dir / SHARING[1])
    offsets = next(p for p in graph.metadata_props if p.key == "egoposevr.rig_offsets_m")
    rows = json.loads(offsets.value)
    rows[0] = [0.0, 0.06, 0.11]  # in the joint's frame: the eyes above and ahead of the head joint
    offsets.value = json.dumps(rows)
    onnx.save(graph, models_dir / SHARING[1])
    registry = ModelRegistry(models_dir, bundled=False)
    registry.rescan()
    heads = {info.name: info.head_joint_m for info in registry.wire_infos()}
    assert heads["hmd-rgbd-concat"] == [0.0, -0.06, 0.11]  # in the headset's frame: below and behind
    assert heads["hmd-rgbd"] == heads["procedural"] == [0.0, -0.024, 0.083]
