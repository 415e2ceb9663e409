"""The picture in docs/: the same six procedural clips rendered as before (capsule bodies, the one fixed rig)
and by synthesis v2 (anny mesh bodies, rigs drawn from the training pool), a frame of each, RGB and depth.

Usage: python benchmarks/synthesis_sheet.py BANK.npz OUT.jpg
"""

import sys

import cv2
import numpy as np

from egoposevr.model.synth.bodies import BodyBank
from egoposevr.model.synth.pipeline import SynthConfig, _letterbox, synthesize_sequence
from egoposevr.model.synth.procedural import Body, generate
from egoposevr.model.synth.variation import POOLS

bank = BodyBank.load(sys.argv[1])
rows = []
for k, family in enumerate(["walk", "squat", "stand_interact", "lunge", "kick", "bend_pick_up"]):
    motion = generate(
        family, 3.0, 60.0, np.random.default_rng([7, k]), Body.from_scale(bank.bone_scale(k % bank.count))
    )
    old = synthesize_sequence(motion, SynthConfig(hmd_rate_hz=90.0), np.random.default_rng([1, k]))
    new = synthesize_sequence(
        motion,
        SynthConfig(hmd_rate_hz=90.0, bodies=bank, rig_pool=POOLS["train"]),
        np.random.default_rng([1, k]),
        body=k % bank.count,
    )
    frame = 45
    tiles = []
    for seq in (old, new):
        bgr = cv2.imdecode(
            np.frombuffer(seq.frames.rgb_jpeg[min(frame, len(seq.frames.rgb_jpeg) - 1)], np.uint8),
            cv2.IMREAD_COLOR,
        )
        depth = cv2.imdecode(
            np.frombuffer(seq.frames.depth_png[min(frame, len(seq.frames.depth_png) - 1)], np.uint8),
            cv2.IMREAD_UNCHANGED,
        )
        colour = cv2.applyColorMap(np.clip(depth / 3000.0 * 255, 0, 255).astype(np.uint8), cv2.COLORMAP_TURBO)
        colour[depth == 0] = 0
        tiles += [_letterbox(bgr, (200, 160)), _letterbox(colour, (200, 160))]
    rows.append(np.concatenate(tiles, axis=1))
sheet = np.concatenate(rows, axis=0)
cv2.putText(
    sheet,
    "before: capsules, one rig",
    (6, 16),
    cv2.FONT_HERSHEY_SIMPLEX,
    0.5,
    (255, 255, 255),
    1,
    cv2.LINE_AA,
)
cv2.putText(
    sheet,
    "v2: anny bodies, drawn rigs",
    (406, 16),
    cv2.FONT_HERSHEY_SIMPLEX,
    0.5,
    (255, 255, 255),
    1,
    cv2.LINE_AA,
)
cv2.imwrite(sys.argv[2], sheet, [cv2.IMWRITE_JPEG_QUALITY, 85])  # sensor noise: PNG would be 0.9 MB
