"""Egocentric RGB-D rendering by ray casting: a capsule body in a textured room, seen from the headset camera.

Every pixel's ray is intersected analytically with the body's capsules (each tested only inside its
projected bounding box), the floor, the room's walls and a few boxes; the nearest hit wins. That gives
true per-pixel depth with correct self-occlusion. Shading is Lambert with ambient light, and clothing
patterns are computed from surface coordinates. After that, the depth gets sensor noise that grows with
distance, holes at depth edges, random dropouts and range limits; the RGB image gets noise and
vignetting, and optionally motion blur.

The kernel is numba-compiled (parallel over image rows, cached on disk after the first compile): about
4-6 ms a frame at 320×256 on this project's 2-core machines.

Shape legend: ``H``×``W`` image, ``C`` capsules, ``M`` materials, ``J`` = 22 joints.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Final

import numpy as np
from numba import njit, prange
from scipy.spatial.transform import Rotation

from ..skeleton import forward_kinematics, rest_offsets
from . import raster
from .bodies import (
    REGION_FACE,
    REGION_FOOT,
    REGION_FOREARM,
    REGION_HAND,
    REGION_HIPS,
    REGION_INNER,
    REGION_NECK,
    REGION_SCALP,
    REGION_SHIN,
    REGION_THIGH,
    REGION_TORSO,
    REGION_UPPER_ARM,
    BodyBank,
    pose_vertices,
)  # fmt: skip
from .headset import CameraModel

# --------------------------------------------------------------------------------------- body model
# (joint a, joint b or -1 for a sphere at a, radius m, material slot, extend): extend > 0 lengthens the
# segment beyond b by that fraction of a->b; extend < 0 instead makes a segment of -extend metres from a,
# pointing away from b. Material slots: 0 shirt, 1 trousers, 2 skin, 3 shoes, 4 sleeve, 5 lower leg,
# 6 controller, 7 hair.
SEGMENTS: Final = (
    (1, 2, 0.085, 1, 0.0),  # hips across
    (0, 3, 0.105, 1, 0.0),  # lower belly
    (3, 6, 0.115, 0, 0.0),
    (6, 9, 0.12, 0, 0.0),
    (13, 14, 0.085, 0, 0.0),  # chest across the collars
    (9, 12, 0.07, 0, 0.0),
    (12, 15, 0.05, 2, 0.0),  # neck
    (15, -1, 0.1, 2, 0.0),  # head (sphere, lifted below)
    (16, 18, 0.05, 4, 0.0),  # upper arms
    (17, 19, 0.05, 4, 0.0),
    (18, 20, 0.04, 4, 0.0),  # forearms (skin when sleeves are short)
    (19, 21, 0.04, 4, 0.0),
    (20, 18, 0.035, 2, -0.08),  # hands: 8 cm from the wrist, away from the elbow
    (21, 19, 0.035, 2, -0.08),
    (13, 16, 0.065, 0, 0.0),  # shoulders
    (14, 17, 0.065, 0, 0.0),
    (1, 4, 0.075, 1, 0.0),  # thighs
    (2, 5, 0.075, 1, 0.0),
    (4, 7, 0.055, 5, 0.0),  # shins (skin for shorts)
    (5, 8, 0.055, 5, 0.0),
    (7, 10, 0.045, 3, 0.35),  # shoes: ankle to beyond the toe base
    (8, 11, 0.045, 3, 0.35),
)
JOINT_RADIUS_M: Final = np.zeros(22)
for _a, _b, _r, _m, _e in SEGMENTS:
    JOINT_RADIUS_M[_a] = max(JOINT_RADIUS_M[_a], _r)
    if _b >= 0 and _e >= 0.0:
        JOINT_RADIUS_M[_b] = max(JOINT_RADIUS_M[_b], _r)
JOINT_RADIUS_M.flags.writeable = False
HEAD_LIFT_M: Final = 0.07  # the head sphere's centre above the SMPL head joint (the joint sits low)
(
    PATTERN_PLAIN,
    PATTERN_STRIPES,
    PATTERN_CHECKER,
    PATTERN_MOTTLE,
    PATTERN_DENIM,
    PATTERN_KNIT,
    PATTERN_PRINT,
) = range(7)
PATTERN_WOOD, PATTERN_TILES, PATTERN_CARPET, PATTERN_CONCRETE = range(7, 11)  # floors
FLOOR_PATTERNS: Final = (
    PATTERN_CHECKER, PATTERN_STRIPES, PATTERN_MOTTLE, PATTERN_WOOD, PATTERN_TILES, PATTERN_CARPET, PATTERN_CONCRETE,
)  # fmt: skip
MATERIAL_FIELDS: Final = 8  # r, g, b, r2, g2, b2 (0..1), pattern, pattern scale (m)
TOP_PATTERNS: Final = (
    PATTERN_PLAIN,
    PATTERN_STRIPES,
    PATTERN_CHECKER,
    PATTERN_MOTTLE,
    PATTERN_PRINT,
    PATTERN_KNIT,
)
TOP_WEIGHTS: Final = (0.35, 0.2, 0.1, 0.1, 0.15, 0.1)  # how often each of TOP_PATTERNS is drawn
# From very light to very dark (sRGB 0..1): the renderer draws any tone between neighbours.
SKIN_TONES: Final = np.array(
    [[0.97, 0.84, 0.75], [0.92, 0.74, 0.62], [0.80, 0.60, 0.46], [0.65, 0.45, 0.31], [0.47, 0.31, 0.21],
     [0.30, 0.19, 0.13]]
)  # fmt: skip
HAIR_COLOURS: Final = np.array(
    [[0.05, 0.04, 0.04], [0.17, 0.10, 0.06], [0.35, 0.22, 0.12], [0.70, 0.55, 0.32], [0.55, 0.25, 0.12],
     [0.62, 0.62, 0.60]]
)  # fmt: skip


@dataclasses.dataclass(frozen=True)
class Appearance:
    """A body's look and its scene: materials (8, MATERIAL_FIELDS), girth, room, boxes and light."""

    materials: np.ndarray
    girth: float
    floor: np.ndarray  # r, g, b, r2, g2, b2, pattern, scale
    walls: np.ndarray  # (4, 3) colours of the -x, +x, -z, +z walls
    room: np.ndarray  # x0, x1, z0, z1, height (m), room centred near the motion's start
    boxes: np.ndarray  # (K, 9): min xyz, max xyz, rgb
    light_dir: np.ndarray  # (3,) unit vector towards the light (the key light: it casts the body's shadow)
    light_rgb: np.ndarray  # (3,)
    ambient: float
    fill_light: np.ndarray = dataclasses.field(
        default_factory=lambda: np.zeros(6)
    )  # dir (3,), rgb (3,); 0: none

    @property
    def lights(self) -> np.ndarray:
        """(L, 6) [direction towards the light (3), colour (3)], the key light first."""
        key = np.concatenate([self.light_dir, self.light_rgb])[None]
        return np.concatenate([key, self.fill_light[None]]) if self.fill_light[3:].any() else key


def _colour(rng: np.random.Generator, lo: float = 0.05, hi: float = 0.95) -> np.ndarray:
    return rng.uniform(lo, hi, 3)


def _skin(rng: np.random.Generator) -> np.ndarray:
    """A skin colour from the whole range of human skin tones (interpolated between SKIN_TONES)."""
    x = rng.uniform(0, len(SKIN_TONES) - 1)
    k = min(int(x), len(SKIN_TONES) - 2)
    return SKIN_TONES[k] + (x - k) * (SKIN_TONES[k + 1] - SKIN_TONES[k])


def _garment(rng: np.random.Generator, patterns: tuple[int, ...], weights: tuple[float, ...]) -> np.ndarray:
    pattern = rng.choice(patterns, p=np.asarray(weights) / sum(weights))
    return np.array([*_colour(rng), *_colour(rng), pattern, rng.uniform(0.02, 0.12)])


FLOOR_LOOKS: Final = {  # colour ranges (low, high) and pattern scale (m) of each floor kind
    PATTERN_WOOD: ((0.35, 0.2, 0.1), (0.8, 0.6, 0.4), (0.08, 0.2)),
    PATTERN_TILES: ((0.4, 0.4, 0.4), (0.95, 0.95, 0.92), (0.2, 0.6)),
    PATTERN_CARPET: ((0.1, 0.1, 0.1), (0.7, 0.6, 0.6), (0.05, 0.1)),
    PATTERN_CONCRETE: ((0.35, 0.35, 0.33), (0.7, 0.7, 0.68), (0.5, 1.0)),
}


def random_floor(rng: np.random.Generator, kinds: tuple[int, ...]) -> np.ndarray:
    """A floor material (MATERIAL_FIELDS,) of one of ``kinds``: realistic colours for wood, tiles, carpet and
    concrete, any colours for the abstract patterns."""
    kind = int(rng.choice(kinds))
    if kind not in FLOOR_LOOKS:
        return np.array([*_colour(rng, 0.15, 0.85), *_colour(rng, 0.15, 0.85), kind, rng.uniform(0.1, 0.6)])
    low, high, scale = FLOOR_LOOKS[kind]
    base = rng.uniform(low, high)
    second = base * 0.6 if kind != PATTERN_TILES else rng.uniform(0.2, 0.9, 3)
    return np.array([*base, *second, kind, rng.uniform(*scale)])


def _box(corner: np.ndarray, size: np.ndarray, colour: np.ndarray) -> list[float]:
    return [*corner, *(corner + size), *colour]


def _piece(rng: np.random.Generator, kind: str, x: float, z: float) -> list[list[float]]:
    """One piece of furniture as axis-aligned boxes [min xyz, max xyz, rgb] standing on the floor at (x, z)."""
    colour = rng.uniform(0.15, 0.85, 3)
    if kind == "table":
        w, d, h = rng.uniform([0.6, 0.6, 0.7], [1.6, 1.0, 0.8])
        leg = 0.05
        out = [_box(np.array([x, h - 0.04, z]), np.array([w, 0.04, d]), colour)]
        for lx, lz in ((0, 0), (w - leg, 0), (0, d - leg), (w - leg, d - leg)):
            out.append(_box(np.array([x + lx, 0.0, z + lz]), np.array([leg, h - 0.04, leg]), colour * 0.8))
        return out
    if kind == "chair":
        w, h = rng.uniform(0.4, 0.5), rng.uniform(0.42, 0.48)
        out = [_box(np.array([x, h - 0.05, z]), np.array([w, 0.05, w]), colour),
               _box(np.array([x, h, z + w - 0.05]), np.array([w, rng.uniform(0.35, 0.5), 0.05]), colour)]  # fmt: skip
        for lx, lz in ((0, 0), (w - 0.04, 0), (0, w - 0.04), (w - 0.04, w - 0.04)):
            out.append(_box(np.array([x + lx, 0.0, z + lz]), np.array([0.04, h - 0.05, 0.04]), colour * 0.7))
        return out
    if kind == "sofa":
        w, d = rng.uniform(1.4, 2.2), rng.uniform(0.8, 1.0)
        return [_box(np.array([x, 0.0, z]), np.array([w, 0.42, d]), colour),
                _box(np.array([x, 0.42, z + d - 0.2]), np.array([w, 0.4, 0.2]), colour * 0.9),
                _box(np.array([x, 0.42, z]), np.array([0.18, 0.2, d]), colour * 0.9),
                _box(np.array([x + w - 0.18, 0.42, z]), np.array([0.18, 0.2, d]), colour * 0.9)]  # fmt: skip
    size = rng.uniform([0.4, 0.8, 0.3], [1.2, 2.0, 0.6])  # a cabinet or shelf
    return [_box(np.array([x, 0.0, z]), size, colour)]


def random_furniture(rng: np.random.Generator, room: np.ndarray, centre_xz: np.ndarray) -> np.ndarray:
    """(K, 9) boxes: 0-5 tables, chairs, sofas and cabinets in the room, none within 0.7 m of where the
    person starts (they stand among it)."""
    boxes: list[list[float]] = []
    for _ in range(rng.integers(0, 6)):
        kind = str(rng.choice(["table", "chair", "sofa", "cabinet"], p=[0.3, 0.35, 0.15, 0.2]))
        x, z = rng.uniform(room[0] + 0.1, room[1] - 2.3), rng.uniform(room[2] + 0.1, room[3] - 1.1)
        piece = np.array(_piece(rng, kind, x, z))
        lo, hi = piece[:, [0, 2]].min(axis=0), piece[:, [3, 5]].max(axis=0)
        gap = np.maximum(np.maximum(lo - centre_xz, centre_xz - hi), 0.0)
        if np.hypot(*gap) > 0.7:
            boxes += piece.tolist()
    return np.array(boxes, dtype=np.float64).reshape(-1, 9)


def random_appearance(
    rng: np.random.Generator,
    centre_xz: np.ndarray,
    floors: tuple[int, ...] = FLOOR_PATTERNS[:3],
    tops: tuple[int, ...] = TOP_PATTERNS,
    fill_light_p: float = 0.0,
) -> Appearance:
    """Random clothing (a shirt of one of ``tops``), skin, shoes, hair, room (a floor of one of ``floors``,
    furniture) and lighting (a second, fill light with chance ``fill_light_p``)."""
    skin = _skin(rng)
    mats = np.zeros((8, MATERIAL_FIELDS))
    mats[0] = _garment(rng, tops, tuple(TOP_WEIGHTS[TOP_PATTERNS.index(t)] for t in tops))
    if rng.random() < 0.45:  # jeans
        blue = rng.uniform([0.08, 0.12, 0.25], [0.3, 0.38, 0.65])
        mats[1] = [*blue, *(blue * 0.8), PATTERN_DENIM, rng.uniform(0.04, 0.08)]
    else:
        mats[1] = _garment(
            rng, (PATTERN_PLAIN, PATTERN_MOTTLE, PATTERN_CHECKER, PATTERN_KNIT), (0.55, 0.2, 0.1, 0.15)
        )
    mats[3] = _garment(rng, (PATTERN_PLAIN, PATTERN_STRIPES), (0.8, 0.2))
    mats[2] = [*skin, *(skin * 0.85), PATTERN_MOTTLE, 0.03]
    mats[4] = mats[0] if rng.random() < 0.6 else mats[2]  # long or short sleeves
    mats[5] = mats[1] if rng.random() < 0.75 else mats[2]  # trousers or shorts
    mats[6] = [0.08, 0.08, 0.09, 0.25, 0.25, 0.27, PATTERN_STRIPES, 0.05]
    hair = HAIR_COLOURS[rng.integers(len(HAIR_COLOURS))] * rng.uniform(0.8, 1.2)
    mats[7] = [*hair, *(hair * 0.8), PATTERN_KNIT, 0.03] if rng.random() > 0.08 else mats[2]  # or bald
    floor = random_floor(rng, floors)
    half = rng.uniform(2.5, 5.0, size=4)
    room = np.array(
        [
            centre_xz[0] - half[0],
            centre_xz[0] + half[1],
            centre_xz[1] - half[2],
            centre_xz[1] + half[3],
            rng.uniform(2.4, 3.2),
        ]
    )
    boxes = random_furniture(rng, room, np.asarray(centre_xz, dtype=np.float64))
    light = np.array([rng.uniform(-0.6, 0.6), 1.0, rng.uniform(-0.6, 0.6)])
    return Appearance(
        materials=mats,
        girth=float(rng.uniform(0.85, 1.2)),
        floor=floor,
        walls=rng.uniform(0.3, 0.95, (4, 3)),
        room=room,
        boxes=boxes,
        light_dir=light / np.linalg.norm(light),
        light_rgb=rng.uniform(0.8, 1.1, 3),
        ambient=float(rng.uniform(0.25, 0.5)),
        fill_light=_fill_light(rng) if rng.random() < fill_light_p else np.zeros(6),
    )


def _fill_light(rng: np.random.Generator) -> np.ndarray:
    """A weaker second light from any direction above the horizon, of its own colour."""
    direction = np.array([rng.uniform(-1, 1), rng.uniform(0.2, 1.0), rng.uniform(-1, 1)])
    return np.concatenate([direction / np.linalg.norm(direction), rng.uniform(0.2, 0.5, 3)])


def body_capsules(
    joints_m: np.ndarray,
    bone_scale: np.ndarray,
    girth: float,
    controllers: np.ndarray | None = None,
) -> np.ndarray:
    """(C, 8) capsules [ax, ay, az, bx, by, bz, radius, material] for one pose (joints (J, 3) world).

    ``controllers`` (2, 7) device poses adds the two hand controllers (short dark capsules along -z).
    """
    size = float(np.mean(bone_scale[1:])) * girth
    rows = []
    for a, b, radius, material, extend in SEGMENTS:
        pa = joints_m[a]
        if b < 0:
            pa = pa + np.array([0.0, HEAD_LIFT_M * bone_scale[15], 0.0])
            pb = pa
        else:
            away = joints_m[a] - joints_m[b]
            if extend < 0:
                pb = pa + (-extend) * bone_scale[a] * away / max(float(np.linalg.norm(away)), 1e-9)
            else:
                pb = joints_m[b] - extend * away
        scale = size if material in (0, 1) else float(np.mean(bone_scale[1:]))
        rows.append([*pa, *pb, radius * scale, material])
    if controllers is not None:
        rows += controller_capsules(controllers).tolist()
    return np.array(rows, dtype=np.float64)


def controller_capsules(controllers: np.ndarray) -> np.ndarray:
    """(2, 8) capsules of the two hand controllers held at device poses controllers (2, 7): short dark
    handles along the device's -z."""
    forward = Rotation.from_quat(controllers[:, 3:]).apply([0.0, 0.0, -1.0])
    return np.array(
        [[*(controllers[k, :3] - 0.03 * forward[k]), *(controllers[k, :3] + 0.07 * forward[k]), 0.025, 6]
         for k in range(2)]
    )  # fmt: skip


# ------------------------------------------------------------------------------------------- kernel
@njit(cache=True, fastmath=True)
def _hash3(x: float, y: float, z: float) -> float:
    h = np.sin(x * 12.9898 + y * 78.233 + z * 37.719) * 43758.5453
    return h - np.floor(h)


@njit(cache=True, fastmath=True)
def _pattern(
    mat: np.ndarray, s: float, q: float, px: float, py: float, pz: float
) -> tuple[float, float, float]:
    """Colour of a material at surface coordinates (s along, q across) and world point p."""
    kind = int(mat[6])
    scale = mat[7]
    second = False
    if kind == 1:
        second = np.sin(s / scale * np.pi) > 0.0
    elif kind == 2:
        second = (int(np.floor(s / scale)) + int(np.floor(q / scale))) % 2 == 0
    elif kind == 6:  # print: a dot in some cells of a grid on the surface
        cs, cq = np.floor(s / scale), np.floor(q / scale)
        if _hash3(cs, cq, 7.0) < 0.35:
            ds, dq = s / scale - cs - 0.5, q / scale - cq - 0.5
            second = ds * ds + dq * dq < 0.09
    elif kind == 8:  # tiles: square tiles of the first colour, grout lines of the second
        fs, fq = s / scale - np.floor(s / scale), q / scale - np.floor(q / scale)
        second = fs < 0.04 or fq < 0.04
    shade = 1.0
    if kind == 3:
        shade = 0.85 + 0.3 * _hash3(np.floor(px / scale), np.floor(py / scale), np.floor(pz / scale))
    elif kind == 7:  # wood: planks across q, each of its own shade, staggered joints, grain along s
        plank = np.floor(q / scale)
        piece = np.floor(s / (scale * 6.0) + _hash3(plank, 3.0, 1.0))
        shade = (0.75 + 0.4 * _hash3(plank, piece, 2.0)) * (
            0.93 + 0.07 * np.sin(s * 40.0 + 9.0 * _hash3(plank, 1.0, 1.0))
        )
        if q / scale - plank < 0.03:
            shade *= 0.6
    elif kind == 8:
        shade = 0.92 + 0.12 * _hash3(np.floor(s / scale), np.floor(q / scale), 5.0)
    elif kind == 9:  # carpet: fine fibre noise
        shade = 0.75 + 0.4 * _hash3(np.floor(px * 300.0), np.floor(pz * 300.0), np.floor(py * 300.0))
    elif kind == 10:  # concrete: fine speckle over slow blotches
        shade = (
            0.88
            + 0.08 * _hash3(np.floor(px * 120.0), np.floor(pz * 120.0), 3.0)
            + 0.06 * np.sin(px * 2.3 + 1.7 * np.sin(pz * 1.9))
        )
    elif kind == 4:  # denim: diagonal twill ridges and thread-level speckle
        shade = (
            0.88
            + 0.12 * np.sin((s + q) / (scale * 0.08))
            + 0.08 * (_hash3(np.floor(s * 400), np.floor(q * 400), 1.0) - 0.5)
        )
    elif kind == 5:  # knit: ribs along the body and a fine row texture
        shade = 0.85 + 0.15 * abs(np.sin(q / (scale * 0.15))) + 0.05 * np.sin(s / (scale * 0.05))
    if second:
        return mat[3] * shade, mat[4] * shade, mat[5] * shade
    return mat[0] * shade, mat[1] * shade, mat[2] * shade


@njit(cache=True, fastmath=True)
def _lit(nx, ny, nz, lights, ambient, two_sided):
    """Light reaching a surface of unit normal n per colour channel: ambient in the key light's colour plus
    Lambert from each light of lights (L, 6)."""
    sr, sg, sb = ambient * lights[0, 3], ambient * lights[0, 4], ambient * lights[0, 5]
    for k in range(lights.shape[0]):
        cos = nx * lights[k, 0] + ny * lights[k, 1] + nz * lights[k, 2]
        cos = abs(cos) if two_sided else max(cos, 0.0)
        sr += (1.0 - ambient) * cos * lights[k, 3]
        sg += (1.0 - ambient) * cos * lights[k, 4]
        sb += (1.0 - ambient) * cos * lights[k, 5]
    return sr, sg, sb


@njit(cache=True, fastmath=True)
def _sphere_hit(ox, oy, oz, dx, dy, dz, cx, cy, cz, r) -> float:
    ocx, ocy, ocz = ox - cx, oy - cy, oz - cz
    b = dx * ocx + dy * ocy + dz * ocz
    h = b * b - (ocx * ocx + ocy * ocy + ocz * ocz - r * r)
    if h < 0.0:
        return -1.0
    t = -b - np.sqrt(h)
    return t if t > 0.0 else -1.0


@njit(cache=True, fastmath=True)
def _capsule_hit(ox, oy, oz, dx, dy, dz, cap) -> float:
    """Distance along a unit ray to a capsule, or -1 (Inigo Quilez's analytic capsule intersection)."""
    bax, bay, baz = cap[3] - cap[0], cap[4] - cap[1], cap[5] - cap[2]
    oax, oay, oaz = ox - cap[0], oy - cap[1], oz - cap[2]
    r = cap[6]
    baba = bax * bax + bay * bay + baz * baz
    if baba < 1e-12:
        return _sphere_hit(ox, oy, oz, dx, dy, dz, cap[0], cap[1], cap[2], r)
    bard = bax * dx + bay * dy + baz * dz
    baoa = bax * oax + bay * oay + baz * oaz
    rdoa = dx * oax + dy * oay + dz * oaz
    oaoa = oax * oax + oay * oay + oaz * oaz
    a = baba - bard * bard
    if a < 1e-12 * baba:  # looking straight down the axis: the nearer end sphere
        ta = _sphere_hit(ox, oy, oz, dx, dy, dz, cap[0], cap[1], cap[2], r)
        tb = _sphere_hit(ox, oy, oz, dx, dy, dz, cap[3], cap[4], cap[5], r)
        if ta < 0.0 or (tb > 0.0 and tb < ta):
            return tb
        return ta
    b = baba * rdoa - baoa * bard
    c = baba * oaoa - baoa * baoa - r * r * baba
    h = b * b - a * c
    if h < 0.0:
        return -1.0  # misses the infinite cylinder, so the capsule too
    t = (-b - np.sqrt(h)) / a
    y = baoa + t * bard
    if y > 0.0 and y < baba:
        return t if t > 0.0 else -1.0
    if y <= 0.0:
        return _sphere_hit(ox, oy, oz, dx, dy, dz, cap[0], cap[1], cap[2], r)
    return _sphere_hit(ox, oy, oz, dx, dy, dz, cap[3], cap[4], cap[5], r)


@njit(cache=True, parallel=True, fastmath=True)
def _render_kernel(
    dirs,
    depth_scale,
    origin,
    caps,
    boxes_px,
    materials,
    floor,
    walls,
    room,
    boxes,
    light,
    ambient,
    rgb_out,
    depth_out,
):
    h, w = depth_scale.shape
    ox, oy, oz = origin[0], origin[1], origin[2]
    for v in prange(h):
        for u in range(w):
            dx, dy, dz = dirs[v, u, 0], dirs[v, u, 1], dirs[v, u, 2]
            best = 1e9
            kind = -1  # -1 none, 0 capsule, 1 floor, 2 wall, 3 ceiling, 4 box
            which = -1
            for c in range(caps.shape[0]):
                if u < boxes_px[c, 0] or u > boxes_px[c, 1] or v < boxes_px[c, 2] or v > boxes_px[c, 3]:
                    continue
                t = _capsule_hit(ox, oy, oz, dx, dy, dz, caps[c])
                if t > 0.0 and t < best:
                    best, kind, which = t, 0, c
            if dy < -1e-9:
                t = -oy / dy
                if t < best:
                    best, kind = t, 1
            if dy > 1e-9:
                t = (room[4] - oy) / dy
                if t < best:
                    best, kind = t, 3
            for k in range(4):
                d = dx if k < 2 else dz
                o = ox if k < 2 else oz
                if abs(d) < 1e-9:
                    continue
                t = (room[k] - o) / d
                if t > 0.0 and t < best:
                    best, kind, which = t, 2, k
            for k in range(boxes.shape[0]):
                tmin, tmax = 0.0, 1e9
                for axis in range(3):
                    d = dirs[v, u, axis]
                    o = origin[axis]
                    if abs(d) < 1e-12:
                        if o < boxes[k, axis] or o > boxes[k, axis + 3]:
                            tmin = 1e9
                        continue
                    t1, t2 = (boxes[k, axis] - o) / d, (boxes[k, axis + 3] - o) / d
                    if t1 > t2:
                        t1, t2 = t2, t1
                    tmin, tmax = max(tmin, t1), min(tmax, t2)
                if tmin < tmax and tmin > 0.0 and tmin < best:
                    best, kind, which = tmin, 4, k
            px, py, pz = ox + best * dx, oy + best * dy, oz + best * dz
            nx, ny, nz = 0.0, 1.0, 0.0
            r, g, b = 0.5, 0.5, 0.5
            if kind == 0:
                cap = caps[which]
                bax, bay, baz = cap[3] - cap[0], cap[4] - cap[1], cap[5] - cap[2]
                baba = bax * bax + bay * bay + baz * baz
                s = 0.0
                if baba > 1e-12:
                    s = ((px - cap[0]) * bax + (py - cap[1]) * bay + (pz - cap[2]) * baz) / baba
                    s = min(max(s, 0.0), 1.0)
                nx, ny, nz = px - (cap[0] + s * bax), py - (cap[1] + s * bay), pz - (cap[2] + s * baz)
                norm = np.sqrt(nx * nx + ny * ny + nz * nz) + 1e-12
                nx, ny, nz = nx / norm, ny / norm, nz / norm
                q = np.arctan2(nx, nz) * cap[6]
                r, g, b = _pattern(materials[int(cap[7])], s * np.sqrt(baba), q, px, py, pz)
            elif kind == 1:
                r, g, b = _pattern(floor, px, pz, px, 0.0, pz)
            elif kind == 2:
                nx, ny, nz = 0.0, 0.0, 0.0
                if which == 0:
                    nx = 1.0
                elif which == 1:
                    nx = -1.0
                elif which == 2:
                    nz = 1.0
                else:
                    nz = -1.0
                shade = 0.9 + 0.1 * _hash3(np.floor(px * 4), np.floor(py * 4), np.floor(pz * 4))
                r, g, b = walls[which, 0] * shade, walls[which, 1] * shade, walls[which, 2] * shade
            elif kind == 3:
                nx, ny, nz = 0.0, -1.0, 0.0
                r, g, b = 0.9, 0.9, 0.88
            elif kind == 4:
                bx = boxes[which]
                eps = 1e-3
                nx = -1.0 if abs(px - bx[0]) < eps else (1.0 if abs(px - bx[3]) < eps else 0.0)
                ny = -1.0 if abs(py - bx[1]) < eps else (1.0 if abs(py - bx[4]) < eps else 0.0)
                nz = -1.0 if abs(pz - bx[2]) < eps else (1.0 if abs(pz - bx[5]) < eps else 0.0)
                r, g, b = bx[6], bx[7], bx[8]
            sr, sg, sb = _lit(nx, ny, nz, light, ambient, False)
            rgb_out[v, u, 0] = min(255.0, r * sr * 255.0)
            rgb_out[v, u, 1] = min(255.0, g * sg * 255.0)
            rgb_out[v, u, 2] = min(255.0, b * sb * 255.0)
            depth_out[v, u] = best * depth_scale[v, u] if kind >= 0 else 0.0


# ---------------------------------------------------------------------------------------- mesh bodies
# Material slot of each body region; SPLIT_SLOT: the far part of a limb region (beyond SPLIT_FRACTION of its
# bone) takes the second slot, so short sleeves and shorts end half way down the limb.
REGION_SLOT: Final = {
    REGION_TORSO: 0, REGION_UPPER_ARM: 0, REGION_FOREARM: 4, REGION_HAND: 2, REGION_HIPS: 1, REGION_THIGH: 1,
    REGION_SHIN: 5, REGION_FOOT: 3, REGION_NECK: 2, REGION_FACE: 2, REGION_SCALP: 7, REGION_INNER: 2,
}  # fmt: skip
SPLIT_SLOT: Final = {REGION_UPPER_ARM: ((16, 18), (17, 19), 4, 0.5), REGION_THIGH: ((1, 4), (2, 5), 5, 0.45)}
SHADOW_MAP_TEXELS = 256
SHADOW_MAP_M = 3.2  # the square the shadow map covers around the body
SHADOW_STRENGTH = 0.8  # how much of the direct light a shadow takes away
SHADOW_BIAS_M = 0.03  # a surface does not shadow itself within this distance along the light


@dataclasses.dataclass(frozen=True)
class MeshBody:
    """One body of a bank, prepared for rendering a sequence.

    rest_m (V, 3): rest vertices (float64); face_slot (F,) material slot per triangle; surface_m (V, 2):
    texture coordinates in metres (height along the body, distance around the vertex's own bone), so that
    patterns stick to the clothes while the body moves."""

    bank: BodyBank
    index: int
    rest_m: np.ndarray
    face_slot: np.ndarray
    surface_m: np.ndarray

    @property
    def faces(self) -> np.ndarray:
        return self.bank.faces


def prepare_mesh_body(bank: BodyBank, index: int) -> MeshBody:
    rest = bank.rest_vertices[index].astype(np.float64)
    joints = bank.rest_joints[index]
    centre = rest[bank.faces].mean(axis=1)
    slot = np.array([REGION_SLOT[r] for r in bank.region], dtype=np.int64)
    for region, (left, right, far_slot, fraction) in SPLIT_SLOT.items():
        for start, end in (left, right):
            side = np.sign(joints[start, 0])
            mask = (bank.region == region) & (np.sign(centre[:, 0]) == side)
            bone = joints[end] - joints[start]
            t = (centre[mask] - joints[start]) @ bone / (bone @ bone)
            slot[np.flatnonzero(mask)[t > fraction]] = far_slot
    own = joints[bank.skin_joint[:, 0]]
    around = np.arctan2(rest[:, 0] - own[:, 0], rest[:, 2] - own[:, 2]) * 0.12
    return MeshBody(bank, index, rest, slot, np.stack([rest[:, 1], around], axis=-1))


@njit(cache=True, parallel=True, fastmath=True)
def _shade_body(
    zbuf, face_id, bary, faces, face_slot, normals, surface, rest, materials, light, ambient, rgb, depth
):
    """Composite the rasterised body over the room render: where the body is nearer, its shaded colour."""
    h, w = zbuf.shape
    for v in prange(h):
        for u in range(w):
            f = face_id[v, u]
            if f < 0 or (depth[v, u] > 0.0 and depth[v, u] <= zbuf[v, u]):
                continue
            nx, ny, nz = raster.interpolate(normals, faces, face_id, bary, v, u)
            px, py, pz = raster.interpolate(rest, faces, face_id, bary, v, u)
            a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
            wb, wc = bary[v, u, 0], bary[v, u, 1]
            wa = 1.0 - wb - wc
            s = wa * surface[a, 0] + wb * surface[b, 0] + wc * surface[c, 0]
            q = wa * surface[a, 1] + wb * surface[b, 1] + wc * surface[c, 1]
            r, g, b_ = _pattern(materials[face_slot[f]], s, q, px, py, pz)
            norm = np.sqrt(nx * nx + ny * ny + nz * nz) + 1e-12
            sr, sg, sb = _lit(nx / norm, ny / norm, nz / norm, light, ambient, True)  # drawn from both sides
            rgb[v, u, 0] = min(255.0, r * sr * 255.0)
            rgb[v, u, 1] = min(255.0, g * sg * 255.0)
            rgb[v, u, 2] = min(255.0, b_ * sb * 255.0)
            depth[v, u] = zbuf[v, u]


def light_frame(light_dir: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(4, 4) world -> light frame: z along the light's travel, origin at centre (3,)."""
    z = -light_dir / np.linalg.norm(light_dir)
    x = np.cross([0.0, 0.0, 1.0] if abs(z[2]) < 0.9 else [1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    out = np.eye(4)
    out[:3, :3] = np.stack([x, np.cross(z, x), z])
    out[:3, 3] = -out[:3, :3] @ centre
    return out


def _distortion_maps(camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """For each pixel of the distorted image, where it lies in the pinhole render: (map_u, map_v) (H, W)
    float32 for cv2.remap (the inverse of the radial model, solved by OpenCV's undistortPoints)."""
    import cv2

    fx, fy, cx, cy = camera.intrinsics()
    k = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    u, v = np.meshgrid(np.arange(camera.width, dtype=np.float64), np.arange(camera.height, dtype=np.float64))
    points = np.stack([u.ravel(), v.ravel()], axis=-1)[:, None, :]
    undistorted = cv2.undistortPoints(points, k, np.array([camera.k1, camera.k2, 0.0, 0.0]), P=k)[:, 0]
    shape = (camera.height, camera.width)
    return undistorted[:, 0].reshape(shape).astype(np.float32), undistorted[:, 1].reshape(shape).astype(
        np.float32
    )


# ------------------------------------------------------------------------------------------ sensor
@njit(cache=True, fastmath=True)
def _sensor_kernel(rgb, depth_m, vignette, gain, params, rng, rgb_out, depth_out):
    """SensorNoise applied to one clean frame (params: rgb_sigma, depth_sigma_at_1m, edge_jump_m,
    edge_hole_prob, flying_pixel_prob, dropout_prob, dark_albedo, dark_hole_prob, min_depth_m, max_depth_m).
    Serial, drawing from the sequence's generator ``rng``: the same seed gives the same frame."""
    rgb_sigma, sigma_1m, jump_m, hole_p, fly_p, drop_p, dark, dark_p, near_m, far_m = params
    h, w = depth_m.shape
    for v in range(h):
        for u in range(w):
            brightness = (rgb[v, u, 0] + rgb[v, u, 1] + rgb[v, u, 2]) / (3.0 * 255.0)
            for c in range(3):
                x = rgb[v, u, c] * vignette[v, u] * gain[c] + rng.standard_normal() * rgb_sigma
                rgb_out[v, u, c] = np.uint8(min(max(x + 0.5, 0.0), 255.0))
            d = depth_m[v, u]
            other = 0.0  # a neighbour's depth across an edge
            for dv, du in ((-1, 0), (1, 0), (0, -1), (0, 1)):
                vv, uu = v + dv, u + du
                if 0 <= vv < h and 0 <= uu < w and abs(depth_m[vv, uu] - d) > jump_m:
                    other = depth_m[vv, uu]
                    break
            noisy = d + rng.standard_normal() * sigma_1m * d * d
            draw = rng.random()
            hole = draw > 1.0 - drop_p or d < near_m or d > far_m
            if other > 0.0:
                if draw < hole_p:
                    hole = True
                elif draw < hole_p + fly_p:
                    mix = rng.random()
                    noisy = mix * d + (1.0 - mix) * other
            if dark > 0.0 and brightness < dark and rng.random() < dark_p:
                hole = True
            depth_out[v, u] = 0 if hole else np.uint16(min(max(noisy * 1000.0 + 0.5, 0.0), 65535.0))


@njit(cache=True, parallel=True, fastmath=True)
def ir_shadow(depth_m, focal_baseline_px_m):
    """(H, W) bool: pixels the projector cannot light. The projector sits to the camera's left by baseline b
    (focal_baseline_px_m = f·b in pixel·metres): a point at depth z in column u is hidden when a nearer point
    z' in a column u' < u covers it, u - u' < f·b·(1/z' - 1/z)."""
    h, w = depth_m.shape
    out = np.zeros((h, w), dtype=np.bool_)
    for v in prange(h):
        for u in range(w):
            z = depth_m[v, u]
            if z <= 0.0:
                continue
            reach = int(focal_baseline_px_m / 0.1)  # the nearest anything can be
            for k in range(1, min(reach, u) + 1):
                z2 = depth_m[v, u - k]
                if 0.0 < z2 < z and k < focal_baseline_px_m * (1.0 / z2 - 1.0 / z):
                    out[v, u] = True
                    break
    return out


# ------------------------------------------------------------------------------------------ driver
@dataclasses.dataclass(frozen=True)
class SensorNoise:
    """Depth and colour sensor imperfections of an active-stereo / structured-light RGB-D camera (Intel
    RealSense D4xx, Orbbec, Azure Kinect class).

    Depth: noise with a standard deviation growing with the square of the distance (stereo disparity noise:
    sigma_z = z² sigma_d / (f b)); on depth edges, holes and flying pixels (a mix of the two sides); no
    reading beyond range or on dark surfaces (they return too little infrared); and, with ``ir_baseline_m``
    > 0, the IR shadow: background the projector beside the camera cannot see next to a nearer object's edge.
    Colour: exposure and white balance, vignetting, noise; JPEG artefacts come from the encoder's quality."""

    depth_sigma_at_1m: float = 0.0015  # grows with the square of the distance
    edge_hole_prob: float = 0.5  # chance a pixel on a depth edge returns nothing
    flying_pixel_prob: float = 0.0  # chance a pixel on a depth edge returns a mix of both sides
    edge_jump_m: float = 0.08
    dropout_prob: float = 0.004
    dark_albedo: float = 0.0  # surfaces whose clean rendered brightness is below this (0..1) ...
    dark_hole_prob: float = 0.7  # ... return nothing with this chance
    ir_baseline_m: float = 0.0  # projector to the camera's left by this much (0: no IR shadow)
    rgb_sigma: float = 2.0  # grey levels
    vignetting: float = 0.25
    exposure: float = 1.0  # gain on the image
    white_balance: tuple[float, float, float] = (1.0, 1.0, 1.0)  # gain per channel


class Renderer:
    """Renders RGB-D frames for one camera model; holds the per-pixel ray grid."""

    def __init__(self, camera: CameraModel, noise: SensorNoise | None = None) -> None:
        self.camera = camera
        self.noise = noise or SensorNoise()
        self.last_body_face: np.ndarray | None = None  # (H, W) of the last mesh render
        fx, fy, cx, cy = camera.intrinsics()
        u, v = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
        rays = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u, dtype=np.float64)], axis=-1)
        length = np.linalg.norm(rays, axis=-1)
        self._rays_cam = rays / length[..., None]  # (H, W, 3) unit rays in the camera frame
        self._depth_scale = 1.0 / length  # distance along a unit ray -> z depth
        self._radius2 = (np.hypot(u - cx, v - cy) / np.hypot(cx, cy)) ** 2  # 1 at the corners
        self._distortion_maps = _distortion_maps(camera) if camera.distorted else None

    def distort(self, *images: np.ndarray) -> tuple[np.ndarray, ...]:
        """The camera's lens distortion applied to pinhole renders: the first image (colour) interpolated,
        the rest (depth, labels) nearest; unchanged without distortion."""
        if self._distortion_maps is None:
            return images
        import cv2

        map_u, map_v = self._distortion_maps
        out = [
            cv2.remap(
                images[0].astype(np.float32), map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
            )
        ]
        for image in images[1:]:
            kind, flat = image.dtype, image.astype(np.float32)  # face ids < 2^24 survive float32
            out.append(
                cv2.remap(flat, map_u, map_v, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE).astype(kind)
            )
        out[0] = out[0].astype(images[0].dtype)
        return tuple(out)

    def _boxes_px(self, caps: np.ndarray, cam_from_world: np.ndarray) -> np.ndarray:
        """(C, 4) int pixel bounds [u0, u1, v0, v1] of each capsule's bounding sphere (whole image if near)."""
        cam = self.camera
        fx, fy, cx, cy = cam.intrinsics()
        centre = (caps[:, :3] + caps[:, 3:6]) / 2
        radius = np.linalg.norm(caps[:, 3:6] - caps[:, :3], axis=-1) / 2 + caps[:, 6] + 0.01
        c = centre @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
        out = np.tile(np.array([0, cam.width - 1, 0, cam.height - 1]), (len(caps), 1))
        ok = c[:, 2] - radius > 0.02
        if ok.any():
            zc, rc = c[ok, 2], radius[ok]
            near, far = zc - rc, zc + rc
            u_lo = np.minimum((c[ok, 0] - rc) / near, (c[ok, 0] - rc) / far) * fx + cx
            u_hi = np.maximum((c[ok, 0] + rc) / near, (c[ok, 0] + rc) / far) * fx + cx
            v_lo = np.minimum((c[ok, 1] - rc) / near, (c[ok, 1] - rc) / far) * fy + cy
            v_hi = np.maximum((c[ok, 1] + rc) / near, (c[ok, 1] + rc) / far) * fy + cy
            out[ok] = np.stack([np.floor(u_lo), np.ceil(u_hi), np.floor(v_lo), np.ceil(v_hi)], -1).astype(int)
        return out

    def render_clean(
        self, world_from_camera: np.ndarray, caps: np.ndarray, look: Appearance
    ) -> tuple[np.ndarray, np.ndarray]:
        """Noise-free (rgb (H, W, 3) float 0..255, depth (H, W) float metres, 0 = nothing)."""
        cam = self.camera
        rot = world_from_camera[:3, :3]
        dirs = np.ascontiguousarray(self._rays_cam @ rot.T)
        cam_from_world = np.linalg.inv(world_from_camera)
        light = np.ascontiguousarray(look.lights)
        rgb = np.empty((cam.height, cam.width, 3))
        depth = np.empty((cam.height, cam.width))
        _render_kernel(
            dirs,
            self._depth_scale,
            np.ascontiguousarray(world_from_camera[:3, 3]),
            np.ascontiguousarray(caps),
            self._boxes_px(caps, cam_from_world),
            look.materials,
            look.floor,
            look.walls,
            look.room,
            look.boxes,
            light,
            look.ambient,
            rgb,
            depth,
        )
        return rgb, depth

    def render_mesh_clean(
        self,
        world_from_camera: np.ndarray,
        body: MeshBody,
        vertices_m: np.ndarray,
        props: np.ndarray,
        look: Appearance,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Noise-free frame of a mesh body (posed vertices (V, 3) world) with capsule props (controllers,
        (C, 8) as :func:`body_capsules`) in the room, the body's shadow on everything -> as render_clean."""
        cam = self.camera
        rgb, depth = self.render_clean(world_from_camera, props, look)
        cam_from_world = np.linalg.inv(world_from_camera)
        verts_cam = vertices_m @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
        zbuf = np.full((cam.height, cam.width), np.inf)
        face_id = np.full((cam.height, cam.width), -1, dtype=np.int32)
        bary = np.zeros((cam.height, cam.width, 2), dtype=np.float32)
        raster.rasterize(verts_cam, body.faces, *cam.intrinsics(), zbuf, face_id, bary)
        normals = np.empty_like(vertices_m)
        raster.vertex_normals(vertices_m, body.faces, normals)
        light = np.ascontiguousarray(look.lights)
        _shade_body(zbuf, face_id, bary, body.faces, body.face_slot, normals, body.surface_m, body.rest_m,
                    look.materials, light, look.ambient, rgb, depth)  # fmt: skip
        self._shadow(world_from_camera, vertices_m, body.faces, look, rgb, depth)
        # the body's triangle at each pixel where the body is what the camera sees, -1 elsewhere (labels)
        self.last_body_face = np.where((face_id >= 0) & (depth == zbuf), face_id, -1)
        return rgb, depth

    def _shadow(
        self, world_from_camera: np.ndarray, vertices_m: np.ndarray, faces: np.ndarray, look: Appearance,
        rgb: np.ndarray, depth: np.ndarray,
    ) -> None:  # fmt: skip
        """Darken, in place, what the body hides from the light (a shadow map along the light)."""
        light_from_world = light_frame(look.light_dir, vertices_m.mean(axis=0))
        texel_m = SHADOW_MAP_M / SHADOW_MAP_TEXELS
        in_light = vertices_m @ light_from_world[:3, :3].T + light_from_world[:3, 3]
        in_light[:, :2] = in_light[:, :2] / texel_m + SHADOW_MAP_TEXELS / 2
        zmap = np.full((SHADOW_MAP_TEXELS, SHADOW_MAP_TEXELS), np.inf)
        raster.shadow_map(in_light, faces, SHADOW_MAP_TEXELS, zmap)
        strength = SHADOW_STRENGTH * (1.0 - look.ambient)
        raster.darken_shadowed(depth, self._rays_cam, self._depth_scale, world_from_camera, light_from_world,
                               texel_m, zmap, SHADOW_BIAS_M, strength, rgb)  # fmt: skip

    def add_noise(
        self,
        rgb: np.ndarray,
        depth_m: np.ndarray,
        rng: np.random.Generator,
        noise: SensorNoise | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Sensor model (``noise``, or the renderer's): clean rgb (H, W, 3) 0..255 and depth (H, W) m ->
        (rgb uint8, depth uint16 millimetres, 0 = no reading)."""
        noise, cam = noise or self.noise, self.camera
        h, w = depth_m.shape
        rgb8, depth_mm = np.empty((h, w, 3), dtype=np.uint8), np.empty((h, w), dtype=np.uint16)
        gain = noise.exposure * np.asarray(noise.white_balance, dtype=np.float64)
        params = np.array([
            noise.rgb_sigma, noise.depth_sigma_at_1m, noise.edge_jump_m, noise.edge_hole_prob,
            noise.flying_pixel_prob, noise.dropout_prob, noise.dark_albedo, noise.dark_hole_prob,
            cam.min_depth_m, cam.max_depth_m,
        ])  # fmt: skip
        vignette = 1.0 - noise.vignetting * self._radius2
        _sensor_kernel(rgb, depth_m, vignette, gain, params, rng, rgb8, depth_mm)
        if noise.ir_baseline_m > 0:
            depth_mm[ir_shadow(depth_m, self.camera.fx * noise.ir_baseline_m)] = 0
        return rgb8, depth_mm


def bank_preview(bank: BodyBank, path: str | Path, columns: int = 8, limit: int = 32) -> None:
    """A PNG of the bank's bodies in SMPL's T-pose, seen from the front, with their SMPL-22 joints in red."""
    import cv2

    camera = CameraModel(width=160, height=320, hfov_deg=34.0, min_depth_m=0.1, max_depth_m=20.0)
    renderer = Renderer(camera)
    rng = np.random.default_rng(0)
    look = dataclasses.replace(
        random_appearance(rng, np.zeros(2)),
        boxes=np.zeros((0, 9)),
        room=np.array([-9.0, 9.0, -9.0, 9.0, 9.0]),
    )
    world_from_camera = np.eye(4)
    world_from_camera[:3, :3] = np.diag([1.0, -1.0, -1.0])  # looking along -z at a body facing +z
    world_from_camera[:3, 3] = [0.0, 0.95, 3.2]
    tiles = []
    for index in range(min(bank.count, limit)):
        joints = forward_kinematics(np.eye(3)[None].repeat(22, 0), bank.rest_joints[index, 0], rest_offsets(bank.bone_scale(index)))[0]  # fmt: skip
        joints[:, 1] += bank.rest_joints[index, 0, 1] - joints[0, 1]
        vertices = pose_vertices(bank, index, np.broadcast_to(np.eye(3), (22, 3, 3)), joints)
        rgb, _ = renderer.render_mesh_clean(world_from_camera, prepare_mesh_body(bank, index), vertices, np.zeros((0, 8)), look)  # fmt: skip
        bgr = cv2.cvtColor(np.clip(rgb, 0, 255).astype(np.uint8), cv2.COLOR_RGB2BGR)
        cam_from_world = np.linalg.inv(world_from_camera)
        for u, v in camera.project(joints @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]):
            cv2.circle(bgr, (round(u), round(v)), 2, (0, 0, 255), -1)
        cv2.putText(bgr, f"{index}: {bank.height_m(index):.2f} m", (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (255, 255, 255), 1)  # fmt: skip
        tiles.append(bgr)
    while len(tiles) % columns:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.concatenate(tiles[i : i + columns], axis=1) for i in range(0, len(tiles), columns)]
    cv2.imwrite(str(path), np.concatenate(rows, axis=0))
