"""A motion library: BVH and AMASS files found in folders and globs, deduplicated, with subject-disjoint splits.

Files are found recursively under folders and by glob patterns, read once for a content hash (the same bytes
twice is one clip, counted and named), and given a **subject**: the person the motion was captured from. No
subject is ever in two splits, so a validation or test figure is always about people the model never saw.

Subjects: a CMU trial name ``SS_TT`` (any of the database's conversions) is CMU subject SS; otherwise the
file's folder is its subject (one performer per folder, as most capture exports are laid out), unless a
``--subject-regex`` whose first group names it matches the file's path.

Splits are assigned to whole subjects by duration (``train=0.8,val=0.1,test=0.1`` by default): see
:func:`split_subjects`.
"""

from __future__ import annotations

import dataclasses
import glob
import hashlib
import re
from collections.abc import Iterable
from pathlib import Path
from typing import Final

import numpy as np

MOTION_SUFFIXES: Final = (".bvh", ".npz")
CMU_TRIAL: Final = re.compile(r"^(\d{1,3})_\d{1,3}$")
DEFAULT_SPLITS: Final = (("train", 0.8), ("val", 0.1), ("test", 0.1))


@dataclasses.dataclass(frozen=True)
class MotionFile:
    """One motion file of the library: its path, content hash and subject."""

    path: Path
    sha256: str
    subject: str


@dataclasses.dataclass
class Library:
    """Files found, and those left out with the reason (duplicates and unreadable files, by path)."""

    files: list[MotionFile]
    duplicates: list[tuple[Path, Path]]  # (skipped, the first copy kept)
    unreadable: list[tuple[Path, str]]


def expand(patterns: Iterable[str]) -> tuple[list[Path], list[str]]:
    """Folders (recursively), globs and files -> (sorted motion files, patterns that matched nothing)."""
    found: set[Path] = set()
    empty: list[str] = []
    for pattern in patterns:
        path = Path(pattern)
        if path.is_dir():
            hits = [p for p in path.rglob("*") if p.suffix.lower() in MOTION_SUFFIXES and p.is_file()]
        elif path.is_file():
            hits = [path]
        else:
            hits = [Path(p) for p in glob.glob(pattern, recursive=True) if Path(p).is_file()]
            hits = [p for p in hits if p.suffix.lower() in MOTION_SUFFIXES]
        if not hits:
            empty.append(pattern)
        found.update(hits)
    return sorted(found), empty


def subject_of(path: Path, subject_regex: str | None = None) -> str:
    """The subject (performer) of a motion file; see the module docstring."""
    if subject_regex:
        match = re.search(subject_regex, path.as_posix())
        if match:
            return match.group(1) if match.groups() else match.group(0)
    trial = CMU_TRIAL.match(path.stem)
    if trial:
        return f"cmu-{int(trial.group(1)):02d}"
    return path.parent.name or "unknown"


def build_library(patterns: Iterable[str], subject_regex: str | None = None) -> tuple[Library, list[str]]:
    """Find, hash and attribute the files; -> (library, patterns that matched nothing)."""
    paths, empty = expand(patterns)
    seen: dict[str, Path] = {}
    library = Library(files=[], duplicates=[], unreadable=[])
    for path in paths:
        try:
            digest = hashlib.sha256(path.read_bytes()).hexdigest()
        except OSError as error:
            library.unreadable.append((path, str(error)))
            continue
        if digest in seen:
            library.duplicates.append((path, seen[digest]))
            continue
        seen[digest] = path
        library.files.append(MotionFile(path, digest, subject_of(path, subject_regex)))
    return library, empty


def motion_seconds(path: Path) -> float:
    """A file's duration from its header alone (BVH ``Frames`` × ``Frame Time``; AMASS poses / rate); 0.0 when
    it cannot be read (the loader then says why)."""
    try:
        if path.suffix.lower() == ".npz":
            with np.load(path, allow_pickle=False) as data:
                return len(data["poses"]) / float(data["mocap_framerate"])
        head = path.read_bytes()
        match = re.search(rb"Frames:\s*(\d+)\s+Frame\s+Time:\s*([0-9.eE+-]+)", head)
        return int(match.group(1)) * float(match.group(2)) if match else 0.0
    except (OSError, ValueError, KeyError):
        return 0.0


def parse_split_shares(text: str) -> tuple[tuple[str, float], ...]:
    """'train=0.8,val=0.1,test=0.1' -> (('train', 0.8), ...), shares normalised to sum to 1."""
    shares = []
    for part in text.split(","):
        name, _, value = part.partition("=")
        try:
            share = float(value)
        except ValueError:
            raise ValueError(f"expected NAME=SHARE pairs such as train=0.8,val=0.2; got {part!r}") from None
        if not name.strip() or not share > 0:
            raise ValueError(f"each split needs a name and a share > 0; got {part!r}")
        shares.append((name.strip(), share))
    if len({n for n, _ in shares}) != len(shares):
        raise ValueError(f"a split is named twice in {text!r}")
    total = sum(s for _, s in shares)
    return tuple((n, s / total) for n, s in shares)


_TIE: Final = 1e-12  # split_subjects: misses this close are a tie


def split_subjects(
    seconds_by_subject: dict[str, float],
    shares: tuple[tuple[str, float], ...] = DEFAULT_SPLITS,
    seed: int = 0,
) -> dict[str, str]:
    """Assign whole subjects to splits by duration; -> {subject: split}. Same input and seed, same result.

    Subjects are taken largest first with seed 0 (the most even split), in a seeded random order with any
    other seed (other folds, less even); each goes to the split that it leaves closest to its share of the
    hours (a tie to the first of them in ``shares``). The last subjects go to splits still empty, so that no split
    is empty when there are at least as many subjects as splits.
    """
    total = sum(seconds_by_subject.values()) or 1.0
    names = sorted(seconds_by_subject)
    if seed == 0:
        order = sorted(names, key=lambda s: (-seconds_by_subject[s], s))
    else:
        order = [names[i] for i in np.random.default_rng(seed).permutation(len(names))]
    hours = {name: 0.0 for name, _ in shares}
    filled = {name: 0 for name, _ in shares}
    assigned: dict[str, str] = {}
    for index, subject in enumerate(order):
        empty = [n for n, count in filled.items() if count == 0]
        left = len(order) - index
        candidates = empty if len(empty) >= left else [n for n, _ in shares]

        def miss(split: str, subject: str = subject) -> float:
            after = {n: h + (seconds_by_subject[subject] if n == split else 0.0) for n, h in hours.items()}
            return sum((after[n] / total - share) ** 2 for n, share in shares)

        misses = [miss(split) for split in candidates]
        # Splits this subject leaves equally close go to the first: left to rounding, two equal shares (folds)
        # tie to the last digit, and a re-render that moves a duration by a microsecond renumbered the folds.
        choice = candidates[next(i for i, m in enumerate(misses) if m <= min(misses) + _TIE)]
        assigned[subject] = choice
        hours[choice] += seconds_by_subject[subject]
        filled[choice] += 1
    return assigned
