"""``egoposevr synth`` end to end on tiny inputs: dataset with manifest and preview, sessions, bad input."""

import json
import shlex

import numpy as np
import pytest

from egoposevr.cli.main import main
from egoposevr.model import provenance
from egoposevr.model.synth.pipeline import iter_shard_sequences, load_shard

TINY = ["--seconds", "2", "--resolution", "64x48", "--no-progress"]


def test_synth_writes_a_deterministic_dataset_with_manifest_and_preview(tmp_path, capsys):
    args = ["synth", "--procedural", "2", "--families", "squat,jump", "--seed", "5", *TINY]
    assert main([*args, "--out", str(tmp_path / "a")]) == 0
    assert "frames/s" in capsys.readouterr().out
    assert main([*args, "--out", str(tmp_path / "a"), "--split", "val"]) == 0
    assert main([*args, "--out", str(tmp_path / "b")]) == 0
    manifest = json.loads((tmp_path / "a" / "manifest.json").read_text())
    train = manifest["splits"]["train"]
    assert set(manifest["splits"]) == {"train", "val"}
    assert train["seed"] == 5 and train["counts"]["sequences"] == 2 and train["camera"]["width"] == 64
    assert train["licences"] and train["shards"] == ["shard-00000.npz"]
    assert (tmp_path / "a" / "preview-train.png").stat().st_size > 1000
    a = (tmp_path / "a" / "train" / "shard-00000.npz").read_bytes()
    assert a == (tmp_path / "b" / "train" / "shard-00000.npz").read_bytes()  # same seed, same bytes
    b = json.loads((tmp_path / "b" / "manifest.json").read_text())["splits"]["train"]
    assert train["shards_sha256"] == b["shards_sha256"] == provenance.folder_digest(tmp_path / "a")  # so:
    assert train["command"] == shlex.join(["egoposevr", *args, "--out", str(tmp_path / "a")])
    seqs = list(iter_shard_sequences(load_shard(tmp_path / "a" / "train" / "shard-00000.npz")))
    assert [s["source"] for s in seqs] == ["procedural:squat", "procedural:jump"]
    assert len(seqs[0]["rgb_jpeg"]) == 60 and seqs[0]["hmd_t_us"].shape == (120,)
    assert np.isfinite(seqs[0]["gt_joints_m"]).all()


def test_synth_sessions(tmp_path):
    assert (
        main(["synth", "--procedural", "1", "--sessions", "--hmd-rate", "72", "--out", str(tmp_path), *TINY])
        == 0
    )
    assert len(list(tmp_path.glob("*.egrec"))) == 1


@pytest.mark.parametrize(
    "extra",
    [[], ["--procedural", "1", "--families", "moonwalk"], ["--motion", "/nonexistent/x.bvh"]],
)
def test_synth_refuses_bad_requests(tmp_path, extra, capsys):
    assert main(["synth", "--out", str(tmp_path), *TINY, *extra]) == 2
    assert "egoposevr synth:" in capsys.readouterr().err


def test_a_corrupt_motion_file_is_skipped_and_named(tmp_path, capsys):
    bad = tmp_path / "broken.bvh"
    bad.write_text("HIERARCHY ROOT")
    assert (
        main(["synth", "--motion", str(bad), "--procedural", "1", "--out", str(tmp_path / "o"), *TINY]) == 0
    )
    assert "broken.bvh" in capsys.readouterr().err


def test_bad_resolution_is_an_argument_error(tmp_path):
    with pytest.raises(SystemExit):
        main(["synth", "--procedural", "1", "--out", str(tmp_path), "--resolution", "big"])


def test_synth_with_mesh_bodies_and_drawn_rigs_records_every_draw(tmp_path):
    from tubebodies import tube_bank

    from egoposevr.model.synth.variation import POOLS, body_is_heldout
    from egoposevr.model.training.dataset import load_split

    bank = tube_bank(scales=tuple(np.linspace(0.9, 1.1, 12))).save(tmp_path / "bank.npz")
    args = ["synth", "--procedural", "3", "--families", "walk", "--seed", "2", "--bodies", str(bank)]
    args += ["--rig-pool", "heldout", *TINY]
    assert main([*args, "--out", str(tmp_path / "a")]) == 0
    assert main([*args, "--out", str(tmp_path / "b")]) == 0
    a, b = (tmp_path / x / "train" / "shard-00000.npz" for x in "ab")
    assert a.read_bytes() == b.read_bytes()
    split = json.loads((tmp_path / "a" / "manifest.json").read_text())["splits"]["train"]
    assert split["rig_pool"] == "heldout" and split["bodies"]["count"] == 12
    for source in split["sources"]:
        assert body_is_heldout(source["body"])
        pitch = source["rig"]["camera"]["pitch_down_deg"]
        assert any(lo <= pitch <= hi for lo, hi in POOLS["heldout"].pitch_down_deg)
        assert (source["rig"]["camera"]["width"], source["rig"]["camera"]["height"]) == (64, 48)
    seqs = load_split(tmp_path / "a", "train")
    assert all(s["camera"]["width"] == 64 for s in seqs)
    assert len({s["camera"]["intrinsics"][0] for s in seqs}) == 3  # a field of view each
    assert [s["body"] for s in seqs] == [src["body"] for src in split["sources"]]


def test_bodies_refuses_a_bad_count(capsys):
    assert main(["bodies", "--count", "0", "--out", "x.npz"]) == 2
    assert "--count" in capsys.readouterr().err


def test_workers_write_the_same_bytes_as_one_process(tmp_path):
    args = ["synth", "--procedural", "2", "--families", "walk,squat", "--seed", "6", *TINY]
    assert main([*args, "--out", str(tmp_path / "one")]) == 0
    assert main([*args, "--out", str(tmp_path / "two"), "--workers", "2"]) == 0
    one, two = (tmp_path / x / "train" / "shard-00000.npz" for x in ("one", "two"))
    assert one.read_bytes() == two.read_bytes()


def test_render_workers_share_the_cpus_out_instead_of_each_taking_all():
    from egoposevr.cli.synth_cmd import worker_threads

    assert worker_threads(16, cpus=16) == 1
    assert worker_threads(2, cpus=16) == 8
    assert worker_threads(4, cpus=2) == 1  # never zero
