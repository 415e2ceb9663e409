"""Test helper: a small egocentric RGB-D frame as files, the way a client's camera would hand them over."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np


def camera_images(folder: Path) -> tuple[Path, Path]:
    """(rgb.jpg, depth.png) in ``folder``: a 160×128 JPEG and 16-bit millimetre PNG of a floor 1.5 m away with a
    warm patch."""
    rgb = np.full((128, 160, 3), 90, np.uint8)
    rgb[40:90, 60:100] = (40, 120, 200)
    depth = np.full((128, 160), 1500, np.uint16)
    ok_rgb, jpeg = cv2.imencode(".jpg", rgb)
    ok_depth, png = cv2.imencode(".png", depth)
    assert ok_rgb and ok_depth
    (folder / "rgb.jpg").write_bytes(jpeg.tobytes())
    (folder / "depth.png").write_bytes(png.tobytes())
    return folder / "rgb.jpg", folder / "depth.png"
