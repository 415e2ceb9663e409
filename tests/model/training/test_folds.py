"""Folds of a split's subjects: whole people go to one fold, every conversion of one capture with them,
the folds even by duration and the same wherever the split is read."""

import numpy as np
import pytest

from egoposevr.model.training.dataset import Fold, fold_members, sequence_subject


def seq(source: str, name: str, seconds: float) -> dict:
    return {"source": source, "name": name, "hmd_t_us": np.arange(0, int(seconds * 1e6) + 1, 100_000)}


SPLIT = [
    seq("cmu:01_02", "01_02-00", 30),
    seq("cmu-daz:01_02", "01_02-00", 30),  # the same capture in another conversion
    seq("cmu:1_05", "1_05-00", 20),  # a conversion without the leading zero
    seq("cmu:60_01", "60_01-00", 40),
    seq("cmu-daz:61_03", "61_03-00", 45),
    *[seq("procedural:walk", f"walk-{k:04d}", 10) for k in range(6)],
]


def test_a_cmu_subject_is_one_person_in_every_conversion_and_procedural_motion_is_its_own():
    assert sequence_subject(SPLIT[0]) == sequence_subject(SPLIT[1]) == sequence_subject(SPLIT[2]) == "cmu-01"
    assert len({sequence_subject(s) for s in SPLIT[5:]}) == 6


@pytest.mark.parametrize("count", [2, 3, 4])
def test_every_subject_is_in_exactly_one_fold_and_the_folds_are_even(count):
    members = np.array([fold_members(SPLIT, Fold(k, count)) for k in range(count)])  # (count, n)
    assert (members.sum(0) == 1).all()
    for k in range(count):
        held = {sequence_subject(s) for s, m in zip(SPLIT, members[k], strict=True) if m}
        assert all(members[k][i] for i, s in enumerate(SPLIT) if sequence_subject(s) in held)
    seconds = np.array([s["hmd_t_us"][-1] / 1e6 for s in SPLIT])
    per_fold = members @ seconds
    assert per_fold.max() - per_fold.min() <= 45  # at most one subject's time apart
    np.testing.assert_array_equal(fold_members(SPLIT, Fold(1, count)), members[1])  # the same every time


@pytest.mark.parametrize("text", ["2/2", "1", "a/b", "-1/3", "0/1", "1/0"])
def test_a_fold_is_k_of_n(text):
    with pytest.raises(ValueError, match="fold"):
        Fold.parse(text)


def test_a_fold_reads_and_writes_as_k_of_n():
    assert str(Fold.parse(" 1 / 5 ")) == "1/5" and Fold.parse("0/2") == Fold(0, 2)
