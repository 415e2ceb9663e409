"""A lost hand's orientation: it starts where tracking left it and fades to the network's, with no jump."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from egoposevr.model.rotations import geodesic_angle
from egoposevr.model.runtime import hands
from egoposevr.model.runtime.hands import LostHandPolicy

DT_US = 11_111


def test_tracked_devices_give_the_head_and_wrists_their_rotations():
    policy, glob = LostHandPolicy(), np.broadcast_to(np.eye(3), (22, 3, 3)).copy()
    device_rot = Rotation.from_rotvec([[0.0, 0.3, 0.0], [0.5, 0.0, 0.0], [0.0, 0.0, -0.5]]).as_matrix()
    leaves, rotations = policy.orientations(0, np.array([True, True, False]), device_rot, glob)
    assert leaves == [15, 20]  # the right controller was never tracked: the network's wrist
    np.testing.assert_allclose(rotations, device_rot[:2])


def test_a_lost_hand_turns_from_its_last_tracked_rotation_to_the_networks_without_a_jump():
    policy = LostHandPolicy()
    network = np.broadcast_to(np.eye(3), (22, 3, 3)).copy()
    network[20] = Rotation.from_rotvec([0.0, 0.0, 1.2]).as_matrix()  # the network's wrist, 69° off
    device_rot = np.broadcast_to(np.eye(3), (3, 3, 3)).copy()
    policy.orientations(0, np.ones(3, dtype=bool), device_rot, network)
    lost = np.array([True, False, True])
    off_deg = []
    for i in range(1, 2000):
        leaves, rotations = policy.orientations(i * DT_US, lost, device_rot, network)
        if 20 not in leaves:
            break
        off_deg.append(np.degrees(geodesic_angle(rotations[leaves.index(20)], device_rot[1])))
    off_deg = np.array(off_deg)
    assert off_deg[0] < 1e-6  # where tracking left it
    assert (np.diff(off_deg) > 0).all() and np.diff(off_deg).max() < 2.0  # towards the network's, smoothly
    share_left = (np.degrees(1.2) - off_deg[-1]) / np.degrees(1.2)
    assert share_left < 2 * hands.FADED  # handed over when what is left is too small to see
    half_life = round(hands.LOST_HAND_FADE_S * np.log(2) / (DT_US * 1e-6))  # samples
    assert abs(off_deg[half_life] - np.degrees(0.6)) < 1.0  # half the turn gone after one half-life


def _found_again(lost_samples: int, found_samples: int) -> tuple[np.ndarray, np.ndarray]:
    """The left controller tracked, lost for ``lost_samples`` and found again, still, 0.3 m from where the
    network puts its wrist -> the served left wrist's KPO target's distance from the controller (m) and its
    rotation's angle from the controller's (deg), from the last lost sample on."""
    policy = LostHandPolicy()
    joints = np.zeros((22, 3))
    joints[20] = [0.3, 1.0, 0.0]  # the network's wrist
    network = np.broadcast_to(np.eye(3), (22, 3, 3)).copy()
    network[20] = Rotation.from_rotvec([0.0, 0.0, 1.2]).as_matrix()
    device_pos, device_rot = np.zeros((3, 3)), np.broadcast_to(np.eye(3), (3, 3, 3)).copy()
    gap_m, gap_deg = [], []
    for i in range(lost_samples + found_samples + 1):
        valid = np.array([True, not 0 < i <= lost_samples, True])
        targets, observed = np.zeros((22, 3)), np.zeros(22, dtype=bool)
        targets[[15, 20, 21]], observed[[15, 20, 21]] = device_pos, valid
        policy.targets(i * DT_US, joints, valid, device_pos, targets, observed)
        leaves, served_rot = policy.orientations(i * DT_US, valid, device_rot, network)
        if i >= lost_samples:
            gap_m.append(np.linalg.norm(targets[20] if observed[20] else joints[20]))
            rot = served_rot[leaves.index(20)] if 20 in leaves else network[20]
            gap_deg.append(np.degrees(geodesic_angle(rot, np.eye(3))))
    return np.array(gap_m), np.array(gap_deg)


@pytest.mark.parametrize("lost_s", [0.05, 0.7, 5.0])  # within the fade, within the hold, long gone
def test_a_controller_found_again_brings_its_wrist_back_smoothly(lost_s):
    gap_m, gap_deg = _found_again(round(lost_s / (DT_US * 1e-6)), 20)
    closed = round(hands.REACQUIRE_S / (DT_US * 1e-6)) + 2  # samples from the last lost one
    for gap in (gap_m, gap_deg):
        assert gap[0] > 0.01 * gap.max()  # the lost wrist was somewhere else
        assert abs(gap[1] - gap[0]) < 1e-6 * gap[0]  # found: still where it was served while lost
        assert (np.diff(gap) <= 1e-12).all() and np.diff(gap).min() > -0.5 * gap[0]  # closing, in steps
        assert (gap[closed:] < 1e-9).all()  # on its controller after REACQUIRE_S
