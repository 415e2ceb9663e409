"""The motion library: files from folders and globs, duplicates skipped, subjects, subject-disjoint splits."""

from pathlib import Path

import numpy as np
import pytest

from egoposevr.model.synth.library import (
    build_library,
    motion_seconds,
    parse_split_shares,
    split_subjects,
    subject_of,
)


def _touch(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def test_folders_are_searched_recursively_and_duplicates_named(tmp_path):
    a = _touch(tmp_path / "lib" / "alice" / "walk.bvh", "one")
    _touch(tmp_path / "lib" / "bob" / "deep" / "run.BVH", "two")
    copy = _touch(tmp_path / "lib" / "carol" / "walk_copy.bvh", "one")
    _touch(tmp_path / "lib" / "notes.txt", "not motion")
    library, empty = build_library([str(tmp_path / "lib"), str(tmp_path / "none" / "*.bvh")])
    assert [f.path.name for f in library.files] == ["walk.bvh", "run.BVH"]
    assert library.duplicates == [(copy, a)]
    assert empty == [str(tmp_path / "none" / "*.bvh")]


def test_globs_and_files_are_taken_once(tmp_path):
    a = _touch(tmp_path / "01_02.bvh", "a")
    library, _ = build_library([str(a), str(tmp_path / "*.bvh")])
    assert len(library.files) == 1 and library.files[0].subject == "cmu-01"


def test_subjects_come_from_cmu_trial_names_folders_or_a_regex():
    assert subject_of(Path("x/cmu-daz/05_01.bvh")) == "cmu-05" == subject_of(Path("cmu/05_11.bvh"))
    assert subject_of(Path("captures/alice/take3.bvh")) == "alice"
    assert subject_of(Path("takes/P07-jump.bvh"), r"(P\d+)-") == "P07"


def test_split_is_subject_disjoint_deterministic_and_fills_every_split():
    seconds = {f"s{i}": 60.0 * (1 + i % 3) for i in range(12)}
    shares = parse_split_shares("train=8,val=1,test=1")
    assignment = split_subjects(seconds, shares, seed=3)
    assert assignment == split_subjects(seconds, shares, seed=3)
    assert set(assignment) == set(seconds) and set(assignment.values()) == {"train", "val", "test"}
    train_s = sum(seconds[s] for s, n in assignment.items() if n == "train")
    assert 0.65 < train_s / sum(seconds.values()) < 0.9


def test_equal_shares_go_in_order_whatever_the_last_digits_of_the_durations():
    """Folds are equal shares: a subject that leaves several of them equally close goes to the first, so that
    a re-render that moves a duration by a microsecond does not renumber them."""
    seconds = {"a": 431.09307, "b": 226.913729, "c": 226.772793, "d": 129.69856, "e": 58.274915, "f": 15.93}
    seconds |= {f"p{i:02d}": 9.99 + 0.001 * i for i in range(40)}
    shares = tuple((str(k), 0.2) for k in range(5))
    for nudge_s in np.linspace(-5e-6, 5e-6, 41):
        folds = split_subjects(seconds | {"p00": seconds["p00"] + nudge_s}, shares)
        assert [folds[s] for s in "abcdef"] == ["0", "1", "2", "3", "4", "4"], nudge_s


@pytest.mark.parametrize("text", ["train", "train=0", "train=0.5,train=0.5", "=1", "a=b"])
def test_bad_split_shares_are_refused(text):
    with pytest.raises(ValueError, match=r"NAME=SHARE|split"):
        parse_split_shares(text)


def test_duration_from_the_header(tmp_path):
    path = _touch(tmp_path / "a.bvh", "HIERARCHY ... MOTION\nFrames: 240\nFrame Time: 0.0083333\n1 2 3")
    assert motion_seconds(path) == pytest.approx(2.0, rel=1e-4)
    assert motion_seconds(_touch(tmp_path / "b.bvh", "garbage")) == 0.0
