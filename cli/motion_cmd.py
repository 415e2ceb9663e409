"""Inspect motion files: the rig read from each BVH, how it retargets to SMPL-22, and a library's splits.

`egoposevr motion inspect FILE|FOLDER|GLOB...` prints, per BVH file, the detected family (or 'unrecognised' when
the structure alone was read), units, up and forward axes, frame rate, duration, reference frames dropped
and the retargeting error (cm: distance between the SMPL-22 result and the source joints it was mapped to;
the pelvis and spine3 are placed by the retargeting and not counted). One file: the whole joint mapping too.
A file that cannot be used is named with the reason. AMASS .npz files (SMPL already) get their frame rate
and duration. With --split-by-subject, the subjects and hours each split would get.

Examples:
  egoposevr motion inspect my_clip.bvh --png my_clip.png
  egoposevr motion inspect ../shared/mocap --split-by-subject train=0.8,val=0.1,test=0.1 --json lib.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    commands = parser.add_subparsers(dest="motion_command", metavar="ACTION", required=True)
    inspect = commands.add_parser("inspect", help="report the rig and retargeting of motion files")
    inspect.add_argument("paths", nargs="+", metavar="FILE", help="BVH files, folders (recursive) or globs")
    inspect.add_argument("--png", type=Path, metavar="PATH", help="a picture per file (a folder for several)")
    inspect.add_argument("--json", type=Path, metavar="FILE", help="write the reports as JSON")
    inspect.add_argument("--subject-regex", metavar="RE", help="the subject is this regex's first group")
    inspect.add_argument(
        "--split-by-subject",
        metavar="SHARES",
        help="report the subject-disjoint split, e.g. train=0.8,val=0.2",
    )
    inspect.add_argument("--split-seed", type=int, default=0, help="seed of the subject split (as synth's)")
    inspect.add_argument("--verbose", action="store_true", help="the joint mapping of every file")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from ..model.synth.amass import AmassError
    from ..model.synth.bvh import BvhError
    from ..model.synth.inspection import amass_report, inspect_bvh, report, sheet, summary_line
    from ..model.synth.library import build_library, motion_seconds, parse_split_shares, split_subjects

    try:
        shares = parse_split_shares(args.split_by_subject) if args.split_by_subject else None
    except ValueError as error:
        print(f"egoposevr motion: {error}", file=sys.stderr)
        return 2
    library, empty = build_library(args.paths, args.subject_regex)
    for pattern in empty:
        print(f"egoposevr motion: {pattern}: no .bvh/.npz file there", file=sys.stderr)
    files = library.files
    several = len(files) > 1
    if args.png and several:
        args.png.mkdir(parents=True, exist_ok=True)
    reports, failures, errors_cm = [], [], []
    seconds: dict[str, float] = {}
    for item in files:
        try:
            if item.path.suffix.lower() == ".npz":
                inspection, entry = None, amass_report(item.path) | {"subject": item.subject}
            else:
                inspection = inspect_bvh(item.path)
                entry = report(inspection) | {"subject": item.subject}
        except (BvhError, AmassError) as error:
            failures.append({"file": str(item.path), "reason": str(error)})
            print(f"{item.path}: cannot use: {error}")
            continue
        reports.append(entry)
        # The split weighs subjects by the files' header durations, exactly as `egoposevr synth` does.
        seconds[item.subject] = seconds.get(item.subject, 0.0) + motion_seconds(item.path)
        print(summary_line(entry))
        if inspection is None:
            continue  # AMASS: no rig, no mapping, no picture of a source skeleton
        errors_cm.append(inspection.result.error_m[::4].ravel() * 100)
        if not several or args.verbose:
            _print_mapping(entry)
        if args.png:
            sheet(inspection, args.png / f"{item.path.stem}.png" if several else args.png)
    pooled = np.concatenate(errors_cm) if errors_cm else np.zeros(0)
    pooled = pooled[np.isfinite(pooled)]
    summary = {
        "files": len(reports),
        "failed": failures,
        "duplicates": [[str(a), str(b)] for a, b in library.duplicates],
        "unreadable": [[str(a), b] for a, b in library.unreadable],
        "hours": round(sum(r["duration_s"] for r in reports) / 3600, 3),
        "retarget_error_cm": {
            "median": round(float(np.median(pooled)), 2) if len(pooled) else None,
            "p95": round(float(np.percentile(pooled, 95)), 2) if len(pooled) else None,
        },
    }
    if shares:
        assignment = split_subjects(seconds, shares, args.split_seed)
        summary["splits"] = {
            name: {
                "subjects": sorted(s for s, n in assignment.items() if n == name),
                "hours": round(sum(seconds[s] for s, n in assignment.items() if n == name) / 3600, 3),
            }
            for name, _ in shares
        }
    if several or shares:
        _print_summary(summary)
    if args.json:
        args.json.write_text(json.dumps({"summary": summary, "files": reports}, indent=2) + "\n")
    return 0 if reports and not failures else 1


def _print_mapping(entry: dict) -> None:
    for joint, where in entry["mapping"].items():
        print(f"    {joint:15s} <- {where}")
    by_joint = entry["retarget_error_cm"]["p95_by_joint"]
    print("    p95 error by joint (cm): " + ", ".join(f"{k} {v:.1f}" for k, v in by_joint.items()))
    for note in entry["notes"]:
        print(f"    note: {note}")


def _print_summary(summary: dict) -> None:
    error = summary["retarget_error_cm"]
    print(
        f"\n{summary['files']} files retargeted ({summary['hours']:.2f} h), {len(summary['failed'])} failed, "
        f"{len(summary['duplicates'])} duplicates skipped, {len(summary['unreadable'])} unreadable; "
        f"retargeting error median {error['median']} cm, p95 {error['p95']} cm"
    )
    for name, split in summary.get("splits", {}).items():
        print(f"  {name}: {split['hours']:.3f} h, subjects {', '.join(split['subjects'])}")
    for failure in summary["failed"]:
        print(f"  failed: {failure['file']}: {failure['reason']}")
    for skipped, kept in summary["duplicates"]:
        print(f"  duplicate: {skipped} (same bytes as {kept})")
