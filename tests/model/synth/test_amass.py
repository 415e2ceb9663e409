"""AMASS .npz loading on a file the test writes itself."""

import numpy as np
import pytest

from egoposevr.model.rotations import axis_angle_to_matrix
from egoposevr.model.synth.amass import AmassError, load_amass_motion


def _write(path, frames=90, rate=120.0):
    rng = np.random.default_rng(3)
    poses = rng.normal(0.0, 0.2, (frames, 156))
    poses[:, :3] = [np.pi / 2, 0.0, 0.0]  # AMASS's upright body in its z-up world
    trans = np.stack([np.linspace(0, 1, frames), np.zeros(frames), np.full(frames, 0.9)], -1)
    np.savez(path, poses=poses, trans=trans, mocap_framerate=rate, betas=np.zeros(16))
    return poses, trans


def test_amass_loader_keeps_body_rotations_and_turns_z_up_into_y_up(tmp_path):
    poses, _trans = _write(tmp_path / "seq.npz")
    motion = load_amass_motion(tmp_path / "seq.npz")
    assert motion.fps == 120 and motion.num_frames == 90
    expected = axis_angle_to_matrix(poses[:, 3:66].reshape(-1, 21, 3))
    assert np.allclose(motion.local_rot[:, 1:], expected)
    assert np.allclose(motion.local_rot[:, 0], np.eye(3), atol=1e-9)  # upright, facing +z
    travel = motion.root_pos_m[-1] - motion.root_pos_m[0]
    assert np.allclose(travel, [1.0, 0.0, 0.0], atol=1e-9)  # AMASS x stays x; its z (up) became y
    assert motion.joints()[..., 1].min() > -0.05  # grounded


def test_amass_loader_resamples(tmp_path):
    _write(tmp_path / "seq.npz")
    assert load_amass_motion(tmp_path / "seq.npz", fps=60).num_frames == 45


@pytest.mark.parametrize(
    "arrays",
    [
        {"poses": np.zeros((4, 30)), "trans": np.zeros((4, 3)), "mocap_framerate": 60.0},
        {"poses": np.zeros((4, 156)), "trans": np.zeros((5, 3)), "mocap_framerate": 60.0},
        {"poses": np.full((4, 156), np.nan), "trans": np.zeros((4, 3)), "mocap_framerate": 60.0},
        {"poses": np.zeros((4, 156)), "trans": np.zeros((4, 3))},
    ],
)
def test_bad_amass_files_get_a_clear_error(tmp_path, arrays):
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(AmassError, match=r"bad\.npz"):
        load_amass_motion(tmp_path / "bad.npz")


def test_corrupt_amass_file(tmp_path):
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(AmassError, match=r"junk\.npz"):
        load_amass_motion(tmp_path / "junk.npz")
