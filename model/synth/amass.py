"""AMASS ``.npz`` motion (SMPL-H parameters) -> :class:`Motion`.

AMASS files hold ``poses`` (F, 156) axis-angle (the first 22 joints are the SMPL body; the rest are hands),
``trans`` (F, 3) metres and ``mocap_framerate``, in a z-up world. Users bring the files (AMASS has its own
licence); nothing from AMASS ships with the project.
"""

from __future__ import annotations

from pathlib import Path
from typing import Final

import numpy as np

from ..rotations import axis_angle_to_matrix
from ..skeleton import NUM_JOINTS
from .motion import Motion, ground, resample

AMASS_LICENCE: Final = "AMASS (amass.is.tue.mpg.de): non-commercial research licence; bring your own copy."

# AMASS's world is z-up; ours is y-up (x stays): a -90° turn about x maps z-up onto y-up.
Z_UP_TO_Y_UP: Final = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


class AmassError(ValueError):
    """An AMASS file that cannot be used; the message names the file and the problem."""


def load_amass_motion(path: str | Path, fps: float | None = None) -> Motion:
    """Load one AMASS sequence, grounded (floor y = 0), optionally resampled to ``fps``.

    The body is the SMPL rest skeleton (bone scale 1): the shape ``betas`` need the SMPL model itself to turn
    into joint positions. The pelvis path is ``trans`` turned to y-up; SMPL's rest pelvis offset J0(β) only
    shifts the whole clip, which grounding removes.
    """
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            poses = np.asarray(data["poses"], dtype=np.float64)
            trans = np.asarray(data["trans"], dtype=np.float64)
            rate = float(np.asarray(data["mocap_framerate"]))
    except (OSError, ValueError, KeyError) as error:
        raise AmassError(
            f"{path}: not an AMASS .npz with poses, trans and mocap_framerate ({error})"
        ) from None
    if (
        poses.ndim != 2
        or poses.shape[1] < 3 * NUM_JOINTS
        or trans.shape != (len(poses), 3)
        or len(poses) == 0
    ):
        raise AmassError(
            f"{path}: poses must be (F, >=66) and trans (F, 3); got {poses.shape}, {trans.shape}"
        )
    if not (np.isfinite(poses).all() and np.isfinite(trans).all() and np.isfinite(rate) and rate > 0):
        raise AmassError(f"{path}: non-finite values or a bad mocap_framerate ({rate})")
    local_rot = axis_angle_to_matrix(poses[:, : 3 * NUM_JOINTS].reshape(-1, NUM_JOINTS, 3))
    local_rot[:, 0] = Z_UP_TO_Y_UP @ local_rot[:, 0]
    motion = Motion(
        name=path.stem,
        fps=rate,
        local_rot=local_rot,
        root_pos_m=trans @ Z_UP_TO_Y_UP.T,
        bone_scale=np.ones(NUM_JOINTS),
        source=f"amass:{path.stem}",
        licence=AMASS_LICENCE,
    )
    motion = ground(motion)
    return motion if fps is None else resample(motion, fps)
