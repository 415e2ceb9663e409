"""Fitting each visual encoder's body regressor (body.py) on datasets' splits: ``egoposevr fit-body``.

For every sequence of one or more datasets' fitting split, the serving code's own
:class:`~egoposevr.model.runtime.body.BodyCalibrator` is fed what a session would feed it, in arrival order —
every camera frame through the encoder and Alg. 1's visibility filter, every headset sample's head joint.
Each moment its evidence changes (height scale, measured bone medians) is one training row, with the
sequence's true bone scales as the target. The calibrator takes a bone's first measurement where the served
pipeline does (``EARLY_BODY_SIGHTINGS``), so the regressor is fitted on the evidence it is asked about. Several
datasets let the regressor see bodies in poses one set lacks (the walks of one, the seated people of another). A
check split, read in each dataset that has it, reports the summed bone-length error of the height scale, of the
fallback without a regressor and of the regressor.

Shape legend: ``N`` sequences, ``J`` = 22 joints.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort

from .. import provenance
from ..inputs import VisibilityFilter, decode_rgbd
from ..rig import joints_from_devices
from ..runtime.body import (
    EARLY_BODY_SIGHTINGS,
    REGRESSOR_SUFFIX,
    BodyCalibrator,
    BodyRegressor,
    regressor_path,
)
from ..runtime.frames import encode_frame
from ..runtime.loading import LoadedModel
from ..skeleton import NUM_JOINTS, rest_offsets
from ..weights import model_files
from .dataset import load_split, split_shards
from .evaluate import CAMERA_LATENCY_US

# Chosen on the validation split's summed bone error, one ridge map for all bodies: 0.3 -> 16.6, 1 -> 16.2,
# 10 -> 19.9 cm.
DEFAULT_RIDGE = 1.0
_REST_BONE_M = np.linalg.norm(rest_offsets(), axis=-1)
Progress = Callable[[str, int, int], None]
Snapshot = tuple[float, dict[int, float]]  # (height scale, {bone: measured scale}) at one moment


def observe_body(model: LoadedModel, seq: dict[str, Any]) -> tuple[BodyCalibrator, list[Snapshot]]:
    """A calibrator without a regressor, fed one sequence in arrival order (head heights, and frames
    ``CAMERA_LATENCY_US`` after capture), and a snapshot of its evidence whenever that changed. The
    snapshots are the regressor's training rows: a session starts with some bones measured and others not,
    and a regressor fitted on whole sequences only mistakes that for an unusual body. A bone is measured from
    its first sighting on, as the served pipeline measures it (``Pipeline(early_body=True)``, the default); the
    rows from the fifth sighting on are the ones a pipeline without it asks about."""
    body = BodyCalibrator(first_measure_sightings=EARLY_BODY_SIGHTINGS)
    visibility = VisibilityFilter()
    camera = seq["camera"]
    cam_from_head = np.asarray(camera["cam_from_head"], dtype=np.float64).reshape(4, 4)
    snapshots: list[Snapshot] = []
    heads = iter(zip(seq["hmd_t_us"], seq["hmd_poses"], seq["hmd_valid"], strict=True))
    pending = next(heads, None)
    for k, t_us in enumerate([*seq["cam_t_us"], None]):  # None: the samples after the last frame
        while pending is not None and (t_us is None or pending[0] < t_us + CAMERA_LATENCY_US):
            tracked_pos, _ = joints_from_devices(pending[1].astype(np.float64), model.info.rig_offsets_m)
            body.push(tracked_pos, pending[2])
            pending = next(heads, None)
        if t_us is None:
            break
        rgb, depth = decode_rgbd(seq["rgb_jpeg"][k], seq["depth_png"][k])
        frame = encode_frame(model, int(t_us), rgb, depth, camera["intrinsics"], cam_from_head)
        if body.push_visual(frame.kp_cam, visibility(frame.t_us, frame.zeta) > 0.0):
            snapshots.append((body.height_scale, dict(body.measured)))
    return body, snapshots


def summed_bone_error_cm(bone_scale: np.ndarray, true_scale: np.ndarray) -> np.ndarray:
    """(N, J) estimated and true scales -> (N,) summed |length error| over bones 1..J-1, cm."""
    return 100 * (np.abs(bone_scale - true_scale)[:, 1:] * _REST_BONE_M[1:]).sum(-1)


def _observe_split(
    model: LoadedModel, data_dirs: Sequence[Path], split: str, progress: Progress | None
) -> tuple[list[BodyCalibrator], list[list[Snapshot]], np.ndarray]:
    """Per sequence of each dataset's split, one dataset after the other: its calibrator at the end, its
    snapshots; true scales (N, J). One dataset is in memory at a time."""
    bodies, snapshots, truth = [], [], []
    for data_dir in data_dirs:
        seqs = load_split(data_dir, split)
        for i, seq in enumerate(seqs):
            body, seen = observe_body(model, seq)
            bodies.append(body)
            snapshots.append(seen)
            truth.append(seq["bone_scale"])
            if progress:
                progress(f"{model.info.visual_path.name} {data_dir} {split}", i + 1, len(seqs))
    return bodies, snapshots, np.array(truth, dtype=np.float64).reshape(len(truth), NUM_JOINTS)


def check_datasets(data_dirs: Sequence[Path], check_split: str | None) -> list[Path]:
    """The datasets that hold ``check_split`` (none when it is None or ''). Raises ValueError when it is asked
    for and no dataset has it."""
    if not check_split:
        return []
    found = [Path(d) for d in data_dirs if split_shards(d, check_split)]
    if not found:
        raise ValueError(f"no --data folder has a {check_split!r} split to check on")
    return found


def fit_encoder(
    model: LoadedModel,
    data_dirs: Sequence[Path],
    split: str = "train",
    check_split: str | None = "val",
    ridge: float = DEFAULT_RIDGE,
    progress: Progress | None = None,
    command: Sequence[str] | None = None,
) -> BodyRegressor:
    """The regressor of ``model``'s visual encoder, fitted on ``split`` of every dataset (and checked on
    ``check_split`` of those that have it); its record names the data's digest and this invocation
    (``command``: model/provenance.py). Raises ValueError when no dataset has the check split."""
    check_dirs = check_datasets(data_dirs, check_split)
    _, snapshots, truth = _observe_split(model, data_dirs, split, progress)
    # Every sequence weighs 1 in all, however many snapshots it made, so that the ridge penalty means
    # the same whatever the frame rate and length.
    rows = [(h, m, truth[n], 1.0 / len(seen)) for n, seen in enumerate(snapshots) for h, m in seen]
    fitted = BodyRegressor.fit(
        np.array([r[0] for r in rows]),
        [r[1] for r in rows],
        np.array([r[2] for r in rows]),
        provenance.file_digest(model.info.visual_path),
        float(model.info.rig_offsets_m[0, 1]),
        ridge,
        np.array([r[3] for r in rows]),
    )
    record: dict[str, Any] = {
        **fitted.record, "data": [str(d) for d in data_dirs], "split": split, "sequences": len(snapshots),
        "data_sha256": provenance.data_digest(data_dirs, split), "run": _fit_record(command),
    }  # fmt: skip
    if check_split:
        bodies, snapshots, truth = _observe_split(model, check_dirs, check_split, progress)
        record["check_split"] = check_split
        record["check_data"] = [str(d) for d in check_dirs]
        record["summed_bone_error_cm"] = _check_errors(fitted, bodies, snapshots, truth)
    return dataclasses.replace(fitted, record=record)


def _fit_record(command: Sequence[str] | None) -> dict[str, Any]:
    """This fit's invocation: the command, the code and the machine (onnxruntime at its default threads)."""
    libraries = {"onnxruntime": ort.__version__, "numpy": np.__version__}
    host = provenance.machine("cpu", 0, libraries)
    return provenance.run_record(command, provenance.code_version(), host)


def _check_errors(
    regressor: BodyRegressor, bodies: list[BodyCalibrator], snapshots: list[list[Snapshot]], truth: np.ndarray
) -> dict[str, float]:
    """Mean summed bone error (cm) per sequence at its end, for the height scale, the fallback (camera
    legs) and the regressor; and the regressor's over every snapshot (what a session sees as it goes)."""
    at_end = {
        "height": np.array([np.full(NUM_JOINTS, b.height_scale) for b in bodies]),
        "camera_legs": np.array([b.bone_scale for b in bodies]),
        "regressor": np.array([regressor.predict(b.height_scale, b.measured) for b in bodies]),
    }
    errors = {k: float(summed_bone_error_cm(v, truth).mean()) for k, v in at_end.items()}
    along = [
        summed_bone_error_cm(regressor.predict(h, m)[None], truth[n][None])[0]
        for n, seen in enumerate(snapshots)
        for h, m in seen
    ]
    errors["regressor_along_sequences"] = float(np.mean(along)) if along else float("nan")
    return {k: round(v, 2) for k, v in errors.items()}


def fit_body_regressors(
    weights_dir: Path,
    data_dirs: Sequence[Path],
    split: str = "train",
    check_split: str | None = "val",
    ridge: float = DEFAULT_RIDGE,
    progress: Progress | None = None,
    command: Sequence[str] | None = None,
) -> dict[Path, BodyRegressor]:
    """A regressor for every depth-seeing visual encoder the folder's models use, fitted on the datasets'
    ``split`` together and written beside it -> {path: regressor}. Earlier regressors in the folder are
    removed first: they are replaced, and one fitted on an older encoder would stop its models from loading.
    A check split no dataset has is refused before anything is removed."""
    check_datasets(data_dirs, check_split)
    for old in Path(weights_dir).glob(f"*{REGRESSOR_SUFFIX}"):
        old.unlink()
    written: dict[Path, BodyRegressor] = {}
    for path in model_files(weights_dir).values():
        model = LoadedModel.load(path)
        encoder = model.info.visual_path
        if not model.measures_body or regressor_path(encoder) in written:
            continue
        regressor = fit_encoder(model, data_dirs, split, check_split, ridge, progress, command)
        regressor.save(regressor_path(encoder))
        written[regressor_path(encoder)] = regressor
    return written
