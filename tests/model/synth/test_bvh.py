"""BVH parsing and retargeting, on a CMU-style rig that the test writes itself."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from egoposevr.model.rotations import geodesic_angle
from egoposevr.model.skeleton import JOINT_NAMES, REST_JOINTS_M
from egoposevr.model.synth.bvh import (
    CMU_MAPPING,
    BvhError,
    bvh_fk,
    load_bvh_motion,
    mapped_positions,
    parse_bvh,
    retarget_bvh,
)
from egoposevr.model.synth.motion import FOOT_JOINT_HEIGHT_M

UNIT_M = CMU_MAPPING.metres_per_unit
J = {name: i for i, name in enumerate(JOINT_NAMES)}


# The trunk of CMU's own BVH files (its 06_01.bvh, CMU units): shoulders 29 cm above the hips, where SMPL's
# are 56 cm; the neck and the clavicles pivot at Spine1.
CMU_TRUNK = {
    "Spine": np.array([-0.00908, 2.00015, -0.35323]),
    "Spine1": np.array([0.05647, 2.02258, 0.04270]),
    "Neck1": np.array([-0.02074, 1.73711, 0.13117]),
    "Head": np.array([-0.02359, 1.73615, -0.24320]),
    "LeftArm": np.array([3.20537, 1.11432, -0.27680]),
    "RightArm": np.array([-3.20537, 1.11432, -0.27680]),
}


def _rig(trunk: dict[str, np.ndarray] | None = None) -> list[tuple[str, str | None, np.ndarray]]:
    """(name, parent, offset in CMU units): CMU's joint names and zero-length hubs on SMPL proportions, the
    trunk's offsets replaced by ``trunk``'s where given."""
    rest = REST_JOINTS_M / UNIT_M

    def rel(a: str, b: str) -> np.ndarray:
        return rest[J[b]] - rest[J[a]]

    rig = _smpl_proportioned(rel)
    return [(name, parent, (trunk or {}).get(name, offset)) for name, parent, offset in rig]


def _smpl_proportioned(rel) -> list[tuple[str, str | None, np.ndarray]]:
    rig = [("Hips", None, np.zeros(3)), ("LowerBack", "Hips", np.zeros(3))]
    rig += [("Spine", "LowerBack", rel("pelvis", "spine1")), ("Spine1", "Spine", rel("spine1", "spine2"))]
    # CMU's neck: a pivot at Spine1, then two short bones up to the Head joint.
    rig += [("Neck", "Spine1", np.zeros(3)), ("Neck1", "Neck", rel("spine2", "neck") * 0.5)]
    rig += [("Head", "Neck1", rel("spine2", "neck") * 0.5 + rel("neck", "head"))]
    for side, s in (("Left", "left"), ("Right", "right")):
        rig += [
            (f"{side[0]}HipJoint", "Hips", np.zeros(3)),
            (f"{side}UpLeg", f"{side[0]}HipJoint", rel("pelvis", f"{s}_hip")),
            (f"{side}Leg", f"{side}UpLeg", rel(f"{s}_hip", f"{s}_knee")),
            (f"{side}Foot", f"{side}Leg", rel(f"{s}_knee", f"{s}_ankle")),
            (f"{side}ToeBase", f"{side}Foot", rel(f"{s}_ankle", f"{s}_foot")),
            (f"{side}Shoulder", "Spine1", np.zeros(3)),
            (f"{side}Arm", f"{side}Shoulder", rel("spine2", f"{s}_shoulder")),
            (f"{side}ForeArm", f"{side}Arm", rel(f"{s}_shoulder", f"{s}_elbow")),
            (f"{side}Hand", f"{side}ForeArm", rel(f"{s}_elbow", f"{s}_wrist")),
        ]
    return rig


# Rotation amplitude per joint (degrees), like CMU's: the hubs (LowerBack, Neck) bend a little.
AMPLITUDE = {"LowerBack": 8, "Neck": 10, "Neck1": 12, "Head": 8, "LHipJoint": 0, "RHipJoint": 0}
AMPLITUDE |= {"LeftShoulder": 0, "RightShoulder": 0}


def write_bvh(frames: int = 240, seed: int = 0, trunk: dict[str, np.ndarray] | None = None) -> str:
    """BVH text: frame 0 a T-pose, then smooth random motion, 120 Hz, ZYX rotation channels."""
    rig = _rig(trunk)
    rng = np.random.default_rng(seed)
    lines = ["HIERARCHY"]
    depth = {}
    children = {name: [n for n, p, _ in rig if p == name] for name, _, _ in rig}

    def emit(name: str, level: int) -> None:
        pad = "\t" * level
        parent = next(p for n, p, _ in rig if n == name)
        offset = next(o for n, _, o in rig if n == name)
        lines.append(f"{pad}{'ROOT' if parent is None else 'JOINT'} {name}")
        lines.append(pad + "{")
        lines.append(f"{pad}\tOFFSET {offset[0]:.5f} {offset[1]:.5f} {offset[2]:.5f}")
        chans = (
            "6 Xposition Yposition Zposition Zrotation Yrotation Xrotation"
            if parent is None
            else "3 Zrotation Yrotation Xrotation"
        )
        lines.append(f"{pad}\tCHANNELS {chans}")
        depth[name] = level
        for child in children[name]:
            emit(child, level + 1)
        if not children[name]:
            lines.extend([f"{pad}\tEnd Site", pad + "\t{", f"{pad}\t\tOFFSET 0 1 0", pad + "\t}"])
        lines.append(pad + "}")

    emit("Hips", 0)
    order = [n for n in _flatten(rig, children)]
    t = np.arange(frames) / 120.0
    values = []
    for name in order:
        amp = AMPLITUDE.get(name, 30)
        cols = 6 if name == "Hips" else 3
        block = np.zeros((frames, cols))
        for c in range(3):
            f, phase = rng.uniform(0.3, 1.2), rng.uniform(0, 2 * np.pi)
            block[:, cols - 3 + c] = amp * np.sin(2 * np.pi * f * t + phase)
        if name == "Hips":
            block[:, 0] = 10 * t
            block[:, 1] = 16 + 0.5 * np.sin(t)
            block[:, 3:] *= 0.5
        values.append(block)
    table = np.concatenate(values, axis=1)
    table[0] = 0.0  # the T-pose frame (the rig's rest pose is a T-pose)
    table[0, 1] = 16
    lines += ["MOTION", f"Frames: {frames}", "Frame Time: .0083333"]
    lines += [" ".join(f"{v:.4f}" for v in row) for row in table]
    return "\n".join(lines) + "\n"


def _flatten(rig, children):
    out = []

    def walk(name):
        out.append(name)
        for child in children[name]:
            walk(child)

    walk("Hips")
    return out


@pytest.fixture(scope="module")
def bvh_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("bvh") / "test_clip.bvh"
    path.write_text(write_bvh())
    return path


def test_parse_reads_hierarchy_and_motion(bvh_file):
    clip = parse_bvh(bvh_file.read_text())
    assert clip.names[0] == "Hips" and len(clip.names) == 30  # 25 joints and 5 end sites
    assert sum(clip.end_site) == 5 and "Head_EndSite" in clip.names
    assert clip.values.shape == (240, 6 + 24 * 3)
    assert clip.frame_time_s == pytest.approx(1 / 120, rel=1e-3)


def test_retargeted_fk_reproduces_mapped_source_joints_within_2cm(bvh_file):
    clip = parse_bvh(bvh_file.read_text())
    pos, _ = bvh_fk(clip)
    source = mapped_positions(pos, clip.names, CMU_MAPPING)[1:] * UNIT_M  # frame 0 is the T-pose
    # retarget_bvh is faithful to the file; load_bvh_motion then levels the feet and may rebuild the path
    # (motion.level_feet, motion.lock_support_feet: tests/model/synth/test_feet.py)
    motion = retarget_bvh(clip, CMU_MAPPING).motion
    joints = motion.joints()
    assert joints.shape == (239, 22, 3)
    hubs = [J["pelvis"], J["spine3"]]  # placed by the retarget itself
    others = np.setdiff1d(np.arange(22), hubs)
    shift = np.median(joints[:, others] - source[:, others], axis=(0, 1))  # grounding moved the whole clip
    error_m = np.linalg.norm(joints - (source + shift), axis=-1)
    # Within 2 cm at the 99th percentile. The peaks come from the rig's LowerBack and Neck pivots, which bend
    # the spine where SMPL has no joint (CMU has them too: DATA.md gives the numbers measured on its clips).
    assert np.percentile(error_m[:, others], 99, axis=0).max() < 0.02, error_m.max(axis=0)
    assert error_m[:, others].max() < 0.03
    assert error_m.mean() < 0.01


def test_retarget_keeps_the_sources_head_orientation(bvh_file):
    """The headset hangs off the head, so its rotation must follow the source's, not only its position."""
    clip = parse_bvh(bvh_file.read_text())
    _, rot = bvh_fk(clip)
    head = clip.names.index("Head")
    source = rot[1:, head] @ rot[0, head].T  # rotation since the T-pose
    _, global_rot = load_bvh_motion(bvh_file).fk()
    assert np.degrees(geodesic_angle(global_rot[:, J["head"]], source)).max() < 2.0


def test_motion_is_grounded_and_resampled(bvh_file):
    motion = load_bvh_motion(bvh_file, fps=60)
    assert motion.fps == 60 and motion.num_frames == 119
    joints = motion.joints()
    assert np.percentile(joints[:, [10, 11], 1].min(axis=1), 1) >= FOOT_JOINT_HEIGHT_M - 0.05
    # The floor is where the feet stand (motion.ground); a foot swinging with its toes down may dip below it.
    assert joints[:, :, 1].min() > -0.02
    assert np.allclose(motion.root_pos_m[0, [0, 2]], 0.0)


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("", "unexpected end of file"),
        ("HIERARCHI", "expected 'HIERARCHY'"),
        ("HIERARCHY ROOT Hips { OFFSET 0 0 x", "expected a number"),
        (
            "HIERARCHY ROOT Hips { OFFSET 0 0 0 CHANNELS 3 Xrotation Yrotation Zrotation } MOTION Frames: 2 Frame Time: 0.01 1 2 3",
            "need more",
        ),
        (
            "HIERARCHY ROOT Hips { OFFSET 0 0 0 CHANNELS 1 Xrotation } MOTION Frames: 1 Frame Time: 0.01 nan",
            "non-finite",
        ),
        (
            "HIERARCHY ROOT Hips { OFFSET 0 0 0 CHANNELS 1 Xrotation } MOTION Frames: 1 Frame Time: 0 1",
            "Frame Time",
        ),
    ],
)
def test_bad_bvh_gets_a_clear_error(text, needle):
    with pytest.raises(BvhError, match=needle):
        parse_bvh(text)


def test_rig_without_a_mapped_joint_is_refused(tmp_path):
    path = tmp_path / "tiny.bvh"
    path.write_text(
        "HIERARCHY ROOT Hips { OFFSET 0 0 0 CHANNELS 1 Xrotation } MOTION Frames: 2 Frame Time: 0.01 1 2\n"
    )
    with pytest.raises(BvhError, match="needs source joints"):
        load_bvh_motion(path, CMU_MAPPING)
    with pytest.raises(BvhError, match="cannot find the legs and spine"):
        load_bvh_motion(path)


def test_a_short_trunk_does_not_fold_the_spine(tmp_path):
    """CMU's trunk puts the spine3 hub (fitted to the neck and collars) below where spine2 reads from the
    source: spine2 must stay between spine1 and spine3, not bend 140-180° back on itself."""
    path = tmp_path / "cmu_trunk.bvh"
    path.write_text(write_bvh(trunk=CMU_TRUNK))
    result = retarget_bvh(parse_bvh(path.read_text()))
    local_rot = result.motion.local_rot
    spine2_deg = np.degrees(geodesic_angle(local_rot[:, J["spine2"]], np.eye(3)[None]))
    assert spine2_deg.max() < 60.0, spine2_deg.max()
    joints = result.motion.joints()
    up = joints[:, J["spine3"]] - joints[:, J["spine1"]]
    along = np.einsum("fi,fi->f", joints[:, J["spine2"]] - joints[:, J["spine1"]], up) / np.einsum(
        "fi,fi->f", up, up
    )
    assert ((along > 0.2) & (along < 0.95)).all()  # spine1 -> spine2 -> spine3 in order, every frame


def test_rotation_channel_order_follows_the_file():
    text = (
        "HIERARCHY ROOT Hips { OFFSET 0 0 0 CHANNELS 3 Xrotation Yrotation Zrotation "
        "JOINT A { OFFSET 1 0 0 CHANNELS 3 Zrotation Yrotation Xrotation End Site { OFFSET 1 0 0 } } } "
        "MOTION Frames: 1 Frame Time: 0.01 10 20 30 0 0 0\n"
    )
    _, rot = bvh_fk(parse_bvh(text))
    expected = Rotation.from_euler("XYZ", [10, 20, 30], degrees=True).as_matrix()
    assert np.allclose(rot[0, 0], expected)


def test_the_cmu_rig_is_detected_and_its_tpose_frame_dropped(bvh_file):
    """Without a mapping the rig is read from the file: CMU's names, its units, Y up, frame 0 dropped."""
    result = retarget_bvh(parse_bvh(bvh_file.read_text()))
    assert result.rig.family == "cmu" and result.rig.units == "cmu" and result.rig.up_axis == "+Y"
    assert result.dropped == 1 and result.motion.num_frames == 239
    pinned = retarget_bvh(parse_bvh(bvh_file.read_text()), CMU_MAPPING).motion
    apart_m = np.linalg.norm(result.motion.joints() - pinned.joints(), axis=-1).max(axis=0)
    # Only spine2 is placed otherwise: 66 % of the way Spine -> Spine1 (SMPL's arc length), not half-way.
    assert apart_m[J["spine2"]] < 0.03
    assert np.delete(apart_m, J["spine2"]).max() < 0.01
