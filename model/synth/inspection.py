"""What ``egoposevr motion inspect`` says about a motion file: the rig read from it, how well it retargets.

A report per file (family, joint mapping, units, axes, frame rate, duration, frames dropped, retargeting
error, whether the feet stand flat and grip: their tilt, how much they slide while the body travels, before
and after synth's import fixes them, and how high a standing foot is) and a PNG of a few frames with the
source skeleton (grey, every joint of the file) beside the retargeted SMPL-22 skeleton (colour), both seen
from the front in our axes.

Shape legend: ``F`` frames, ``S`` source joints, ``J`` = 22 SMPL joints.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..skeleton import JOINT_NAMES, PARENTS
from .amass import load_amass_motion
from .bvh import BvhClip, Retargeted, bvh_fk, load_bvh, mapped_positions, retarget_bvh
from .motion import Motion, fix_feet, foot_slide, stance_foot_height_m, standing_foot_tilt_deg
from .rigs import DetectedRig


@dataclasses.dataclass
class Inspection:
    """A retargeted file with its source skeleton in our frame (metres), for reports and pictures."""

    path: Path
    clip: BvhClip
    result: Retargeted
    source_m: np.ndarray  # (F, S, 3) source joints in our axes, the result's frames, grounded like it

    @property
    def rig(self) -> DetectedRig:
        assert self.result.rig is not None
        return self.result.rig


def inspect_bvh(path: Path) -> Inspection:
    """Load, detect and retarget one BVH file (raises ``BvhError`` with the reason when it cannot)."""
    clip = load_bvh(path)
    result = retarget_bvh(clip, name=path.stem)
    rig = result.rig
    assert rig is not None
    pos, _ = bvh_fk(clip)
    source = (pos @ rig.world_from_file.T * rig.mapping.metres_per_unit)[result.dropped :]
    shift = np.nanmedian(
        result.motion.joints()[:, [1, 2]] - _named(source, clip, rig, ("L_hip", "R_hip")), (0, 1)
    )
    return Inspection(path, clip, result, source + shift)


def _named(source: np.ndarray, clip: BvhClip, rig: DetectedRig, roles: tuple[str, ...]) -> np.ndarray:
    return source[:, [clip.names.index(rig.roles[r]) for r in roles]]


def amass_report(path: Path) -> dict[str, Any]:
    """The report of an AMASS file: SMPL already, so nothing to detect and no retargeting error."""
    motion = load_amass_motion(path)
    return {
        "file": str(path),
        "family": "amass",
        "anchors_from": "smpl",
        "units": "m",
        "metres_per_unit": 1.0,
        "up_axis": "+Z",
        "forward_axis": "(per clip)",
        "frame_rate_hz": round(motion.fps, 3),
        "duration_s": round(motion.duration_s, 3),
        "frames_dropped": 0,
        "source_joints": 22,
        "retarget_error_cm": {"median": 0.0, "p95": 0.0, "max": 0.0, "p95_by_joint": {}},
        "roles": {},
        "mapping": {},
        "notes": ["AMASS: SMPL-H parameters, the body at SMPL's mean shape (bone scale 1)"],
        "feet": feet_report(motion, None, motion),  # AMASS is SMPL already: imported as it is
    }


def report(item: Inspection) -> dict[str, Any]:
    """The JSON-able report of one file."""
    rig, motion, error_cm = item.rig, item.result.motion, item.result.error_m * 100
    measured = [j for j in range(len(JOINT_NAMES)) if np.isfinite(error_cm[:, j]).any()]  # hubs are NaN
    return {
        "file": str(item.path),
        "family": rig.family or "unrecognised",
        "anchors_from": rig.anchors_from,
        "units": rig.units,
        "metres_per_unit": rig.mapping.metres_per_unit,
        "up_axis": rig.up_axis,
        "forward_axis": rig.forward_axis,
        "frame_rate_hz": round(motion.fps, 3),
        "duration_s": round(motion.duration_s, 3),
        "frames_dropped": item.result.dropped,
        "source_joints": int(sum(not e for e in item.clip.end_site)),
        "retarget_error_cm": {
            "median": round(float(np.nanmedian(error_cm)), 2),
            "p95": round(float(np.nanpercentile(error_cm, 95)), 2),
            "max": round(float(np.nanmax(error_cm)), 2),
            "p95_by_joint": {
                JOINT_NAMES[j]: round(float(np.nanpercentile(error_cm[:, j], 95)), 2) for j in measured
            },
        },
        "roles": rig.roles,
        "mapping": {
            joint: _describe(source.a, source.b, source.weight, source.rotation, source.hub)
            for joint, source in rig.mapping.joints.items()
        },
        "notes": list(rig.notes),
        "feet": feet_report(motion, _source_smpl(item), fix_feet(motion)),
    }


def _source_smpl(item: Inspection) -> np.ndarray:
    """(F, J, 3) the source's joints where the mapping reads SMPL's, the pelvis between the mapped hips (a hub
    may have no position of its own)."""
    mapped = mapped_positions(item.source_m, item.clip.names, item.rig.mapping).copy()
    mapped[:, 0] = mapped[:, [1, 2]].mean(axis=1)
    return mapped


def feet_report(motion: Motion, source_m: np.ndarray | None, imported: Motion) -> dict[str, float | None]:
    """Do the feet stand flat and grip: how far a standing foot's toes point up (the mean of
    :func:`~.motion.standing_foot_tilt_deg`; synth turns it back), :func:`~.motion.foot_slide` of the result
    and of the file's own skeleton ``source_m`` (F, J, 3) (does the file slide, or the retargeting?), and of
    ``imported``, the motion as synth trains on it (for BVH :func:`~.motion.fix_feet`): its slide and where a
    standing foot is (:func:`~.motion.stance_foot_height_m`, 3.5 cm when it stands flat on the floor)."""
    joints, imported_joints = motion.joints(), imported.joints()

    def rounded(value: float | None, scale: float = 1.0) -> float | None:
        return None if value is None else round(value * scale, 3)

    return {
        "tilt_deg": rounded(float(np.mean(standing_foot_tilt_deg(motion)))),
        "slide": rounded(foot_slide(joints, motion.fps)),
        "source_slide": None if source_m is None else rounded(foot_slide(source_m, motion.fps)),
        "imported_slide": rounded(foot_slide(imported_joints, imported.fps)),
        "stance_foot_height_cm": rounded(stance_foot_height_m(imported_joints, imported.fps), 100.0),
    }


def _describe(a: str, b: str | None, weight: float, rotation: str, hub: bool) -> str:
    if hub:
        return f"hub at {a} (placed from its children), turned by {rotation}"
    where = a if b is None else f"{weight:.2f} of the way {a} -> {b}"
    return where if rotation == a else f"{where}, turned by {rotation}"


def summary_line(item: dict[str, Any]) -> str:
    error = item["retarget_error_cm"]
    return (
        f"{item['file']}: {item['family']} ({item['anchors_from']}), {item['units']}, up {item['up_axis']}, "
        f"forward {item['forward_axis']}, {item['frame_rate_hz']:g} Hz, {item['duration_s']:.1f} s, "
        f"dropped {item['frames_dropped']}, error median {error['median']:.2f} / p95 {error['p95']:.2f} cm"
        + _feet_words(item.get("feet", {}))
    )


def _feet_words(feet: dict[str, float | None]) -> str:
    """', toes up 13°, feet slide 0.41 (file 0.40), stand at 6.5 cm' -- whatever of it was measured."""
    words = []
    if feet.get("tilt_deg") is not None:
        words.append(f"toes up {feet['tilt_deg']:.0f}°")
    if feet.get("slide") is not None:
        source = feet.get("source_slide")
        words.append(f"feet slide {feet['slide']:.2f}" + ("" if source is None else f" (file {source:.2f})"))
    if feet.get("imported_slide") is not None:
        words.append(f"{feet['imported_slide']:.2f} imported")
    if feet.get("stance_foot_height_cm") is not None:
        words.append(f"stand at {feet['stance_foot_height_cm']:.1f} cm")
    return "".join(f", {w}" for w in words)


# ------------------------------------------------------------------------------------------- picture
def _draw(canvas: np.ndarray, points: np.ndarray, parents: np.ndarray, colour, origin, scale) -> None:
    uv = np.stack([origin[0] - points[:, 0] * scale, origin[1] - points[:, 1] * scale], axis=-1)
    uv = np.round(uv).astype(int)
    for j, p in enumerate(parents):
        if p >= 0:
            cv2.line(canvas, tuple(uv[p]), tuple(uv[j]), colour, 2, cv2.LINE_AA)
    for point in uv:
        cv2.circle(canvas, tuple(point), 3, colour, -1, cv2.LINE_AA)


def sheet(item: Inspection, path: Path, frames: int = 4, tile_px: int = 300) -> None:
    """A PNG: for ``frames`` frames, the source skeleton (grey) beside the retargeted SMPL-22 (colour)."""
    joints = item.result.motion.joints()
    picks = np.linspace(0, len(joints) - 1, frames).astype(int)
    scale = tile_px / 2.2  # a 2.2 m tall view
    tiles = []
    for k in picks:
        centre = joints[k, 0, [0, 2]]
        tile = np.full((tile_px, 2 * tile_px, 3), 255, np.uint8)
        floor_v = tile_px - 20
        cv2.line(tile, (0, floor_v), (2 * tile_px, floor_v), (180, 180, 180), 1)
        source = item.source_m[k] - [centre[0], 0, centre[1]]
        smpl = joints[k] - [centre[0], 0, centre[1]]
        _draw(tile, source, item.clip.parents, (150, 150, 150), (tile_px / 2, floor_v), scale)
        _draw(tile, smpl, PARENTS, (40, 90, 220), (1.5 * tile_px, floor_v), scale)
        label = f"frame {k + item.result.dropped}  source | SMPL-22"
        cv2.putText(tile, label, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
        tiles.append(tile)
    header = np.full((24, 2 * tile_px, 3), 255, np.uint8)
    title = f"{item.path.name}: {item.rig.family or 'unrecognised'}, {item.rig.units}, up {item.rig.up_axis}"
    cv2.putText(header, title[:70], (6, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    image = np.concatenate([header, *tiles], axis=0)
    if not cv2.imwrite(str(path), image):
        raise OSError(f"could not write {path}")
