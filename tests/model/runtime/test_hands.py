"""A lost hand's orientation: it starts where tracking left it and fades to the network's, with no jump."""

import numpy as np
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
