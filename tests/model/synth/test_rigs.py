"""Any-rig retargeting: one known motion written in many rig families retargets to the same SMPL-22 joints."""

import dataclasses
import re

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from rigfamilies import FAMILIES, FAMILY, Layout, reference_motion, write_family_bvh
from scipy.spatial.transform import Rotation

from egoposevr.model.skeleton import JOINT_NAMES, forward_kinematics, rest_offsets
from egoposevr.model.synth.bvh import BvhError, parse_bvh, retarget_bvh
from egoposevr.model.synth.rigs import RigError, detect_rig, read_name

FPS = 60.0
LOCAL_ROT, ROOT_M = reference_motion(fps=FPS)
TRUTH_M = forward_kinematics(LOCAL_ROT, ROOT_M, rest_offsets())[0]
LAYOUTS = {
    "plain": Layout(),
    "a-pose": Layout(a_pose_deg=40.0),
    "z-up": Layout(z_up=True),
    "cm": Layout(units_per_m=100.0),
    "inches": Layout(units_per_m=1 / 0.0254, order="XYZ"),
    "yxz-channels": Layout(order="YXZ", root_order="XZY"),
    "six-channels-mm": Layout(six_channels=True, units_per_m=1000.0, order="XYZ"),
    "z-up-cm-a-pose": Layout(z_up=True, units_per_m=100.0, a_pose_deg=30.0, order="YZX"),
}


def _joints(family: str, layout: str) -> tuple[np.ndarray, object]:
    text = write_family_bvh(FAMILY[family], LAYOUTS[layout], LOCAL_ROT, ROOT_M, FPS)
    result = retarget_bvh(parse_bvh(text, name=f"{family}-{layout}"), name=family)
    joints = result.motion.joints()
    shift = np.median(joints - TRUTH_M[: len(joints)], axis=(0, 1))  # grounding's shift
    return joints - shift, result


@pytest.fixture(scope="module")
def reference() -> np.ndarray:
    return _joints("mixamo", "plain")[0]


@pytest.mark.parametrize("family", [f.name for f in FAMILIES])
def test_every_family_retargets_to_the_same_joints_within_2cm(family, reference):
    joints, result = _joints(family, "plain")
    assert result.dropped == 0 and len(joints) == len(TRUTH_M)
    to_truth = np.linalg.norm(joints - TRUTH_M, axis=-1)
    to_each_other = np.linalg.norm(joints - reference, axis=-1)
    assert to_truth.max() < 0.02, dict(zip(JOINT_NAMES, to_truth.max(0).round(3), strict=False))
    assert to_each_other.max() < 0.02, dict(zip(JOINT_NAMES, to_each_other.max(0).round(3), strict=False))


@pytest.mark.parametrize("layout", list(LAYOUTS))
@pytest.mark.parametrize("family", ["cmu", "3ds-max-biped", "daz", "unknown-names"])
def test_rest_pose_axes_units_and_channel_order_do_not_change_the_result(family, layout, reference):
    joints, result = _joints(family, layout)
    error = np.linalg.norm(joints - reference, axis=-1)
    assert error.max() < 0.02, dict(zip(JOINT_NAMES, error.max(0).round(3), strict=False))
    rig = result.rig
    assert rig.up_axis == ("+Z" if LAYOUTS[layout].z_up else "+Y")
    assert rig.forward_axis == ("-Y" if LAYOUTS[layout].z_up else "+Z")
    expected_units = {1.0: "m", 100.0: "cm", 1000.0: "mm", 1 / 0.0254: "inch"}[LAYOUTS[layout].units_per_m]
    assert rig.units == expected_units


def test_left_and_right_swapped_in_the_names_are_swapped_back(reference):
    family = dataclasses.replace(FAMILY["mixamo"], sides=("Right", "Left"))
    result = retarget_bvh(parse_bvh(write_family_bvh(family, Layout(), LOCAL_ROT, ROOT_M, FPS)))
    joints = result.motion.joints()
    joints -= np.median(joints - reference, axis=(0, 1))
    assert np.linalg.norm(joints - reference, axis=-1).max() < 0.02
    assert any("swapped" in note for note in result.rig.notes)


def test_a_clavicle_pivoting_at_the_chest_keeps_the_limbs_within_3cm():
    """CMU's conversion starts the clavicles at the chest joint: SMPL's collar is then a point on the chest ->
    shoulder line and the girdle is placed by convention (spine3 7 cm and the collars 6 cm from SMPL's own);
    the limbs and head still land on the source within 3 cm."""
    family = dataclasses.replace(FAMILY["cmu"], clavicle_at_chest=True)
    rot = LOCAL_ROT.copy()
    rot[:, [JOINT_NAMES.index("left_collar"), JOINT_NAMES.index("right_collar")]] = np.eye(3)
    truth = forward_kinematics(rot, ROOT_M, rest_offsets())[0]
    motion = retarget_bvh(parse_bvh(write_family_bvh(family, Layout(), rot, ROOT_M, FPS))).motion
    joints = motion.joints()
    girdle = [JOINT_NAMES.index(n) for n in ("spine3", "left_collar", "right_collar")]
    others = np.setdiff1d(np.arange(22), girdle)
    joints -= np.median(joints[:, others] - truth[:, others], axis=(0, 1))
    error = np.linalg.norm(joints - truth, axis=-1)
    assert error[:, others].max() < 0.03, dict(zip(JOINT_NAMES, error.max(0).round(3), strict=True))
    assert error[:, girdle].max() < 0.08


def _generic_names(text: str) -> str:
    """The same file with every joint renamed j000, j001, ... (names carry no information)."""
    counter = iter(range(10_000))
    return re.sub(
        r"^(\s*(?:ROOT|JOINT)\s+).*$", lambda m: f"{m.group(1)}j{next(counter):03d}", text, flags=re.M
    )


@pytest.mark.parametrize("family", [f.name for f in FAMILIES if f.head_top != "joint"])
def test_the_structure_alone_reads_every_rig_as_its_names_do(family):
    """Names renamed away: the structural fallback finds the same chains (a Mixamo-style HeadTop_End joint
    is the known exception: without a name it looks like the head)."""
    text = write_family_bvh(FAMILY[family], LAYOUTS["z-up-cm-a-pose"], LOCAL_ROT, ROOT_M, FPS)
    named = retarget_bvh(parse_bvh(text))
    generic = retarget_bvh(parse_bvh(_generic_names(text)))
    assert generic.rig.anchors_from == "structure"
    assert np.abs(generic.motion.joints() - named.motion.joints()).max() < 1e-6


def test_head_rotation_follows_the_source():
    """The headset hangs off the head: its orientation must be the source's, not only its position."""
    _, result = _joints("3ds-max-biped", "z-up-cm-a-pose")
    _, global_rot = result.motion.fk()
    truth_rot = forward_kinematics(LOCAL_ROT, ROOT_M)[1][:, JOINT_NAMES.index("head")]
    cos = (np.trace(np.swapaxes(global_rot[:, 15], -1, -2) @ truth_rot, axis1=-2, axis2=-1) - 1) / 2
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 2.0


@pytest.mark.parametrize(
    ("family", "expected"),
    [("cmu", "cmu"), ("mixamo", "mixamo"), ("3ds-max-biped", "3ds-max-biped"), ("vrm", "vrm"),
     ("unity-humanoid", "unity-humanoid"), ("rokoko", "rokoko"), ("xsens-mvn", "xsens-mvn"),
     ("optitrack-motive", "optitrack-motive"), ("unreal-suffix", "unreal"), ("h-anim-prefix", "h-anim"),
     ("unknown-names", "")],
)  # fmt: skip
def test_family_and_anchor_source_are_reported(family, expected):
    text = write_family_bvh(FAMILY[family], Layout(), LOCAL_ROT[:5], ROOT_M[:5], FPS)
    rig = detect_rig(parse_bvh(text))
    assert rig.family == expected
    assert rig.anchors_from == ("structure" if family == "unknown-names" else "names")


def test_a_reference_frame_0_and_its_blend_are_dropped():
    rot, root = reference_motion(fps=120.0)
    for side, sign in (("left", -1), ("right", 1)):  # arms down, 75° from the T-pose, as people hold them
        shoulder = JOINT_NAMES.index(f"{side}_shoulder")
        rot[:, shoulder] = Rotation.from_rotvec([0, 0, sign * np.radians(75)]).as_matrix() @ rot[:, shoulder]
    clean = retarget_bvh(
        parse_bvh(write_family_bvh(FAMILY["daz"], Layout(units_per_m=100.0), rot, root, 120.0))
    )
    assert clean.dropped == 0
    rot[0] = np.eye(3)  # a rest-pose reference frame, then a blend into the motion over 4 frames (cmu-daz's)
    for k in range(1, 5):
        rot[k] = Rotation.from_rotvec(Rotation.from_matrix(rot[5]).as_rotvec() * k / 5).as_matrix()
    text = write_family_bvh(FAMILY["daz"], Layout(units_per_m=100.0), rot, root, 120.0)
    assert retarget_bvh(parse_bvh(text)).dropped == 5


def _legs_and_head_only() -> str:
    chans = "CHANNELS 3 Zrotation Xrotation Yrotation"
    legs = "".join(
        f"JOINT {s}UpLeg {{ OFFSET {x} 0 0 {chans} JOINT {s}Leg {{ OFFSET 0 -40 0 {chans} JOINT {s}Foot {{ "
        f"OFFSET 0 -40 0 {chans} End Site {{ OFFSET 0 -5 10 }} }} }} }} "
        for s, x in (("Left", 8), ("Right", -8))
    )
    return (
        "HIERARCHY ROOT Hips { OFFSET 0 0 0 CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation "
        f"Yrotation JOINT Spine {{ OFFSET 0 30 0 {chans} JOINT Head {{ OFFSET 0 30 0 {chans} End Site {{ OFFSET "
        f"0 10 0 }} }} }} {legs}}} MOTION Frames: 1 Frame Time: 0.01 " + "0 " * 30
    )


def test_a_rig_without_arms_is_refused_naming_the_chains():
    with pytest.raises(RigError, match="arm chains"):
        detect_rig(parse_bvh(_legs_and_head_only()))


def test_a_rest_pose_that_does_not_stand_is_refused():
    text = write_family_bvh(FAMILY["mixamo"], Layout(), LOCAL_ROT[:3], ROOT_M[:3], FPS)
    flat = "\n".join(
        "  OFFSET 0 0 0" if line.strip().startswith("OFFSET") else line for line in text.splitlines()
    )
    with pytest.raises(RigError, match="cannot map the rig"):
        detect_rig(parse_bvh(flat))


def test_joint_names_are_read_across_families():
    def side_part(name: str) -> tuple[str, str]:
        info = read_name(name)
        return info.side, info.part

    assert side_part("mixamorig:LeftForeArm") == ("L", "forearm")
    assert side_part("Bip01 R Calf") == ("R", "shin")
    assert read_name("upperarm_twist_01_l").twist
    assert read_name("lShldr").side == "L" and read_name("LHipJoint").side == "L"
    assert side_part("l_hip") == ("L", "thigh") and side_part("Hips") == ("", "hips")
    assert side_part("ltibia") == ("L", "shin") and read_name("lowerback").side == ""
    assert side_part("J_Bip_C_Head") == ("", "head") and side_part("LEFTHAND") == ("L", "hand")


def test_parser_reads_spaced_names_and_end_sites():
    text = write_family_bvh(FAMILY["3ds-max-biped"], Layout(), LOCAL_ROT[:3], ROOT_M[:3], FPS)
    clip = parse_bvh(text)
    assert "Bip01 L Thigh" in clip.names
    assert [n for n, end in zip(clip.names, clip.end_site, strict=True) if end] == ["Bip01 Head_EndSite"]
    daz = parse_bvh(write_family_bvh(FAMILY["daz"], Layout(), LOCAL_ROT[:3], ROOT_M[:3], FPS))
    assert "lFoot_EndSite" in daz.names and daz.end_site[daz.names.index("lFoot_EndSite")]


_SAMPLE = write_family_bvh(FAMILY["cmu"], Layout(), LOCAL_ROT[:3], ROOT_M[:3], FPS)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    cut=st.integers(0, len(_SAMPLE)),
    junk=st.text(max_size=40),
    data=st.data(),
)
def test_fuzzed_files_give_a_bvh_error_or_a_motion(cut, junk, data):
    """Truncation, insertion and token swaps anywhere: a BvhError (or a clip), never another exception."""
    tokens = _SAMPLE[:cut].split() + junk.split() + _SAMPLE[cut:].split()
    if tokens and data.draw(st.booleans()):
        k = data.draw(st.integers(0, len(tokens) - 1))
        tokens[k] = data.draw(
            st.sampled_from(["{", "}", "JOINT", "End", "nan", "-1", "1e309", "7", "ROOT", "x"])
        )
    try:
        clip = parse_bvh(" ".join(tokens))
        retarget_bvh(clip)
    except BvhError:
        pass


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=300))
def test_random_bytes_give_a_bvh_error(blob):
    with pytest.raises(BvhError):
        parse_bvh(blob.decode("latin-1"))
