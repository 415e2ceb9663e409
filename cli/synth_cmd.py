"""Synthesise training data or recorded sessions from motion capture and procedural motion.

Motion (BVH in CMU conventions, AMASS .npz, procedural families) becomes headset + controller tracks and
rendered egocentric RGB-D frames. Without --sessions it writes a sharded dataset under OUT/SPLIT/ with
OUT/manifest.json and a contact-sheet preview; with --sessions, one .egrec recording per clip. The same
--seed gives the same bytes. DATA.md describes both formats.

Example (the development set; DATA.md has the full recipe):
  egoposevr synth --motion ../shared/mocap/cmu/0[1-7]_*.bvh --procedural 240 --out data --split train --seed 1
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


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
        "--motion", nargs="*", default=[], metavar="PATH", help="BVH or AMASS .npz files or folders"
    )
    parser.add_argument("--procedural", type=int, default=0, metavar="N", help="procedural clips to add")
    parser.add_argument("--families", default="", help="comma-separated procedural families (default: all)")
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
    parser.add_argument("--resolution", type=_resolution, default=(320, 256), metavar="WxH")
    parser.add_argument(
        "--seconds", type=_positive, default=10.0, metavar="S", help="clip length; longer captures are cut"
    )
    parser.add_argument(
        "--blur", type=int, default=1, metavar="N", help="motion blur: renders averaged per frame"
    )
    parser.add_argument("--jpeg-quality", type=int, default=90, metavar="Q")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _motion_files(paths: list[str]) -> list[Path]:
    files: list[Path] = []
    for text in paths:
        path = Path(text)
        if path.is_dir():
            files += sorted(p for p in path.iterdir() if p.suffix.lower() in (".bvh", ".npz"))
        elif path.suffix.lower() in (".bvh", ".npz") and path.is_file():
            files.append(path)
        else:
            raise FileNotFoundError(f"{path}: not a .bvh/.npz file or a folder of them")
    return files


def run(args: argparse.Namespace) -> int:
    import numpy as np
    from tqdm import tqdm

    from ..model.synth.amass import AmassError, load_amass_motion
    from ..model.synth.bvh import BvhError, load_bvh_motion
    from ..model.synth.headset import CameraModel
    from ..model.synth.pipeline import (
        DatasetWriter,
        SynthConfig,
        camera_manifest,
        contact_sheet,
        iter_shard_sequences,
        load_shard,
        synthesize_sequence,
        update_manifest,
        write_session,
    )
    from ..model.synth.procedural import FAMILIES, generate
    from ..model.synth.render import Renderer

    try:
        files = _motion_files(args.motion)
    except FileNotFoundError as error:
        print(f"egoposevr synth: {error}", file=sys.stderr)
        return 2
    families = [f for f in args.families.split(",") if f] or sorted(FAMILIES)
    unknown = set(families) - set(FAMILIES)
    if unknown:
        print(
            f"egoposevr synth: unknown families {sorted(unknown)}; known: {sorted(FAMILIES)}", file=sys.stderr
        )
        return 2
    if not files and args.procedural <= 0:
        print("egoposevr synth: nothing to do: give --motion files and/or --procedural N", file=sys.stderr)
        return 2
    hmd_rate = args.hmd_rate or (90.0 if args.sessions else 60.0)
    width, height = args.resolution
    cfg = SynthConfig(
        hmd_rate_hz=hmd_rate,
        camera_rate_hz=args.camera_rate,
        camera=CameraModel(width=width, height=height),
        blur_samples=args.blur,
        jpeg_quality=args.jpeg_quality,
    )
    renderer = Renderer(cfg.camera)
    args.out.mkdir(parents=True, exist_ok=True)

    # Jobs in a fixed order; each gets its own generator seeded by (seed, job index): deterministic.
    jobs: list[tuple[str, object]] = [("file", f) for f in files]
    jobs += [("procedural", families[i % len(families)]) for i in range(args.procedural)]
    writer = None if args.sessions else DatasetWriter(args.out, args.split)
    sources: list[dict] = []
    failures: list[str] = []
    frames = 0
    started = time.perf_counter()
    bar = tqdm(total=len(jobs), unit="clip", disable=args.no_progress, dynamic_ncols=True)
    for index, (kind, what) in enumerate(jobs):
        rng = np.random.default_rng([args.seed, index])
        try:
            if kind == "file":
                path = Path(what)
                motion = load_amass_motion(path) if path.suffix.lower() == ".npz" else load_bvh_motion(path)
            else:
                motion = generate(str(what), args.seconds, 60.0, rng)
                motion = motion.replace(name=f"{what}-{index:04d}")
        except (BvhError, AmassError) as error:
            failures.append(str(error))
            bar.update(1)
            continue
        chunk = max(2, round(args.seconds * motion.fps))
        for start in range(0, motion.num_frames, chunk):
            piece = motion.slice(start, start + chunk)
            if piece.duration_s < min(2.0, args.seconds):
                continue
            name = (
                motion.name
                if start == 0 and chunk >= motion.num_frames
                else f"{motion.name}-{start // chunk:02d}"
            )
            seq = synthesize_sequence(piece, cfg, rng, renderer, name=name)
            frames += len(seq.frames.t_us)
            if writer is None:
                write_session(seq, args.out / f"{name}.egrec", cfg)
            else:
                writer.add(seq)
            sources.append(
                {
                    "name": name,
                    "source": piece.source,
                    "seconds": round(piece.duration_s, 3),
                    "licence": piece.licence,
                }
            )
        bar.update(1)
        bar.set_postfix(fps=f"{frames / (time.perf_counter() - started):.1f}")
    bar.close()
    if writer is not None:
        writer.flush()
    elapsed = time.perf_counter() - started
    rate = frames / elapsed if elapsed > 0 else 0.0
    print(f"{frames} camera frames from {len(sources)} sequences in {elapsed:.1f} s: {rate:.1f} frames/s")
    for failure in failures:
        print(f"skipped: {failure}", file=sys.stderr)

    if writer is not None:
        licences = sorted({s["licence"] for s in sources})
        entry = {
            "seed": args.seed,
            "command": "egoposevr synth " + " ".join(sys.argv[2:]) if sys.argv[1:2] == ["synth"] else "",
            "hmd_rate_hz": hmd_rate,
            "camera_rate_hz": args.camera_rate,
            "seconds": args.seconds,
            "camera": camera_manifest(cfg.camera),
            "counts": writer.counts,
            "shards": writer.shards,
            "sources": sources,
            "licences": licences,
            "procedural_families": families if args.procedural else [],
            "skipped": failures,
        }
        manifest = update_manifest(args.out, args.split, entry)
        if writer.shards:
            shard = load_shard(writer.split_dir / writer.shards[0])
            preview = args.out / f"preview-{args.split}.png"
            contact_sheet(list(iter_shard_sequences(shard)), preview)
            print(f"wrote {manifest} and {preview}")
    return 0 if sources else 1
