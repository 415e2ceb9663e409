"""Evaluate served models on a dataset split: the paper's Tables 2-3 as a markdown table.

Runs the serving runtime (ONNX models, the same code the server uses) over every sequence of --split,
pushing camera frames as they would arrive, and reports MPJPE / PA-MPJPE / MPJRE (upper and lower body),
H-PE, jitter and full-pipeline FPS (one stream, a new RGB-D frame every headset sample), then whether the
body behaves like one: foot skating and floor error while the true foot is planted, leg leakage while the
true legs are still (skating and leakage also after a session's first second, once the model's windows hold
real history), jerk, beside the truth's and that of the truth with its head and tracked wrists where the
devices put them (model/training/plausibility.py defines each). --by-category adds
MPJPE per motion category (stand or sit with the upper body moving, walk, crouch or bend, leg actions,
other: read from the true motion, model/training/evaluate.py says how); --keypoints the visual encoders' 3D
keypoint error on joints in view and not occluded, overall and per body part (torso, knees, ankles and feet,
arms, head and shoulders) with how often each part is seen; --calibrate serves each sequence after the T-pose
calibration (PROTOCOL.md §4.1) that its own rig and body would give. A held-out rig split (`egoposevr synth
--rig-pool heldout --split NAME`) is evaluated like any split. --fold K/N serves only the split's subjects of
fold K of N (with --split train, the people `train --hold-out K/N` left out; --json names them). --source
captured (or procedural) serves only the split's sequences whose motion was captured (or made by synth's
procedural families).

--intervals R adds 95 % intervals over R resamples of the split's people (model/training/intervals.py: a
person is drawn with all their sequences) for each model, and each later model's paired difference from the
first one named: whether a gap between two models is more than the people in the split make it. A model file
that is not the bundled one is served under a label: --models egoposevr,candidate=runs/x-weights/egoposevr.onnx
(its folder holds the visual encoder it reads, as export writes it). A model named with @SWITCH after it is
served with that runtime stage off (the switches are the --no-... flags' names: @no-foot-contacts,
@no-steady-stance, @no-leg-hold, @no-camera), or with the lean gate on or off (@lean-gate, @no-lean-gate;
by default as the model file says), the re-seating hold on (@reseat, off by default), the legs' size kept
while they are held off or on (@no-body-hold, @body-hold; on by default: MODEL_CARD.md, rule 57), or a
planted foot the contact head is sure of kept down however high the net lifts it (@sure-plant, off by
default), or held legs and a still stance's planted feet re-seated once the net's windows fill where it
folds the legs then off or on (@no-warm-reseat, @warm-reseat; on by default: MODEL_CARD.md, rule 62), or a
folded pelvis that keeps its heading while no camera frame is in the window on or off (@seated-yaw,
@no-seated-yaw; off by default: MODEL_CARD.md, rule 65), or a body estimate never shorter than the highest quiet
head says on or off (@quiet-lift, @no-quiet-lift; by default as the model file says, ModelMetadata.quiet_lift:
MODEL_CARD.md, rules 77 and 78), or a body estimate that takes a bone's first sighting by the camera as its
first measurement instead of the median of five (@early-body, @no-early-body; on by default: MODEL_CARD.md,
rule 86), or the joints' filter applied to the pose relative to the head, the head where the headset puts it
(@head-relative-filter, @no-head-relative-filter; off by default: MODEL_CARD.md, rule 90), so --models
egoposevr@no-leg-hold,egoposevr says, paired, what one stage of the runtime changes.
@no-first-frame-wait answers a stream's first headset samples at once instead of once its first camera frame is in
(at most 150 ms after the first), as the server does by default (PROTOCOL.md §first-frame; MODEL_CARD.md, rules
68 and 69; @first-frame-wait with); @low-head-wait makes a stream whose first sample has the head low (seated or
crouched) wait for the net's visual window of frames instead (at most 1 s), as the server's --low-head-wait-ms
(MODEL_CARD.md, rules 70 and 71; @no-low-head-wait without).
--no-camera (or @no-camera) sends no RGB-D frame: what a headset without the camera is served (the RGB-D models run on
the headset stream alone, as PROTOCOL.md's `camera: false`). --truth-body (or @truth-body) serves each
sequence the truth's body, its bone lengths, from the first sample instead of the session's running
estimate (model/runtime/body.py): what a perfect body estimate would buy, a diagnosis no user can have.
--truth-contact (or @truth-contact) gives every net with a contact head the truth's contact labels in place of its
contact output (model/training/plausibility.py): what a perfect contact head would buy, a diagnosis too.
--returning (or @returning) serves each sequence with the body an earlier session ended with given from its
first sample: another sequence of the same body where the split has one (a synthetic set's bodies come from a
bank), else the same sequence served once before; a returning wearer whose client kept their body
(PROTOCOL.md §4.2's set_body).
procedural@seat serves the procedural baseline with a seat for a stream that begins seated (@no-seat
without; off by default: MODEL_CARD.md, rule 63); the network models ignore it.

Examples:
  egoposevr eval --data data/dev --split val --json eval.json
  egoposevr eval --data data/dev --split val --models egoposevr,mine=runs/x-weights/egoposevr.onnx --intervals 2000
  egoposevr eval --data data/dev --split val --models egoposevr@no-leg-hold,egoposevr --intervals 2000
  egoposevr eval --data data/dev --split val --models procedural,egoposevr@no-camera,egoposevr --by-category
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

# Each resample is a row of weights over the split's sequences (intervals.py): 100 000 rows of a few hundred
# sequences are a few hundred MB; the percentiles are steady to 0.01 cm long before that (2 000 is plenty).
MAX_RESAMPLES = 100_000
# --models' @SWITCH: the runtime stage it turns off (or on) for that model, or the camera it sends no frame
# from, as (evaluate's option, its value)
SWITCHES = {
    "no-foot-contacts": ("contacts", False),
    "no-steady-stance": ("steady_stance", False),
    "no-leg-hold": ("leg_hold", False),
    "lean-gate": ("lean_gate", True),
    "no-lean-gate": ("lean_gate", False),
    "reseat": ("reseat", True),
    "body-hold": ("body_hold", True),
    "no-body-hold": ("body_hold", False),
    "sure-plant": ("sure_plant", True),
    "no-sure-plant": ("sure_plant", False),
    "warm-reseat": ("warm_reseat", True),
    "no-warm-reseat": ("warm_reseat", False),
    "seated-yaw": ("seated_yaw", True),
    "no-seated-yaw": ("seated_yaw", False),
    "quiet-lift": ("quiet_lift", True),
    "no-quiet-lift": ("quiet_lift", False),
    "early-body": ("early_body", True),
    "no-early-body": ("early_body", False),
    "head-relative-filter": ("head_relative_filter", True),
    "no-head-relative-filter": ("head_relative_filter", False),
    "no-camera": ("send_frames", False),
    "first-frame-wait": ("first_frame_wait", True),
    "no-first-frame-wait": ("first_frame_wait", False),
    "low-head-wait": ("low_head_wait", True),
    "no-low-head-wait": ("low_head_wait", False),
    "truth-body": ("truth_body", True),
    "truth-contact": ("truth_contact", True),
    "returning": ("returning", True),
    "seat": ("seat", True),
    "no-seat": ("seat", False),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, required=True, metavar="DIR", help="dataset root")
    parser.add_argument("--split", default="val", help="split to evaluate (default val)")
    parser.add_argument(
        "--models", default="all",
        help="comma-separated model names (default all); LABEL=FILE serves a model file under a label of "
        "your own (a candidate beside the bundled model of its name); NAME@SWITCH serves it with one runtime "
        "stage off (@no-foot-contacts, @no-steady-stance, @no-leg-hold, @no-lean-gate, @no-body-hold, "
        "@no-warm-reseat, @no-seated-yaw, @no-quiet-lift, @no-early-body) or on (@lean-gate, @reseat, "
        "@body-hold, @sure-plant, @warm-reseat, @seated-yaw, @quiet-lift, @early-body), its first samples "
        "answered before the first camera frame "
        "(@no-first-frame-wait; by "
        "default they wait for it, @first-frame-wait), a low head's first answer made once the net's visual window "
        "is full (@low-head-wait, @no-low-head-wait), without the camera (@no-camera), with the truth's body "
        "(@truth-body) or contact labels (@truth-contact), or as a returning wearer whose body the client kept "
        "(@returning); "
        "procedural@seat: the baseline with a seat for a stream that begins seated",
    )  # fmt: skip
    parser.add_argument("--models-dir", type=Path, default=None, metavar="DIR", help="default: bundled")
    parser.add_argument("--limit", type=int, default=None, metavar="N", help="at most N sequences")
    parser.add_argument(
        "--fold", default=None, metavar="K/N",
        help="only the split's subjects of fold K of N: with --split train, the ones `train --hold-out K/N` "
        "left out",
    )  # fmt: skip
    parser.add_argument(
        "--source", default="all", metavar="WHICH",
        help="captured: only the sequences whose motion is captured; procedural: only synth's procedural "
        "ones; all (default)",
    )  # fmt: skip
    parser.add_argument(
        "--by-category", action="store_true", help="also MPJPE per motion category (read from the truth)"
    )
    parser.add_argument(
        "--per-sequence", action="store_true",
        help="also each sequence's lower-body MPJPE and foot skating (the first model's worst first), and in "
        "--json every metric per sequence",
    )  # fmt: skip
    parser.add_argument(
        "--keypoints",
        action="store_true",
        help="also each visual encoder's 3D keypoint error on visible joints",
    )
    parser.add_argument(
        "--calibrate",
        action="store_true",
        help="serve each sequence after the T-pose calibration its own rig and body would give "
        "(rig-pool datasets)",
    )
    parser.add_argument(
        "--no-foot-contacts",
        action="store_true",
        help="serve without planted feet and the floor (model/runtime/contact.py): the network's own feet",
    )
    parser.add_argument(
        "--no-steady-stance",
        action="store_true",
        help="planted feet step on the network's drift even while the headset is still "
        "(model/runtime/stance.py): the runtime before the steady stance",
    )
    parser.add_argument(
        "--no-leg-hold",
        action="store_true",
        help="the pelvis, hips and knees wander with the network while both feet are down and the headset "
        "is quiet (model/runtime/stance.py, LegHold): the runtime before the leg hold",
    )
    parser.add_argument(
        "--lean-gate",
        action="store_true",
        help="every model: a head that leans round the served pelvis holds the legs and feet as a still one "
        "does (model/runtime/stance.py); by default each model as its file says (ModelMetadata.lean_gate)",
    )
    parser.add_argument(
        "--reseat",
        action="store_true",
        help="a held leg or a still foot's anchor far from the network's mean placement moves to it within a "
        "second or so instead of at 0.25 cm/s (model/runtime/stance.py; off by default: it failed "
        "MODEL_CARD.md rules 38 and 39)",
    )
    parser.add_argument(
        "--no-camera",
        action="store_true",
        help="send no RGB-D frame: every model as a headset without the camera is served (the RGB-D models on "
        "the headset stream alone)",
    )
    parser.add_argument(
        "--truth-body",
        action="store_true",
        help="a diagnosis: every model serves each sequence the truth's body (its bone lengths) from the first "
        "sample instead of the session's running estimate (model/runtime/body.py)",
    )
    parser.add_argument(
        "--truth-contact",
        action="store_true",
        help="a diagnosis: every net with a contact head is given the truth's contact labels in place of its "
        "contact output at every sample it answers (what a contact head right at every sample would buy)",
    )
    parser.add_argument(
        "--returning",
        action="store_true",
        help="every model serves each sequence given from its first sample the body an earlier session ended "
        "with (another sequence of the same body, else the same one served before), as a client that kept a "
        "returning wearer's body (PROTOCOL.md §4.2)",
    )
    parser.add_argument(
        "--providers",
        default="cpu",
        help="onnxruntime execution providers, most preferred first (as serve's)",
    )
    parser.add_argument(
        "--intervals", type=int, default=0, metavar="R",
        help="also 95%% intervals over R resamples of the split's people (e.g. 2000), and each model's paired "
        "difference from the first model named",
    )  # fmt: skip
    parser.add_argument("--seed", type=int, default=0, help="the resamples' seed (default 0)")
    parser.add_argument("--json", type=Path, default=None, metavar="OUT")
    parser.add_argument("--no-progress", action="store_true")


def run(args: argparse.Namespace) -> int:
    from ..model.runtime.loading import ModelError, ProviderError, resolve_providers
    from ..model.runtime.procedural import NAME as PROCEDURAL
    from ..model.training.dataset import DatasetError, Fold, subjects
    from ..model.training.evaluate import (
        SOURCES,
        category_difference_table,
        category_table,
        evaluate,
        interval_table,
        keypoint_accuracy,
        keypoint_table,
        markdown_table,
        plausibility_table,
        sequence_table,
        split_sequences,
    )
    from ..model.weights import WEIGHTS_DIR, model_files

    try:
        providers = resolve_providers(args.providers)
    except ProviderError as error:
        print(f"egoposevr eval: {error}", file=sys.stderr)
        return 2
    if not 0 <= args.intervals <= MAX_RESAMPLES:
        print(f"egoposevr eval: --intervals must be 0 (off) to {MAX_RESAMPLES} resamples", file=sys.stderr)
        return 2
    available = {PROCEDURAL: None} | model_files(args.models_dir or WEIGHTS_DIR)  # the baseline has no file
    wanted = list(available) if args.models in ("", "all") else [m.strip() for m in args.models.split(",")]
    try:
        chosen, runtime = _chosen_models(wanted, available)
    except ValueError as error:
        print(f"egoposevr eval: {error}", file=sys.stderr)
        return 2

    try:
        fold = Fold.parse(args.fold) if args.fold is not None else None
    except ValueError as error:
        print(f"egoposevr eval: --fold: {error}", file=sys.stderr)
        return 2

    def progress(name: str, done: int, total: int) -> None:
        if not args.no_progress:
            print(f"\r{name}: {done}/{total} sequences", end="" if done < total else "\n", file=sys.stderr)

    if args.source not in SOURCES:
        print(f"egoposevr eval: --source must be one of {', '.join(SOURCES)}", file=sys.stderr)
        return 2
    try:
        loaded = split_sequences(args.data, args.split, args.limit, fold, args.source)  # read once for both
        results = evaluate(
            args.data,
            args.split,
            chosen,
            args.limit,
            progress,
            by_category=args.by_category,
            providers=providers,
            calibrate=args.calibrate,
            foot_contacts=not args.no_foot_contacts,
            steady_stance=not args.no_steady_stance,
            leg_hold=not args.no_leg_hold,
            lean_gate=True if args.lean_gate else None,
            reseat=args.reseat,
            send_frames=not args.no_camera,
            truth_body=args.truth_body,
            truth_contact=args.truth_contact,
            returning=args.returning,
            runtime=runtime,
            fold=fold,
            loaded=loaded,
            resamples=args.intervals,
            seed=args.seed,
            per_sequence=args.per_sequence,
        )
        keypoints = (
            keypoint_accuracy(args.data, args.split, chosen, args.limit, fold, loaded)
            if args.keypoints
            else None
        )
    except (DatasetError, ModelError) as error:
        print(f"egoposevr eval: {error}", file=sys.stderr)
        return 2
    print(markdown_table(results))
    print(
        "\nDoes the body behave (foot skating and floor error while the true foot is planted, leg leakage while"
    )
    print("the true legs are still; how far the standing height of the body a session ends with is from the")
    print("wearer's):\n")
    print(plausibility_table(results))
    if args.by_category:
        print("\nMPJPE per motion category (upper / lower body, cm):\n")
        print(category_table(results))
        print("\nFoot skating (cm/s) and leg leakage (cm) per motion category, each also after a session's")
        print("first second, and the leakage that did not bring the legs nearer the truth (wander, cm):\n")
        keys = ("foot_skate_cm_s", "foot_skate_settled_cm_s", "leg_leakage_cm", "leg_leakage_settled_cm")
        keys += ("leg_wander_cm",)
        print(category_table(results, keys, "skate / after 1 s / leak / after 1 s / wander"))
    if args.intervals:
        people = len(subjects(loaded[0]))
        print(
            f"\n95 % intervals over {args.intervals} resamples of the split's {people} people, and each model's"
        )
        print(
            f"paired difference from {next(iter(results))} (an interval that holds 0: no difference told):\n"
        )
        print(interval_table(results))
        if args.by_category and len(results) > 1:
            print(
                f"\nLower-body MPJPE per motion category, paired difference from {next(iter(results))} (cm):\n"
            )
            print(category_difference_table(results))
    if args.per_sequence:
        first = next(iter(results))
        print(f"\nLower-body MPJPE (cm) / foot skating (cm/s) per sequence, {first}'s worst first:\n")
        print(sequence_table(results))
    if keypoints is not None:
        print("\nVisual encoders: 3D keypoint error on joints in view and not occluded:\n")
        print(keypoint_table(keypoints))
    read_from = _provenance(args, chosen)
    print(f"\n{_read_from_line(read_from)}")
    if args.json:
        report = {"split": args.split} | (_fold_field(fold, loaded[0]) if fold else {}) | {"models": results}
        report |= {"keypoints": keypoints} if keypoints else {}
        report["provenance"] = read_from
        if args.intervals:
            report["intervals"] = {"resamples": args.intervals, "seed": args.seed, "level": 0.95,
                                   "people": people}  # fmt: skip
        args.json.write_text(json.dumps(_without_nan(report), indent=2, allow_nan=False) + "\n")
    return 0


def _provenance(args: argparse.Namespace, chosen: dict[str, Path | None]) -> dict[str, Any]:
    """What a report's numbers were read from and by what (model/provenance.py): this invocation, the split's
    shard digest, and each served file's and its encoder's digest (the procedural baseline has none)."""
    import onnxruntime

    from ..model import provenance
    from ..model.runtime.loading import LoadedModel

    models: dict[str, Any] = {}
    for label, path in chosen.items():
        if path is None:
            models[label] = None
            continue
        encoder = LoadedModel.load(path).info.visual_path
        models[label] = {"file": str(path), "sha256": provenance.file_digest(path)}
        if encoder is not None:
            models[label]["encoder"] = {"file": str(encoder), "sha256": provenance.file_digest(encoder)}
    host = provenance.machine("cpu", 0, {"onnxruntime": onnxruntime.__version__})
    return {
        "run": provenance.run_record(args.command_line, provenance.code_version(), host),
        "data": {
            "dir": str(args.data),
            "split": args.split,
            "sha256": provenance.data_digest([args.data], args.split),
        },
        "models": models,
    }


def _read_from_line(read_from: dict[str, Any]) -> str:
    """The report's provenance in one line under its tables: the data's and each file's digest, the code."""
    from ..model import provenance

    data, code = read_from["data"], read_from["run"]["code"]
    files = [
        f"{label} {entry['sha256'][:12]}"
        + (f" (encoder {entry['encoder']['sha256'][:12]})" if "encoder" in entry else "")
        for label, entry in read_from["models"].items()
        if entry is not None
    ]
    commit = provenance.short_commit(code)
    return (
        f"Read from {data['dir']} {data['split']} (shards sha256 {data['sha256'][:12]}); "
        f"{', '.join(files) or 'no model file'}; code {commit}."
    )


def _chosen_models(
    wanted: list[str], available: dict[str, Path | None]
) -> tuple[dict[str, Path | None], dict[str, dict[str, bool]]]:
    """({label: model file (None: the procedural baseline)}, {label: runtime options it is served with}) for
    --models' entries: a model's name, or LABEL=FILE, either with @SWITCH... after it (SWITCHES; a name's
    label keeps them: ``egoposevr@no-leg-hold``). Raises ValueError naming what is missing or clashes."""
    chosen: dict[str, Path | None] = {}
    runtime: dict[str, dict[str, bool]] = {}
    for entry in wanted:
        label, is_file, file = entry.partition("=")
        label = label.strip()
        model, *switches = (part.strip() for part in (file if is_file else label).split("@"))
        unknown = [w for w in switches if w not in SWITCHES]
        if unknown:
            raise ValueError(f"--models {entry!r}: unknown @{unknown[0]}; have @{', @'.join(SWITCHES)}")
        if is_file:
            path = Path(model)
            if not label or not path.is_file():
                raise ValueError(f"--models {entry!r}: LABEL=FILE needs a label and an existing model file")
        elif model in available:
            path = available[model]
        else:
            raise ValueError(f"no model file for {model!r}; have {sorted(available)}")
        if label in chosen:
            raise ValueError(f"--models names {label!r} twice")
        chosen[label] = path
        if switches:
            runtime[label] = dict(SWITCHES[w] for w in switches)
    if not chosen:
        raise ValueError(f"no model named; have {sorted(available)}")
    return chosen, runtime


def _without_nan(value):
    """NaN (a metric with nothing to measure on the split) as JSON null."""
    if isinstance(value, dict):
        return {k: _without_nan(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_without_nan(v) for v in value]
    if isinstance(value, float) and value != value:
        return None
    return value


def _fold_field(fold: Any, seqs: list[dict[str, Any]]) -> dict[str, Any]:
    """The JSON report's record of a fold: K/N and the people it served (a fold's number alone names other
    people on other data)."""
    from ..model.training.dataset import subjects

    return {"fold": str(fold), "fold_subjects": subjects(seqs)}
