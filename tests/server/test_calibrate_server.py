"""calibrate / calibration over a real loopback server (PROTOCOL.md §4.1), with a synthetic user whose body
and grips differ from the rig's defaults."""

from __future__ import annotations

import time

import numpy as np
import pytest
from loopback import Client, hmd_messages, pack
from syntheticusers import User, device_poses, holding, posed_joints

from egoposevr.protocol import Calibrate, Hmd, SelectModel

USER = User(height_scale=0.94, arm_scale=1.1, head_tilt_deg=10.0, grip_pitch_deg=(30.0, -30.0))


def _send_paced(client: Client, messages: list[Hmd]) -> None:
    """A few ms apart: a burst of more than the server's 64 pending samples would drop the oldest before the
    calibration sees them (newest wins), as it should under overload."""
    for msg in messages:
        client.send(msg)
        time.sleep(0.003)


def _statuses(client: Client) -> list:
    return [m for _, m in client.received if m.type == "calibration"]


def _served_wrist_error_m(headset: Client, pose_yaw_deg: float, first_seq: int) -> float:
    """Stream the user standing arms half down for 30 samples -> the served wrists' error, m."""
    joints, glob = posed_joints(USER, pose_yaw_deg, -50.0)
    still = np.repeat(device_poses(USER, joints, glob)[None], 30, axis=0)
    t_us = 100_000_000 + first_seq * 11_111 + np.arange(30) * 11_111
    _send_paced(headset, hmd_messages(t_us, still, np.ones((30, 3), bool), first_seq=first_seq))
    last_seq = first_seq + 29
    headset.wait_for(lambda: any(p.seq == last_seq for p in headset.poses()), timeout=30)
    served = np.asarray(next(p for p in headset.poses() if p.seq == last_seq).joints).reshape(22, 3)
    return float(np.linalg.norm(served[[20, 21]] - joints[[20, 21]], axis=-1).max())


def _calibrate_tpose(headset: Client, t0_us: int) -> None:
    headset.send(Calibrate(pose="tpose", seconds=1.0))
    t_us, poses, valid = holding(USER, seconds=1.5)
    _send_paced(headset, hmd_messages(t_us + t0_us, poses, valid, first_seq=t0_us // 11_111))
    headset.wait_for(lambda: any(m.status == "done" for m in _statuses(headset)), timeout=30)


@pytest.mark.protocol("calibrate")
def test_a_tpose_calibration_is_announced_to_every_client_and_puts_the_wrists_in_place(server):
    viewer = Client(server.url, "calib")
    viewer.hello("render", "calib")
    viewer.collect()
    with Client(server.url, "calib") as headset:
        headset.hello("input", "calib", model="procedural")
        headset.collect()
        headset.send(Calibrate(pose="tpose", seconds=1.0))
        t_us, poses, valid = holding(USER, seconds=1.5)
        _send_paced(headset, hmd_messages(t_us, poses, valid))
        for client in (headset, viewer):
            client.wait_for(lambda c=client: any(m.status == "done" for m in _statuses(c)), timeout=30)
            assert [m.status for m in _statuses(client)] == ["started", "done"]
        done = _statuses(headset)[-1]
        true_head_m = posed_joints(USER, 30.0, 0.0)[0][15, 1]
        assert done.head_height_m == pytest.approx(true_head_m, abs=0.01)
        assert done.arm_span_m > 1.3 and len(done.corrections) == 12

        # Arms half down, turned: the served wrists are where the procedural model puts tracked wrists (its
        # body sits 1-2 cm off this pose), where the default grips put them 4+ cm off (test_calibration.py).
        assert _served_wrist_error_m(headset, -20.0, first_seq=1000) < 0.03

        # A pose not held fails with the reason; clear goes back to estimating.
        headset.send(Calibrate(pose="tpose", seconds=1.0))
        t_us, poses, valid = holding(USER, seconds=1.5)
        poses[:, 1, :3] += np.linspace(0.0, 0.4, len(poses))[:, None]
        _send_paced(headset, hmd_messages(t_us + 200_000_000, poses, valid, first_seq=20000))
        headset.wait_for(lambda: _statuses(headset)[-1].status == "failed", timeout=30)
        assert "left controller moved" in _statuses(headset)[-1].message
        headset.send(Calibrate(clear=True))  # answered without any headset sample
        headset.wait_for(lambda: _statuses(headset)[-1].status == "cleared", timeout=30)
    viewer.close()


def test_a_bad_calibrate_is_refused_and_the_session_goes_on(server):
    with Client(server.url, "calib-bad") as headset:
        headset.hello("input", "calib-bad", model="procedural")
        headset.send(pack({"type": "calibrate", "v": 1, "seconds": 60.0}))
        error = headset.recv_type("error")
        assert error.code == "out_of_range" and error.ref.type == "calibrate" and not error.fatal
        headset.send(pack({"type": "calibrate", "v": 1, "pose": "lotus"}))
        assert headset.recv_type("error").code == "invalid_field"
        headset.send(Calibrate(pose="stand", seconds=0.5))
        assert headset.recv_type("calibration").status == "started"


@pytest.mark.protocol("calibration-kept")
def test_a_calibration_outlives_model_switches_and_a_reconnect(server):
    viewer = Client(server.url, "calib-kept")  # keeps the session while the headset reconnects
    viewer.hello("render", "calib-kept")
    viewer.collect()
    with Client(server.url, "calib-kept") as headset:
        headset.hello("input", "calib-kept", model="procedural")
        headset.collect()
        uncalibrated_m = _served_wrist_error_m(headset, 40.0, first_seq=0)
        _calibrate_tpose(headset, t0_us=150_000_000)
        for model in ("hmd", "procedural"):
            headset.send(SelectModel(model=model))
        assert _served_wrist_error_m(headset, 40.0, first_seq=5000) < 0.03 < 0.04 < uncalibrated_m
    with Client(server.url, "calib-kept") as headset:
        headset.hello("input", "calib-kept")
        headset.collect()
        assert _served_wrist_error_m(headset, 40.0, first_seq=9000) < 0.03
        headset.send(Calibrate(clear=True))
        headset.wait_for(lambda: any(m.status == "cleared" for m in _statuses(headset)), timeout=30)
        assert _served_wrist_error_m(headset, 40.0, first_seq=12000) > 0.04
    viewer.close()
