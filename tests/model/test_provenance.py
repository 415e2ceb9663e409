"""Provenance records: the data's digest follows the shards' bytes, the code's commit comes from git when the
package runs from a work tree, and records read back as lines for people."""

import shutil
import subprocess

import pytest

from egoposevr.model import provenance


def _dataset(root, shards):
    """A dataset folder whose train split holds the given {name: bytes} shards."""
    (root / "train").mkdir(parents=True)
    for name, data in shards.items():
        (root / "train" / name).write_bytes(data)
    return root


def test_the_data_digest_follows_the_shards_bytes_names_and_order(tmp_path):
    a = _dataset(tmp_path / "a", {"shard-00000.npz": b"one", "shard-00001.npz": b"two"})
    same = _dataset(tmp_path / "same", {"shard-00000.npz": b"one", "shard-00001.npz": b"two"})
    other = _dataset(tmp_path / "other", {"shard-00000.npz": b"one", "shard-00001.npz": b"TWO"})
    b = _dataset(tmp_path / "b", {"shard-00000.npz": b"three"})
    assert provenance.data_digest([a]) == provenance.data_digest(
        [same]
    )  # where a folder lies is not its data
    assert provenance.data_digest([a]) != provenance.data_digest([other])
    assert provenance.data_digest([a, b]) != provenance.data_digest([b, a])
    (a / "train" / "shard-00001.npz").write_bytes(b"changed")  # a change since the last digest is seen
    assert provenance.data_digest([a]) != provenance.data_digest([same])
    assert provenance.data_digest([b]) == provenance.folder_digest(b)  # one folder: its own digest
    (a / "val").mkdir()
    (a / "val" / "shard-00000.npz").write_bytes(b"val")  # another split is not what training reads
    assert provenance.data_digest([a]) == provenance.data_digest([a], "train")


@pytest.mark.skipif(shutil.which("git") is None, reason="git is not installed")
def test_the_code_is_the_work_trees_commit_and_whether_it_was_changed(tmp_path, monkeypatch):
    def git(*args):
        return subprocess.run(["git", "-C", str(tmp_path), *args], check=True, capture_output=True, text=True)

    git("init", "-q")
    (tmp_path / "f.py").write_text("x = 1\n")
    git("add", "f.py")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "one")
    monkeypatch.setattr(provenance, "_SOURCE_DIR", tmp_path)
    monkeypatch.setattr(provenance, "_code_at_start", None)
    head = git("rev-parse", "HEAD").stdout.strip()
    assert provenance.code_version() | {"version": None} == {"version": None, "commit": head, "dirty": False}
    provenance.remember_code()  # a process's start: what it imported, whatever is committed later
    (tmp_path / "f.py").write_text("x = 2\n")
    assert provenance.code_version()["dirty"] is False
    monkeypatch.setattr(provenance, "_code_at_start", None)
    assert provenance.code_version()["dirty"] is True
    monkeypatch.setattr(provenance, "_SOURCE_DIR", tmp_path / "not-a-repo")
    assert provenance.code_version()["commit"] is None and provenance.code_version()["dirty"] is None


def test_a_run_record_names_the_command_folder_code_and_machine():
    host = provenance.machine("cpu", 3, {"torch": "9.9"})
    run = provenance.run_record(["egoposevr", "train", "--data", "my data"], {"commit": "abc"}, host)
    assert run["command"] == "egoposevr train --data 'my data'"  # quoted as a shell would need it
    assert run["machine"]["threads"] == 3 and run["machine"]["torch"] == "9.9" and run["machine"]["cpus"] >= 1
    assert run["code"] == {"commit": "abc"} and run["started_utc"].endswith("+00:00") and run["cwd"]


def test_records_read_as_nested_lines_and_say_what_was_not_recorded():
    run = {
        "command": "egoposevr train --seed 3", "cwd": "/w", "started_utc": "T",
        "code": {"version": "1", "commit": "c0ffee", "dirty": True},
        "machine": {"cpu": "X", "cpus": 2, "device": "cpu", "threads": 1, "platform": "P"},
        "from_step": 0, "to_step": 8,
    }  # fmt: skip
    net = {
        "steps": 8, "seed": 3,
        "data": {"dir": ["d1", "d2"], "sequences": 5, "sha256": "ab" * 32, "folders_sha256": ["01" * 32, "23" * 32]},
        "init": {"from": "start.onnx", "member": 1, "sha256": "cd" * 32}, "runs": [run],
        "encoders": [{"from": "e.onnx", "sha256": "ef" * 32}],
    }  # fmt: skip
    old = {"steps": 4, "seed": 0, "data": {"dir": "d1", "sequences": 5}}
    blend = {"blend": {"from": ["a.pt", "b.pt"], "weights": [0.5, 0.5], "nets": [net, old]}}
    lines = provenance.describe({"ensemble": [blend, {"blend": {"from": ["x.pt"], "weights": [1.0]}}]})
    text = "\n".join(lines)
    assert lines[0] == "the mean of 2 nets:" and lines[2] == "    a weight-space blend (0.50, 0.50) of:"
    assert "data d1 d2 (5 sequences), sha256 abababababababab" in text
    assert "each folder's shards: 0101010101010101, 2323232323232323" in text  # as their manifests say
    assert "started from start.onnx member 1, sha256 cdcdcdcdcdcdcdcd" in text
    assert "keypoints from e.onnx, sha256 efefefefefefefef" in text
    assert "ran steps 0-8 on T in /w: egoposevr train --seed 3" in text
    assert "code 1 c0ffee (with local changes)" in text
    assert "data d1 (5 sequences), sha256 not recorded" in text  # a net from before digests were kept
    assert "ran: not recorded (made before runs were recorded)" in text
    assert "its record was not kept" in text  # the first blends named their files only
    resumed = {**net, "runs": [{"from_step": 0, "to_step": 4, "recorded": False}, run | {"from_step": 4}]}
    assert "ran steps 0-4: not recorded (run before runs were recorded)" in "\n".join(
        provenance.describe(resumed)
    )


def _run(command, started="T"):
    machine = {"threads": 1, "device": "cpu"}
    return {
        "command": command,
        "cwd": "/w",
        "started_utc": started,
        "code": {"commit": "c" * 40},
        "machine": machine,
    }


def test_ancestors_gather_at_the_root_once_and_are_described_once():
    start = {"steps": 2, "seed": 0, "data": {"dir": "d"}, "runs": [_run("egoposevr train A")]}
    child = {
        "steps": 4, "seed": 1, "init": {"from": "s.onnx", "sha256": "5" * 64},
        "ancestors": provenance.ancestry("5" * 64, start | {"ancestors": {"9" * 64: {"steps": 7}}}),
    }  # fmt: skip
    root = provenance.hoist_ancestors({"ensemble": [child, child]})
    assert set(root["ancestors"]) == {"5" * 64, "9" * 64} and "ancestors" not in root["ensemble"][0]
    text = "\n".join(provenance.describe(root))
    assert text.count("egoposevr train A") == 1  # the start's record, under the first net that names it
    assert text.count("started from s.onnx") == 2


def test_a_net_trained_on_part_of_the_people_says_which():
    for data, said in (
        ({"held_out_fold": "0/2"}, "people of fold 0/2 left out"),
        ({"trained_fold": "1/4"}, "only the people of fold 1/4"),
    ):
        text = "\n".join(provenance.describe({"steps": 2, "seed": 0, "data": {"dir": "d", **data}}))
        assert said in text
    whole = "\n".join(provenance.describe({"steps": 2, "seed": 0, "data": {"dir": "d"}}))
    assert "fold" not in whole


def test_a_recipe_runs_ancestors_first_each_command_once_and_says_what_was_not_recorded():
    start = {
        "steps": 2,
        "seed": 0,
        "runs": [_run("egoposevr train A", "1")],
        "export": _run("egoposevr export A"),
    }
    tuned = {"steps": 4, "seed": 1, "init": {"sha256": "5" * 64}, "runs": [_run("egoposevr train B", "2")]}
    old = {"steps": 9, "seed": 3}
    root = {
        "blend": {"nets": [tuned, tuned | {"seed": 2}, old], "run": _run("egoposevr blend")},
        "export": _run("egoposevr export C"),
        "ancestors": {"5" * 64: start},
    }
    lines = provenance.recipe(root)
    assert [line.split("  # ")[0] for line in lines] == [
        "cd /w && egoposevr train A",
        "cd /w && egoposevr export A",
        "cd /w && egoposevr train B",  # the second net of the same invocation is not listed again
        "# 9 steps, seed 3: not recorded",
        "cd /w && egoposevr blend",
        "cd /w && egoposevr export C",
    ]
    assert lines[0].endswith(f"# code {'c' * 12}; 1 threads on cpu")


@pytest.mark.parametrize("record", [{"ensemble": 5}, {"blend": "x"}, {"runs": [3]}, {"data": [1], "run": 2}])
def test_a_record_of_another_shape_is_a_clear_error(record):
    with pytest.raises(provenance.RecordError, match="not one this version reads"):
        provenance.describe(record)
    for read in (provenance.recipe, provenance.describe_fit):  # what they read of it is readable, or said so
        try:
            read(record)
        except provenance.RecordError as error:
            assert "not one this version reads" in str(error)


def test_a_mirror_averaged_file_says_so_and_its_recipe_ends_with_the_rewrite():
    net = {"steps": 1, "seed": 0, "runs": [_run("egoposevr train A")]}
    record = {"ensemble": [net, net], "export": _run("egoposevr export A"), "mirror_averaged": True}
    rewritten = record | {"mirror_run": _run("egoposevr export --mirror-average w/egoposevr.onnx")}
    assert [line.split("  # ")[0] for line in provenance.recipe(rewritten)][-1] == (
        "cd /w && egoposevr export --mirror-average w/egoposevr.onnx"
    )
    assert provenance.recipe(record)[-1] == "# the mirror averaging: not recorded"
    assert "mirror-averaged on T in /w: egoposevr export --mirror-average" in "\n".join(
        provenance.describe(rewritten)
    )
