"""Served feet and the floor over a real loopback server (PROTOCOL.md §3 `§floor`): a user who stands still and
moves only the upper body, in a floor-level space and in a LOCAL one (no floor at y = 0: the session finds its own)."""

from __future__ import annotations

import time

import numpy as np
import pytest
from loopback import Client, hmd_messages

from egoposevr.model.skeleton import FOOT_JOINT_HEIGHT_M
from egoposevr.model.synth.headset import simulate_headset
from egoposevr.model.synth.procedural import generate
from egoposevr.model.training.plausibility import FEET

STANDING_SKATING_BAR_M_S = 0.02  # issue 25: a standing user's served feet skate at most 2 cm/s
SEND_GAP_S = 0.004  # 250 samples/s: under the server's 400 messages/s per session


def answered(client: Client, seq: int) -> bool:
    """Whether the newest pose the client has received answers sample `seq` (or a later one)."""
    poses = client.poses()
    return bool(poses) and poses[-1].seq >= seq


def served_feet(server, session: str, drop_m: float, model: str = "egoposevr") -> tuple[np.ndarray, list]:
    """Stream 6 s of a still-standing user (its whole stream lowered by drop_m) to ``model`` -> the served
    foot joints (N, 2, 3) of the last two seconds, and every pose (in order).

    Lockstep: each sample waits for its pose, so none is dropped as stale (newest wins) however busy the
    machine is, and the served stream, hence every bound below, does not depend on pacing. At most one
    sample per SEND_GAP_S: a model that answers at once (procedural) stays under the rate limit."""
    rng = np.random.default_rng(0)
    track = simulate_headset(generate("still_stand", 6.0, 60.0, rng), 90.0, rng)
    poses = track.poses.copy()
    poses[..., 1] -= drop_m
    with Client(server.url, session) as headset:
        headset.hello("input", session, model=model)
        headset.collect()
        for k, msg in enumerate(hmd_messages(track.t_us, poses, track.valid)):
            sent_s = time.monotonic()
            headset.send(msg)
            headset.wait_for(lambda k=k: answered(headset, k), timeout=10, poll_s=0.001)
            time.sleep(max(0.0, SEND_GAP_S - (time.monotonic() - sent_s)))
        last = len(track.t_us) - 1
        poses = headset.poses()
    late = [m for m in poses if m.seq >= last - 180]
    assert [m.seq for m in late] == list(range(last - 180, last + 1))  # every sample answered, none dropped
    return np.array([np.asarray(m.joints).reshape(22, 3)[list(FEET)] for m in late]), poses


@pytest.mark.protocol("floor")
def test_planted_feet_stay_on_the_floor_and_a_local_space_gets_the_sessions_own_floor(server):
    feet, _ = served_feet(server, "floor-stage", 0.0)
    assert np.abs(feet[..., 1] - FOOT_JOINT_HEIGHT_M).max() < 0.02  # soles on y = 0
    assert np.ptp(feet, axis=0).max() < 0.02  # planted: no skating while only the arms move

    local, _ = served_feet(server, "floor-local", 1.6)  # y = 0 at the head: the feet hang far below it
    assert local[..., 1].max() < -0.5  # not pulled up to y = 0
    # With y = 0 at the head the body's height is unknown and the network's legs are a crouch whose pelvis
    # wanders (about 15 cm over these 2 s): a free foot would follow it. A planted foot may creep (its anchor
    # settles, and KPO reconciles it with legs of unknown length: about 0.75 cm/s here), but never faster
    # than what issue 25 allows a standing user's feet, and no sole goes below the floor the session
    # estimated under them.
    floor_y_m = local[..., 1].min()
    creep_m_s = min(np.ptp(local[:, k], axis=0).max() for k in range(2)) / 2.0  # the last 2 s
    assert creep_m_s < STANDING_SKATING_BAR_M_S
    assert np.abs(local[:, np.argmin(np.ptp(local[..., 0], axis=0)), 1] - floor_y_m).max() < 0.02


@pytest.mark.protocol("planted-feet")
def test_poses_say_which_feet_are_planted_and_the_floor_they_are_held_to(server):
    feet, poses = served_feet(server, "planted-stage", 0.0)
    late = poses[-len(feet) :]
    assert all(m.planted == [True, True] for m in late)  # a still stander's feet are down
    assert all(m.floor_y_m == 0.0 for m in late)  # a floor-level space: the floor is y = 0
    assert np.ptp(feet, axis=0).max() < 0.02  # and they stay where they are

    local, poses = served_feet(server, "planted-local", 1.6)
    assert poses[0].floor_y_m is None  # no floor yet: the feet hang far below y = 0, which is not the floor
    late = poses[-len(local) :]
    assert all(m.planted == [True, True] for m in late)
    floors = np.array([m.floor_y_m for m in late])  # the session's own estimate, under the served soles
    assert floors.max() < -0.5
    assert np.abs(local[..., 1].min(axis=1) - FOOT_JOINT_HEIGHT_M - floors).max() < 0.03

    _, poses = served_feet(server, "planted-procedural", 0.0, model="procedural")
    assert all(m.planted == [True, True] and m.floor_y_m == 0.0 for m in poses[-180:])  # standing, no step
    _, poses = served_feet(server, "planted-hmd", 0.0, model="hmd")
    assert all(m.planted is None and m.floor_y_m is None for m in poses)  # its feet are the network's alone
