"""Reading the synthesis engine's dataset (DATA.md): shards, splits, decoded frames. numpy + OpenCV only.

A shard ``DIR/<split>/shard-NNNNN.npz`` holds several sequences concatenated; ``hmd_start`` / ``cam_start``
index them. Shape legend: ``N`` headset samples, ``K`` camera frames, ``J`` = 22 joints.
"""

from __future__ import annotations

import dataclasses
import json
import re
import zipfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..inputs import decode_rgbd, resize_frame
from ..synth.library import CMU_TRIAL, split_subjects

HMD_KEYS = ("hmd_t_us", "hmd_poses", "hmd_valid", "gt_local_quat", "gt_root_m", "gt_joints_m")
CAMERA_KEYS = ("cam_t_us", "cam_head_pose", "joints_cam_m", "joints_uv_px", "visible", "occluded")


class DatasetError(ValueError):
    """A dataset folder or shard that cannot be read."""


def load_shard(path: str | Path) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as data:
            return {key: data[key] for key in data.files}
    except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
        raise DatasetError(f"{path}: not a readable shard ({exc})") from exc


def iter_shard_sequences(shard: dict[str, np.ndarray]) -> Iterator[dict[str, Any]]:
    """Per sequence views of a loaded shard: the same keys, sliced (images stay encoded)."""
    for i, name in enumerate(shard["seq_name"]):
        h0, h1 = shard["hmd_start"][i : i + 2]
        c0, c1 = shard["cam_start"][i : i + 2]
        out: dict[str, Any] = {
            "name": str(name),
            "source": str(shard["seq_source"][i]),
            "bone_scale": shard["bone_scale"][i],
            "body": int(shard["body"][i]) if "body" in shard else -1,  # mesh body of the bank, -1: capsules
        }
        if "cam_size" in shard:  # the sequence's own camera (rigs drawn per sequence)
            width, height = (int(v) for v in shard["cam_size"][i])
            out["camera"] = {
                "width": width,
                "height": height,
                "intrinsics": [float(v) for v in shard["cam_intrinsics"][i]],
                "cam_from_head": [float(v) for v in shard["cam_from_head"][i]],
            }
        for key in HMD_KEYS:
            out[key] = shard[key][h0:h1]
        for key in CAMERA_KEYS:
            out[key] = shard[key][c0:c1]
        rgb_o, depth_o = shard["rgb_offsets"], shard["depth_offsets"]
        out["rgb_jpeg"] = [shard["rgb_jpeg"][rgb_o[k] : rgb_o[k + 1]].tobytes() for k in range(c0, c1)]
        out["depth_png"] = [shard["depth_png"][depth_o[k] : depth_o[k + 1]].tobytes() for k in range(c0, c1)]
        yield out


def split_camera(data_dir: str | Path, split: str) -> dict[str, Any]:
    """The split's camera entry from ``manifest.json``: width, height, intrinsics, cam_from_head (16)."""
    path = Path(data_dir) / "manifest.json"
    try:
        manifest = json.loads(path.read_text())
        return manifest["splits"][split]["camera"]
    except (OSError, ValueError, KeyError) as exc:
        raise DatasetError(f"{path}: no camera entry for split {split!r} ({exc})") from exc


def split_shards(data_dir: str | Path, split: str) -> list[Path]:
    """A split's shard files, in order; none when the dataset has no such split."""
    return sorted((Path(data_dir) / split).glob("shard-*.npz"))


def load_split(data_dir: str | Path, split: str, limit: int | None = None) -> list[dict[str, Any]]:
    """All sequences of a split (images still encoded), at most ``limit``; each with its ``camera`` (width,
    height, intrinsics, cam_from_head (16)): its own, or the split's for shards that carry none."""
    shards = split_shards(data_dir, split)
    if not shards:
        raise DatasetError(f"no shards in {Path(data_dir) / split}")
    seqs: list[dict[str, Any]] = []
    for path in shards:
        seqs += iter_shard_sequences(load_shard(path))
        if limit is not None and len(seqs) >= limit:
            seqs = seqs[:limit]
            break
    for index, seq in enumerate(seqs):
        seq["key"] = f"{split}/{index}"  # names repeat (one capture in several conversions); keys do not
    if any("camera" not in s for s in seqs):  # shards made before cameras were drawn per sequence
        camera = split_camera(data_dir, split)
        for seq in seqs:
            seq.setdefault("camera", camera)
    return seqs


@dataclasses.dataclass(frozen=True)
class Fold:
    """Fold ``index`` of ``count`` of a split's subjects: the ones ``train --hold-out`` leaves out and ``eval
    --fold`` serves, so that a training choice can be judged on people the nets never saw without looking
    at val or test. Subjects go to folds whole and by duration (synth.library.split_subjects, as splits
    are made; a subject that leaves two folds equally close goes to the lower-numbered), each dataset's split
    on its own, so the same data gives the same folds wherever it is read, and a re-render whose durations
    differ in their last digits gives the same folds too."""

    index: int
    count: int

    def __post_init__(self) -> None:
        if not (self.count >= 2 and 0 <= self.index < self.count):
            raise ValueError(f"a fold is K/N with N >= 2 and 0 <= K < N, got {self.index}/{self.count}")

    @classmethod
    def parse(cls, text: str) -> Fold:
        """``"K/N"`` -> Fold; ValueError for anything else."""
        match = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", text)
        if not match:
            raise ValueError(f"a fold is K/N (fold K of N, from 0), got {text!r}")
        return cls(int(match[1]), int(match[2]))

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"


def sequence_subject(seq: dict[str, Any]) -> str:
    """The person a sequence's motion was captured from, named as the motion library names subjects: CMU
    subject SS for trial SS_TT in any of the database's conversions (``cmu:1_02``, ``cmu-daz:01_02`` ->
    ``cmu-01``); otherwise the sequence itself (procedural motion has no performer: each is its own)."""
    kind, _, clip = str(seq["source"]).partition(":")
    trial = CMU_TRIAL.match(clip)
    if kind.startswith("cmu") and trial:
        return f"cmu-{int(trial[1]):02d}"
    return f"{seq['source']}/{seq['name']}"


def subjects(seqs: Sequence[dict[str, Any]]) -> list[str]:
    """The people the sequences were taken from (:func:`sequence_subject`), sorted, each once."""
    return sorted({sequence_subject(s) for s in seqs})


def fold_members(seqs: Sequence[dict[str, Any]], fold: Fold) -> np.ndarray:
    """(len(seqs),) bool: whether each sequence's subject is in the fold. ``seqs`` is one dataset's whole
    split: which fold a subject falls in depends on every subject's duration."""
    subjects = [sequence_subject(s) for s in seqs]
    seconds: dict[str, float] = {}
    for seq, subject in zip(seqs, subjects, strict=True):
        t_us = np.asarray(seq["hmd_t_us"])
        seconds[subject] = seconds.get(subject, 0.0) + (float(t_us[-1] - t_us[0]) / 1e6 if len(t_us) else 0.0)
    shares = tuple((str(k), 1.0 / fold.count) for k in range(fold.count))
    folds = split_subjects(seconds, shares)
    return np.array([folds[subject] == str(fold.index) for subject in subjects], dtype=bool)


def load_fold(
    data_dir: str | Path, split: str, fold: Fold, held: bool, limit: int | None = None
) -> tuple[list[dict[str, Any]], np.ndarray]:
    """The split's sequences whose subjects are in the fold (``held``) or outside it, at most ``limit``, and
    their places in the split (n,). The whole split is read: the folds depend on every subject."""
    seqs = load_split(data_dir, split)
    places = np.flatnonzero(fold_members(seqs, fold) == held)[:limit]
    return [seqs[i] for i in places], places


def load_splits(
    data_dirs: Sequence[str | Path],
    split: str,
    limit: int | None = None,
    hold_out: Fold | None = None,
    only: Fold | None = None,
) -> list[dict[str, Any]]:
    """:func:`load_split` of several datasets, one after the other, at most ``limit`` in all, without the
    subjects of ``hold_out``, or with only the subjects of ``only`` (each dataset's own fold; not both).
    Keys stay unique: the second and later datasets' are prefixed with their folder."""
    if hold_out is not None and only is not None:
        raise ValueError("a fold is either left out or kept alone, not both")
    seqs: list[dict[str, Any]] = []
    for k, data_dir in enumerate(data_dirs):
        left = None if limit is None else limit - len(seqs)
        if hold_out is None and only is None:
            more = load_split(data_dir, split, left)
        else:
            more, _ = load_fold(data_dir, split, only or hold_out, only is not None, left)
        for seq in more if k else []:
            seq["key"] = f"{data_dir}:{seq['key']}"
        seqs += more
        if limit is not None and len(seqs) >= limit:
            break
    return seqs


def decode_frames(seq: dict[str, Any], size_wh: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """A sequence's frames resized for the visual encoder: RGB (K, h, w, 3) uint8, depth (K, h, w) uint16."""
    return decode_frame_list(seq["rgb_jpeg"], seq["depth_png"], size_wh)


def decode_frame_list(
    rgb_jpeg: Sequence[bytes], depth_png: Sequence[bytes], size_wh: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """K encoded frames (JPEG colour, PNG depth) resized for the visual encoder: RGB (K, h, w, 3) uint8,
    depth (K, h, w) uint16."""
    w, h = size_wh
    rgb = np.empty((len(rgb_jpeg), h, w, 3), np.uint8)
    depth = np.empty((len(rgb_jpeg), h, w), np.uint16)
    for k, (jpeg, png) in enumerate(zip(rgb_jpeg, depth_png, strict=True)):
        rgb[k], depth[k] = resize_frame(*decode_rgbd(jpeg, png), size_wh)
    return rgb, depth
