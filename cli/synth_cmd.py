"""Synthesise training data or recorded sessions from motion capture and procedural motion.

Motion (BVH from any humanoid rig, AMASS .npz, procedural families) becomes headset + controller tracks and
rendered egocentric RGB-D frames. --motion takes files, folders (searched recursively) and globs; the same
bytes twice and files that cannot be used are skipped and named. --split-by-subject keeps only the clips
whose subject (performer) falls in --split, so that no person is in two splits (`egoposevr motion inspect`
shows the assignment). Without --sessions it writes a sharded dataset under OUT/SPLIT/ with
OUT/manifest.json and a contact-sheet preview; with --sessions, one .egrec recording per clip. The same
--seed gives the same bytes. DATA.md describes both formats.

Example (the development set; DATA.md has the full recipe):
  egoposevr synth --motion ../shared/mocap --split-by-subject train=0.8,val=0.1,test=0.1 --split train \
      --procedural 240 --out data --seed 1
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import shlex
import sys
import time
from pathlib import Path

MIN_PIECE_S = 2.0  # a clip's last piece shorter than this (or --seconds) is dropped


def _shortest_piece_s(seconds: float) -> float:
    """The shortest piece of a clip that becomes a sequence, for sequences of ``seconds`` (--seconds)."""
    return min(MIN_PIECE_S, seconds)


def _resolution(text: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH such as 320x256, got {text!r}") from None
    if not (16 <= width <= 4096 and 16 <= height <= 4096):
        raise argparse.ArgumentTypeError("width and height must be within 16..4096")
    return width, height


def _positive(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--motion", nargs="*", default=[], metavar="PATH", help="BVH/AMASS .npz files, folders or globs"
    )
    parser.add_argument(
        "--split-by-subject",
        metavar="SHARES",
        help="split the motion files by subject, e.g. train=0.8,val=0.1,test=0.1; --split picks one",
    )
    parser.add_argument("--subject-regex", metavar="RE", help="the subject is this regex's first group")
    parser.add_argument(
        "--split-seed", type=int, default=0, help="seed of the subject split (the same for every split's run)"
    )
    parser.add_argument(
        "--licence",
        default="",
        metavar="TEXT",
        help="the motion files' terms (CMU rigs get CMU's by default)",
    )
    parser.add_argument("--procedural", type=int, default=0, metavar="N", help="procedural clips to add")
    parser.add_argument("--families", default="", help="comma-separated procedural families (default: all)")
    parser.add_argument(
        "--mixed",
        type=int,
        default=0,
        metavar="N",
        help="clips that put one --motion file's trunk, head and arms on another's legs (model/synth/mixing.py)",
    )
    parser.add_argument(
        "--no-files",
        action="store_true",
        help="the --motion files are only --mixed's sources: none is synthesised as it is",
    )
    parser.add_argument("--out", type=Path, required=True, metavar="DIR")
    parser.add_argument(
        "--split", default="train", help="dataset split name (folder under OUT); default train"
    )
    parser.add_argument("--sessions", action="store_true", help="write .egrec recorded sessions instead")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--hmd-rate", type=_positive, default=None, metavar="HZ", help="default 60 (90 with --sessions)"
    )
    parser.add_argument("--camera-rate", type=_positive, default=30.0, metavar="HZ")
    parser.add_argument(
        "--resolution",
        type=_resolution,
        metavar="WxH",
        help="default 320x256; with --rig-pool, the only one drawn",
    )
    parser.add_argument(
        "--seconds", type=_positive, default=10.0, metavar="S", help="clip length; longer captures are cut"
    )
    parser.add_argument(
        "--blur", type=int, default=1, metavar="N", help="motion blur: renders averaged per frame"
    )
    parser.add_argument("--jpeg-quality", type=int, default=90, metavar="Q")
    parser.add_argument(
        "--bodies",
        type=Path,
        metavar="FILE",
        help="a body bank (.npz from `egoposevr bodies`): mesh bodies instead of capsules",
    )
    parser.add_argument(
        "--rig-pool",
        choices=["train", "heldout"],
        help="draw each sequence's camera mount and lens, headset fit, grips, tracking, rate, sensor, floor and "
        "body from this pool (heldout: rigs and bodies the train pool never uses); without it one fixed rig",
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=1,
        metavar="N",
        help="processes rendering clips in parallel (default 1)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _select(args: argparse.Namespace) -> tuple[list, dict]:
    """The motion files to use, and the manifest's record of the library (duplicates, split, subjects)."""
    from ..model.synth.library import build_library, motion_seconds, parse_split_shares, split_subjects

    library, empty = build_library(args.motion, args.subject_regex)
    if empty:
        raise FileNotFoundError(f"no .bvh/.npz files in {empty}")
    record: dict = {
        "duplicates_skipped": [f"{a} (same bytes as {b})" for a, b in library.duplicates],
        "unreadable": [f"{a}: {b}" for a, b in library.unreadable],
    }
    files = library.files
    if args.split_by_subject:
        shares = parse_split_shares(args.split_by_subject)
        if args.split not in dict(shares):
            raise ValueError(f"--split {args.split!r} is not one of {[n for n, _ in shares]}")
        seconds: dict[str, float] = {}
        for item in files:
            seconds[item.subject] = seconds.get(item.subject, 0.0) + motion_seconds(item.path)
        assignment = split_subjects(seconds, shares, args.split_seed)
        files = [f for f in files if assignment[f.subject] == args.split]
        record["subject_split"] = {
            "shares": dict(shares),
            "seed": args.split_seed,
            "subjects": {name: sorted(s for s, n in assignment.items() if n == name) for name, _ in shares},
            "hours": {
                name: round(sum(seconds[s] for s, n in assignment.items() if n == name) / 3600, 4)
                for name, _ in shares
            },
        }
    return files, record


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from ..model import provenance
    from ..model.synth.bodies import BodyBank, BodyBankError
    from ..model.synth.headset import CameraModel
    from ..model.synth.pipeline import (
        DatasetWriter,
        SynthConfig,
        camera_manifest,
        contact_sheet,
        iter_shard_sequences,
        load_shard,
        update_manifest,
        write_session,
    )
    from ..model.synth.procedural import FAMILIES
    from ..model.synth.variation import POOLS

    try:
        files, library_record = _select(args) if args.motion else ([], {})
    except (FileNotFoundError, ValueError) as error:
        print(f"egoposevr synth: {error}", file=sys.stderr)
        return 2
    families = [f for f in args.families.split(",") if f] or sorted(FAMILIES)
    unknown = set(families) - set(FAMILIES)
    if unknown:
        print(
            f"egoposevr synth: unknown families {sorted(unknown)}; known: {sorted(FAMILIES)}", file=sys.stderr
        )
        return 2
    if args.mixed > 0 and len(files) < 2:
        print("egoposevr synth: --mixed needs two --motion files or more to mix", file=sys.stderr)
        return 2
    try:
        pairs = _pairs(files, args)
    except ValueError as error:
        print(f"egoposevr synth: {error}", file=sys.stderr)
        return 2
    if (not files or args.no_files) and args.procedural <= 0 and args.mixed <= 0:
        print("egoposevr synth: nothing to do: give --motion files and/or --procedural N", file=sys.stderr)
        return 2
    try:
        bank = BodyBank.load(args.bodies) if args.bodies else None
    except BodyBankError as error:
        print(f"egoposevr synth: {error}", file=sys.stderr)
        return 2
    hmd_rate = args.hmd_rate or (90.0 if args.sessions else 60.0)
    width, height = args.resolution or (320, 256)
    pool = None
    if args.rig_pool:
        pool = POOLS[args.rig_pool]
        pool = dataclasses.replace(pool, resolutions=(args.resolution,)) if args.resolution else pool
    cfg = SynthConfig(
        hmd_rate_hz=hmd_rate,
        camera_rate_hz=args.camera_rate,
        camera=CameraModel(width=width, height=height),
        blur_samples=args.blur,
        jpeg_quality=args.jpeg_quality,
        bodies=bank,
        rig_pool=pool,
    )
    args.out.mkdir(parents=True, exist_ok=True)

    # Jobs in a fixed order; each gets its own generator seeded by (seed, job index): deterministic, and the
    # results are written in job order whichever worker made them.
    jobs: list[tuple[int, str, object]] = (
        [] if args.no_files else [(i, "file", f) for i, f in enumerate(files)]
    )
    jobs += [(len(files) + i, "procedural", families[i % len(families)]) for i in range(args.procedural)]
    jobs += [(len(files) + args.procedural + i, "mixed", pair) for i, pair in enumerate(pairs)]
    writer = None if args.sessions else DatasetWriter(args.out, args.split)
    sources: list[dict] = []
    failures: list[str] = []
    frames = 0
    started = time.perf_counter()
    bar = tqdm(total=len(jobs), unit="clip", disable=args.no_progress, dynamic_ncols=True)
    for seqs, job_sources, failure in _run_jobs(jobs, args, cfg):
        if failure:
            failures.append(failure)
        for seq, source in zip(seqs, job_sources, strict=True):
            frames += len(seq.frames.t_us)
            if writer is None:
                write_session(seq, args.out / f"{seq.name}.egrec", cfg)
            else:
                writer.add(seq)
            sources.append(source)
        bar.update(1)
        bar.set_postfix(fps=f"{frames / (time.perf_counter() - started):.1f}")
    bar.close()
    if writer is not None:
        writer.flush()
    elapsed = time.perf_counter() - started
    rate = frames / elapsed if elapsed > 0 else 0.0
    print(f"{frames} camera frames from {len(sources)} sequences in {elapsed:.1f} s: {rate:.1f} frames/s")
    for failure in failures + library_record.get("duplicates_skipped", []):
        print(f"skipped: {failure}", file=sys.stderr)

    if writer is not None:
        licences = sorted({s["licence"] for s in sources})
        entry = {
            "seed": args.seed,
            "command": shlex.join(args.command_line),
            "code": provenance.code_version(),
            "hmd_rate_hz": hmd_rate,
            "camera_rate_hz": args.camera_rate,
            "seconds": args.seconds,
            "camera": camera_manifest(cfg.camera),
            "counts": writer.counts,
            "shards": writer.shards,
            "sources": sources,
            "licences": licences,
            "procedural_families": families if args.procedural else [],
            "mixed": args.mixed,
            "skipped": failures,
            "motion_library": library_record,
            "bodies": _bank_record(args.bodies, bank) if bank is not None else None,
            "rig_pool": args.rig_pool,
        }
        entry["shards_sha256"] = provenance.folder_digest(args.out, args.split)  # what a net's record names
        manifest = update_manifest(args.out, args.split, entry)
        if writer.shards:
            shard = load_shard(writer.split_dir / writer.shards[0])
            preview = args.out / f"preview-{args.split}.png"
            contact_sheet(list(iter_shard_sequences(shard)), preview)
            print(f"wrote {manifest} and {preview}")
    return 0 if sources else 1


_JOB_CONTEXT: dict = {}  # args and config of the run, set once per process (workers: by the initializer)


def _set_context(args: argparse.Namespace, cfg) -> None:
    _JOB_CONTEXT.update(args=args, cfg=cfg)


def worker_threads(workers: int, cpus: int | None = None) -> int:
    """Threads each of ``workers`` render processes may use: the machine's CPUs shared out. Left at numba's
    and OpenCV's default (every CPU each), 16 workers on 16 cores ran 256 threads and wrote nothing in 7
    minutes (MODEL_CARD.md, the lent H100)."""
    return max(1, (cpus or os.cpu_count() or 1) // max(1, workers))


def _init_worker(args: argparse.Namespace, cfg, threads: int) -> None:
    import cv2
    import numba

    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    cv2.setNumThreads(threads)
    _set_context(args, cfg)


def _run_jobs(jobs: list, args: argparse.Namespace, cfg):
    """Each job's (sequences, their manifest sources, failure or None), in job order; in --workers processes
    when asked."""
    if args.workers <= 1:
        _set_context(args, cfg)
        yield from map(_job, jobs)
        return
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    context = multiprocessing.get_context("spawn")  # no fork of a process that holds numba's threads
    threads = worker_threads(args.workers)
    with ProcessPoolExecutor(
        args.workers, mp_context=context, initializer=_init_worker, initargs=(args, cfg, threads)
    ) as pool:
        yield from pool.map(_job, jobs)


def _job(job: tuple[int, str, object]) -> tuple[list, list[dict], str | None]:
    """One motion source -> its sequences (cut into --seconds pieces) with their manifest entries."""
    import numpy as np

    from ..model.synth.amass import AmassError
    from ..model.synth.bvh import BvhError
    from ..model.synth.mixing import mix_halves
    from ..model.synth.pipeline import synthesize_sequence
    from ..model.synth.procedural import Body, generate
    from ..model.synth.variation import pool_bodies

    index, kind, what = job
    args, cfg = _JOB_CONTEXT["args"], _JOB_CONTEXT["cfg"]
    bank = cfg.bodies
    rng = np.random.default_rng([args.seed, index])
    body = None
    if bank is not None:  # drawn before the motion: procedural motion is made on this body's bones
        body = int(rng.choice(pool_bodies(bank.count, cfg.rig_pool) if cfg.rig_pool else bank.count))
    try:
        if kind == "file":
            motion = _load(what, args)
        elif kind == "mixed":
            legs, upper = (_load(item, args) for item in what)
            motion = mix_halves(legs, upper, rng, args.seconds, name=f"mixed-{index:04d}")
        else:
            on = Body.from_scale(bank.bone_scale(body)) if bank is not None else None
            motion = generate(str(what), args.seconds, 60.0, rng, on)
            motion = motion.replace(name=f"{what}-{index:04d}")
    except (BvhError, AmassError) as error:
        return [], [], f"{what.path}: {error}" if kind == "file" else f"{kind} {index}: {error}"
    except ValueError as error:  # a clip too short to mix; anything else is a bug and stops the run
        if kind != "mixed":
            raise
        return [], [], f"mixed {index}: {error}"
    seqs, sources = [], []
    chunk = max(2, round(args.seconds * motion.fps))
    for start in range(0, motion.num_frames, chunk):
        piece = motion.slice(start, start + chunk)
        if piece.duration_s < _shortest_piece_s(args.seconds):
            continue
        name = (
            motion.name
            if start == 0 and chunk >= motion.num_frames
            else f"{motion.name}-{start // chunk:02d}"
        )
        seq = synthesize_sequence(piece, cfg, rng, name=name, body=body)
        seqs.append(seq)
        sources.append(
            {
                "name": name,
                "source": piece.source,
                "seconds": round(piece.duration_s, 3),
                "licence": piece.licence,
            }
            | ({"body": seq.body} if bank is not None else {})
            | ({"rig": seq.rig} if seq.rig is not None else {})
            | ({"file": str(what.path), "subject": what.subject} if kind == "file" else {})
            | (
                {"files": [str(item.path) for item in what], "subjects": [item.subject for item in what]}
                if kind == "mixed"
                else {}
            )
        )
    return seqs, sources, None


def _load(item, args: argparse.Namespace):
    """One motion file of the library -> its Motion, with --licence's terms or its source's default."""
    from ..model.synth.amass import load_amass_motion
    from ..model.synth.bvh import load_bvh_motion

    path = item.path
    motion = load_amass_motion(path) if path.suffix.lower() == ".npz" else load_bvh_motion(path)
    if args.licence:
        return motion.replace(licence=args.licence)
    return motion if motion.licence else motion.replace(licence=_default_licence(motion.source))


def _pairs(files: list, args: argparse.Namespace) -> list[tuple]:
    """--mixed's (legs, upper body) file pairs, drawn with --seed: the legs' file in proportion to its length
    (a second of anyone's walking is as likely as any other), the upper body's from another subject where
    the files have two or more (one person's arms on their own legs teach little new)."""
    import numpy as np

    from ..model.synth.library import motion_seconds

    if args.mixed <= 0:
        return []
    rng = np.random.default_rng([args.seed, len(files), args.mixed])
    # legs shorter than a sequence's shortest piece would make nothing (as such a file makes nothing itself)
    seconds = np.array([motion_seconds(item.path) for item in files])
    shortest_s = _shortest_piece_s(args.seconds)
    seconds[seconds < shortest_s] = 0.0
    if not seconds.any():
        raise ValueError(f"--mixed: no --motion file is {shortest_s:g} s long, to take legs from")
    pairs = []
    for _ in range(args.mixed):
        legs = files[int(rng.choice(len(files), p=seconds / seconds.sum()))]
        others = [f for f in files if f.subject != legs.subject] or [f for f in files if f is not legs]
        pairs.append((legs, others[int(rng.integers(len(others)))]))
    return pairs


def _bank_record(path: Path, bank) -> dict:
    """The manifest's record of a body bank: file, source, and each body's shape parameters."""
    return {
        "file": str(path),
        "source": bank.source,
        "count": bank.count,
        "phenotype_names": list(bank.phenotype_names),
        "phenotype": [[round(float(v), 4) for v in row] for row in bank.phenotype],
    }


def _default_licence(source: str) -> str:
    """CMU's terms for motion read from one of the CMU database's rigs; otherwise say that none was given."""
    from ..model.synth.bvh import CMU_LICENCE

    if source.startswith("cmu"):
        return CMU_LICENCE
    return "not given: pass --licence with the terms of these files"
