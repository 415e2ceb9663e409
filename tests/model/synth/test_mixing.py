"""Mixed clips: one clip's legs under another's trunk, head and arms (model/synth/mixing.py)."""

import numpy as np
import pytest
from rigfamilies import reference_motion
from scipy.spatial.transform import Rotation

from egoposevr.model.skeleton import LOWER_BODY, UPPER_BODY
from egoposevr.model.synth.mixing import SPEED_RANGE, back_and_forth, mix_halves
from egoposevr.model.synth.motion import Motion, resample


def _motion(name: str, frames: int, fps: float, seed: int) -> Motion:
    local_rot, root_pos_m = reference_motion(frames=frames, fps=fps, seed=seed)
    return Motion(name, fps, local_rot, root_pos_m, np.ones(22), f"test:{name}", "CC0")


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between rotation matrices a (..., 3, 3) and b (..., 3, 3)."""
    return np.degrees(Rotation.from_matrix((a @ np.swapaxes(b, -1, -2)).reshape(-1, 3, 3)).magnitude())


def test_a_mixed_clip_walks_on_the_first_clips_legs_and_moves_the_seconds_arms():
    legs, upper = _motion("legs", 600, 60.0, 0), _motion("upper", 1200, 120.0, 1)
    mixed = mix_halves(legs, upper, np.random.default_rng(3), seconds=4.0)
    assert mixed.num_frames == 240 and mixed.fps == 60.0
    start = int(np.flatnonzero(np.all(legs.root_pos_m == mixed.root_pos_m[0], axis=1))[0])
    window = legs.slice(start, start + 240)
    np.testing.assert_array_equal(mixed.root_pos_m, window.root_pos_m)
    np.testing.assert_allclose(mixed.joints()[:, LOWER_BODY], window.joints()[:, LOWER_BODY], atol=1e-12)
    # every upper-body pose is one the other clip took (within its sampling), and none is the legs clip's own
    dense = resample(upper, 480.0).local_rot[:, UPPER_BODY]
    for frame in mixed.local_rot[::20, UPPER_BODY]:
        off_deg = _angle_deg(dense, np.broadcast_to(frame, dense.shape)).reshape(len(dense), -1)
        assert off_deg.max(axis=1).min() < 1.0  # some pose of the other clip, every joint within 1°
    assert _angle_deg(mixed.local_rot[:, UPPER_BODY], window.local_rot[:, UPPER_BODY]).mean() > 5.0
    assert mixed.source == "mixed:test:legs+test:upper" and mixed.licence == "CC0"


def test_a_short_upper_body_is_played_back_and_forth_without_a_jump():
    legs, upper = _motion("legs", 900, 60.0, 0), _motion("upper", 90, 60.0, 1)  # 15 s of legs, 1.5 s of arms
    mixed = mix_halves(legs, upper, np.random.default_rng(0), seconds=10.0)
    assert mixed.num_frames == 600
    step_deg = _angle_deg(mixed.local_rot[1:, UPPER_BODY], mixed.local_rot[:-1, UPPER_BODY])
    own_step_deg = _angle_deg(upper.local_rot[1:, UPPER_BODY], upper.local_rot[:-1, UPPER_BODY])
    assert step_deg.max() <= own_step_deg.max() * SPEED_RANGE[1] * 1.1


def test_mixing_is_drawn_from_its_generator():
    legs, upper = _motion("legs", 600, 60.0, 0), _motion("upper", 600, 60.0, 1)
    a, b, c = (mix_halves(legs, upper, np.random.default_rng(s), 3.0) for s in (1, 1, 2))
    np.testing.assert_array_equal(a.local_rot, b.local_rot)
    assert not np.array_equal(a.local_rot, c.local_rot)
    short = mix_halves(legs.slice(0, 100), upper, np.random.default_rng(1), 3.0)
    assert short.num_frames == 100  # a clip of legs shorter than asked is used whole


def test_back_and_forth_folds_time_into_the_clip():
    t_s = np.array([0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.5])
    np.testing.assert_allclose(back_and_forth(t_s, 1.0), [0.0, 0.5, 1.0, 0.5, 0.0, 0.5, 0.5])


def test_a_clip_of_one_frame_cannot_be_mixed():
    with pytest.raises(ValueError, match="two frames"):
        mix_halves(_motion("legs", 600, 60.0, 0), _motion("one", 1, 60.0, 1), np.random.default_rng(0), 3.0)
