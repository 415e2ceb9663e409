"""Train the model zoo: stage 1 the visual keypoint nets, stage 2 the fusion nets.

Reads a dataset written by `egoposevr synth` (its `train` split; several datasets' train splits together
when --data names more than one) and writes checkpoints to --out:
visual-rgb.pt, visual-rgbd.pt and fusion-<model>.pt. Models that share parts share checkpoints
(`egoposevr` is `hmd-rgbd` + KPO). Checkpoints store their config; --resume continues where a run stopped.
Then `egoposevr export` turns them into the ONNX models the runtime serves.
--hold-out K/N leaves the train split's subjects of fold K of N out (whole people, by duration; every
conversion of one capture together), so a training choice can be judged on people the nets never saw with
`egoposevr eval --split train --fold K/N`, without looking at val or test. The checkpoint records the fold and
the people it trained on; --resume refuses a run whose fold held other people in the data as it is now.
--train-fold K/N is its complement: only fold K's people train (a learning curve's smaller shares).

Example (the bundled weights; MODEL_CARD.md has the full recipe):
  egoposevr train --data data/dev --model all --out runs/cpu16 --preset cpu --seed 0 --fusion-steps 16000
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from ..model.config import KEEP_JOINTS_CHOICES, TRUNK_FREE_KEEPS

if TYPE_CHECKING:
    from ..model.training.train import InitialVisual, InitialWeights, TrainConfig


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--data",
        type=Path,
        nargs="+",
        required=True,
        metavar="DIR",
        help="dataset root (with train/); several: their train splits together",
    )
    parser.add_argument("--model", default="all", help="zoo names, comma-separated, or all (default)")
    parser.add_argument("--out", type=Path, default=Path("runs/default"), metavar="DIR", help="checkpoints")
    parser.add_argument("--preset", default="cpu", choices=("cpu", "gpu", "tiny"), help="default cpu")
    parser.add_argument("--seed", type=int, default=None, help="overrides the preset's seed")
    parser.add_argument("--visual-steps", type=int, default=None, metavar="N")
    parser.add_argument(
        "--fusion-steps",
        type=int,
        default=None,
        metavar="N",
        help="fusion training steps (default: the preset's); 0 with --init-from writes the loaded net as it is, "
        "a runs folder for `egoposevr blend`",
    )
    parser.add_argument("--limit", type=int, default=None, metavar="N", help="use at most N train sequences")
    parser.add_argument("--threads", type=int, default=None, metavar="N", help="torch threads")
    _number(
        parser,
        "--temporal-weight",
        "W",
        "weight of the fusion nets' temporal term (the error's change between consecutive samples); 0 off",
    )
    parser.add_argument(
        "--window", type=int, default=None, metavar="T", help="fusion nets' HMD window, headset samples"
    )
    parser.add_argument(
        "--visual-window",
        type=int,
        default=None,
        metavar="TV",
        help="fusion nets' camera window, frames (default 8; frames older than 0.5 s leave it whatever its length)",
    )
    parser.add_argument(
        "--batch", type=int, default=None, metavar="B", help="windows (fusion) or frames (encoder) per step"
    )
    _number(
        parser,
        "--skate-weight",
        "W",
        "weight of the fusion nets' skating term (a truly planted foot's served slide, m); 0 off",
    )
    _number(parser, "--weight-decay", "D", "AdamW's weight decay (default 0.01)")
    _number(
        parser,
        "--lr",
        "LR",
        "the peak learning rate after the warm-up (default: the preset's, 5e-4); a fine-tuned encoder trains "
        "at a fifth of it",
    )
    _number(
        parser,
        "--contact-weight",
        "W",
        "weight of the fusion nets' contact output's cross-entropy (default 1)",
    )
    _number(
        parser,
        "--timing-weight",
        "W",
        "weight of an auxiliary, training-only target: each foot's time to its next contact change and since "
        "its last (0, the default: no such head)",
    )
    _number(
        parser,
        "--foot-weight",
        "W",
        "the fusion nets' position loss on the ankles and feet, against 1 for the other joints (default 1)",
    )
    _number(
        parser,
        "--dropout",
        "P",
        "the fusion nets' dropout in attention and feed-forward layers (default 0.1)",
    )
    _number(
        parser,
        "--served-rotation-weight",
        "W",
        "weight of the fusion nets' rotation term as served (6D after Gram-Schmidt): no degenerate column; 0 off",
    )
    parser.add_argument(
        "--device",
        choices=("cpu", "cuda"),
        default=None,
        help="where to train (default: the preset's; gpu: cuda)",
    )
    parser.add_argument(
        "--encoders",
        type=Path,
        metavar="DIR",
        help="train only fusion nets, on the keypoints of DIR's exported visual-<kind>.onnx (e.g. the bundled)",
    )
    parser.add_argument(
        "--tracking-cone",
        type=float,
        nargs=2,
        default=None,
        metavar=("MIN", "MAX"),
        help="fusion nets: the mirrored copies also lose controllers outside a cone drawn from MIN-MAX degrees",
    )
    _number(
        parser,
        "--hanging-loss",
        "M",
        "fusion nets: the mirrored copies also lose a controller whose wrist hangs more than M metres "
        "under its shoulder",
    )
    _number(
        parser,
        "--keypoint-error-gain",
        "G",
        "fusion nets: each keypoint's error against the truth scaled by G (> 1: as bad as unseen "
        "people and rigs get; default 1)",
    )
    _number(
        parser,
        "--drop-camera",
        "P",
        "fusion nets: the share P of training windows served with no camera frame at all, which teaches the "
        "answer a headset without the camera gets, and every stream's before its first frame (default 0.1)",
    )
    _number(
        parser,
        "--cold-start",
        "P",
        "fusion nets: the share P of training windows that begin as a new stream inside their own span (the "
        "headset window padded with its first sample, only the frames since), as a session's first answers "
        "are (default 0)",
    )
    _number(
        parser,
        "--target-lead-ms",
        "MS",
        "fusion nets: learn the pose MS milliseconds after each window's newest sample, an answer ahead by about "
        "what the runtime's joint filter lags (default 0: the newest sample's pose)",
    )
    _number(
        parser,
        "--arm-swap",
        "P",
        "fusion nets: a share P of the sequences also trains with another sequence's arm motion "
        "(legs as they were, arm keypoints unseen)",
    )
    parser.add_argument(
        "--teachers",
        type=Path,
        nargs="+",
        default=(),
        metavar="DIR",
        help="distil: each fusion net also learns the mean output of these runs folders' nets of its kind",
    )
    _number(
        parser,
        "--distill-weight",
        "W",
        "with --teachers: the share of each loss term taken against the teachers (default 0.5)",
    )
    parser.add_argument(
        "--init-from",
        type=Path,
        default=None,
        metavar="PATH",
        help="fine-tune: each fusion net starts from the weights of the folder PATH's exported <net>.onnx "
        "(e.g. the bundled hmd-rgbd.onnx) instead of a random draw, or the run's one fusion net from the "
        "model file PATH (e.g. model/weights/egoposevr-lite.onnx); give it the keypoints it learnt from "
        "(--encoders with the encoder it was trained on)",
    )
    _number(
        parser,
        "--keep-upper",
        "W",
        "with --init-from: each fusion net also learns, with weight W (the truth's is 1), the upper body the "
        "net it starts from serves, frozen: a fine-tune for the legs that keeps the arms and trunk; 0 off",
    )
    parser.add_argument(
        "--keep-joints",
        choices=KEEP_JOINTS_CHOICES,
        default=None,
        help="with --keep-upper: the joints it keeps: upper, the 13 of the upper body under the head "
        "(default); arms, the collars, shoulders, elbows and wrists in the chest's frame, the trunk's lean free; "
        "arms_legs, those and the pelvis, hips, knees, ankles and feet in the pelvis's frame, with each foot's "
        "contact probability: only the trunk under the head free",
    )
    parser.add_argument(
        "--reanchor", action="store_true",
        help="with --init-from: train at today's default head offsets (or --head-offsets-from's) although the "
        "net it starts from was trained at others: the fine-tune learns the body under the new head joint "
        "(e.g. the bundled hmd-rgbd.onnx's legacy offsets, MODEL_CARD rule 76)",
    )  # fmt: skip
    parser.add_argument(
        "--init-member",
        type=int,
        default=0,
        metavar="K",
        help="with --init-from: which net of a file that serves several (default 0)",
    )
    parser.add_argument(
        "--head-offsets-from", type=Path, default=None, metavar="FILE",
        help="train the fusion nets at the head offsets the model file FILE records instead of today's "
        "default; --init-from (unless --reanchor) and --teachers must agree. The offset must be where the data "
        "puts the headset: on today's renders the default is (the bundled hmd-rgbd.onnx's legacy ones cost 1-2 "
        "cm, MODEL_CARD)",
    )  # fmt: skip
    parser.add_argument(
        "--hold-out", default=None, metavar="K/N",
        help="leave the train split's subjects of fold K of N out (whole subjects, by duration), to judge a "
        "training choice on them with `eval --split train --fold K/N` instead of on val or test",
    )  # fmt: skip
    parser.add_argument(
        "--train-fold", default=None, metavar="K/N",
        help="train on the train split's subjects of fold K of N alone (the complement of --hold-out): a "
        "learning curve's smaller shares of the people",
    )  # fmt: skip
    parser.add_argument(
        "--init-visual", type=Path, default=None, metavar="FILE",
        help="fine-tune: the run's encoder of this file's kind starts from the exported encoder FILE (e.g. "
        "the bundled visual-rgbd.onnx) instead of a random draw, its batch norms' statistics frozen and at a "
        "fifth of the preset's learning rate",
    )  # fmt: skip
    parser.add_argument(
        "--encoders-out-of-fold", nargs="+", type=Path, default=(), metavar="DIR",
        help="train only fusion nets, each training sequence's keypoints from the one of these folders' "
        "exported encoders that left its person out (each trained with --hold-out K/N on the same --data): "
        "keypoints as far off as a new person's; export with --encoders (the encoder to serve)",
    )  # fmt: skip
    parser.add_argument("--resume", action="store_true", help="continue from the checkpoints in --out")
    parser.add_argument("--no-progress", action="store_true")


def _number(parser: argparse.ArgumentParser, flag: str, metavar: str, help_text: str) -> None:
    """A float option that overrides the preset's value when given (None: the preset's)."""
    parser.add_argument(flag, type=float, default=None, metavar=metavar, help=help_text)


def run(args: argparse.Namespace) -> int:
    from ..model.runtime.loading import ModelError
    from ..model.training.dataset import DatasetError, Fold
    from ..model.training.train import PRESETS, CheckpointError, DeviceError, TeacherError, train_zoo
    from ..model.zoo import resolve

    try:
        names = resolve(args.model)
    except ValueError as error:
        print(f"egoposevr train: {error}", file=sys.stderr)
        return 2
    overrides = {
        key: value
        for key, value in (
            ("seed", args.seed), ("visual_steps", args.visual_steps), ("fusion_steps", args.fusion_steps),
            ("limit_sequences", args.limit), ("threads", args.threads), ("device", args.device),
            ("window", args.window), ("visual_window", args.visual_window), ("batch", args.batch),
            ("temporal_weight", args.temporal_weight), ("skate_weight", args.skate_weight),
            ("served_rotation_weight", args.served_rotation_weight),
            ("contact_weight", args.contact_weight), ("timing_weight", args.timing_weight),
            ("dropout", args.dropout),
            ("foot_weight", args.foot_weight),
            ("weight_decay", args.weight_decay), ("lr", args.lr),
            ("distill_weight", args.distill_weight), ("keep_upper_weight", args.keep_upper),
            ("keep_joints", args.keep_joints),
            ("tracking_cone_deg", tuple(args.tracking_cone) if args.tracking_cone else None),
            ("hanging_loss_m", args.hanging_loss), ("keypoint_error_gain", args.keypoint_error_gain),
            ("arm_swap_p", args.arm_swap), ("drop_camera_p", args.drop_camera),
            ("cold_start_p", args.cold_start), ("target_lead_ms", args.target_lead_ms),
            ("reanchor", args.reanchor or None),
        )
        if value is not None
    }  # fmt: skip
    refusal = _out_of_range(args)
    if refusal is not None:
        print(f"egoposevr train: {refusal}", file=sys.stderr)
        return 2
    if args.hold_out is not None and args.train_fold is not None:
        print("egoposevr train: --hold-out and --train-fold exclude each other", file=sys.stderr)
        return 2
    for flag, key, text in (
        ("--hold-out", "hold_out", args.hold_out),
        ("--train-fold", "train_fold", args.train_fold),
    ):
        try:
            overrides |= {key: str(Fold.parse(text))} if text is not None else {}
        except ValueError as error:
            print(f"egoposevr train: {flag}: {error}", file=sys.stderr)
            return 2
    config = dataclasses.replace(PRESETS[args.preset], **overrides)
    try:
        initial = _initial_weights(names, args.init_from, args.init_member, config)
    except ValueError as error:
        print(f"egoposevr train: --init-from: {error}", file=sys.stderr)
        return 2
    try:
        initial_visual = _initial_encoder(
            args.init_visual, config, names, args.encoders is not None or bool(args.encoders_out_of_fold)
        )
    except ValueError as error:
        print(f"egoposevr train: --init-visual: {error}", file=sys.stderr)
        return 2
    head_offsets_m = None
    if args.head_offsets_from is not None:
        from ..model.training.export import recorded_offsets

        try:
            head_offsets_m = recorded_offsets(args.head_offsets_from)
        except ValueError as error:
            print(f"egoposevr train: --head-offsets-from: {error}", file=sys.stderr)
            return 2
    started = time.perf_counter()
    try:
        paths = train_zoo(
            names,
            args.data,
            args.out,
            config,
            args.resume,
            not args.no_progress,
            args.encoders,
            args.teachers,
            initial,
            initial_visual,
            args.encoders_out_of_fold,
            head_offsets_m,
            args.command_line,
        )
    except (DatasetError, ModelError, DeviceError, TeacherError, CheckpointError) as error:
        print(f"egoposevr train: {error}", file=sys.stderr)
        return 2
    for name, path in paths.items():
        print(f"{name}: {path}")
    print(f"trained in {time.perf_counter() - started:.0f} s")
    return 0


def _out_of_range(args: argparse.Namespace) -> str | None:
    """The first option given outside its range, as the line that says what it needs; None when none is."""
    cone = args.tracking_cone
    checks = (
        (cone and not 0.0 < cone[0] <= cone[1] <= 180.0, "--tracking-cone MIN MAX needs 0 < MIN <= MAX <= 180 degrees"),
        (args.hanging_loss is not None and not 0.0 < args.hanging_loss < 2.0, "--hanging-loss M needs 0 < M < 2 metres"),
        (args.keypoint_error_gain is not None and not 0.0 <= args.keypoint_error_gain <= 10.0,
         "--keypoint-error-gain G needs 0 <= G <= 10"),
        (args.dropout is not None and not 0.0 <= args.dropout < 1.0, "--dropout P needs 0 <= P < 1"),
        (args.weight_decay is not None and not 0.0 <= args.weight_decay < 1.0, "--weight-decay D needs 0 <= D < 1"),
        (args.lr is not None and not 0.0 < args.lr <= 0.1, "--lr LR needs 0 < LR <= 0.1"),
        (args.contact_weight is not None and args.contact_weight < 0.0, "--contact-weight W needs W >= 0"),
        (args.timing_weight is not None and not 0.0 <= args.timing_weight <= 100.0,
         "--timing-weight W needs 0 <= W <= 100"),
        (args.keep_upper is not None and not 0.0 <= args.keep_upper <= 100.0, "--keep-upper W needs 0 <= W <= 100"),
        (args.keep_upper and args.init_from is None, "--keep-upper W needs --init-from (the net whose upper body it keeps)"),
        (args.keep_joints and not args.keep_upper, "--keep-joints needs --keep-upper W > 0 (the term it chooses joints for)"),
        (args.reanchor and args.init_from is None, "--reanchor needs --init-from (the net it moves to another head joint)"),
        (args.reanchor and args.keep_upper and args.keep_joints not in TRUNK_FREE_KEEPS, "--reanchor keeps no more than the arms and the legs (--keep-joints arms or arms_legs): the trunk under the head is what it moves"),
        (args.foot_weight is not None and not 0.0 < args.foot_weight <= 100.0, "--foot-weight W needs 0 < W <= 100"),
        (args.arm_swap is not None and not 0.0 <= args.arm_swap <= 1.0, "--arm-swap P needs 0 <= P <= 1"),
        (args.drop_camera is not None and not 0.0 <= args.drop_camera <= 1.0, "--drop-camera P needs 0 <= P <= 1"),
        (args.cold_start is not None and not 0.0 <= args.cold_start <= 1.0, "--cold-start P needs 0 <= P <= 1"),
        (args.target_lead_ms is not None and not 0.0 <= args.target_lead_ms <= 200.0, "--target-lead-ms MS needs 0 <= MS <= 200"),
        (args.window is not None and args.window < 1, "--window T needs T >= 1 headset samples"),
        (args.visual_window is not None and args.visual_window < 1, "--visual-window TV needs TV >= 1 frames"),
        (args.batch is not None and not 1 <= args.batch <= 4096, "--batch B needs 1 <= B <= 4096"),
    )  # fmt: skip
    return next((needs for bad, needs in checks if bad), None)


def _initial_encoder(
    source: Path | None, config: TrainConfig, names: list[str], reads_exported: bool
) -> dict[str, InitialVisual] | None:
    """--init-visual: {kind: the weights the encoder of that kind starts from}, or None. Raises ValueError for
    a file that is not an encoder, or one of a kind this run trains no encoder of (``names`` its models;
    ``reads_exported``: its fusion nets read exported encoders, --encoders or --encoders-out-of-fold, and it
    trains none)."""
    if source is None:
        return None
    from ..model.runtime.loading import ModelError, load_encoder
    from ..model.training.export import initial_visual_state
    from ..model.training.train import fusion_names, visual_config
    from ..model.zoo import ZOO

    try:
        _, metadata = load_encoder(source)
    except (ModelError, OSError) as error:
        raise ValueError(str(error)) from error
    kind = "rgbd" if metadata.config.channels == 4 else "rgb"
    if reads_exported or all(ZOO[f].visual != kind for f in fusion_names(names)):
        raise ValueError(
            f"{source} is a {kind} encoder, and this run trains none (--model, --encoders, --encoders-out-of-fold)"
        )
    return {kind: initial_visual_state(source, visual_config(kind, config))}


def _initial_weights(
    names: list[str], source: Path | None, member: int, config: TrainConfig
) -> dict[str, InitialWeights] | None:
    """--init-from: each named model's fusion net -> the weights it starts from (raises ValueError). A
    folder gives each net its own file; one model file can start one net only."""
    if source is None:
        return None
    from ..model.training.export import initial_fusion_state
    from ..model.training.train import fusion_config
    from ..model.zoo import fusion_names

    nets = fusion_names(names)
    if len(nets) > 1 and not source.is_dir():
        raise ValueError(
            f"{source} is one model file and this run trains {len(nets)} fusion nets ({', '.join(nets)}): "
            "name a folder, or one model"
        )
    return {f: initial_fusion_state(source, f, member, fusion_config(f, config)) for f in nets}
