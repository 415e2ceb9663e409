"""Weight-space blends of fusion checkpoints: one net whose every learnt weight is the weighted mean of that
weight in several nets of one shape.

This is for a net and a fine-tune of it (the fine-tune starts from the net's weights, so the two lie in one
basin and every blend between them is a working net): a blend keeps part of what the fine-tune learnt and part
of what it unlearnt, the "weight-space ensemble" of robust fine-tuning (Wortsman et al., WiSE-FT, CVPR 2022).
Two nets trained from different random draws share no basin, and their blend serves nonsense; nothing here
can tell that, so ``egoposevr blend`` says it in its help. An output ensemble (``export --runs A B``) is the
other kind of mean: it runs every net and costs their sum.

The nets' buffers (input normalisation) are not learnt and must be equal; a blend of nets that normalise
their inputs differently is refused. The blended checkpoint records what it was made from (each net's own
training record, which ``export`` writes into the model file's) and is finished (its step is its total), so
``train --resume`` never continues it and ``export`` treats it like any run's.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from .. import provenance
from .export import training_record
from .train import CheckpointError, build_net, invocation_record, load_checkpoint, save_checkpoint

# Fields of the first checkpoint a blend keeps as they are (what the net is and what it learnt from).
_KEPT_FIELDS = ("kind", "name", "config", "visual", "data", "rig_offsets_m", "init", "train_config")
# What must agree between the blended checkpoints for their weights to mean the same thing.
_SAME_FIELDS = ("kind", "name", "config", "visual")


def blend_weights(weights: list[float], count: int) -> list[float]:
    """The blend's weights, normalised to sum to 1: one per checkpoint, each >= 0, not all 0."""
    if len(weights) != count:
        raise ValueError(f"{count} checkpoints need {count} weights, not {len(weights)}")
    if any(not (0.0 <= w < math.inf) for w in weights) or sum(weights) <= 0.0:  # refuses NaN too
        raise ValueError(f"the weights must be finite, >= 0 and not all 0, not {weights}")
    total = float(sum(weights))
    return [float(w) / total for w in weights]


def blend_checkpoints(
    paths: list[Path], weights: list[float], command: Sequence[str] | None = None
) -> dict[str, Any]:
    """The checkpoint of the net whose learnt weights are ``weights``' mean of ``paths``' nets; its record
    names each net's file and digest and this invocation (``command``). ValueError (CheckpointError for an
    unreadable file) when the nets are not of one kind, config and encoder, or their buffers differ."""
    if len(paths) < 2:
        raise ValueError("a blend needs two checkpoints or more")
    shares = blend_weights(weights, len(paths))
    ckpts = [load_checkpoint(p) for p in paths]
    first = ckpts[0]
    for path, ckpt in zip(paths[1:], ckpts[1:], strict=True):
        for field in _SAME_FIELDS:
            if ckpt.get(field) != first.get(field):
                raise ValueError(f"{path} is not the net {paths[0]} is: its {field} differs")
    buffers = {name for name, _ in build_net(first, paths[0]).named_buffers()}
    state: dict[str, torch.Tensor] = {}
    for key, tensor in first["state_dict"].items():
        values = [ckpt["state_dict"].get(key) for ckpt in ckpts]
        if any(v is None or v.shape != tensor.shape for v in values):
            raise CheckpointError(f"the checkpoints' weights differ in {key}: not one net's shape")
        if key in buffers or not tensor.dtype.is_floating_point:
            if any(not torch.equal(v, tensor) for v in values):
                raise ValueError(f"the nets' {key} differ: a blend needs nets that normalise alike")
            state[key] = tensor.clone()
            continue
        state[key] = sum(share * v.double() for share, v in zip(shares, values, strict=True)).to(tensor.dtype)
    payload = {field: first[field] for field in _KEPT_FIELDS if field in first}
    return payload | provenance.hoist_ancestors(
        {
            "state_dict": state,
            "step": first["total_steps"],
            "total_steps": first["total_steps"],
            "history": [],
            "train_seconds": 0.0,
            # the top level's data, seed and start are the first net's; each blended net's own are here
            "blend": {
                "from": [str(p) for p in paths],
                "weights": shares,
                "nets": [training_record(ckpt, path) for ckpt, path in zip(ckpts, paths, strict=True)],
                "run": invocation_record(command),
            },
        }
    )


def blend_runs(
    runs_dirs: list[Path], weights: list[float], out_dir: Path, command: Sequence[str] | None = None
) -> list[Path]:
    """Each fusion checkpoint that every runs folder holds, blended with its namesakes, written to
    ``out_dir`` under the same name; returns the files written. FileNotFoundError when they share none.
    ``command``: the command line the blends record."""
    held = [{p.name for p in Path(d).glob("fusion-*.pt")} for d in runs_dirs]
    names = sorted(set.intersection(*held))
    if not names:
        folders = ", ".join(str(d) for d in runs_dirs)
        raise FileNotFoundError(f"{folders}: no fusion checkpoint (fusion-<model>.pt) is in every one")
    blends = {
        name: blend_checkpoints([Path(d) / name for d in runs_dirs], weights, command) for name in names
    }
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for name, payload in blends.items():
        save_checkpoint(out_dir / name, **payload)
        written.append(out_dir / name)
    return written
