"""get_body / set_body / body over a real loopback server (PROTOCOL.md §4.2): a known wearer's body is served
from the next sample, kept across model switches and a reconnect, and a body out of range is refused to its
sender while the session goes on."""

from __future__ import annotations

import numpy as np
import pytest
from loopback import Client, hmd_messages, pack
from syntheticusers import User, holding

from egoposevr.model.runtime.body import bone_lengths_m
from egoposevr.model.skeleton import joint_bone_lengths
from egoposevr.protocol import GetBody, SelectModel, SetBody

USER = User(height_scale=1.05, arm_scale=1.0, head_tilt_deg=0.0, grip_pitch_deg=(0.0, 0.0))
KNOWN = bone_lengths_m(np.full(22, 0.9))  # a smaller wearer than the headset's height says


def _bodies(client: Client) -> list:
    return [m for _, m in client.received if m.type == "body"]


def _served_lengths(headset: Client, first_seq: int, count: int = 15) -> np.ndarray:
    """Stream the user standing still for ``count`` samples -> the bone lengths (21,) of the last pose, m."""
    t_us, poses, valid = holding(USER, seconds=count / 90.0 + 0.05)
    t_us = t_us[:count] + first_seq * 11_111
    for msg in hmd_messages(t_us, poses[:count], valid[:count], first_seq=first_seq):
        headset.send(msg)
    last = first_seq + count - 1
    headset.wait_for(lambda: any(m.seq == last for m in headset.poses()), timeout=30)
    joints = np.asarray(next(m for m in headset.poses() if m.seq == last).joints).reshape(22, 3)
    return joint_bone_lengths(joints)


@pytest.mark.protocol("known-body")
def test_a_known_body_is_served_from_the_next_sample_and_kept_until_cleared(server):
    viewer = Client(server.url, "body")  # keeps the session while the headset reconnects
    viewer.hello("render", "body")
    viewer.collect()
    with Client(server.url, "body") as headset:
        headset.hello("input", "body", model="procedural")
        headset.collect()
        headset.send(GetBody())  # answered with no headset sample yet, to every client
        for client in (headset, viewer):
            client.wait_for(lambda c=client: len(_bodies(c)) == 1, timeout=30)
        first = _bodies(headset)[0]
        assert not first.given and not first.measured and len(first.bone_lengths_m) == 21
        estimated = _served_lengths(headset, first_seq=0)
        assert estimated[3] > KNOWN[3] * 1.1  # the headset's height gives a larger body

        headset.send(SetBody(bone_lengths_m=KNOWN.tolist()))
        headset.wait_for(lambda: len(_bodies(headset)) == 2, timeout=30)
        given = _bodies(headset)[1]
        assert given.given and np.allclose(given.bone_lengths_m, KNOWN, atol=1e-6)
        assert np.allclose(_served_lengths(headset, first_seq=100), KNOWN, atol=2e-3)
        for model in ("hmd", "procedural", "hmd"):
            headset.send(SelectModel(model=model))
        assert np.allclose(_served_lengths(headset, first_seq=200), KNOWN, atol=2e-3)
    with Client(server.url, "body") as headset:  # a reconnect keeps it too
        headset.hello("input", "body")
        headset.collect()
        assert np.allclose(_served_lengths(headset, first_seq=300), KNOWN, atol=2e-3)
        headset.send(SetBody(clear=True))
        headset.wait_for(lambda: len(_bodies(headset)) == 1, timeout=30)
        assert not _bodies(headset)[0].given
        assert _served_lengths(headset, first_seq=400, count=120)[3] > KNOWN[3] * 1.05  # estimated again
    viewer.close()


def test_a_body_out_of_range_is_refused_to_its_sender_and_the_session_goes_on(server):
    viewer = Client(server.url, "body-bad")
    viewer.hello("render", "body-bad")
    with Client(server.url, "body-bad") as headset:
        headset.hello("input", "body-bad", model="procedural")
        giant = KNOWN.copy()
        giant[4] = 1.0  # a 1 m shin: within the wire's range, not a body's
        viewer.send(SetBody(bone_lengths_m=giant.tolist()))
        error = viewer.recv_type("error")
        assert error.code == "out_of_range" and error.ref.type == "set_body" and not error.fatal
        assert "bone 5" in error.message
        headset.send(pack({"type": "set_body", "v": 1}))  # neither lengths nor clear
        assert headset.recv_type("error").code == "invalid_field"
        headset.send(pack({"type": "set_body", "v": 1, "bone_lengths_m": [0.2] * 20}))
        assert headset.recv_type("error").code == "wrong_length"
        headset.send(GetBody())
        assert not headset.recv_type("body").given
    viewer.close()
