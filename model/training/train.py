"""Training (torch): stage 1 the visual keypoint nets, stage 2 the fusion nets of the zoo.

Stage 1 (per modality, ``visual-rgb`` / ``visual-rgbd``): heatmap cross-entropy against a Gaussian at the
labelled 2D joint + L1 on the lifted 3D joints (camera frame) for joints in view, + BCE on visibility ζ.
Stage 2 (per zoo fusion net): the frozen stage-1 encoder's keypoints (its checkpoint's, or an exported
encoder's: :class:`ExportedEncoder`) go through exactly the runtime's preparation
(:mod:`egoposevr.model.inputs`: heading frame, Alg. 1, visual tokens); losses are L1 on the 6D rotations +
L1 on FK joint positions anchored at the headset's head joint, as the runtime anchors them, + BCE on each
foot's contact, + optionally the temporal term (``TrainConfig.temporal_weight``) and the skating term
(``TrainConfig.skate_weight``), both on pairs of windows a headset sample apart.

The nets train on the CPU or on CUDA (``TrainConfig.device``); batches are built in numpy either way.

Everything is seeded; checkpoints store their net config, the training config, the step, optimiser state
and loss history, so ``resume`` continues and export rebuilds the net from the file alone.
Shape legend: ``B`` batch, ``T`` HMD window, ``Tv`` visual window, ``J`` = 22, ``K`` camera frames.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Final

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from .. import provenance
from ..config import TRUNK_FREE_KEEPS, FusionConfig, VisualConfig, parse, to_fields
from ..hmd import hmd_features, hmd_input_dim, tracking_features
from ..inputs import (
    VisibilityFilter,
    camera_to_world,
    canonicalize_hmd,
    heading_frame,
    lift_keypoints,
    nearest_sample,
    network_input,
    normalise_uv,
    to_heading,
    visual_tokens,
    visual_window,
)
from ..rig import DEFAULT_OFFSETS_M, joints_from_devices
from ..rotations import matrix_to_sixd, quat_xyzw_to_matrix
from ..runtime.contact import FEET as ANKLES_AND_FEET
from ..runtime.loading import load_encoder
from ..skeleton import ARM_JOINTS, HEAD, JOINT_INDEX, LOWER_BODY, UPPER_BODY, rest_offsets
from ..synth.headset import TRACKING_CONE_DEG
from ..zoo import ZOO, fusion_names
from .augment import (
    crop_and_flip,
    lose_hanging_arms,
    mirror_sequence,
    mirror_world_keypoints,
    narrow_tracking_cone,
    retime_sequence,
    swap_arms,
)
from .dataset import (
    DatasetError,
    Fold,
    decode_frame_list,
    decode_frames,
    fold_members,
    load_splits,
    sequence_subject,
    split_camera,
    subjects,
)
from .nets.fusion import FusionNet, SeedEnsemble, orthonormal_sixd, set_input_statistics
from .nets.kinematics import forward_kinematics, sixd_to_matrix
from .nets.visual import KeypointNet
from .plausibility import FEET, contact_timing, contacts


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """One preset of training hyper-parameters (the paper's AdamW, lr 5e-4, batch 32)."""

    seed: int = 0
    batch: int = 32
    lr: float = 5e-4
    weight_decay: float = 1e-2
    warmup_steps: int = 100
    visual_steps: int = 5000
    fusion_steps: int = 8000
    visual_width: int = 80
    visual_height: int = 64
    visual_stem: int = 0  # VisualConfig.stem_channels
    window: int = 40
    visual_window: int = 8
    d_model: int = 64
    joint_dim: int = 32
    dropout: float = 0.1  # the fusion nets' (FusionConfig.dropout): attention and feed-forward layers
    heatmap_sigma_cells: float = 1.0
    camera_latency_ms: tuple[float, float] = (10.0, 50.0)  # capture -> arrival, drawn per sequence
    drop_camera_p: float = 0.1  # whole visual window missing: teaches the HMD-only fallback
    # The share of windows that begin as a new stream inside their own span (a session's start or restart):
    # the headset window padded with its first sample and only the frames captured since. A session's first
    # answers are such windows, and the runtime's planted feet and held legs begin on them. 0: only the
    # sequences' own starts are (the bundled nets' recipe).
    cold_start_p: float = 0.0
    # The nets learn the pose this many ms after each window's newest sample (its rotations, its joints under
    # the head and the feet's contact then, in the window's own heading frame): an answer ahead by about what
    # the runtime's joint filter lags (pipeline.POSITION_MIN_CUTOFF_HZ). 0: the pose at the window's newest
    # sample, as the paper (the bundled nets' recipe).
    target_lead_ms: float = 0.0
    drop_frame_p: float = 0.05
    position_weight: float = 10.0  # L1 metres vs L1 6D
    rotation_weight: float = 3.0  # without it, a leg could settle twisted half a turn with the knee reversed
    # L1 of each rotation as served (its 6D after Gram-Schmidt) against the truth's. The L1 of the raw 6D alone
    # is flat between two modes of the truth, where a seed can settle with a column near zero, whose direction
    # Gram-Schmidt then serves: a neck 120 degrees off (MODEL_CARD.md, "A neck that cannot settle twisted").
    # 0: off (the bundled nets' recipe).
    served_rotation_weight: float = 0.0
    device_validity: bool = True  # the nets read each device's tracking state after x_t (hmd.py)
    lost_hand_weight: float = 3.0  # position loss of a lost controller's wrist and elbow, against 1
    # Position loss of the ankles and feet, against 1: where a planted foot is served is the anchor the
    # runtime holds, and on people the nets never saw a walking foot is placed worst (MODEL_CARD.md, rule 13).
    foot_weight: float = 1.0
    contact_head: bool = True  # the nets also predict each foot's contact (labels: plausibility.contacts)
    contact_weight: float = 1.0  # binary cross-entropy of the contact logits, against the losses above
    # L1 of each foot's step timing (plausibility.contact_timing: time to its next contact change and since its
    # last, in [0, 1]) from a training-only head (FusionConfig.timing_head): an auxiliary target that asks the
    # nets for the steps' rhythm. 0: off, no such head (the bundled nets' recipe).
    timing_weight: float = 0.0
    # L1 (m, summed over x, y, z) of how much each joint's error changes from the sample before: the served
    # body's jitter is mostly the network's own sample-to-sample noise (MODEL_CARD.md). 0: off, the batch is
    # tc.batch windows; on, each window also runs with the one a sample before it (2 x batch).
    temporal_weight: float = 0.0
    # L1 (m, summed over x, y, z) of how much each foot's error changes, in the world, from the sample before,
    # where the truth has that foot down at both samples: a planted foot that the net lets slide. Summed over
    # the feet (not averaged over the 22 joints as the temporal term is). 0: off; on, pairs as above.
    skate_weight: float = 0.0
    # With teachers (train_fusion's ``teachers``): the share of each fusion loss term taken against the
    # teachers' mean output instead of the truth (knowledge distillation; MODEL_CARD.md).
    distill_weight: float = 0.5
    # With a fine-tune (train_fusion's ``initial``): weight of the upper body's fit terms (UPPER_BODY's
    # rotations and joints) taken against the net it starts from, frozen, on top of the truth's: a fine-tune
    # for the legs that leaves the arms and the trunk where its start put them (MODEL_CARD.md, rule 41). 0: off.
    keep_upper_weight: float = 0.0
    # Which joints keep_upper_weight keeps: "upper", UPPER_BODY's 13 (their rotations, their joints under the
    # head); "arms", ARM_JOINTS' 8 (their rotations, their joints in the chest's frame), so the spine, the neck
    # and the trunk's lean over the hips stay free (MODEL_CARD.md, rule 42); "arms_legs", those 8 and
    # LOWER_BODY's 9 (their rotations, their joints in the pelvis's frame, turned as the pelvis is) and the
    # contact probabilities: only the trunk under the head is free, for a fine-tune that moves the head joint
    # and keeps the legs and feet its start served (MODEL_CARD.md, rule 78).
    keep_joints: str = "upper"
    # With a fine-tune: train at today's default head offsets (or ``--head-offsets-from``'s) although the net
    # it starts from was trained at others, so the fine-tune learns the body under the new head joint instead
    # of keeping the one its start compensated for (MODEL_CARD.md, rule 76). False: a fine-tune keeps its
    # start's offsets.
    reanchor: bool = False
    mirror_p: float = 0.5  # stage 1: frames mirrored; stage 2: every sequence also trains mirrored
    crop_p: float = 0.5  # stage 1: frames cropped to other aspect ratios and fields of view (augment.py)
    speed_range: tuple[float, float] = (0.8, 1.25)  # stage 2: the mirrored copies play at a random speed
    # Stage 2: the mirrored copies also lose each controller outside a tracking cone drawn from this range,
    # degrees off the headset's forward axis (augment.narrow_tracking_cone); None: the losses as rendered.
    tracking_cone_deg: tuple[float, float] | None = None
    # Stage 2: the mirrored copies also lose a controller whose true wrist hangs more than this many metres
    # under its shoulder (augment.lose_hanging_arms: a hand at the side, a walking arm); None: off.
    hanging_loss_m: float | None = None
    # Stage 2: each camera-frame keypoint's error (the encoder's, against the truth, in the camera) is scaled
    # by this before the nets see it. The encoder is better on its own training images than on anyone else's
    # (MODEL_CARD.md): > 1 trains the nets on keypoints as bad as unseen people and rigs give. 1: as predicted.
    keypoint_error_gain: float = 1.0
    # Stage 2: this share of the sequences also trains as a copy with another training sequence's arm motion
    # (augment.swap_arms; its arm keypoints unseen): arms that move over legs that do what they did. 0: off.
    arm_swap_p: float = 0.0
    limit_sequences: int | None = None
    # "K/N": the train split's subjects of fold K of N are left out (dataset.Fold), for choices judged on
    # them (``eval --split train --fold K/N``) instead of on val or test. None: every subject trains.
    hold_out: str | None = None
    # "K/N": only fold K's subjects train (the complement of hold_out): a learning curve's smaller shares
    train_fold: str | None = None
    threads: int = 0  # torch intra-op threads; 0 = torch's default
    device: str = "cpu"  # where the nets train: "cpu" or "cuda" (checkpoints are always loadable on the CPU)


# The ankles and the feet (the runtime's planted pairs): the joints --foot-weight weighs
FOOT_JOINTS: Final = [j for ankle_and_foot in ANKLES_AND_FEET for j in ankle_and_foot]
CHEST: Final = JOINT_INDEX["spine3"]  # the collars' parent
# TrainConfig.keep_joints: the joints each choice keeps (upper_body_term)
# (its keys are config.KEEP_JOINTS_CHOICES, which the command line offers: tests hold the two together)
KEPT_JOINTS: Final = {
    "upper": UPPER_BODY,
    "arms": ARM_JOINTS,
    "arms_legs": np.concatenate([ARM_JOINTS, LOWER_BODY]),
}
LOST_HAND_JOINTS: Final = ((18, 20), (19, 21))  # the elbow and wrist a lost left / right controller held

PRESETS: dict[str, TrainConfig] = {
    # The whole zoo on a 2-core CPU in about 60 minutes, inside the 90-minute budget for the default. The
    # bundled weights add --fusion-steps 16000 (about 1 h 45 min; MODEL_CARD.md has the measured times).
    # The visual encoder reads 160×128 through a strided stem: what 80×64 costs (PERFORMANCE.md / MODEL_CARD).
    "cpu": TrainConfig(visual_width=160, visual_height=128, visual_stem=16),
    # For a GPU: wider nets, longer schedules.
    "gpu": TrainConfig(
        visual_steps=20000, fusion_steps=30000, d_model=128, joint_dim=64, visual_width=160, visual_height=128,
        visual_stem=16, device="cuda",
    ),
    # For tests: seconds.
    "tiny": TrainConfig(
        visual_steps=30, fusion_steps=30, batch=8, visual_width=40, visual_height=32, window=8,
        visual_window=3, d_model=16, joint_dim=8, warmup_steps=5, mirror_p=0.0, crop_p=0.0,
    ),
}  # fmt: skip


def visual_config(kind: str, tc: TrainConfig) -> VisualConfig:
    return VisualConfig(
        channels=4 if kind == "rgbd" else 3, width=tc.visual_width, height=tc.visual_height,
        stem_channels=tc.visual_stem,
    )  # fmt: skip


def fusion_config(name: str, tc: TrainConfig) -> FusionConfig:
    base = {"window": tc.window, "visual_window": tc.visual_window, "d_model": tc.d_model}
    base |= {
        "joint_dim": tc.joint_dim,
        "dropout": tc.dropout,
        "device_validity": tc.device_validity,
        "contact_head": tc.contact_head,
        "timing_head": tc.timing_weight > 0,
    }
    return FusionConfig(**{**base, **ZOO[name].fusion})


# ------------------------------------------------------------------------------------------- checkpoints
def save_checkpoint(path: Path, **payload: Any) -> None:
    tmp = path.with_suffix(".tmp")
    torch.save(payload, tmp)
    tmp.replace(path)  # never a half-written checkpoint


class CheckpointError(ValueError):
    """A checkpoint file that cannot be read back (truncated, corrupt, not a checkpoint): the user's file."""


_CHECKPOINT_KEYS: Final = ("kind", "config", "state_dict", "step", "total_steps", "history", "train_config")


def load_checkpoint(path: Path) -> dict[str, Any]:
    """A checkpoint written by :func:`save_checkpoint`. A missing file raises FileNotFoundError; one that
    is unreadable or lacks a checkpoint's fields raises CheckpointError naming the file."""
    path = Path(path)
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False)
    except FileNotFoundError:
        raise
    # torch reports a damaged file as OSError, RuntimeError, EOFError, an unpickling error, ...
    except Exception as error:
        raise CheckpointError(
            f"{path} is not a readable checkpoint ({type(error).__name__}: {error}); it may be truncated "
            "or corrupt: delete it and train again to replace it"
        ) from error
    missing = [k for k in _CHECKPOINT_KEYS if not isinstance(ckpt, dict) or k not in ckpt]
    if missing:
        raise CheckpointError(f"{path} is not an egoposevr checkpoint (it lacks {', '.join(missing)})")
    return ckpt


def build_net(ckpt: dict[str, Any], source: Path | None = None) -> torch.nn.Module:
    """The net a checkpoint describes, with its weights, in eval mode. CheckpointError (naming ``source``,
    the file it came from) when its config describes no net or its weights do not fit that net."""
    try:
        if ckpt["kind"] == "visual":
            net: torch.nn.Module = KeypointNet(parse(VisualConfig, ckpt["config"]))
        else:
            net = FusionNet(parse(FusionConfig, ckpt["config"]))
        net.load_state_dict(ckpt["state_dict"])
    except (RuntimeError, ValueError, TypeError) as error:
        where = f"{source}: " if source is not None else ""
        raise CheckpointError(
            f"{where}a {ckpt['kind']} checkpoint whose config and weights do not fit together: {error}"
        ) from error
    return net.eval()


def load_net(path: Path) -> torch.nn.Module:
    """:func:`build_net` of the checkpoint at ``path``."""
    return build_net(load_checkpoint(path), path)


def _finished(path: Path, tc: TrainConfig, seqs: list[dict[str, Any]]) -> bool:
    """A checkpoint exists and reached its planned number of steps (resume skips it); CheckpointError when
    it was trained without the subjects ``tc`` leaves out of ``seqs``' data, or with others."""
    if not path.exists():
        return False
    ckpt = load_checkpoint(path)
    _check_same_hold_out(ckpt, path, tc, seqs)
    return ckpt["step"] >= ckpt["total_steps"]


def _check_same_data(ckpt: dict[str, Any], path: Path, data: dict[str, Any]) -> None:
    """A run resumes on the bytes it started on: CheckpointError when its recorded data digest is not this
    data's ``data`` record's (a checkpoint from before 2026-12-06 records none and is not checked)."""
    then = (ckpt.get("data") or {}).get("sha256") if isinstance(ckpt.get("data"), dict) else None
    if then is not None and then != data.get("sha256"):
        raise CheckpointError(
            f"{path} was trained on other data (sha256 {then[:16]}, this data {data.get('sha256', '')[:16]}): "
            "a resumed run would learn from both; train into another --out"
        )


def _check_same_hold_out(
    ckpt: dict[str, Any], path: Path, tc: TrainConfig, seqs: list[dict[str, Any]]
) -> None:
    """A run resumes on the data it started on: its fold left out (``--hold-out``) or kept alone
    (``--train-fold``) must be this one, and give the same people (a checkpoint from before 2026-11-27
    records only the fold)."""
    data = ckpt.get("data")
    data = data if isinstance(data, dict) else {}
    for flag, key, now in (
        ("--hold-out", "held_out_fold", tc.hold_out),
        ("--train-fold", "trained_fold", tc.train_fold),
    ):
        if data.get(key) != now:
            raise CheckpointError(
                f"{path} was trained with {flag} {data.get(key) or 'none'}, not {now or 'none'}: "
                "its data would change under it; train into another --out"
            )
    people_then = data.get("trained_subjects_sha256")
    if (tc.hold_out or tc.train_fold) and people_then is not None and people_then != _people_digest(seqs):
        which = f"--hold-out {tc.hold_out} leaves" if tc.hold_out else f"--train-fold {tc.train_fold} keeps"
        raise CheckpointError(
            f"{path} was trained on other people than {which} in this data (its folds fall otherwise now); "
            "train into another --out"
        )


def _people_digest(seqs: list[dict[str, Any]]) -> str:
    """sha256 of the sorted subjects the sequences were taken from: which people a run learnt from."""
    return hashlib.sha256("\n".join(subjects(seqs)).encode()).hexdigest()


def invocation_record(command: Sequence[str] | None, device: str = "cpu") -> dict[str, Any]:
    """This invocation's provenance (train, blend, export): the command, the code, and the machine with the
    device and torch's thread count (a net's bits depend on them)."""
    libraries = {"torch": torch.__version__}
    if device.startswith("cuda") and torch.cuda.is_available():
        libraries["gpu"] = torch.cuda.get_device_name(torch.device(device))
    host = provenance.machine(device, torch.get_num_threads(), libraries)
    return provenance.run_record(command, provenance.code_version(), host)


def _unrecorded_runs(step: int) -> list[dict[str, Any]]:
    """What a checkpoint from before runs were recorded (2026-12-06) says of the steps it had run."""
    return [{"from_step": 0, "to_step": step, "recorded": False}] if step else []


def _schedule(tc: TrainConfig, total: int) -> Callable[[int], float]:
    def factor(step: int) -> float:
        if step < tc.warmup_steps:
            return (step + 1) / tc.warmup_steps
        return 0.5 * (
            1 + math.cos(math.pi * min(1.0, (step - tc.warmup_steps) / max(1, total - tc.warmup_steps)))
        )

    return factor


def _run_steps(
    net: torch.nn.Module,
    loss_fn: Callable[[np.random.Generator], dict[str, torch.Tensor]],
    ckpt_path: Path,
    total: int,
    tc: TrainConfig,
    meta: dict[str, Any],
    resume: bool,
    progress: bool,
    invocation: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The shared optimisation loop: AdamW + warmup/cosine, checkpoints every 500 steps and at the end. The
    checkpoint's ``runs`` lists each invocation that advanced it (:func:`invocation_record`: ``invocation``, or
    this call's without a command) with the steps it ran."""
    # fused: one kernel over every parameter instead of a loop over 182 tensors (CPU: 7.4 -> 1.4 ms a step of
    # the cpu preset's fusion net, about a tenth of the step; the same update up to rounding).
    opt = torch.optim.AdamW(net.parameters(), lr=tc.lr, weight_decay=tc.weight_decay, fused=True)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, _schedule(tc, total))
    step, history, elapsed, runs = 0, [], 0.0, []
    if resume and ckpt_path.exists():
        ckpt = load_checkpoint(ckpt_path)
        _check_same_data(ckpt, ckpt_path, meta["data"])
        if (
            "rig_offsets_m" in ckpt
            and "rig_offsets_m" in meta
            and ckpt["rig_offsets_m"] != meta["rig_offsets_m"]
        ):
            raise CheckpointError(
                f"{ckpt_path} cannot be resumed: it was trained at head offsets {ckpt['rig_offsets_m']}, and "
                f"these flags train at {meta['rig_offsets_m']} (--head-offsets-from, --init-from and --teachers "
                "decide them); train into another --out, or resume with the flags it began with"
            )
        try:
            net.load_state_dict(ckpt["state_dict"])
            opt.load_state_dict(ckpt["optimizer"])
            sched.load_state_dict(ckpt["scheduler"])
            # the saved state carries the decay and the learning rate it began with; the flags rule
            for group in opt.param_groups:
                group["weight_decay"] = tc.weight_decay
                group["initial_lr"] = tc.lr
                group["lr"] = tc.lr * sched.lr_lambdas[0](sched.last_epoch)  # as the schedule has it now
            sched.base_lrs = [tc.lr] * len(opt.param_groups)
            step, history, elapsed = ckpt["step"], ckpt["history"], ckpt["train_seconds"]
            runs = ckpt.get("runs") or _unrecorded_runs(step)
        except (RuntimeError, ValueError, KeyError) as error:
            raise CheckpointError(
                f"{ckpt_path} cannot be resumed: its weights do not fit the net these flags train, or it lacks "
                f"the optimiser's state ({type(error).__name__}: {error}); train into another --out, or delete it"
            ) from error
    rng = np.random.default_rng([tc.seed, step])
    torch.manual_seed(tc.seed * 1_000_003 + step)
    net.train()
    bar = tqdm(total=total, initial=step, desc=ckpt_path.stem, disable=not progress, dynamic_ncols=True)
    running: dict[str, float] = {}
    started = time.perf_counter()
    this_run = (invocation or invocation_record(None, tc.device)) | {"from_step": step}

    def save() -> dict[str, Any]:
        payload = {
            **meta,
            "runs": [*runs, this_run | {"to_step": step, "seconds": round(time.perf_counter() - started, 1)}],
            "state_dict": net.state_dict(),
            "optimizer": opt.state_dict(),
            "scheduler": sched.state_dict(),
            "step": step,
            "total_steps": total,
            "history": history,
            "train_seconds": elapsed + time.perf_counter() - started,
            "train_config": dataclasses.asdict(tc),
        }
        save_checkpoint(ckpt_path, **payload)
        return payload

    while step < total:
        losses = loss_fn(rng)
        loss = sum(losses.values())
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        opt.step()
        sched.step()
        step += 1
        for key, value in losses.items():
            v = value.item()
            running[key] = 0.98 * running.get(key, v) + 0.02 * v
        bar.update(1)
        bar.set_postfix({k: f"{v:.4f}" for k, v in running.items()}, refresh=False)
        if step % 100 == 0 or step == total:
            history.append({"step": step, **running})
        if step % 500 == 0 and step < total:
            save()
    bar.close()
    net.eval()
    return save()


# ----------------------------------------------------------------------------------------- stage 1
@dataclasses.dataclass
class VisualData:
    """A split's camera frames with their labels, K frames. The frames stay as rendered (JPEG colour, PNG
    depth: the sequences' own bytes) and a batch is decoded and resized when it is drawn. Decoded up front
    at the net's input size they took 100 kB a frame, and the training sets with the many-body renders
    outgrew the machine's 24 GB; decoding a batch of 32 costs about 10 ms of a step's 270."""

    rgb_jpeg: list[bytes]  # (K,)
    depth_png: list[bytes]  # (K,) mm
    size_net_wh: tuple[int, int]  # the net's input size, what frames() returns
    uv: np.ndarray  # (K, J, 2) normalised
    intrinsics: np.ndarray  # (K, 4) fx, fy, cx, cy of each frame's own camera, pixels
    size_wh: np.ndarray  # (K, 2) that camera's image size
    joints_cam_m: np.ndarray  # (K, J, 3)
    visible: np.ndarray  # (K, J) bool

    def __len__(self) -> int:
        return len(self.rgb_jpeg)

    def frames(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Frames idx (B,) at the net's input size: RGB (B, h, w, 3) uint8, depth (B, h, w) uint16 mm."""
        return decode_frame_list(
            [self.rgb_jpeg[i] for i in idx], [self.depth_png[i] for i in idx], self.size_net_wh
        )


def _camera_wh(seq: dict[str, Any]) -> tuple[int, int]:
    return seq["camera"]["width"], seq["camera"]["height"]


def load_visual_data(seqs: list[dict[str, Any]], size_wh: tuple[int, int]) -> VisualData:
    """Every sequence's frames (kept encoded) with labels, each sequence's labels in its own camera
    (``seq["camera"]``); frames() gives them resized to size_wh."""
    per_frame = [np.ones((len(s["cam_t_us"]), 1)) for s in seqs]
    return VisualData(
        rgb_jpeg=[jpeg for s in seqs for jpeg in s["rgb_jpeg"]],
        depth_png=[png for s in seqs for png in s["depth_png"]],
        size_net_wh=tuple(size_wh),
        uv=np.concatenate([normalise_uv(s["joints_uv_px"], _camera_wh(s)) for s in seqs]).astype(np.float32),
        intrinsics=np.concatenate(
            [n * np.asarray(s["camera"]["intrinsics"]) for n, s in zip(per_frame, seqs, strict=True)]
        ),
        size_wh=np.concatenate([n * np.asarray(_camera_wh(s)) for n, s in zip(per_frame, seqs, strict=True)]),
        joints_cam_m=np.concatenate([s["joints_cam_m"] for s in seqs]),
        visible=np.concatenate([s["visible"] for s in seqs]),
    )


def lift_torch(
    uv: torch.Tensor, depth_m: torch.Tensor, intrinsics: torch.Tensor, cam_wh: torch.Tensor
) -> torch.Tensor:
    """Torch twin of :func:`egoposevr.model.inputs.lift_keypoints`: uv (B, J, 2), depth_m (B, J) with each
    sample's intrinsics (B, 4) and image size (B, 2) -> (B, J, 3)."""
    fx, fy, cx, cy = (intrinsics[:, k, None] for k in range(4))
    u = uv[..., 0] * cam_wh[:, 0, None] - 0.5
    v = uv[..., 1] * cam_wh[:, 1, None] - 0.5
    return torch.stack([(u - cx) / fx * depth_m, (v - cy) / fy * depth_m, depth_m], dim=-1)


def visual_loss_fn(net: KeypointNet, data: VisualData, tc: TrainConfig):
    cfg = net.cfg
    dev = torch.device(tc.device)
    hw, hh = cfg.heatmap_wh
    gu = ((torch.arange(hw) + 0.5) / hw).to(dev)
    gv = ((torch.arange(hh) + 0.5) / hh).to(dev)
    sigma_u, sigma_v = tc.heatmap_sigma_cells / hw, tc.heatmap_sigma_cells / hh

    def loss(rng: np.random.Generator) -> dict[str, torch.Tensor]:
        idx = rng.integers(0, len(data), tc.batch)
        rgb, depth, uv_np, visible, intrinsics_np, size_np, joints_np = crop_and_flip(
            rng, *data.frames(idx), data.uv[idx], data.visible[idx], data.intrinsics[idx],
            data.size_wh[idx], data.joints_cam_m[idx], crop_p=tc.crop_p, flip_p=tc.mirror_p,
        )  # fmt: skip
        image = torch.from_numpy(network_input(rgb, depth, cfg.channels)).to(dev)
        uv_t = torch.from_numpy(uv_np).to(dev)
        vis = torch.from_numpy(visible).float().to(dev)
        uv, depth_m, zeta, logits = net(image)
        # Gaussian target distribution on the heatmap grid, (B, J, hh, hw)
        du = (gu[None, None, None, :] - uv_t[..., 0, None, None]) / sigma_u
        dv = (gv[None, None, :, None] - uv_t[..., 1, None, None]) / sigma_v
        target = torch.exp(-0.5 * (du**2 + dv**2))
        target = target / target.flatten(2).sum(-1).clamp_min(1e-8)[..., None, None]
        log_p = torch.log_softmax(logits.flatten(2), -1).view_as(logits)
        n_vis = vis.sum().clamp_min(1.0)
        heat = -((target * log_p).flatten(2).sum(-1) * vis).sum() / n_vis
        intrinsics = torch.from_numpy(intrinsics_np).float().to(dev)
        xyz = lift_torch(uv, depth_m, intrinsics, torch.from_numpy(size_np).float().to(dev))
        joints = torch.from_numpy(joints_np).to(dev)
        pos = ((xyz - joints).abs().sum(-1) * vis).sum() / n_vis
        bce = F.binary_cross_entropy(zeta.clamp(1e-6, 1 - 1e-6), vis)
        return {"heat": heat * 0.1, "pos": pos * tc.position_weight, "vis": bce}

    return loss


def train_visual(
    kind: str,
    data: Path | Sequence[Path],
    out_dir: Path,
    tc: TrainConfig,
    resume: bool = False,
    progress: bool = True,
    seqs: list[dict[str, Any]] | None = None,
    initial: InitialVisual | None = None,
    invocation: dict[str, Any] | None = None,
) -> Path:
    """Stage 1 for one modality -> ``out_dir/visual-<kind>.pt``; with ``initial``, a fine-tune of that
    encoder (its batch norms' statistics frozen, the learning rate FINE_TUNE_LR_SCALE of the preset's)."""
    path = out_dir / f"visual-{kind}.pt"
    data_dirs = dataset_dirs(data)
    seqs = seqs if seqs is not None else training_sequences(data_dirs, tc)
    if resume and _finished(path, tc, seqs):
        return path
    torch.manual_seed(tc.seed)
    cfg = visual_config(kind, tc)
    net = KeypointNet(cfg).to(tc.device)
    camera = split_camera(data_dirs[0], "train")  # the encoder's default camera: the first dataset's
    frames = load_visual_data(seqs, (cfg.width, cfg.height))
    meta = {"kind": "visual", "name": f"visual-{kind}", "config": to_fields(cfg), "camera": camera,
            "data": _data_field(data_dirs, tc, seqs, frames=len(frames))}  # fmt: skip
    if initial is not None:
        net.load_state_dict(initial.state_dict)
        net.freeze_statistics()
        digest = provenance.file_digest(initial.source)
        meta["init"] = {"from": initial.source, "sha256": digest}
        meta["ancestors"] = provenance.ancestry(digest, initial.training)
        tc = dataclasses.replace(tc, lr=tc.lr * FINE_TUNE_LR_SCALE)
    loss_fn = visual_loss_fn(net, frames, tc)
    _run_steps(net, loss_fn, path, tc.visual_steps, tc, meta, resume, progress, invocation)
    return path


# ----------------------------------------------------------------------------------------- stage 2
@dataclasses.dataclass
class FusionSequence:
    """One sequence prepared for stage 2. N headset samples, K camera frames. The targets at sample i (the
    rotations, the joints, their head anchor and the contacts) are the truth's at ``led_samples(t_us,
    tc.target_lead_ms)[i]`` (i itself without a lead), in sample i's heading frame."""

    hmd: np.ndarray  # (N, 72 + 6) world-frame features, then the tracking state (nets without it read 72)
    valid: np.ndarray  # (N, 3) bool: devices tracked
    head_pose: np.ndarray  # (N, 7) measured headset poses
    t_us: np.ndarray  # (N,)
    target_sixd: np.ndarray  # (N, J, 6): pelvis in the heading frame, then local rotations
    joints_h: np.ndarray  # (N, J, 3) ground truth in the heading frame
    anchor_h: np.ndarray  # (N, 3) head joint from the headset, heading frame
    offsets: np.ndarray  # (J, 3) the body's bone offsets
    frame_t_us: np.ndarray  # (K,) capture times
    arrival_us: np.ndarray  # (K,) capture + latency
    kp_world: np.ndarray  # (K, J, 3) stage-1 keypoints in the world
    confidence: np.ndarray  # (K, J) Alg. 1 confidence
    contact: np.ndarray  # (N, 2) float32: each foot (left, right) on the floor in the truth
    timing: np.ndarray  # (N, 2, 2) float32: each foot's time to its next contact change and since its last


class ExportedEncoder:
    """An exported visual encoder (``visual-<kind>.onnx``, e.g. the bundled one) standing in for its
    checkpoint in stage 2: fusion nets then train on exactly the keypoints it serves."""

    def __init__(self, path: Path, threads: int = 0) -> None:
        self.session, metadata = load_encoder(path, threads)
        self.cfg = metadata.config
        self.training = metadata.training  # its training record (data, steps, ...)

    def __call__(self, image: np.ndarray) -> list[np.ndarray]:
        """image (B, C, h, w) float32 -> [uv (B, J, 2), depth_m (B, J), zeta (B, J)]."""
        return self.session.run(["uv", "depth_m", "zeta"], {"image": image})


class OutOfFoldEncoders:
    """Exported encoders that each left one fold of the training people out (``train --hold-out K/N``):
    each training sequence's keypoints come from the encoder that never saw its person, so that fusion nets
    learn from keypoints as far off as a new person's, not from the encoder's own training frames
    (MODEL_CARD.md, "Folds hide a new person from the nets, not from the camera").

    Built over the run's training sequences, which must be the data the encoders split: each encoder's
    recorded people (the digest of those it trained on) must be what its fold leaves of them, and every
    person must be left out by one of them. Raises DatasetError otherwise."""

    def __init__(self, paths: Sequence[Path], seqs: list[dict[str, Any]], threads: int = 0) -> None:
        encoders = [ExportedEncoder(p, threads) for p in paths]
        self.cfg = encoders[0].cfg
        self._by_person: dict[str, ExportedEncoder] = {}
        for path, encoder in zip(paths, encoders, strict=True):
            data = encoder.training.get("data") or {}
            if encoder.cfg != self.cfg:
                raise DatasetError(f"{path}: configured otherwise than {paths[0]}")
            if not data.get("held_out_fold"):
                raise DatasetError(f"{path}: it left no fold of people out (train --hold-out K/N)")
            held = fold_members(seqs, Fold.parse(data["held_out_fold"]))
            if _people_digest([s for s, h in zip(seqs, held, strict=True) if not h]) != data.get(
                "trained_subjects_sha256"
            ):
                raise DatasetError(
                    f"{path}: it trained on other people than fold {data['held_out_fold']} of this data leaves"
                )
            for seq in (s for s, h in zip(seqs, held, strict=True) if h):
                self._by_person.setdefault(sequence_subject(seq), encoder)
        unseen = sorted({sequence_subject(s) for s in seqs} - set(self._by_person))
        if unseen:
            raise DatasetError(
                f"no encoder left out {', '.join(unseen)}: each person needs one that did not see them"
            )

    def for_sequence(self, seq: dict[str, Any]) -> ExportedEncoder:
        """The encoder that never saw this sequence's person."""
        return self._by_person[sequence_subject(seq)]


@torch.no_grad()
def predict_keypoints(
    net: KeypointNet | ExportedEncoder, rgb: np.ndarray, depth: np.ndarray, batch: int = 256
) -> tuple[np.ndarray, ...]:
    """Stage-1 outputs for frames (K, h, w, 3) / (K, h, w) -> uv (K, J, 2), depth_m (K, J), zeta (K, J)."""
    outs = []
    device = None if isinstance(net, ExportedEncoder) else next(net.parameters()).device
    for s in range(0, len(rgb), batch):
        image = network_input(rgb[s : s + batch], depth[s : s + batch], net.cfg.channels)
        if device is None:
            outs.append(net(image))
        else:
            outs.append([t.cpu().numpy() for t in net(torch.from_numpy(image).to(device))[:3]])
    return (
        tuple(np.concatenate([o[i] for o in outs]) for i in range(3))
        if outs
        else (np.zeros((0, net.cfg.joints, 2)), np.zeros((0, net.cfg.joints)), np.zeros((0, net.cfg.joints)))
    )


def frame_keypoints(
    uv: np.ndarray,
    depth_m: np.ndarray,
    zeta: np.ndarray,
    frame_t_us: np.ndarray,
    camera: dict[str, Any],
    hmd_t_us: np.ndarray,
    head_pose: np.ndarray,
    truth_cam_m: np.ndarray | None = None,
    error_gain: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Stage-1 outputs of a sequence's frames -> world keypoints (K, J, 3) and Alg. 1 confidence (K, J),
    exactly as the runtime computes them frame by frame (head pose = the nearest headset sample). With
    ``truth_cam_m`` (K, J, 3), the true joints in the camera, each keypoint's error against them is first
    scaled by ``error_gain``: the same mistakes, larger."""
    cam = lift_keypoints(uv, depth_m, camera["intrinsics"], (camera["width"], camera["height"]))
    if truth_cam_m is not None and error_gain != 1.0:
        cam = truth_cam_m + error_gain * (cam - truth_cam_m)
    heads = head_pose[nearest_sample(frame_t_us, hmd_t_us)]
    world = camera_to_world(cam, heads, np.asarray(camera["cam_from_head"]).reshape(4, 4))
    vis_filter = VisibilityFilter()
    conf = (
        np.stack([vis_filter(int(t), z) for t, z in zip(frame_t_us, zeta, strict=True)])
        if len(zeta)
        else zeta
    )
    return world, conf


def _cached(cache: dict[Any, Any] | None, key: Any, compute: Callable[[], Any]) -> Any:
    """``compute()`` once per key across the zoo's fusion nets (no cache: every time)."""
    if cache is None:
        return compute()
    if key not in cache:
        cache[key] = compute()
    return cache[key]


def prepare_fusion_sequence(
    seq: dict[str, Any],
    rng: np.random.Generator,
    tc: TrainConfig,
    visual: KeypointNet | ExportedEncoder | OutOfFoldEncoders | None,
    cache: dict[Any, Any] | None = None,
    rig_offsets_m: np.ndarray = DEFAULT_OFFSETS_M,
) -> FusionSequence:
    """Stage-2 arrays of one sequence; ``cache`` keeps HMD features and stage-1 predictions across zoo models.
    The joints are anchored at the head joint that ``rig_offsets_m`` (3, 3) put under the headset, as the
    runtime anchors a model trained with them."""
    t_us, poses = seq["hmd_t_us"], seq["hmd_poses"].astype(np.float64)
    rot, origin = heading_frame(poses[:, 0])
    local = quat_xyzw_to_matrix(seq["gt_local_quat"].astype(np.float64))  # (N, J, 3, 3), pelvis in the world
    head_joint = joints_from_devices(poses, rig_offsets_m)[0][:, 0]
    K, J = len(seq["cam_t_us"]), local.shape[1]
    kp_world, conf = np.zeros((K, J, 3)), np.zeros((K, J))
    if visual is not None and K:
        size = (visual.cfg.width, visual.cfg.height)
        shot = seq.get("mirror_of", seq)  # whose headset the images were taken from
        encoder = visual.for_sequence(shot) if isinstance(visual, OutOfFoldEncoders) else visual
        uv, depth_m, zeta = _cached(
            cache,
            (visual.cfg.channels, seq.get("images_key", seq["key"])),
            lambda: predict_keypoints(encoder, *decode_frames(shot, size)),
        )
        gain = tc.keypoint_error_gain
        truth_cam_m = None if gain == 1.0 else np.asarray(shot["joints_cam_m"], dtype=np.float64)
        kp_world, conf = frame_keypoints(
            uv, depth_m, zeta, shot["cam_t_us"], shot["camera"], shot["hmd_t_us"],
            shot["hmd_poses"][:, 0].astype(np.float64), truth_cam_m, gain,
        )  # fmt: skip
        if shot is not seq:
            kp_world, conf = mirror_world_keypoints(kp_world, conf)
        if seq.get("arms_unseen"):  # the images show another person's arms than the truth's
            conf[:, ARM_JOINTS] = 0.0
    latency_us = rng.uniform(*tc.camera_latency_ms) * 1000
    contact = contacts(seq["gt_joints_m"], t_us)
    ahead = led_samples(t_us, tc.target_lead_ms)
    target_local = local[ahead]  # a copy (fancy indexing)
    target_local[:, 0] = np.swapaxes(rot, -1, -2) @ target_local[:, 0]  # the later pelvis, this heading frame
    return FusionSequence(
        hmd=_cached(
            cache,
            ("hmd", seq["key"]),
            lambda: np.concatenate(
                [hmd_features(t_us, poses, seq["hmd_valid"]), tracking_features(t_us, seq["hmd_valid"])],
                axis=-1,
            ).astype(np.float32),
        ),
        valid=np.asarray(seq["hmd_valid"], dtype=bool),
        head_pose=poses[:, 0],
        t_us=t_us,
        target_sixd=matrix_to_sixd(target_local).astype(np.float32),
        joints_h=to_heading(seq["gt_joints_m"][ahead].astype(np.float64), rot, origin).astype(np.float32),
        anchor_h=to_heading(head_joint[ahead, None], rot, origin)[:, 0].astype(np.float32),
        offsets=rest_offsets(seq["bone_scale"]).astype(np.float32),
        frame_t_us=seq["cam_t_us"],
        arrival_us=(seq["cam_t_us"] + latency_us).astype(np.int64),
        kp_world=kp_world,
        confidence=conf,
        contact=contact[ahead].astype(np.float32),
        timing=contact_timing(contact, t_us)[ahead].astype(np.float32),
    )


def led_samples(t_us: np.ndarray, lead_ms: float) -> np.ndarray:
    """(N,) for each sample of t_us (N,) the first sample at least lead_ms later (the last one near the
    end): whose pose a net trained with ``TrainConfig.target_lead_ms`` answers at it. 0 ms: each itself."""
    if lead_ms <= 0:
        return np.arange(len(t_us))
    later = np.searchsorted(t_us, np.asarray(t_us, dtype=np.float64) + lead_ms * 1000.0, side="left")
    return np.minimum(later, len(t_us) - 1)


def sample_window(
    fs: FusionSequence, i: int, cfg: FusionConfig, rng: np.random.Generator | None, tc: TrainConfig
):
    """Inputs at headset sample i, as the runtime builds them: hmd (T, 72) and visual tokens (Tv, 90)."""
    first = _stream_start(i, cfg, rng, tc)
    idx = np.clip(np.arange(i - cfg.window + 1, i + 1), first, None)  # the runtime pads with the first sample
    rot, origin = heading_frame(fs.head_pose[i])
    hmd = canonicalize_hmd(fs.hmd[idx, : hmd_input_dim(cfg.device_validity)], rot, origin)
    now = int(fs.t_us[i])
    arrived = int(np.searchsorted(fs.arrival_us, now, side="right"))
    frames = visual_window(fs.frame_t_us[:arrived], now, cfg.visual_window)
    if first > 0:  # a stream begun at sample `first` has only the frames captured since
        frames = frames[fs.frame_t_us[frames] >= fs.t_us[first]]
    if rng is not None and len(frames):
        if rng.random() < tc.drop_camera_p:
            frames = frames[:0]
        else:
            frames = frames[rng.random(len(frames)) >= tc.drop_frame_p]
    age_s = (now - fs.frame_t_us[frames]) * 1e-6
    tokens = visual_tokens(fs.kp_world[frames], fs.confidence[frames], age_s, cfg.visual_window, rot, origin)
    return hmd, tokens


def _stream_start(i: int, cfg: FusionConfig, rng: np.random.Generator | None, tc: TrainConfig) -> int:
    """The sample that the stream a window at sample i belongs to began at: the sequence's first, or, for
    ``tc.cold_start_p`` of the windows, a sample drawn uniformly among the window's own (a session that began
    0 to ``cfg.window`` - 1 samples ago). No draw is made while ``cold_start_p`` is 0, so earlier recipes keep
    their random streams."""
    if rng is None or tc.cold_start_p <= 0.0 or rng.random() >= tc.cold_start_p:
        return 0
    return max(i - int(rng.integers(0, cfg.window)), 0)


def fusion_loss_fn(
    net: FusionNet,
    seqs: list[FusionSequence],
    tc: TrainConfig,
    teacher: SeedEnsemble | None = None,
    keeper: FusionNet | None = None,
):
    """The fusion net's loss terms on a random batch. With ``teacher`` (frozen nets that read the same
    inputs), each term is split: ``1 - tc.distill_weight`` of it against the truth, the rest (keys
    ``*_teacher``) against the teacher's output: its rotations, its joints and its contact probabilities.
    With ``keeper`` (the frozen net a fine-tune starts from) the term ``keep_upper`` adds
    ``tc.keep_upper_weight`` times the upper body's fit against the keeper's output (:func:`upper_body_term`)."""
    cfg = net.cfg
    dev = torch.device(tc.device)
    lengths = np.array([len(s.t_us) for s in seqs])
    weights = lengths / lengths.sum()

    def batch(rng: np.random.Generator):
        which = rng.choice(len(seqs), tc.batch, p=weights)
        items = [(seqs[s], int(rng.integers(0, lengths[s]))) for s in which]
        if _uses_pairs(tc):
            items, inputs = _with_previous_samples(items, rng, cfg, tc)
        else:
            inputs = [sample_window(fs, i, cfg, rng, tc) for fs, i in items]
        hmd = torch.from_numpy(np.stack([x[0] for x in inputs]))
        vis = torch.from_numpy(np.stack([x[1] for x in inputs]))
        target = torch.from_numpy(np.stack([fs.target_sixd[i] for fs, i in items]))
        joints = torch.from_numpy(np.stack([fs.joints_h[i] for fs, i in items]))
        anchor = torch.from_numpy(np.stack([fs.anchor_h[i] for fs, i in items]))
        offsets = torch.from_numpy(np.stack([fs.offsets for fs, _ in items]))
        lost = np.stack([~fs.valid[i, 1:] for fs, i in items])  # (B, 2) left, right controller lost
        weight = np.ones((len(items), cfg.joints), dtype=np.float32)
        weight[:, FOOT_JOINTS] = tc.foot_weight
        for side, arm in enumerate(LOST_HAND_JOINTS):
            weight[np.ix_(lost[:, side], arm)] = tc.lost_hand_weight
        contact = torch.from_numpy(np.stack([fs.contact[i] for fs, i in items]))
        weight_t = torch.from_numpy(weight / weight.mean(1, keepdims=True))
        tensors = (hmd, vis, target, joints, anchor, offsets, weight_t, contact)
        if cfg.timing_head:
            tensors += (torch.from_numpy(np.stack([fs.timing[i] for fs, i in items])),)
        if tc.skate_weight > 0:  # only the skating term needs each window's frame (B, 3, 3)
            heading = np.stack([fs.head_pose[i] for fs, i in items])
            tensors += (torch.from_numpy(heading_frame(heading)[0].astype(np.float32)),)
        return tuple(t.to(dev, non_blocking=True) for t in tensors)

    def loss(rng: np.random.Generator) -> dict[str, torch.Tensor]:
        hmd, vis, target, joints, anchor, offsets, weight, contact, *rest = batch(rng)
        timing_wanted, world_from_heading = (rest[0], rest[1:]) if cfg.timing_head else (None, rest)
        visual = vis if cfg.uses_camera else None
        timing = None
        if cfg.timing_head:
            sixd, contact_logits, timing = net.forward_with_timing(hmd, visual)
        elif cfg.contact_head:
            sixd, contact_logits = net.forward_with_contact(hmd, visual)
        else:
            sixd, contact_logits = net(hmd, visual), None
        pos = _anchored_joints(sixd, anchor, offsets)
        losses = _fit_terms(sixd, pos, contact_logits, (target, joints, contact), weight, tc)
        if timing is not None:
            losses["timing"] = (timing - timing_wanted).abs().mean() * tc.timing_weight
        error = pos - joints  # with pairs (2B, J, 3): each window's, then the previous sample's
        if tc.temporal_weight > 0:
            now, before = error.chunk(2)
            losses["temporal"] = (now - before).abs().sum(-1).mean() * tc.temporal_weight
        if tc.skate_weight > 0:
            losses["skate"] = skate_term(error, world_from_heading[0], contact) * tc.skate_weight
        if keeper is not None:
            with torch.no_grad():
                kept, kept_contact = (
                    keeper.forward_with_contact(hmd, visual)
                    if cfg.contact_head
                    else (keeper(hmd, visual), None)
                )
            kept_terms = upper_body_term(sixd, pos, kept, anchor, offsets, tc)
            if tc.keep_joints == "arms_legs" and kept_contact is not None:
                kept_terms = kept_terms + kept_contact_term(contact_logits, kept_contact) * tc.contact_weight
            losses["keep_upper"] = kept_terms * tc.keep_upper_weight
        if teacher is None:
            return losses
        with torch.no_grad():
            taught = teacher(hmd, visual)
            t_sixd, t_contact = taught if cfg.contact_head else (taught, None)
            t_pos = _anchored_joints(t_sixd, anchor, offsets)
        mimic = _fit_terms(sixd, pos, contact_logits, (t_sixd, t_pos, t_contact), weight, tc)
        share = tc.distill_weight
        fitted = {k: v * (1 - share) if k in mimic else v for k, v in losses.items()}
        return fitted | {f"{k}_teacher": v * share for k, v in mimic.items()}

    return loss


def _uses_pairs(tc: TrainConfig) -> bool:
    """Whether each batch also holds every window's sample before (the temporal and skating terms)."""
    return tc.temporal_weight > 0 or tc.skate_weight > 0


def skate_term(error: torch.Tensor, world_from_heading: torch.Tensor, contact: torch.Tensor) -> torch.Tensor:
    """How far the served feet slide while the true feet are down: for joint errors (2B, J, 3) in each
    window's heading frame (world_from_heading (2B, 3, 3)), the B windows then the B a sample before them,
    the L1 (m) of each foot's error change in the world, where contact (2B, 2) has that foot down at both
    samples; summed over the feet, mean over the B pairs. The truth's own motion cancels: only the served
    foot's motion beyond the true foot's counts."""
    feet_world = error[:, list(FEET)] @ world_from_heading.transpose(-1, -2)  # (2B, 2, 3)
    now, before = feet_world.chunk(2)
    down_now, down_before = contact.chunk(2)
    return ((now - before).abs().sum(-1) * down_now * down_before).sum(-1).mean()


def upper_body_term(
    sixd: torch.Tensor,
    pos: torch.Tensor,
    kept_sixd: torch.Tensor,
    anchor: torch.Tensor,
    offsets: torch.Tensor,
    tc: TrainConfig,
) -> torch.Tensor:
    """How far the upper body is from the one to keep (kept_sixd, (B, J, 6), no gradient): the L1 of the kept
    joints' 6D rotations (B, J, 6) and of their positions (B, J, 3, m, summed over x, y, z; mean over the
    joints), weighted as the truth's terms are (``tc.rotation_weight``, ``tc.position_weight``).
    ``tc.keep_joints`` (KEPT_JOINTS) "upper": UPPER_BODY's 13 joints, placed under the head at anchor (B, 3)
    (pos is sixd's so placed); "arms": ARM_JOINTS' 8, placed in the chest's frame from their own rotations
    and the bone offsets (B, J, 3), so that how the trunk leans is not kept; "arms_legs": those and
    LOWER_BODY's 9, placed in the pelvis's frame turned as the pelvis is (:func:`_limbs_unanchored`)."""
    if tc.keep_joints in TRUNK_FREE_KEEPS:
        pos, kept_pos = (
            _limbs_unanchored(sixd, offsets, tc.keep_joints),
            _limbs_unanchored(kept_sixd, offsets, tc.keep_joints),
        )
    else:
        kept_pos = _anchored_joints(kept_sixd, anchor, offsets)
    kept = torch.as_tensor(KEPT_JOINTS[tc.keep_joints], device=sixd.device)
    rot = (sixd[:, kept] - kept_sixd[:, kept]).abs().mean()
    joints = (pos[:, kept] - kept_pos[:, kept]).abs().sum(-1).mean()
    return rot * tc.rotation_weight + joints * tc.position_weight


def _limbs_unanchored(sixd: torch.Tensor, offsets: torch.Tensor, keep_joints: str) -> torch.Tensor:
    """Joints (B, J, 3) of the rotations sixd (B, J, 6) where the trunk's are left out: the arms' in the
    chest's own frame (every joint but ARM_JOINTS unrotated, less the chest's, spine3's), which its lean does
    not move; with "arms_legs" the legs' too, in the pelvis's frame turned as the pelvis is (every joint but
    LOWER_BODY unrotated, less the pelvis's), which the head joint's place does not move."""
    pos = _only_rotated(sixd, offsets, ARM_JOINTS)
    placed = pos - pos[:, CHEST][:, None]
    if keep_joints == "arms_legs":
        legs = torch.as_tensor(LOWER_BODY, device=sixd.device)
        hung = _only_rotated(sixd, offsets, LOWER_BODY)
        placed[:, legs] = hung[:, legs] - hung[:, :1]
    return placed


def _only_rotated(sixd: torch.Tensor, offsets: torch.Tensor, joints: np.ndarray) -> torch.Tensor:
    """Joints (B, J, 3) on the bone offsets (B, J, 3) with only ``joints``' rotations of sixd (B, J, 6), the
    others unrotated, the pelvis at the origin."""
    chosen = torch.as_tensor(joints, device=sixd.device)
    rot = torch.eye(3, dtype=sixd.dtype, device=sixd.device).expand(*sixd.shape[:2], 3, 3).clone()
    rot[:, chosen] = sixd_to_matrix(sixd[:, chosen])
    pos, _ = forward_kinematics(rot, torch.zeros(len(sixd), 3, device=sixd.device), offsets)
    return pos


def kept_contact_term(contact_logits: torch.Tensor, kept_logits: torch.Tensor) -> torch.Tensor:
    """The binary cross-entropy of the contact logits (B, 2) against the probabilities of the kept ones
    (B, 2, no gradient): a fine-tune that lifts and plants the feet when its start did."""
    return F.binary_cross_entropy_with_logits(contact_logits, torch.sigmoid(kept_logits))


def _anchored_joints(sixd: torch.Tensor, anchor: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """Joints (B, J, 3) of the rotations sixd (B, J, 6) on the bone offsets (B, J, 3), the head at
    anchor (B, 3)."""
    pos, _ = forward_kinematics(sixd_to_matrix(sixd), torch.zeros(len(sixd), 3, device=sixd.device), offsets)
    return pos + (anchor - pos[:, HEAD])[:, None]


def _fit_terms(
    sixd: torch.Tensor,
    pos: torch.Tensor,
    contact_logits: torch.Tensor | None,
    wanted: tuple[torch.Tensor, torch.Tensor, torch.Tensor | None],
    weight: torch.Tensor,
    tc: TrainConfig,
) -> dict[str, torch.Tensor]:
    """L1 of the 6D rotations (raw, and as served if ``tc.served_rotation_weight``), weighted L1 of the joints
    (m) and the contact's cross-entropy against wanted = (rot6d (B, J, 6), joints (B, J, 3), contact (B, 2)
    probabilities or None)."""
    target, joints, contact = wanted
    rot_loss = (sixd - target).abs().mean()
    pos_loss = ((pos - joints).abs().sum(-1) * weight).mean()
    losses = {"rot": rot_loss * tc.rotation_weight, "pos": pos_loss * tc.position_weight}
    if tc.served_rotation_weight > 0:
        served = (orthonormal_sixd(sixd) - target).abs().mean()
        losses["rot_served"] = served * tc.served_rotation_weight
    if contact_logits is not None and contact is not None:
        bce = F.binary_cross_entropy_with_logits(contact_logits, contact)
        losses["contact"] = bce * tc.contact_weight
    return losses


def _with_previous_samples(
    items: list[tuple[FusionSequence, int]], rng: np.random.Generator, cfg: FusionConfig, tc: TrainConfig
) -> tuple[list[tuple[FusionSequence, int]], list[tuple[np.ndarray, np.ndarray]]]:
    """The B items' windows, then each one's window a headset sample earlier (2B of each), with the same
    camera-drop draws for a pair, so that what differs between the two is only time."""
    items = [(fs, max(i, 1)) for fs, i in items]
    seeds = rng.integers(0, 2**63, len(items))
    pairs = [*items, *[(fs, i - 1) for fs, i in items]]
    inputs = [
        sample_window(fs, i, cfg, np.random.default_rng(seed), tc)
        for (fs, i), seed in zip(pairs, [*seeds, *seeds], strict=True)
    ]
    return pairs, inputs


def train_fusion(
    name: str,
    data: Path | Sequence[Path],
    out_dir: Path,
    tc: TrainConfig,
    resume: bool = False,
    progress: bool = True,
    seqs: list[dict[str, Any]] | None = None,
    cache: dict[Any, Any] | None = None,
    encoders_dir: Path | None = None,
    teacher: Teacher | None = None,
    initial: InitialWeights | None = None,
    out_of_fold: Sequence[Path] = (),
    head_offsets_m: np.ndarray | None = None,
    invocation: dict[str, Any] | None = None,
) -> Path:
    """Stage 2 for one zoo entry -> ``out_dir/fusion-<name>.pt``. Its visual encoder is ``out_dir``'s
    checkpoint, or with ``encoders_dir`` that folder's exported ``visual-<kind>.onnx``, or with
    ``out_of_fold`` those folders' encoders, each sequence read by the one that never saw its person
    (:class:`OutOfFoldEncoders`). With ``teacher``
    (:func:`load_teacher`, for this entry's fusion net) it also learns the teacher's mean output. With
    ``initial`` the net starts from those weights (its input statistics included) instead of a random
    draw: a fine-tune, with this run's own warmup and schedule. The net is anchored at
    :func:`training_offsets` (``head_offsets_m`` where given, else the initial net's head offset, else the
    teachers', else the default)."""
    path = out_dir / f"fusion-{name}.pt"
    data_dirs = dataset_dirs(data)
    seqs = seqs if seqs is not None else training_sequences(data_dirs, tc)
    if resume and _finished(path, tc, seqs):
        return path
    entry = ZOO[name]
    visual: KeypointNet | ExportedEncoder | OutOfFoldEncoders | None = None
    encoder_files: list[Path] = []
    if entry.visual:
        visual, encoder_files = _stage_one(entry.visual, out_dir, encoders_dir, tc, out_of_fold, seqs)
    torch.manual_seed(tc.seed)
    cfg = fusion_config(name, tc)
    net = FusionNet(cfg)
    rng = np.random.default_rng([tc.seed, 7])
    offsets_m = training_offsets(initial, teacher, head_offsets_m, tc.reanchor)
    prepared = [prepare_fusion_sequence(s, rng, tc, visual, cache, offsets_m) for s in augmented(seqs, tc)]
    _set_statistics(net, prepared, tc, rng)
    if initial is not None:
        _load_start(net, initial.state_dict)
    net.to(tc.device)
    keeper = _upper_body_keeper(cfg, initial, tc)
    hmd_samples = int(sum(len(p.t_us) for p in prepared))
    meta = {"kind": "fusion", "name": name, "config": to_fields(cfg), "visual": entry.visual,
            "data": _data_field(data_dirs, tc, seqs, hmd_samples=hmd_samples),
            "rig_offsets_m": offsets_m.tolist()}  # fmt: skip
    if teacher is not None:
        meta["teachers"] = list(teacher.runs_dirs)
        files = [Path(d) / f"fusion-{name}.pt" for d in teacher.runs_dirs]  # what load_teacher read
        meta["teacher_files"] = [{"from": str(f), "sha256": provenance.file_digest(f)} for f in files]
    ancestors: dict[str, dict[str, Any]] = {}
    if encoder_files:  # the bytes its keypoints came from, and how an exported encoder was made
        meta["encoders"] = [{"from": str(f), "sha256": provenance.file_digest(f)} for f in encoder_files]
        for file, read in zip(encoder_files, meta["encoders"], strict=True):
            if file.suffix == ".onnx":
                ancestors |= provenance.ancestry(read["sha256"], load_encoder(file)[1].training)
    if initial is not None:
        digest = provenance.file_digest(initial.source)
        meta["init"] = {"from": initial.source, "member": initial.member, "sha256": digest}
        if tc.reanchor:  # the head joint its start hung the body from, which this net was moved away from
            meta["init"]["rig_offsets_m"] = [list(row) for row in initial.rig_offsets_m]
        ancestors |= provenance.ancestry(digest, initial.training)
    if ancestors:
        meta["ancestors"] = ancestors
        if keeper is not None:
            meta["init"]["keep_upper_weight"] = tc.keep_upper_weight
            meta["init"]["keep_joints"] = tc.keep_joints
    if out_of_fold and entry.visual:
        meta["keypoints_out_of_fold"] = [str(d) for d in out_of_fold]
    loss_fn = fusion_loss_fn(net, prepared, tc, teacher.nets if teacher is not None else None, keeper)
    _run_steps(net, loss_fn, path, tc.fusion_steps, tc, meta, resume, progress, invocation)
    return path


def _upper_body_keeper(
    cfg: FusionConfig, initial: InitialWeights | None, tc: TrainConfig
) -> FusionNet | None:
    """With ``tc.keep_upper_weight``: a frozen copy of the net a fine-tune starts from, whose upper body the
    fine-tune keeps (None when the weight is 0). TeacherError without a net to start from."""
    _check_keeps_a_start(initial, tc)
    if tc.keep_upper_weight <= 0:
        return None
    keeper = FusionNet(cfg.served)  # the file's net: it is only asked for the pose
    keeper.load_state_dict(initial.state_dict)
    return keeper.eval().requires_grad_(False).to(tc.device)


def _load_start(net: FusionNet, state: dict[str, torch.Tensor]) -> None:
    """A fine-tune's starting weights into ``net``: every weight must fit, but a training-only timing head
    (``FusionConfig.timing_head``), which no exported file holds, keeps its fresh initialisation."""
    missing, unexpected = net.load_state_dict(state, strict=False)
    unfilled = [key for key in missing if not key.startswith("timing_head.")]
    if unfilled or unexpected:
        raise ValueError(
            f"the starting net does not fit this one: missing {unfilled}, unexpected {unexpected}"
        )


def _check_keeps_a_start(initial: InitialWeights | None, tc: TrainConfig) -> None:
    """TeacherError when ``tc.keep_upper_weight`` asks to keep the upper body of a start there is not, or
    the trunk under the head of a start ``tc.reanchor`` moves to another head joint; ValueError when
    ``tc.keep_joints`` names no joints of KEPT_JOINTS."""
    if tc.keep_joints not in KEPT_JOINTS:
        raise ValueError(f"keep_joints must be one of {sorted(KEPT_JOINTS)}, got {tc.keep_joints!r}")
    if tc.keep_upper_weight > 0 and initial is None:
        raise TeacherError("keeping the upper body (--keep-upper) needs the net it starts from (--init-from)")
    if tc.keep_upper_weight > 0 and tc.reanchor and tc.keep_joints not in TRUNK_FREE_KEEPS:
        raise TeacherError(
            "--reanchor keeps no more than the arms and the legs (--keep-joints arms or arms_legs): the trunk "
            "under the head is what it moves"
        )


@dataclasses.dataclass(frozen=True)
class InitialVisual:
    """Where an encoder starts instead of a random draw (``egoposevr train --init-visual``): the weights of
    an exported encoder, its batch norms as folded (export.initial_visual_state)."""

    source: str  # the encoder file
    state_dict: dict[str, torch.Tensor]
    training: dict[str, Any] = dataclasses.field(default_factory=dict)  # the file's own training record


# A fine-tuned encoder's learning rate against the preset's: it starts from a trained net, whose features a
# full-size first step (after the warm-up) would shake loose before the new data could shape them.
FINE_TUNE_LR_SCALE: Final = 0.2


@dataclasses.dataclass(frozen=True)
class InitialWeights:
    """Where a fusion net starts instead of a random draw (``egoposevr train --init-from``): the weights of
    one net of an exported model file (export.initial_fusion_state)."""

    source: str  # the model file
    member: int  # which of its nets
    state_dict: dict[str, torch.Tensor]
    rig_offsets_m: tuple[tuple[float, ...], ...]  # (3, 3) the offsets the file's nets were trained with
    training: dict[str, Any] = dataclasses.field(default_factory=dict)  # the file's own training record


class TeacherError(ValueError):
    """Teachers that are missing, or that cannot read the student's inputs."""


@dataclasses.dataclass(frozen=True)
class Teacher:
    """What a student learns from: the frozen nets, the runs folders they came from (for its record), and
    the head offsets (3, 3) they were trained at, where their checkpoints record them (None where not)."""

    nets: SeedEnsemble
    runs_dirs: tuple[str, ...]
    rig_offsets_m: tuple[tuple[float, ...], ...] | None = None


_TEACHER_MUST_MATCH: Final = ("window", "device_validity", "fusion")


def load_teacher(
    fusion_name: str, runs_dirs: Sequence[Path], student: FusionConfig, device: str
) -> Teacher | None:
    """A :class:`Teacher`: the frozen :class:`SeedEnsemble` of each runs folder's ``fusion-<fusion_name>.pt``
    (None without folders). Its nets must read the student's inputs and, where the student predicts contact,
    predict it."""
    if not runs_dirs:
        return None
    paths = [Path(d) / f"fusion-{fusion_name}.pt" for d in runs_dirs]
    missing = [str(p) for p in paths if not p.exists()]
    if missing:
        raise TeacherError(f"no teacher checkpoint: {', '.join(missing)}")
    ckpts = [load_checkpoint(p) for p in paths]
    nets = [build_net(c, p) for c, p in zip(ckpts, paths, strict=True)]
    wanted = _TEACHER_MUST_MATCH + (("visual_window",) if student.uses_camera else ())
    wanted += ("contact_head",) if student.contact_head else ()
    for path, net in zip(paths, nets, strict=True):
        differ = [f for f in wanted if getattr(net.cfg, f) != getattr(student, f)]
        if differ:
            raise TeacherError(f"teacher {path} differs from the student in {', '.join(differ)}")
    try:
        ensemble = SeedEnsemble(nets)
    except ValueError as error:
        raise TeacherError(f"teachers {', '.join(map(str, runs_dirs))}: {error}") from error
    recorded = {tuple(map(tuple, c["rig_offsets_m"])) for c in ckpts if "rig_offsets_m" in c}
    if len(recorded) > 1:
        raise TeacherError(
            f"teachers {', '.join(map(str, runs_dirs))} were trained at different head offsets"
        )
    offsets = recorded.pop() if recorded else None
    return Teacher(ensemble.eval().requires_grad_(False).to(device), tuple(map(str, runs_dirs)), offsets)


def training_offsets(
    initial: InitialWeights | None,
    teacher: Teacher | None,
    chosen_m: np.ndarray | None = None,
    reanchor: bool = False,
) -> np.ndarray:
    """(3, 3) the head offsets a fusion net trains at (its anchor, recorded in its checkpoint and export): the
    offsets ``chosen_m`` (``--head-offsets-from``) where given; a net has learnt the body under its own head
    joint, so a fine-tune keeps the offsets of the net it starts from, and a student takes its teachers'
    (their joints, which it learns, hang from their head joint); otherwise today's default. With ``reanchor``
    a fine-tune's start does not choose: it moves to ``chosen_m``, its teachers' or the default. TeacherError
    when two of them are given and disagree."""
    theirs = None if teacher is None or teacher.rig_offsets_m is None else np.asarray(teacher.rig_offsets_m)
    mine = None if initial is None or reanchor else np.asarray(initial.rig_offsets_m, dtype=np.float64)
    if mine is not None and theirs is not None and not np.allclose(mine, theirs):
        raise TeacherError(
            f"{initial.source} was trained at other head offsets than the teachers "
            f"{', '.join(teacher.runs_dirs)}: a student would learn joints hung from another head joint"
        )
    if chosen_m is not None:
        for given, what in ((mine, "the net it starts from"), (theirs, "its teachers")):
            if given is not None and not np.allclose(given, chosen_m):
                raise TeacherError(
                    f"--head-offsets-from gives other head offsets than {what} were trained at: a net "
                    "has learnt the body under its own head joint"
                )
        return np.asarray(chosen_m, dtype=np.float64)
    if mine is not None:
        return mine
    return DEFAULT_OFFSETS_M if theirs is None else theirs.astype(np.float64)


def _stage_one(
    kind: str,
    out_dir: Path,
    encoders_dir: Path | None,
    tc: TrainConfig,
    out_of_fold: Sequence[Path] = (),
    seqs: list[dict[str, Any]] | None = None,
) -> tuple[KeypointNet | ExportedEncoder | OutOfFoldEncoders, list[Path]]:
    """Stage 2's encoder of ``kind`` (out-of-fold encoders, an exported one, or this run's checkpoint) and
    the files it was read from."""
    if out_of_fold:
        files = [d / f"visual-{kind}.onnx" for d in out_of_fold]
        return OutOfFoldEncoders(files, seqs or [], tc.threads), files
    if encoders_dir is not None:
        file = encoders_dir / f"visual-{kind}.onnx"
        return ExportedEncoder(file, tc.threads), [file]
    file = out_dir / f"visual-{kind}.pt"
    return load_net(file).to(tc.device), [file]


def augmented(seqs: list[dict[str, Any]], tc: TrainConfig) -> list[dict[str, Any]]:
    """Stage 2's sequences: each as recorded and, with ``mirror_p`` > 0, mirrored at a random speed (and with
    ``tracking_cone_deg``, tracked over a narrower cone; with ``hanging_loss_m``, losing hanging hands), and
    with ``arm_swap_p`` > 0 some again with another sequence's arms."""
    if tc.mirror_p <= 0:
        return list(seqs) + arm_swaps(seqs, tc)
    speeds = np.random.default_rng([tc.seed, 11]).uniform(*tc.speed_range, len(seqs))
    copies = [mirror_sequence(retime_sequence(s, v)) for s, v in zip(seqs, speeds, strict=True)]
    if tc.tracking_cone_deg is not None:
        cones = np.random.default_rng([tc.seed, 13]).uniform(*tc.tracking_cone_deg, len(seqs))
        copies = [narrow_tracking_cone(c, deg) for c, deg in zip(copies, cones, strict=True)]
    if tc.hanging_loss_m is not None:
        copies = [lose_hanging_arms(c, tc.hanging_loss_m) for c in copies]
    return list(seqs) + copies + arm_swaps(seqs, tc)


def arm_swaps(seqs: list[dict[str, Any]], tc: TrainConfig) -> list[dict[str, Any]]:
    """``tc.arm_swap_p`` of the sequences again, each with a random other sequence's arms from a random
    sample on, tracked over a cone drawn as the renders draw theirs (synth.headset.TRACKING_CONE_DEG)."""
    if tc.arm_swap_p <= 0 or len(seqs) < 2:
        return []
    rng = np.random.default_rng([tc.seed, 17])
    out = []
    for i, seq in enumerate(seqs):
        if rng.random() >= tc.arm_swap_p:
            continue
        donor = seqs[(i + int(rng.integers(1, len(seqs)))) % len(seqs)]
        start = int(rng.integers(0, len(donor["hmd_t_us"])))
        out.append(swap_arms(seq, donor, start, float(rng.uniform(*TRACKING_CONE_DEG))))
    return out


def _set_statistics(
    net: FusionNet, prepared: list[FusionSequence], tc: TrainConfig, rng: np.random.Generator
) -> None:
    """Input normalisation from 512 random training windows (no augmentation)."""
    lengths = np.array([len(p.t_us) for p in prepared])
    picks = [
        (prepared[s], int(rng.integers(0, lengths[s])))
        for s in rng.choice(len(prepared), 512, p=lengths / lengths.sum())
    ]
    inputs = [sample_window(fs, i, net.cfg, None, tc) for fs, i in picks]
    set_input_statistics(net.hmd_stream, torch.from_numpy(np.concatenate([x[0] for x in inputs])))
    if net.cfg.uses_camera:
        set_input_statistics(net.visual_stream, torch.from_numpy(np.concatenate([x[1] for x in inputs])))


def dataset_dirs(data: Path | Sequence[Path]) -> tuple[Path, ...]:
    """One dataset root or several (their train splits are used together) -> the roots."""
    return (Path(data),) if isinstance(data, str | Path) else tuple(Path(d) for d in data)


def training_sequences(data_dirs: tuple[Path, ...], tc: TrainConfig) -> list[dict[str, Any]]:
    """The train split of every dataset, without ``tc.hold_out``'s subjects or with only ``tc.train_fold``'s,
    at most ``tc.limit_sequences``."""
    hold_out = Fold.parse(tc.hold_out) if tc.hold_out else None
    only = Fold.parse(tc.train_fold) if tc.train_fold else None
    seqs = load_splits(data_dirs, "train", tc.limit_sequences, hold_out, only)
    if not seqs:
        which = f"with only fold {only}" if only else f"without fold {hold_out}"
        raise DatasetError(f"no train sequence is left to train on {which}")
    return seqs


def _data_field(
    data_dirs: tuple[Path, ...], tc: TrainConfig, seqs: list[dict[str, Any]], **counts: int
) -> dict[str, Any]:
    """A checkpoint's ``data`` record: the folders, the digest of their training shards' bytes, the fold left
    out or kept alone and the people who trained (when a fold decides them), the sequences and other counts."""
    held = {"held_out_fold": tc.hold_out} if tc.hold_out else {}
    held |= {"trained_fold": tc.train_fold} if tc.train_fold else {}
    held |= {"trained_subjects_sha256": _people_digest(seqs)} if held else {}
    digests = {
        "sha256": provenance.data_digest(data_dirs),
        "folders_sha256": [provenance.folder_digest(d) for d in data_dirs],
    }
    return {"dir": _dirs_field(data_dirs), **digests, **held, "sequences": len(seqs), **counts}


def _dirs_field(data_dirs: tuple[Path, ...]) -> str | list[str]:
    """The checkpoint's record of its data: one folder as before, several as a list."""
    return str(data_dirs[0]) if len(data_dirs) == 1 else [str(d) for d in data_dirs]


class DeviceError(ValueError):
    """The training device is not one torch can train on here (a user's error)."""


def check_device(device: str) -> None:
    """Raise DeviceError when ``device`` is not one torch can train on here."""
    if device == "cpu":
        return
    if device != "cuda":
        raise DeviceError(f"unknown training device {device!r}: use cpu or cuda")
    if not torch.cuda.is_available():
        raise DeviceError(
            "--device cuda: this torch has no CUDA device (the CPU wheel, or no GPU); use --device cpu"
        )


def train_zoo(
    names: list[str],
    data: Path | Sequence[Path],
    out_dir: Path,
    tc: TrainConfig,
    resume: bool = False,
    progress: bool = True,
    encoders_dir: Path | None = None,
    teachers: Sequence[Path] = (),
    initial: dict[str, InitialWeights] | None = None,
    initial_visual: dict[str, InitialVisual] | None = None,
    out_of_fold: Sequence[Path] = (),
    head_offsets_m: np.ndarray | None = None,
    command: Sequence[str] | None = None,
) -> dict[str, Path]:
    """Everything the named models need, in dependency order: visual encoders, then fusion nets. With
    ``encoders_dir`` the fusion nets read that folder's exported encoders and none is trained; with
    ``teachers`` each fusion net also learns the mean output of those runs folders' nets of its kind;
    ``initial`` maps a fusion net's name to the weights it starts from, ``initial_visual`` an encoder's kind
    ("rgb", "rgbd") to the exported encoder it is fine-tuned from; with ``out_of_fold`` (folders of encoders
    that each left a fold of people out) the fusion nets read each sequence's keypoints from the one that
    never saw its person, and none is trained; ``head_offsets_m`` (3, 3) the offsets the fusion nets train
    at instead of :func:`training_offsets`' choice; ``command`` the command line each checkpoint records (one
    invocation record for every net this call trains)."""
    check_device(tc.device)
    out_dir.mkdir(parents=True, exist_ok=True)
    if tc.threads:
        torch.set_num_threads(tc.threads)
    fusions = fusion_names(names)
    visuals = [k for k in ("rgb", "rgbd") if any(ZOO[f].visual == k for f in fusions)]
    # Loaded first: teachers that cannot teach are an error now, not after the encoders have trained.
    taught = {f: load_teacher(f, teachers, fusion_config(f, tc), tc.device) for f in fusions}
    for f in fusions:  # refused now, too: a fine-tune and teachers at different head offsets, nothing to keep
        training_offsets((initial or {}).get(f), taught[f], head_offsets_m, tc.reanchor)
        _check_keeps_a_start((initial or {}).get(f), tc)
    data_dirs = dataset_dirs(data)
    if out_of_fold and (tc.hold_out or tc.train_fold or len(data_dirs) > 1):
        raise DatasetError(
            "out-of-fold encoders read one dataset's whole train split (no --hold-out or --train-fold, one "
            "--data)"
        )
    seqs = training_sequences(data_dirs, tc)
    invocation = invocation_record(command, tc.device)
    paths = {}
    if encoders_dir is None and not out_of_fold:
        paths = {
            f"visual-{k}": train_visual(
                k, data_dirs, out_dir, tc, resume, progress, seqs, (initial_visual or {}).get(k), invocation
            )
            for k in visuals
        }
    cache: dict[Any, Any] = {}  # HMD features and stage-1 keypoints, shared by the fusion nets
    for f in fusions:
        paths[f"fusion-{f}"] = train_fusion(
            f, data_dirs, out_dir, tc, resume, progress, seqs, cache, encoders_dir, taught[f],
            (initial or {}).get(f), out_of_fold, head_offsets_m, invocation,
        )  # fmt: skip
    return paths
