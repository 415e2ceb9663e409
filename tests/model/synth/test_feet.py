"""Do a motion's feet grip and stand flat: foot_slide, stance_foot_height_m and level_feet on bodies with known
answers."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from egoposevr.model.skeleton import FOOT_JOINT_HEIGHT_M
from egoposevr.model.synth.motion import (
    Motion,
    foot_slide,
    level_feet,
    lock_support_feet,
    stance_foot_height_m,
    support_lock_offsets_m,
)

FPS = 60.0
STEP_S = 0.5  # each foot stands this long, then swings while the other stands
SPEED_M_S = 1.0  # the pelvis's


def walker(frames: int = 300, slide: float = 0.0, ball_lift_m: float = 0.0) -> np.ndarray:
    """(F, 22, 3) a body walking along +z at SPEED_M_S: the pelvis moves steadily, each foot stands for
    STEP_S (moving at ``slide`` times the pelvis's speed) and then catches up at the pace that keeps it beside
    the body. The balls of the feet stand ``ball_lift_m`` above where a flat foot has them."""
    t_s = np.arange(frames) / FPS
    joints = np.zeros((frames, 22, 3))
    joints[:, 0] = np.stack([np.zeros(frames), np.full(frames, 0.9), SPEED_M_S * t_s], axis=1)
    for side, (ankle, ball) in enumerate(((7, 10), (8, 11))):
        phase = (t_s / STEP_S + side) % 2.0  # < 1: standing
        z = np.zeros(frames)
        for i in range(1, frames):
            pace = slide if phase[i] < 1.0 else 2.0 - slide  # the two phases average to the pelvis's pace
            z[i] = z[i - 1] + pace * SPEED_M_S / FPS
        lift = np.where(phase < 1.0, 0.0, 0.1 * np.sin(np.pi * (phase - 1.0)))
        x = 0.1 if side else -0.1
        joints[:, ankle] = np.stack([np.full(frames, x), 0.08 + lift, z], axis=1)
        joints[:, ball] = joints[:, ankle] + [0.0, FOOT_JOINT_HEIGHT_M - 0.08 + ball_lift_m, 0.12]
    return joints


def test_feet_that_grip_hardly_slide():
    assert foot_slide(walker(), FPS) == pytest.approx(0.0, abs=0.02)


@pytest.mark.parametrize("slide", [0.3, 0.5])
def test_standing_feet_that_slide_measure_their_share_of_the_pelvis_speed(slide):
    assert foot_slide(walker(slide=slide), FPS) == pytest.approx(slide, abs=0.03)


def test_a_body_that_glides_slides_wholly():
    joints = walker()
    joints[:, [7, 8, 10, 11]] = joints[:, [0]] + [0.0, -0.8, 0.0]  # feet carried along with the pelvis
    assert foot_slide(joints, FPS) == pytest.approx(1.0, abs=1e-6)


def test_a_body_that_does_not_travel_has_no_slide():
    joints = walker()
    joints[:, :, 2] = joints[:1, :, 2]
    assert foot_slide(joints, FPS) is None
    assert foot_slide(walker()[:2], FPS) is None


@pytest.mark.parametrize("lift_m", [0.0, 0.03])
def test_a_standing_foot_is_where_its_ball_stands(lift_m):
    height_m = stance_foot_height_m(walker(ball_lift_m=lift_m), FPS)
    assert height_m == pytest.approx(FOOT_JOINT_HEIGHT_M + lift_m, abs=1e-9)


def test_no_standing_foot_has_no_height():
    joints = walker()
    joints[:, [7, 8, 10, 11]] = joints[:, [0]] + [0.0, -0.8, 0.0]
    assert stance_foot_height_m(joints, FPS) is None


def _standing(frames: int = 120) -> Motion:
    """A body standing in SMPL's rest pose, its pelvis swaying a little."""
    local = np.broadcast_to(np.eye(3), (frames, 22, 3, 3)).copy()
    root = np.zeros((frames, 3))
    root[:, 1] = 1.0
    root[:, 0] = 0.02 * np.sin(np.arange(frames) / 10)
    return Motion("stand", FPS, local, root, np.ones(22), "test:stand", "test")


def _tilted(motion: Motion, toes_up_deg: float) -> Motion:
    """Every frame's ankles turned toes-up by the same angle, as a conversion's rest-pose mismatch does."""
    local = motion.local_rot.copy()
    offsets = motion.offsets_m()
    for ankle, ball in ((7, 10), (8, 11)):
        axis = np.cross([0.0, 1.0, 0.0], offsets[ball])
        axis /= np.linalg.norm(axis)
        local[:, ankle] = local[:, ankle] @ Rotation.from_rotvec(-np.radians(toes_up_deg) * axis).as_matrix()
    return motion.replace(local_rot=local)


@pytest.mark.parametrize("toes_up_deg", [13.0, -8.0])
def test_feet_tilted_by_a_conversion_stand_flat_again(toes_up_deg):
    flat = _standing()
    tilted = _tilted(flat, toes_up_deg)
    raised_m = tilted.joints()[0, 10, 1] - flat.joints()[0, 10, 1]
    assert abs(raised_m) > 0.015  # the ball moved: the test's tilt is real
    levelled = level_feet(tilted)
    np.testing.assert_allclose(levelled.joints(), flat.joints(), atol=1e-6)
    np.testing.assert_allclose(levelled.local_rot[:, [7, 8]], flat.local_rot[:, [7, 8]], atol=1e-6)


def test_flat_feet_are_left_alone():
    flat = _standing()
    np.testing.assert_allclose(level_feet(flat).local_rot, flat.local_rot, atol=1e-12)


def test_a_tilt_beyond_any_rigs_is_turned_back_only_so_far():
    levelled = level_feet(_tilted(_standing(), 60.0))
    residual = levelled.joints()[0, 10, 1] - _standing().joints()[0, 10, 1]
    assert residual > 0.03  # 60° toes up, turned back by MAX_FOOT_TURN_DEG: the toes stay up


def test_feet_that_slide_are_held_by_rebuilding_the_path_from_the_strides():
    sliding = walker(slide=0.4)
    shifted = sliding.copy()
    shifted[..., [0, 2]] += support_lock_offsets_m(sliding, FPS)[:, None]
    assert foot_slide(shifted, FPS) == pytest.approx(0.0, abs=0.02)
    # the body now travels as far as its strides carry it: 1.6 of the pelvis pace in swing, half the time
    travelled = shifted[-1, 0, 2] - shifted[0, 0, 2]
    assert travelled == pytest.approx(0.6 * (sliding[-1, 0, 2] - sliding[0, 0, 2]), rel=0.05)


def test_feet_that_grip_keep_their_path():
    gripping = walker()
    assert np.abs(support_lock_offsets_m(gripping, FPS)).max() < 0.01
    motion = _standing()
    assert lock_support_feet(motion) is motion  # nothing travels: nothing to lock
