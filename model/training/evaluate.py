"""Evaluation of the served runtime (DESIGN §6): what a client would receive, replayed over a dataset split.

Each sequence is played through a fresh :class:`~egoposevr.model.runtime.Pipeline` in arrival order: a
camera frame is pushed once it would have arrived (capture + ``CAMERA_LATENCY_US``), every headset sample
asks for a pose. Metrics, per the paper's Tables 2-3:

- MPJPE (cm): mean joint position error of the served world joints, no alignment; upper / lower body;
- PA-MPJPE (cm): the same after a per-frame similarity Procrustes fit over all 22 joints;
- MPJRE (deg): geodesic angle between served and true local rotations (row 0: pelvis global);
- H-PE (cm): wrists' position error; H-PE lost: the same over the wrists whose controller is lost at that
  sample (``lost_share``: how often that is);  Jitter (m/s³): mean norm of the third time derivative of positions;
- Facing (deg): geodesic angle between the served and true GLOBAL rotations of the head and of the wrists
  (which way the face looks and the hands point: what a viewer sees, which MPJRE's local angles do not say);
- Body height (%): how far the standing head height (runtime.body.standing_head_height_m) of the wearer's body
  as the session knows it at a sequence's end (``served_body``: the running estimate the served skeleton
  follows, or a body given) is from the truth's, a mean over sequences: the body estimate's error (0 with
  ``truth_body``);
- FPS: one stream, batch 1, a NEW RGB-D frame before every headset sample (decode + visual encoder
  included), wall clock, median of ``FPS_REPEATS`` runs.

Shape legend: ``N`` headset samples, ``J`` = 22 joints.
"""

from __future__ import annotations

import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Final

import numpy as np

from ..inputs import decode_rgbd
from ..rig import TRACKED_JOINTS, joints_from_devices
from ..rotations import geodesic_angle, quat_xyzw_to_matrix
from ..runtime.body import standing_head_height_m
from ..runtime.calibration import DEFAULT_SECONDS, Calibration, CalibrationCollector
from ..runtime.frames import (
    FIRST_FRAME_WAIT_US,
    LOW_HEAD_WAIT_ON,
    LOW_HEAD_WAIT_US,
    FirstAnswerWait,
    encode_frame,
    first_answer_wait,
)
from ..runtime.loading import DEFAULT_PROVIDERS, LoadedModel
from ..runtime.pipeline import Pipeline, PoseResult, run_fusion
from ..runtime.procedural import ProceduralModel, pipeline_for
from ..skeleton import JOINT_INDEX, LOWER_BODY, NUM_JOINTS, UPPER_BODY, forward_kinematics, pelvis_over_legs
from . import intervals
from .dataset import DatasetError, Fold, load_fold, load_split, sequence_subject
from .plausibility import add_totals, contacts, plausibility, plausibility_totals, pooled_means, total

CAMERA_LATENCY_US = 25_000  # capture -> arrival, as in the recorded sessions
FPS_SAMPLES = 200
FPS_REPEATS = 3
METRIC_KEYS = (
    "mpjpe_u_cm", "mpjpe_l_cm", "pa_mpjpe_u_cm", "pa_mpjpe_l_cm", "mpjre_u_deg", "mpjre_l_deg", "hpe_cm",
    "hpe_lost_cm", "lost_share", "facing_head_deg", "facing_hands_deg",
    "jitter", "foot_skate_cm_s", "foot_skate_settled_cm_s", "floor_float_cm", "floor_penetration_cm",
    "leg_leakage_cm", "leg_leakage_settled_cm", "leg_wander_cm", "jerk", "jerk_true", "jerk_devices",
    "body_height_err_pct", "fps",
)  # fmt: skip
WRISTS = np.array([20, 21])
# Head, left wrist, right wrist: the joints whose global rotation "facing" measures.
FACING: Final = np.array(TRACKED_JOINTS)


def replay_sequence(
    pipeline: Pipeline,
    seq: dict[str, Any],
    camera: dict[str, Any] | None = None,
    send_frames: bool = True,
    first_frame_wait: bool = True,
    low_head_wait: bool = LOW_HEAD_WAIT_ON,
    truth_contact: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Served joints (N, J, 3) and local rotations (N, J, 3, 3) for one dataset sequence, its frames sent with
    its own camera (or ``camera``); with ``send_frames`` False none is sent, as from a headset without the
    camera (every pose then has ``camera = False``). As the server does (PROTOCOL.md §first-frame), the stream's
    first samples wait, up to ``FIRST_FRAME_WAIT_US`` after the first, for the first frame to arrive (with
    ``low_head_wait``, a stream that begins with the head low waits for the net's visual window of frames, up to
    ``LOW_HEAD_WAIT_US``: frames.first_answer_wait); then the newest is answered and the older ones feed its
    history, each scored with that first pose; ``first_frame_wait`` and ``low_head_wait`` False answer every
    sample at once (the server's ``--first-frame-wait-ms 0 --low-head-wait-ms 0``). With ``truth_contact``, a
    net with a contact head is given, at every sample it answers, the truth's contact labels
    (plausibility.contacts) in place of its contact output: what a contact head right at every sample would
    buy, a diagnosis no user can have."""
    camera = camera or seq["camera"]
    pipeline.reset()
    intrinsics, cam_from_head = camera["intrinsics"], np.asarray(camera["cam_from_head"]).reshape(4, 4)
    uses_camera = send_frames and pipeline.model.visual is not None
    t_all = np.asarray(seq["hmd_t_us"])
    wait = _first_answer_wait(pipeline, seq, first_frame_wait, low_head_wait) if uses_camera else None
    touch = contacts(np.asarray(seq["gt_joints_m"]), t_all).astype(np.float32) if truth_contact else None
    joints, rots, k, held = [], [], 0, []
    for i, t_us in enumerate(t_all):
        while uses_camera and k < len(seq["cam_t_us"]) and seq["cam_t_us"][k] + CAMERA_LATENCY_US <= t_us:
            rgb, depth = decode_rgbd(seq["rgb_jpeg"][k], seq["depth_png"][k])
            pipeline.push_rgbd(int(seq["cam_t_us"][k]), rgb, depth, intrinsics, cam_from_head)
            k += 1
        held.append(i)
        first = len(held) == i + 1  # nothing answered yet
        waiting = first and wait is not None and not wait.met(k, int(t_us - t_all[0]))
        if waiting and i < len(t_all) - 1:  # (a stream shorter than the wait ends)
            continue
        pose = _answer_newest(pipeline, seq, held, touch)
        joints += [pose.joints] * len(held)
        rots += [pose.local_rot] * len(held)
        held = []
    return np.array(joints), np.array(rots)


def _first_answer_wait(
    pipeline: Pipeline, seq: dict[str, Any], first_frame_wait: bool, low_head_wait: bool
) -> FirstAnswerWait:
    """What the server makes this sequence's first answer wait for (frames.first_answer_wait)."""
    return first_answer_wait(
        seq["hmd_poses"][0][0],
        bool(seq["hmd_valid"][0][0]),
        pipeline.visual_window,
        FIRST_FRAME_WAIT_US if first_frame_wait else 0,
        LOW_HEAD_WAIT_US if low_head_wait else 0,
    )


def _answer_newest(
    pipeline: Pipeline, seq: dict[str, Any], samples: list[int], touch: np.ndarray | None = None
) -> PoseResult:
    """The server's newest-wins for ``samples`` (indices, in order): all but the last feed the history, the
    last is answered. A sample answered by no pose is scored with the first pose served after it, the one its
    user sees first. touch (N, 2), if given: each sample's contact probabilities, served in place of the
    net's contact output (where it has one)."""
    for j in samples[:-1]:
        pipeline.observe_hmd(int(seq["hmd_t_us"][j]), seq["hmd_poses"][j], seq["hmd_valid"][j])
    j = samples[-1]
    if touch is None:
        return pipeline.push_hmd(int(seq["hmd_t_us"][j]), seq["hmd_poses"][j], seq["hmd_valid"][j])
    pending = pipeline.begin_hmd(int(seq["hmd_t_us"][j]), seq["hmd_poses"][j], seq["hmd_valid"][j])
    sixd = run_fusion([pending])[0]  # push_hmd's own steps, the contact output replaced in between
    if pending.contact_p is not None:
        pending.contact_p = touch[j]
    return pipeline.finish_hmd(pending, sixd)


def procrustes_aligned(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Per-frame similarity alignment of pred (N, J, 3) onto gt (N, J, 3) -> aligned pred (N, J, 3)."""
    mu_p, mu_g = pred.mean(1, keepdims=True), gt.mean(1, keepdims=True)
    p, g = pred - mu_p, gt - mu_g
    u, s, vt = np.linalg.svd(np.swapaxes(p, 1, 2) @ g)  # (N, 3, 3)
    d = np.sign(np.linalg.det(u @ vt))
    s[:, -1] *= d
    u[:, :, -1] *= d[:, None]
    rot = u @ vt  # p @ rot ~ g
    scale = s.sum(-1) / (p**2).sum((1, 2))
    return scale[:, None, None] * p @ rot + mu_g


def _global_rot(local_rot: np.ndarray) -> np.ndarray:
    """(N, J, 3, 3) local rotations (row 0 the pelvis' global) -> global rotations."""
    return forward_kinematics(local_rot, np.zeros(3))[1]


def sequence_errors(
    joints: np.ndarray, rots: np.ndarray, seq: dict[str, Any], served_scale: np.ndarray
) -> dict[str, np.ndarray]:
    """Per-sample, per-joint errors of one sequence: position (N, J) m, aligned (N, J) m, rotation (N, J) deg,
    the jitter of the served joints (N-3,) m/s³, and, from the bone scale (J,) served at its end, the body
    height's error (1,) %."""
    gt = seq["gt_joints_m"].astype(np.float64)
    gt_rot = quat_xyzw_to_matrix(seq["gt_local_quat"].astype(np.float64))
    dt_s = np.diff(seq["hmd_t_us"]).mean() * 1e-6 if len(joints) > 1 else 1.0
    third = np.diff(joints, n=3, axis=0) / dt_s**3 if len(joints) > 3 else np.zeros((0, joints.shape[1], 3))
    return {
        "pos": np.linalg.norm(joints - gt, axis=-1),
        "pa": np.linalg.norm(procrustes_aligned(joints, gt) - gt, axis=-1),
        "rot": np.degrees(geodesic_angle(rots, gt_rot)),
        "facing": np.degrees(geodesic_angle(_global_rot(rots)[:, FACING], _global_rot(gt_rot)[:, FACING])),
        "jitter": np.linalg.norm(third, axis=-1).mean(-1),
        "plausibility": plausibility(joints, gt, np.asarray(seq["hmd_t_us"]), truth_on_devices(gt, seq)),
        "lost": ~np.asarray(seq["hmd_valid"], dtype=bool)[:, 1:],  # (N, 2) left, right controller lost
        "body_height": np.array([body_height_error_pct(served_scale, seq)]),
    }


def body_height_error_pct(served_scale: np.ndarray, seq: dict[str, Any]) -> float:
    """|standing head height of the served bone scale (J,) / the truth's - 1| × 100."""
    true_m = standing_head_height_m(np.asarray(seq["bone_scale"], dtype=np.float64))
    return abs(standing_head_height_m(served_scale) / true_m - 1.0) * 100.0


def truth_on_devices(gt: np.ndarray, seq: dict[str, Any]) -> np.ndarray:
    """The true joints gt (N, J, 3) with the head and each wrist moved, at every sample its device is
    tracked, to where the device puts it (the rig's default offsets, as the runtime reads them): what a
    perfect network would serve once the served head and hands follow their devices."""
    device_m, _ = joints_from_devices(seq["hmd_poses"])  # (N, 3, 3)
    valid = np.asarray(seq["hmd_valid"], dtype=bool)
    out = gt.copy()
    for device, joint in enumerate(TRACKED_JOINTS):
        out[valid[:, device], joint] = device_m[valid[:, device], device]
    return out


def sequence_totals(errors: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """One sequence's :func:`sequence_errors` as (2,) [sum, count] per metric of :func:`summarize` (without
    fps): every metric is a mean pooled over samples, so a set of sequences' value is the ratio of its summed
    totals (what :mod:`.intervals` reweights to resample people)."""
    pos, lost, facing = errors["pos"], errors["lost"], errors["facing"]  # (N, J), (N, 2), (N, 3)
    wrists = pos[:, WRISTS]
    return {
        "mpjpe_u_cm": total(pos[:, UPPER_BODY], 100.0),
        "mpjpe_l_cm": total(pos[:, LOWER_BODY], 100.0),
        "pa_mpjpe_u_cm": total(errors["pa"][:, UPPER_BODY], 100.0),
        "pa_mpjpe_l_cm": total(errors["pa"][:, LOWER_BODY], 100.0),
        "mpjre_u_deg": total(errors["rot"][:, UPPER_BODY]),
        "mpjre_l_deg": total(errors["rot"][:, LOWER_BODY]),
        "hpe_cm": total(wrists, 100.0),
        "hpe_lost_cm": total(wrists[lost], 100.0),
        "lost_share": total(lost.astype(np.float64)),
        "facing_head_deg": total(facing[:, 0]),
        "facing_hands_deg": total(facing[:, 1:]),
        "jitter": total(errors["jitter"]),
        # errors put together without a served body (no sequence_errors) have no height error to pool
        "body_height_err_pct": total(errors.get("body_height", np.zeros(0))),
        **plausibility_totals(errors["plausibility"]),
    }


def summarize(errors: list[dict[str, np.ndarray]]) -> dict[str, float]:
    """Pool per-sample errors over sequences -> the metric dict (without fps): NaN where a metric has
    nothing to measure (no lost controller, no contact, no still legs), jitter 0 for sequences too short
    for it."""
    return summarize_totals([sequence_totals(e) for e in errors])


def summarize_totals(totals: list[dict[str, np.ndarray]]) -> dict[str, float]:
    """:func:`summarize` of sequences already reduced to their :func:`sequence_totals`."""
    metrics = pooled_means(add_totals(totals))
    if metrics["jitter"] != metrics["jitter"]:
        metrics["jitter"] = 0.0
    return metrics


def measure_fps(
    pipeline: Pipeline,
    seq: dict[str, Any],
    camera: dict[str, Any] | None = None,
    samples: int = FPS_SAMPLES,
    send_frames: bool = True,
) -> float:
    """Headset samples per second with a new RGB-D frame decoded and pushed before each one (median run); with
    ``send_frames`` False, the headset stream alone."""
    n = min(samples, len(seq["hmd_t_us"]))
    frames = len(seq["rgb_jpeg"]) if send_frames else 0
    rates = []
    for _ in range(FPS_REPEATS):
        pipeline.reset()
        started = time.perf_counter()
        for i in range(n):
            t_us = int(seq["hmd_t_us"][i])
            if pipeline.model.visual is not None and frames:
                rgb, depth = decode_rgbd(seq["rgb_jpeg"][i % frames], seq["depth_png"][i % frames])
                pipeline.push_rgbd(t_us - 1, rgb, depth, (camera or seq["camera"])["intrinsics"])
            pipeline.push_hmd(t_us, seq["hmd_poses"][i], seq["hmd_valid"][i])
        rates.append(n / (time.perf_counter() - started))
    return statistics.median(rates)


# Motion categories read from the truth (not from names, which captured clips do not carry): thresholds on the
# pelvis's horizontal speed, its height below the clip's standing height, how fast the ankles move, and, for
# still legs, how high the pelvis is above the ankles for the legs' length (standing or seated).
SOURCES: Final = ("all", "captured", "procedural")  # eval --source: which sequences' motion is served
CATEGORIES: Final = ("stand, upper body", "sit, upper body", "walk", "crouch, bend", "legs", "other")
WALK_SPEED_M_S = 0.3  # mean pelvis speed over the floor
CROUCH_DROP_M = 0.2  # the pelvis this far below its highest (90th percentile) height at some point
STILL_ANKLE_M_S = 0.15  # 90th percentile ankle speed below this: the legs stand still
LEG_ACTION_ANKLE_M_S = 0.6  # ... above this without walking: kicks, knee raises, lunges, steps in place
# Still legs whose pelvis is less than this share of the legs' length above the ankles are folded: a seated
# person (the truth's pelvis is ~0.5 leg lengths above the ankles seated and ~0.95 standing).
SEATED_LEG_SHARE = 0.7


def _seated(joints: np.ndarray) -> bool:
    """Whether the true joints (N, J, 3) hold the pelvis less than SEATED_LEG_SHARE of the legs' length
    (thigh + shin, both sides) above the ankles, at the median sample (skeleton.pelvis_over_legs)."""
    above_m, legs_m = pelvis_over_legs(joints)
    return float(np.median(above_m)) < SEATED_LEG_SHARE * float(np.median(legs_m))


def motion_category(seq: dict[str, Any]) -> str:
    """One of CATEGORIES for a sequence, from its true joints (N, J, 3) and times."""
    joints = seq["gt_joints_m"].astype(np.float64)
    dt_s = np.diff(seq["hmd_t_us"]) * 1e-6
    if len(joints) < 3 or (dt_s <= 0).any():
        return "other"
    pelvis_speed = np.linalg.norm(np.diff(joints[:, 0, [0, 2]], axis=0), axis=-1) / dt_s
    ankle_speed = np.linalg.norm(np.diff(joints[:, [7, 8]], axis=0), axis=-1).max(-1) / dt_s
    drop = np.percentile(joints[:, 0, 1], 90) - joints[:, 0, 1].min()
    ankle_p90 = np.percentile(ankle_speed, 90)
    if pelvis_speed.mean() > WALK_SPEED_M_S:
        return "walk"
    if drop > CROUCH_DROP_M:
        return "crouch, bend"
    if ankle_p90 < STILL_ANKLE_M_S:
        return "sit, upper body" if _seated(joints) else "stand, upper body"
    if ankle_p90 > LEG_ACTION_ANKLE_M_S:
        return "legs"
    return "other"


def calibrate_like_a_user(pipeline: Any, seq: dict[str, Any], headset: dict[str, Any]) -> Calibration:
    """Run the T-pose calibration a user of this sequence's rig would do, and apply it to ``pipeline``."""
    from ..synth.headset import rig_from_fields, tpose_samples

    rate_hz = 1e6 / float(np.median(np.diff(seq["hmd_t_us"])))
    collector = CalibrationCollector("tpose", DEFAULT_SECONDS, pipeline.model.info.rig_offsets_m)
    samples = tpose_samples(seq["bone_scale"], rig_from_fields(headset), rate_hz, DEFAULT_SECONDS + 0.5)
    for sample in zip(*samples, strict=True):
        calibration = collector.push(*sample)
        if calibration is not None:
            pipeline.calibrate(calibration)
            return calibration
    raise AssertionError("the T-pose was shorter than the calibration")  # tpose_samples lasts longer


def sequence_rigs(
    data_dir: Path, split: str, seqs: list[dict[str, Any]], indices: np.ndarray
) -> list[dict[str, Any]]:
    """Each sequence's headset draw from the manifest; ``indices`` (n,) are the sequences' places in the
    split (names repeat: one capture in several conversions). Raises DatasetError when the manifest has no
    rigs (no --rig-pool) or disagrees."""
    manifest = json.loads((Path(data_dir) / "manifest.json").read_text())
    sources = manifest["splits"][split].get("sources", [])
    picked = [sources[i] if i < len(sources) else {} for i in indices]
    if any("rig" not in src or src.get("name") != seq["name"] for src, seq in zip(picked, seqs, strict=True)):
        raise DatasetError(f"{data_dir}: --calibrate needs each sequence's rig in manifest.json (--rig-pool)")
    return [src["rig"]["headset"] for src in picked]


def evaluate(
    data_dir: Path,
    split: str,
    models: dict[str, Path | None],
    limit: int | None = None,
    on_sequence: Callable[[str, int, int], None] | None = None,
    by_category: bool = False,
    providers: tuple[str, ...] = DEFAULT_PROVIDERS,
    calibrate: bool = False,
    foot_contacts: bool = True,
    steady_stance: bool = True,
    leg_hold: bool = True,
    lean_gate: bool | None = None,
    reseat: bool = False,
    body_hold: bool = True,
    sure_plant: bool = False,
    warm_reseat: bool = True,
    send_frames: bool = True,
    first_frame_wait: bool = True,
    low_head_wait: bool = LOW_HEAD_WAIT_ON,
    truth_body: bool = False,
    truth_contact: bool = False,
    returning: bool = False,
    runtime: dict[str, dict[str, bool]] | None = None,
    fold: Fold | None = None,
    loaded: tuple[list[dict[str, Any]], np.ndarray] | None = None,
    resamples: int = 0,
    seed: int = 0,
    per_sequence: bool = False,
    source: str = "all",
) -> dict[str, dict[str, Any]]:
    """{model name: metrics} over a split (with ``fold``, only its subjects': dataset.Fold; with ``source``,
    only its captured or its procedural sequences: :func:`split_sequences`) for each model
    file given as {name: path} (None: the procedural baseline); with ``by_category``,
    each model's metrics also under ``categories`` {category: metrics (without fps) and ``sequences``}.
    With ``calibrate`` every sequence is served after the T-pose calibration its rig and body would give
    (:func:`calibrate_like_a_user`; needs a rig-pool dataset, whose manifest has each sequence's rig).
    ``foot_contacts`` False serves the network's own feet (no planting, no floor; runtime/contact.py),
    ``steady_stance`` False lets planted feet step on the network's drift while the headset is still
    (runtime/stance.py), ``leg_hold`` False lets the pelvis, hips and knees wander with the network while both
    feet are down (stance.LegHold), ``lean_gate`` True holds them and the feet while the head leans round the
    served pelvis too (stance.py; None: as each model file says, False: off), ``reseat`` True moves a held leg
    or a still foot's anchor far from the network's mean placement to it faster (stance.RESEAT_SLACK_M; off by
    default), ``body_hold`` False lets the hips, thighs, shins and feet follow every new body estimate while
    the legs are held (by default they keep their size once the body's first measurement is a second old:
    body.held_target), ``sure_plant`` True keeps a planted foot the contact head is sure of down however
    high the network lifts it (contact.SURE_P; off by default), ``warm_reseat`` False does not re-seat held
    legs and planted feet at the network's answers once its windows fill where it folds the legs (Pipeline's;
    on by default: MODEL_CARD.md, rule 62);
    ``send_frames`` False sends no camera frame, as a headset without the camera (:func:`replay_sequence`, which
    ``waits`` ({``first_frame_wait``, ``low_head_wait``}) go to too);
    ``first_frame_wait`` False answers a stream's first samples at once instead of once its first frame is in,
    as the server does by default (:func:`replay_sequence`; MODEL_CARD.md, rules 68 and 69); ``low_head_wait``
    makes a stream that begins with the head low wait for the net's visual window of frames
    (frames.first_answer_wait; MODEL_CARD.md, rules 70 and 71);
    ``truth_body`` True serves each sequence the truth's body (its bone lengths) from its first sample instead
    of the session's running estimate (runtime/body.py): what a perfect body estimate would buy, a diagnosis.
    ``truth_contact`` True gives a net with a contact head the truth's contact labels in place of its contact
    output (:func:`replay_sequence`): what a perfect contact head would buy, a diagnosis.
    ``returning`` True serves each sequence after learning the wearer's body from an earlier session (the
    estimate the end of another sequence of the same body gives, or of the same sequence where the split has no
    other: :func:`earlier_sessions`; what ``get_body`` answers), given from the first sample (``set_body``,
    PROTOCOL.md §4.2): a returning wearer whose client kept their body.
    ``runtime`` {label: {option: bool}} serves a label with some of those fourteen (as ``contacts``,
    ``steady_stance``, ``leg_hold``, ``lean_gate``, ``reseat``, ``body_hold``, ``sure_plant``,
    ``warm_reseat``, ``send_frames``, ``first_frame_wait``, ``low_head_wait``, ``truth_body``,
    ``truth_contact``, ``returning``) set
    otherwise, or with the network pipeline's ``seated_yaw`` (a folded pelvis keeps its heading while no camera frame
    is in the window; Pipeline's, off by default: MODEL_CARD.md, rule 65), or the procedural baseline's ``seat``
    (ProceduralPipeline's; the network pipeline ignores it): one file served twice, with and without a runtime
    stage or the camera, is a paired comparison. ``loaded``: what :func:`split_sequences` gave for
    these arguments, when the caller has already read the split (``eval --keypoints`` reads it once for both
    reports).
    With ``resamples`` R > 0, each model's metrics also get ``intervals`` {metric: [low, high]}, 95 % over R
    resamples of the split's people (:mod:`.intervals`, drawn with ``seed``), and every model after the first
    ``versus`` {``model``: the first, ``difference`` {metric: its value − the first's}, ``intervals`` of
    that difference, paired, ``relative`` and ``relative_intervals``: the same for its value / the first's
    − 1}; with ``by_category`` each category's metrics too, over that category's people. With
    ``per_sequence``, each model's ``sequences``: [{``name``, ``person``, ``category``, its metrics}] in the
    split's order (where a model's error comes from)."""
    seqs, indices = loaded or split_sequences(data_dir, split, limit, fold, source)
    rigs = sequence_rigs(data_dir, split, seqs, indices) if calibrate else []
    categories = [motion_category(s) for s in seqs]
    shared: dict[Path, Any] = {}
    results: dict[str, dict[str, Any]] = {}
    totals: dict[str, list[dict[str, np.ndarray]]] = {}
    # every file is loaded before any is served: a damaged third file is an error now, not after two models
    served_models = {
        name: ProceduralModel()
        if path is None
        else LoadedModel.load(path, shared=shared, providers=providers)
        for name, path in models.items()
    }
    for name, model in served_models.items():
        options = {"contacts": foot_contacts, "steady_stance": steady_stance, "leg_hold": leg_hold,
                   "lean_gate": lean_gate, "reseat": reseat, "body_hold": body_hold,
                   "sure_plant": sure_plant, "warm_reseat": warm_reseat}  # fmt: skip
        options |= (runtime or {}).get(name, {})
        frames = options.pop("send_frames", send_frames)  # the replay's, not the pipeline's
        waits = {  # the server's (the replay's), too
            "first_frame_wait": options.pop("first_frame_wait", first_frame_wait),
            "low_head_wait": options.pop("low_head_wait", low_head_wait),
        }
        replay = {**waits, "truth_contact": options.pop("truth_contact", truth_contact)}
        known_body = options.pop("truth_body", truth_body)  # a pipeline per sequence, made with its body
        returns = options.pop("returning", returning)
        pipeline = pipeline_for(model, **options)
        earlier = earlier_sessions(seqs) if returns else []
        errors = []
        for i, seq in enumerate(seqs):
            if known_body:
                pipeline = pipeline_for(model, bone_scale=seq["bone_scale"], **options)
            if calibrate:
                calibrate_like_a_user(pipeline, seq, rigs[i])
            if returns:
                learn_the_wearer(pipeline, seqs[earlier[i]], frames, **waits)
            served = replay_sequence(pipeline, seq, send_frames=frames, **replay)
            errors.append(sequence_errors(*served, seq, pipeline.served_body()[0]))
            if on_sequence:
                on_sequence(name, i + 1, len(seqs))
        totals[name] = [sequence_totals(e) for e in errors]  # each view below pools these
        fps = measure_fps(pipeline, seqs[0], send_frames=frames)
        results[name] = {**summarize_totals(totals[name]), "fps": fps}
        if per_sequence:
            results[name]["sequences"] = [
                {"name": str(seq["name"]), "person": sequence_subject(seq), "category": category,
                 **summarize_totals([t])}
                for seq, category, t in zip(seqs, categories, totals[name], strict=True)
            ]  # fmt: skip
        if by_category:
            results[name]["categories"] = {
                c: {**summarize_totals([t for t, k in zip(totals[name], categories, strict=True) if k == c]),
                    "sequences": categories.count(c)}
                for c in CATEGORIES if c in categories
            }  # fmt: skip
    if resamples > 0:
        people = [sequence_subject(s) for s in seqs]
        _add_intervals(results, totals, people, resamples, seed)
        for c in CATEGORIES if by_category else ():
            members = [i for i, k in enumerate(categories) if k == c]
            if members:
                _add_intervals(
                    {n: r["categories"][c] for n, r in results.items()},
                    {n: [t[i] for i in members] for n, t in totals.items()},
                    [people[i] for i in members], resamples, seed,
                )  # fmt: skip
    return results


def earlier_sessions(seqs: list[dict[str, Any]]) -> list[int]:
    """For each sequence, the index of the one that stands in for its wearer's earlier session: the next
    sequence (cyclically) of the same body (equal bone scales: a synthetic set draws its bodies from a bank, so
    several sequences share one, each with its own motion and rig), or itself where no other has its body."""
    keys = [np.asarray(s["bone_scale"], dtype=np.float64).round(6).tobytes() for s in seqs]
    members: dict[bytes, list[int]] = {}
    for i, key in enumerate(keys):
        members.setdefault(key, []).append(i)
    out = []
    for i, key in enumerate(keys):
        same = members[key]
        out.append(same[(same.index(i) + 1) % len(same)])
    return out


def learn_the_wearer(pipeline: Any, seq: dict[str, Any], send_frames: bool, **waits: bool) -> None:
    """A returning wearer (``evaluate``'s ``returning``): the wearer's earlier session ``seq`` served with the
    body estimated, and the body it ends with given to the pipeline, as a client that kept it sends
    ``set_body`` (PROTOCOL.md §4.2); none where ``body.measured`` says it is not worth keeping (the wearer only
    sat, or the camera measured nothing), and the body is estimated as usual."""
    pipeline.give_body(None)
    replay_sequence(pipeline, seq, send_frames=send_frames, **waits)
    scale, worth_keeping = pipeline.served_body()
    pipeline.give_body(scale if worth_keeping else None)  # a client keeps only a body worth keeping


def _add_intervals(
    results: dict[str, dict[str, Any]],
    totals: dict[str, list[dict[str, np.ndarray]]],
    people: list[str],
    resamples: int,
    seed: int,
) -> None:
    """Each model's ``intervals`` and, after the first, its paired ``versus`` the first (:func:`evaluate`)."""
    weights = intervals.resample_weights(people, resamples, seed)
    resampled = {
        name: intervals.resampled_metrics(t, weights) for name, t in totals.items()
    }  # once per model
    first = next(iter(totals))
    for name, values in resampled.items():
        results[name]["intervals"] = _listed(intervals.metric_intervals(values))
        if name != first:
            difference = {k: results[name][k] - results[first][k] for k in values}
            paired = intervals.difference_intervals(resampled[first], values)
            relative = {k: results[name][k] / results[first][k] - 1.0 if results[first][k] else float("nan")
                        for k in values}  # fmt: skip
            ratio = intervals.difference_intervals(resampled[first], values, relative=True)
            results[name]["versus"] = {
                "model": first, "difference": difference, "intervals": _listed(paired),
                "relative": relative, "relative_intervals": _listed(ratio),
            }  # fmt: skip


def _listed(bounds: dict[str, tuple[float, float]]) -> dict[str, list[float]]:
    return {k: list(v) for k, v in bounds.items()}


# Body parts of the keypoint report: the feet and knees are what the lower body's pose needs from the
# camera, and the parts a downward camera sees least and smallest.
KEYPOINT_PARTS: Final = {
    part: [JOINT_INDEX[name] for name in names]
    for part, names in {
        "torso": ("pelvis", "left_hip", "right_hip", "spine1", "spine2", "spine3"),
        "knees": ("left_knee", "right_knee"),
        "ankles, feet": ("left_ankle", "right_ankle", "left_foot", "right_foot"),
        "arms": ("left_elbow", "right_elbow", "left_wrist", "right_wrist"),
        "head, shoulders": ("neck", "left_collar", "right_collar", "head", "left_shoulder", "right_shoulder"),
    }.items()
}


def is_procedural(seq: dict[str, Any]) -> bool:
    """Whether a dataset sequence's motion was made by synth's procedural families (not captured)."""
    return str(seq["source"]).startswith("procedural:")


def split_sequences(
    data_dir: Path, split: str, limit: int | None = None, fold: Fold | None = None, source: str = "all"
) -> tuple[list[dict[str, Any]], np.ndarray]:
    """The split's sequences (with ``fold`` only its subjects'; with ``source`` one of SOURCES, only those
    whose motion is captured or procedural; at most ``limit`` of them) and their indices in the split
    (n,)."""
    if source not in SOURCES:
        raise ValueError(f"source must be one of {', '.join(SOURCES)}, not {source!r}")
    read_limit = limit if source == "all" else None  # otherwise the limit counts the kept sequences
    if fold is None:
        seqs = load_split(data_dir, split, read_limit)
        places = np.arange(len(seqs))
    else:
        seqs, places = load_fold(data_dir, split, fold, True, read_limit)
    if source != "all":
        kept = [i for i, seq in enumerate(seqs) if is_procedural(seq) == (source == "procedural")][:limit]
        seqs, places = [seqs[i] for i in kept], places[kept]
    if not seqs:
        kind = "" if source == "all" else f"{source} "
        within = f" in fold {fold}" if fold is not None else ""
        raise DatasetError(f"{data_dir}: split {split!r} has no {kind}sequence{within}")
    return seqs, places


def keypoint_accuracy(
    data_dir: Path,
    split: str,
    models: dict[str, Path],
    limit: int | None = None,
    fold: Fold | None = None,
    loaded: tuple[list[dict[str, Any]], np.ndarray] | None = None,
) -> dict[str, dict[str, Any]]:
    """{encoder: accuracy} of the visual encoders the given models use (each once), on a split: the keypoints
    it lifts to 3D in the camera frame against the truth, on joints in view and not occluded: median, mean and
    90th percentile error (cm), and under ``parts`` each of KEYPOINT_PARTS' median (cm) and how often its
    joints are seen (share of frame × joint). ``loaded`` as :func:`evaluate`'s."""
    seqs, _ = loaded or split_sequences(data_dir, split, limit, fold)
    encoders: dict[str, LoadedModel] = {}
    for path in models.values():
        if path is None:  # the procedural baseline reads no camera
            continue
        model = LoadedModel.load(path)
        if model.info.visual_path is not None:
            encoders.setdefault(model.info.visual_path.stem, model)
    return {name: _encoder_accuracy(model, seqs) for name, model in encoders.items()}


def _encoder_accuracy(model: LoadedModel, seqs: list[dict[str, Any]]) -> dict[str, Any]:
    """keypoint_accuracy's numbers for one encoder over sequences."""
    errors = []  # per frame: (J,) cm, NaN where the joint is not seen
    for seq in seqs:
        camera = seq["camera"]
        for k in range(len(seq["cam_t_us"])):
            seen = seq["visible"][k] & ~seq["occluded"][k]
            if not seen.any():
                errors.append(np.full(len(seen), np.nan))
                continue
            rgb, depth = decode_rgbd(seq["rgb_jpeg"][k], seq["depth_png"][k])
            frame = encode_frame(model, int(seq["cam_t_us"][k]), rgb, depth, camera["intrinsics"])
            error_cm = 100 * np.linalg.norm(frame.kp_cam - seq["joints_cam_m"][k], axis=-1)
            errors.append(np.where(seen, error_cm, np.nan))
    error_cm = np.array(errors).reshape(-1, NUM_JOINTS)  # (frames, J)
    seen = ~np.isnan(error_cm)
    parts = {
        part: {"seen_share": float(seen[:, joints].mean()) if seen.size else 0.0}
        | _error_stats(error_cm[:, joints])
        for part, joints in KEYPOINT_PARTS.items()
    }
    return _error_stats(error_cm) | {"parts": parts}


def _error_stats(error_cm: np.ndarray) -> dict[str, Any]:
    """joints, median_cm, mean_cm, p90_cm of the seen (not NaN) entries of an error array (NaN if none)."""
    values = error_cm[~np.isnan(error_cm)]
    if not values.size:
        return {"joints": 0, "median_cm": float("nan"), "mean_cm": float("nan"), "p90_cm": float("nan")}
    return {
        "joints": int(values.size),
        "median_cm": float(np.median(values)),
        "mean_cm": float(values.mean()),
        "p90_cm": float(np.percentile(values, 90)),
    }


def category_table(
    results: dict[str, dict[str, Any]],
    keys: tuple[str, ...] = ("mpjpe_u_cm", "mpjpe_l_cm"),
    unit: str = "U / L cm",
) -> str:
    """Metrics (``keys``, shown as "a / b") per motion category (rows) and model (columns), each with its
    95 % interval where ``evaluate(resamples=...)`` gave one."""
    names = list(results)
    categories = [c for c in CATEGORIES if any(c in r.get("categories", {}) for r in results.values())]
    rows = ["| category (sequences) | " + " | ".join(f"{n} {unit}" for n in names) + " |",
            "|" + "---|" * (len(names) + 1)]  # fmt: skip
    for c in categories:
        count = next(r["categories"][c]["sequences"] for r in results.values() if c in r["categories"])
        cells = [" / ".join(_value(results[n]["categories"][c], k) for k in keys) for n in names]
        rows.append(f"| {c} ({count}) | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def sequence_table(
    results: dict[str, dict[str, Any]],
    keys: tuple[str, str] = ("mpjpe_l_cm", "foot_skate_cm_s"),
    unit: str = "L cm / skate cm/s",
) -> str:
    """Two metrics (``keys``, shown as "a / b") per sequence (rows, the first model's ``keys[0]`` highest
    first) and model (columns): ``evaluate(per_sequence=True)``."""
    names = list(results)
    rows = ["| sequence | person | category | " + " | ".join(f"{n} {unit}" for n in names) + " |",
            "|" + "---|" * 3 + "---:|" * len(names)]  # fmt: skip
    first = results[names[0]]["sequences"]
    order = sorted(range(len(first)), key=lambda i: -np.nan_to_num(first[i][keys[0]], nan=-np.inf))
    for i in order:
        cells = [" / ".join(f"{results[n]['sequences'][i][k]:.2f}" for k in keys) for n in names]
        row = first[i]
        rows.append(f"| {row['name']} | {row['person']} | {row['category']} | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def category_difference_table(results: dict[str, dict[str, Any]], key: str = "mpjpe_l_cm") -> str:
    """One metric's paired difference from the first model [95 % interval] per motion category (rows) and
    later model (columns): ``evaluate(by_category=True, resamples=...)``."""
    first, *later = results
    categories = [c for c in CATEGORIES if c in results[first].get("categories", {})]
    rows = ["| category (sequences) | " + " | ".join(f"{n} − {first}" for n in later) + " |",
            "|---|" + "---:|" * len(later)]  # fmt: skip
    for c in categories:
        cells = []
        for n in later:
            versus = results[n]["categories"][c]["versus"]
            cells.append(_with_interval(versus["difference"][key], versus["intervals"][key], "+.2f"))
        rows.append(f"| {c} ({results[first]['categories'][c]['sequences']}) | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def keypoint_table(accuracy: dict[str, dict[str, Any]]) -> str:
    """One row per encoder: every seen joint, then each body part's median (cm) and how often it is seen."""
    parts = list(KEYPOINT_PARTS)
    rows = [
        "| encoder | joints | median cm | mean cm | p90 cm | "
        + " | ".join(f"{p}: median cm (seen)" for p in parts)
        + " |",
        "|---|---:|---:|---:|---:|" + "---:|" * len(parts),
    ]
    for name, a in accuracy.items():
        by_part = " | ".join(
            f"{a['parts'][p]['median_cm']:.2f} ({a['parts'][p]['seen_share']:.0%})" for p in parts
        )
        rows.append(
            f"| {name} | {a['joints']} | {a['median_cm']:.2f} | {a['mean_cm']:.2f} | {a['p90_cm']:.2f} | {by_part} |"
        )
    return "\n".join(rows)


def plausibility_table(results: dict[str, dict[str, Any]]) -> str:
    """Does the served body behave like one (plausibility.py): one row per model; NaN where the split has no
    foot contact or no still legs."""
    rows = ["| model | foot skating cm/s (after 1 s) | floating cm | penetration cm | leg leakage cm (after 1 s; wander) "
            "| jerk m/s³ (truth; truth on the devices) | body height error % |",
            "|---|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
    for name, m in results.items():
        skating = f"{m['foot_skate_cm_s']:.1f} ({m['foot_skate_settled_cm_s']:.1f})"
        leakage = f"{m['leg_leakage_cm']:.1f} ({m['leg_leakage_settled_cm']:.1f}; {m['leg_wander_cm']:.1f})"
        jerk = f"{m['jerk']:.0f} ({m['jerk_true']:.0f}; {m['jerk_devices']:.0f})"
        rows.append(
            f"| {name} | {skating} | {m['floor_float_cm']:.1f} | {m['floor_penetration_cm']:.1f} | {leakage} | {jerk} "
            f"| {m['body_height_err_pct']:.1f} |"
        )
    return "\n".join(rows)


def markdown_table(results: dict[str, dict[str, float]]) -> str:
    """The paper's Tables 2-3 shape: one row per model."""
    head = (
        "| model | MPJPE-U cm | MPJPE-L cm | PA-MPJPE-U cm | PA-MPJPE-L cm | MPJRE-U ° | MPJRE-L ° | H-PE cm "
        "| H-PE lost cm | facing head / hands ° | Jitter m/s³ | FPS |"
    )
    rows = [head, "|" + "---|" * 12]
    for name, m in results.items():
        rows.append(
            f"| {name} | {m['mpjpe_u_cm']:.2f} | {m['mpjpe_l_cm']:.2f} | {m['pa_mpjpe_u_cm']:.2f} | "
            f"{m['pa_mpjpe_l_cm']:.2f} | {m['mpjre_u_deg']:.2f} | {m['mpjre_l_deg']:.2f} | {m['hpe_cm']:.2f} | "
            f"{m['hpe_lost_cm']:.2f} | {m['facing_head_deg']:.1f} / {m['facing_hands_deg']:.1f} | "
            f"{m['jitter']:.1f} | {m['fps']:.0f} |"
        )
    return "\n".join(rows)


INTERVAL_KEYS: Final = (
    ("mpjpe_u_cm", "MPJPE-U cm"), ("mpjpe_l_cm", "MPJPE-L cm"), ("mpjre_l_deg", "MPJRE-L °"),
    ("hpe_lost_cm", "H-PE lost cm"), ("foot_skate_cm_s", "skating cm/s"), ("leg_leakage_cm", "leakage cm"),
    ("foot_skate_settled_cm_s", "skating after 1 s cm/s"), ("leg_leakage_settled_cm", "leakage after 1 s cm"),
    ("leg_wander_cm", "wander cm"),
)  # fmt: skip


def interval_table(results: dict[str, dict[str, Any]]) -> str:
    """Each model's value [95 % interval] over resampled people, then each later model's paired difference
    from the first (``evaluate(resamples=...)``): a difference whose interval holds 0 is not told apart from
    no difference on this many people. "[–]": fewer than two people have the metric."""
    rows = ["| model | " + " | ".join(label for _, label in INTERVAL_KEYS) + " |",
            "|---|" + "---:|" * len(INTERVAL_KEYS)]  # fmt: skip
    for name, m in results.items():
        cells = [_value(m, k) for k, _ in INTERVAL_KEYS]
        rows.append(f"| {name} | " + " | ".join(cells) + " |")
    for name, m in results.items():
        if "versus" in m:
            versus = m["versus"]
            cells = [
                _with_interval(versus["difference"][k], versus["intervals"][k], "+.2f")
                for k, _ in INTERVAL_KEYS
            ]
            rows.append(f"| {name} − {versus['model']} | " + " | ".join(cells) + " |")
    for name, m in results.items():
        if "versus" in m:
            versus = m["versus"]
            cells = [
                _as_percent(versus["relative"][k], versus["relative_intervals"][k]) for k, _ in INTERVAL_KEYS
            ]
            rows.append(f"| {name} / {versus['model']} − 1 | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def _value(metrics: dict[str, Any], key: str) -> str:
    """A metric as "value", or "value [low, high]" where the metrics carry its interval."""
    if "intervals" not in metrics:
        return f"{metrics[key]:.2f}"
    return _with_interval(metrics[key], metrics["intervals"][key], ".2f")


def _as_percent(value: float, bounds: list[float]) -> str:
    return _with_interval(100.0 * value, [100.0 * b for b in bounds], "+.1f", " %")


def _with_interval(value: float, bounds: list[float], spec: str, unit: str = "") -> str:
    """ "value[unit] [low, high]" in the format ``spec``; "–" for no value, "[–]" for no interval."""
    low, high = bounds
    if value != value:
        return "–"
    if low != low:
        return f"{value:{spec}}{unit} [–]"
    return f"{value:{spec}}{unit} [{low:{spec}}, {high:{spec}}]"
