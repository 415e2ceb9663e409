"""Body banks from ``anny`` (NAVER's parametric body model, Apache-2.0, built on MakeHuman's CC0 assets): torch
and anny, so only ``egoposevr synth bodies`` imports this module; rendering reads the saved bank.

Each body is a random adult (anny's phenotype: gender, age about 20-80 years, muscle, weight, height,
proportions, all recorded), standing in anny's rest pose. Its SMPL-22 joints are anny bone heads (the table
below), its skinning collapses anny's 104 bones onto the 22 joints, and each triangle gets a region from
anny's body-part segmentation (head, hands, feet) and from the joint that moves it (the rest).

Shape legend: ``V`` vertices, ``F`` triangles, ``J`` = 22 joints, ``K`` skinning slots.
"""

from __future__ import annotations

from typing import Any, Final

import cv2
import numpy as np
import torch
import yaml

from ..skeleton import NUM_JOINTS, REST_JOINTS_M
from . import bodies
from .bodies import SKIN_SLOTS, BodyBank

# SMPL-22 joint -> the anny bone whose head it is. The spine joints and the collars are not bone heads: they
# sit along anny's spine (pelvis -> neck) and clavicles where SMPL's do (SPINE_FRACTIONS, COLLAR_FRACTION).
JOINT_BONES: Final = (
    "root", "upperleg01.L", "upperleg01.R", None, "lowerleg01.L", "lowerleg01.R", None, "foot.L",
    "foot.R", None, "toe*-1.L", "toe*-1.R", "neck01", None, None, "head", "upperarm01.L",
    "upperarm01.R", "lowerarm01.L", "lowerarm01.R", "wrist.L", "wrist.R",
)  # fmt: skip
SPINE_BONES: Final = ("root", "spine04", "spine03", "spine02", "spine01", "neck01")
COLLAR_FRACTION: Final = 0.4  # from the clavicle's head towards the shoulder joint
# anny bone name prefix -> the SMPL joint whose transform moves it (side suffixes handled below).
BONE_PREFIX_JOINT: Final = (
    ("root", 0), ("pelvis", 0), ("spine05", 0), ("spine04", 3), ("spine03", 3), ("spine02", 6), ("spine01", 9),
    ("upperleg", 1), ("lowerleg", 4), ("foot", 7), ("toe", 10), ("neck", 12), ("head", 15), ("eye", 15),
    ("clavicle", 13), ("shoulder", 13), ("upperarm", 16), ("lowerarm", 18), ("wrist", 20), ("finger", 20),
    ("metacarpal", 20),
)  # fmt: skip
RIGHT_OF: Final = {1: 2, 4: 5, 7: 8, 10: 11, 13: 14, 16: 17, 18: 19, 20: 21}
# Adult range of anny's age parameter: its anchors are newborn -1/3, baby 0, child 1/3, young 2/3 (25
# years), old 1 (90 years).
ADULT_AGE: Final = (0.6, 0.95)
PHENOTYPE_RANGES: Final = {
    "gender": (0.0, 1.0), "age": ADULT_AGE, "muscle": (0.1, 0.9), "weight": (0.1, 0.9), "height": (0.0, 1.0),
    "proportions": (0.0, 0.6),
}  # fmt: skip
STATURE_MALE_M, STATURE_FEMALE_M, STATURE_SD_M = 1.76, 1.63, 0.07
STATURE_RANGE_M: Final = (1.48, 2.0)
# anny's axes (z up, -y forward, x to the body's left) -> SMPL's (y up, +z forward, x to the left).
ANNY_TO_SMPL: Final = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
JOINT_REGION: Final = {
    0: bodies.REGION_HIPS, 1: bodies.REGION_THIGH, 2: bodies.REGION_THIGH, 3: bodies.REGION_TORSO,
    4: bodies.REGION_SHIN, 5: bodies.REGION_SHIN, 6: bodies.REGION_TORSO, 7: bodies.REGION_FOOT,
    8: bodies.REGION_FOOT, 9: bodies.REGION_TORSO, 10: bodies.REGION_FOOT, 11: bodies.REGION_FOOT,
    12: bodies.REGION_NECK, 13: bodies.REGION_TORSO, 14: bodies.REGION_TORSO, 15: bodies.REGION_NECK,
    16: bodies.REGION_UPPER_ARM, 17: bodies.REGION_UPPER_ARM, 18: bodies.REGION_FOREARM,
    19: bodies.REGION_FOREARM, 20: bodies.REGION_HAND, 21: bodies.REGION_HAND,
}  # fmt: skip


def bone_joint(label: str) -> int:
    """The SMPL joint that moves an anny bone."""
    for prefix, joint in BONE_PREFIX_JOINT:
        if label.startswith(prefix):
            return RIGHT_OF.get(joint, joint) if label.endswith(".R") else joint
    raise ValueError(f"anny bone {label!r} has no SMPL joint")


def load_anny() -> Any:
    import anny

    return anny.Anny().to(dtype=torch.float32).eval()


def _spine_fractions() -> dict[int, float]:
    """SMPL's spine joints as fractions of its pelvis -> neck height."""
    neck_y = REST_JOINTS_M[12, 1]
    return {j: float(REST_JOINTS_M[j, 1] / neck_y) for j in (3, 6, 9)}


def _along(points: np.ndarray, fraction: float) -> np.ndarray:
    """The point at ``fraction`` of a polyline (P, 3)'s arc length."""
    lengths = np.linalg.norm(np.diff(points, axis=0), axis=1)
    target = fraction * lengths.sum()
    k = int(np.searchsorted(np.cumsum(lengths), target))
    k = min(k, len(lengths) - 1)
    before = lengths[:k].sum()
    return points[k] + (target - before) / lengths[k] * (points[k + 1] - points[k])


def smpl_joints(labels: list[str], heads: np.ndarray) -> np.ndarray:
    """(J, 3) SMPL-22 joints from anny bone heads (B, 3)."""
    index = {name: i for i, name in enumerate(labels)}
    out = np.empty((NUM_JOINTS, 3))
    for j, name in enumerate(JOINT_BONES):
        if name is None:
            continue
        if "*" in name:
            side = name[-2:]
            toes = [i for n, i in index.items() if n.startswith("toe") and n.endswith(f"-1{side}")]
            out[j] = heads[toes].mean(axis=0)
        else:
            out[j] = heads[index[name]]
    spine = heads[[index[n] for n in SPINE_BONES]]
    for j, fraction in _spine_fractions().items():
        out[j] = _along(spine, fraction)
    for j, side in ((13, "L"), (14, "R")):
        clavicle = heads[index[f"clavicle.{side}"]]
        out[j] = clavicle + COLLAR_FRACTION * (heads[index[f"upperarm01.{side}"]] - clavicle)
    return out


def collapse_skinning(
    labels: list[str], bone_index: np.ndarray, bone_weight: np.ndarray
) -> tuple[np.ndarray, ...]:
    """anny's skinning (V, 9 bones) -> the SMPL joints' (V, K) indices and weights, top K renormalised."""
    joint_of_bone = np.array([bone_joint(n) for n in labels])
    per_joint = np.zeros((len(bone_index), NUM_JOINTS))
    np.add.at(per_joint, (np.arange(len(bone_index))[:, None], joint_of_bone[bone_index]), bone_weight)
    top = np.argsort(-per_joint, axis=1, kind="stable")[:, :SKIN_SLOTS]
    weight = np.take_along_axis(per_joint, top, axis=1)
    weight /= weight.sum(axis=1, keepdims=True)
    return top.astype(np.int32), weight.astype(np.float32)


def face_parts(model: Any) -> dict[str, np.ndarray]:
    """{part: (F,) bool} from anny's body-part segmentation texture (head, hand.L, foot.R, eyes, mouth...)."""
    from anny.paths import get_anny_root_dir

    folder = get_anny_root_dir() / "data" / "segmentation"
    image = cv2.cvtColor(cv2.imread(str(folder / "body_parts_segmentation.png")), cv2.COLOR_BGR2RGB)
    colours = yaml.safe_load((folder / "body_parts_segmentation.yaml").read_text())["colors"]
    uv = model.texture_coordinates[model.face_texture_coordinate_indices].mean(dim=1).numpy()
    h, w = image.shape[:2]
    u = np.clip(np.round(uv[:, 0] * w).astype(int), 0, w - 1)
    v = np.clip(np.round((1 - uv[:, 1]) * h).astype(int), 0, h - 1)
    face_rgb = image[v, u]
    return {part: (face_rgb == np.asarray(rgb)).all(axis=-1) for part, rgb in colours.items()}


def face_regions(
    parts: dict[str, np.ndarray], faces: np.ndarray, skin_joint: np.ndarray, rest_vertices: np.ndarray,
    joints: np.ndarray, eyes_m: np.ndarray,
) -> np.ndarray:  # fmt: skip
    """(F,) REGION_* per triangle: segmentation first (head, hands, feet), the moving joint for the rest."""
    dominant = skin_joint[faces, 0]  # (F, 3) each corner's strongest joint
    corner_regions = np.vectorize(JOINT_REGION.get)(dominant)
    region = np.array([np.bincount(r, minlength=12).argmax() for r in corner_regions], dtype=np.uint8)
    head = np.zeros(len(faces), dtype=bool)
    for part, mask in parts.items():
        if part.startswith(("head", "eye", "mouth", "tongue")):
            head |= mask
    region[head] = bodies.REGION_FACE
    centre = rest_vertices[faces].mean(axis=1)
    behind = centre[:, 2] < joints[15, 2] - 0.02
    scalp = head & ((centre[:, 1] > eyes_m[1] + 0.035) | (behind & (centre[:, 1] > eyes_m[1] - 0.04)))
    region[scalp] = bodies.REGION_SCALP
    for part in ("mouth_cavity", "tongue", "eye_cavity.L", "eye_cavity.R", "eye_back.L", "eye_back.R"):
        region[parts[part]] = bodies.REGION_INNER
    region[parts.get("hand.L", 0) | parts.get("hand.R", 0)] = bodies.REGION_HAND
    region[parts.get("foot.L", 0) | parts.get("foot.R", 0)] = bodies.REGION_FOOT
    return region


def sample_phenotype(rng: np.random.Generator) -> dict[str, float]:
    """anny's shape parameters, uniform in PHENOTYPE_RANGES, and a stature in metres: anny's own height
    parameter spans 1.35-2.15 m, so the body is scaled to a height drawn like adults' (normal, men 1.76 m,
    women 1.63 m, sd 7 cm, between 1.48 and 2.00 m; anny's gender 0 is male)."""
    phenotype = {name: float(rng.uniform(*span)) for name, span in PHENOTYPE_RANGES.items()}
    mean_m = STATURE_MALE_M + (STATURE_FEMALE_M - STATURE_MALE_M) * phenotype["gender"]
    phenotype["height_m"] = float(np.clip(rng.normal(mean_m, STATURE_SD_M), *STATURE_RANGE_M))
    return phenotype


def rest_body(model: Any, phenotype: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """anny at rest for one phenotype -> vertices (V, 3) and bone heads (B, 3) in SMPL axes, feet on y = 0,
    the pelvis above the origin, scaled to ``phenotype["height_m"]``."""
    identity = torch.eye(4)[None, None].repeat(1, model.bone_count, 1, 1)
    shape = {name: value for name, value in phenotype.items() if name in PHENOTYPE_RANGES}
    with torch.no_grad():
        out = model(pose_parameters=identity, phenotype_kwargs=shape)
    vertices = out["rest_vertices"][0].double().numpy() @ ANNY_TO_SMPL.T
    heads = out["rest_bone_heads"][0].double().numpy() @ ANNY_TO_SMPL.T
    origin = np.array([heads[0, 0], vertices[:, 1].min(), heads[0, 2]])
    scale = phenotype["height_m"] / (vertices[:, 1].max() - vertices[:, 1].min())
    return (vertices - origin) * scale, (heads - origin) * scale


def build_bank(count: int, seed: int, model: Any | None = None) -> BodyBank:
    """``count`` random adult bodies, drawn from ``default_rng([seed, index])``."""
    model = model or load_anny()
    labels = list(model.bone_labels)
    index = {name: i for i, name in enumerate(labels)}
    faces = model.faces.numpy().astype(np.int32)
    skin_joint, skin_weight = collapse_skinning(
        labels, model.vertex_bone_indices.numpy(), model.vertex_bone_weights.double().numpy()
    )
    parts = face_parts(model)
    vertices, joints, aligns, eyes, phenotypes, region = [], [], [], [], [], None
    for k in range(count):
        phenotype = sample_phenotype(np.random.default_rng([seed, k]))
        verts, heads = rest_body(model, phenotype)
        body_joints = smpl_joints(labels, heads)
        hand_dirs = np.stack([heads[index[f"finger3-1.{s}"]] - heads[index[f"wrist.{s}"]] for s in "LR"])
        eyes_m = (heads[index["eye.L"]] + heads[index["eye.R"]]) / 2
        if region is None:
            region = face_regions(parts, faces, skin_joint, verts, body_joints, eyes_m)
        vertices.append(verts.astype(np.float32))
        joints.append(body_joints)
        aligns.append(bodies.rest_alignment(body_joints, hand_dirs))
        eyes.append(eyes_m)
        phenotypes.append(list(phenotype.values()))
    return BodyBank(
        faces=faces, region=region, skin_joint=skin_joint, skin_weight=skin_weight,
        rest_vertices=np.stack(vertices), rest_joints=np.stack(joints), align=np.stack(aligns),
        eyes_m=np.stack(eyes), phenotype=np.array(phenotypes), phenotype_names=(*PHENOTYPE_RANGES, "height_m"),
        source=f"anny (Apache-2.0, MakeHuman CC0 assets), seed {seed}",
    )  # fmt: skip
