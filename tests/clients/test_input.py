"""The input library against a real loopback server: streaming, frame encoding, reconnect and resume."""

from __future__ import annotations

import asyncio
import socket

import numpy as np
import pytest
from loopback import RECORDINGS, running_server
from syntheticusers import User, holding

from egoposevr.clients.input import BodyRefused, HeadsetClient, InputClientError, encode_frame
from egoposevr.model.inputs import decode_rgbd
from egoposevr.protocol import decode, encode
from egoposevr.protocol.examples import example_messages
from egoposevr.recordings.egrec import KIND_CLIENT, read_records

MESSAGES = [decode(r.payload) for r in read_records(RECORDINGS / "walk-0000.egrec") if r.kind == KIND_CLIENT]


async def stream(headset: HeadsetClient, count: int) -> None:
    """Send the first ``count`` hmd samples and the frames between them, as a rig would (decoded images)."""
    sent = 0
    for msg in MESSAGES:
        if msg.type == "rgbd":
            rgb, depth = decode_rgbd(msg.rgb, msg.depth)
            await headset.send_rgbd(
                msg.t_us, rgb, depth, msg.intrinsics, np.reshape(msg.cam_from_head, (4, 4))
            )
        elif msg.type == "hmd":
            await headset.send_hmd(msg.t_us, msg.head, msg.left, msg.right, msg.valid)
            sent += 1
            if sent == count:
                return
        await asyncio.sleep(0.004)


async def first_poses(headset: HeadsetClient, n: int) -> list:
    out = []
    async for pose in headset.poses():
        out.append(pose)
        if len(out) == n:
            return out
    return out


async def poses_until_the_camera(headset: HeadsetClient) -> list:
    """Poses, in arrival order, up to the first a camera frame contributed to, the rig streaming meanwhile (a
    frame counts from the first sample answered after the server has read it, which may take a while)."""
    sender = asyncio.create_task(stream(headset, sum(m.type == "hmd" for m in MESSAGES)))
    out = []
    try:
        async for pose in headset.poses():
            out.append(pose)
            if pose.camera:
                return out
    finally:
        sender.cancel()
    return out


@pytest.mark.asyncio
async def test_a_rig_streams_and_gets_poses_with_the_camera():
    with running_server() as server:
        async with HeadsetClient(server.url, "rig", model="hmd-rgbd") as headset:
            assert headset.welcome.model == "hmd-rgbd"
            poses = await asyncio.wait_for(poses_until_the_camera(headset), 20)
    assert [p.seq for p in poses] == sorted(p.seq for p in poses)
    assert poses[-1].camera is True and poses[-1].model == "hmd-rgbd"
    assert not headset.errors


@pytest.mark.asyncio
async def test_reconnects_and_resumes_the_session_after_a_server_restart():
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    with running_server(port=port) as server:
        headset = HeadsetClient(server.url, "resume", model="hmd", backoff_s=(0.05, 0.2))
        await headset.connect()
        await stream(headset, 10)
        await asyncio.wait_for(first_poses(headset, 5), 10)
    await asyncio.sleep(0.3)  # offline now: what is sent is dropped and counted
    await headset.send_hmd(10**9, MESSAGES[1].head, MESSAGES[1].left, MESSAGES[1].right)
    assert headset.dropped_offline >= 1
    with running_server(port=port):
        await headset.wait_online(10)
        assert headset.reconnects == 1
        await stream(headset, 10)
        poses = await asyncio.wait_for(first_poses(headset, 5), 10)
        assert all(p.model == "hmd" for p in poses)
        await headset.close()


@pytest.mark.asyncio
async def test_a_refused_session_raises():
    with running_server(token="s3cret") as server, pytest.raises(InputClientError, match="auth_failed"):
        await HeadsetClient(server.url, "no-token").connect()


def test_encode_frame_round_trips_and_checks_its_input():
    rgb = np.zeros((48, 64, 3), np.uint8)
    rgb[..., 0] = 200  # red stays red: RGB in, RGB out (OpenCV's BGR stays inside)
    rgb[..., 1] = np.linspace(0, 255, 64, dtype=np.uint8)
    depth = np.full((48, 64), 1234, np.uint16)
    jpeg, png = encode_frame(rgb, depth)
    rgb_back, depth_back = decode_rgbd(jpeg, png, expected_wh=(64, 48))
    assert np.array_equal(depth_back, depth) and np.abs(rgb_back.astype(int) - rgb).mean() < 3
    with pytest.raises(ValueError, match="uint16"):
        encode_frame(rgb, depth.astype(np.float32))
    with pytest.raises(ValueError, match="rgb must be"):
        encode_frame(rgb[..., 0], depth)


@pytest.mark.asyncio
async def test_calibrate_returns_the_servers_verdict_while_the_rig_streams():
    t_us, poses, valid = holding(User(height_scale=1.05), seconds=3.0)

    async def stream_tpose(headset: HeadsetClient) -> None:
        for t, p, v in zip(t_us, poses, valid, strict=True):
            await headset.send_hmd(int(t), p[0], p[1], p[2], v)
            await asyncio.sleep(0.004)

    with running_server() as server:
        async with HeadsetClient(server.url, "rig-calibrates", model="procedural") as headset:
            streaming = asyncio.create_task(stream_tpose(headset))
            result = await headset.calibrate("tpose", seconds=1.0, timeout_s=20)
            await streaming
            assert result.status == "done" and result.head_height_m > 1.6
            cleared = await headset.clear_calibration()
            assert cleared.status == "cleared"


@pytest.mark.asyncio
async def test_a_body_read_at_the_end_of_one_session_is_given_back_at_the_next():
    """PROTOCOL.md §4.2 from the client: get_body after a stream, set_body with it in a new session, whose poses
    then have those bone lengths from the first sample; None gives the estimate back."""
    from egoposevr.model.skeleton import joint_bone_lengths

    t_us, poses, valid = holding(User(height_scale=1.1), seconds=0.5)

    async def stream_lengths(headset: HeadsetClient) -> np.ndarray:
        """Stream the samples -> the bone lengths (21,) of the first pose, m."""
        poses_seen = headset.poses()
        for t, p, v in zip(t_us, poses, valid, strict=True):
            await headset.send_hmd(int(t), p[0], p[1], p[2], v)
        first = await asyncio.wait_for(anext(poses_seen), 20)
        joints = np.asarray(first.joints).reshape(22, 3)
        return joint_bone_lengths(joints)

    with running_server() as server:
        async with HeadsetClient(server.url, "wearer-1", model="procedural") as headset:
            await stream_lengths(headset)
            kept = await headset.get_body()
            assert not kept.given and len(kept.bone_lengths_m) == 21
        async with HeadsetClient(server.url, "wearer-2", model="procedural") as headset:
            smaller = [0.9 * x for x in kept.bone_lengths_m]
            given = await headset.set_body(smaller)
            assert given.given
            assert np.allclose(await stream_lengths(headset), smaller, atol=2e-3)
            assert not (await headset.set_body(None)).given


@pytest.mark.asyncio
async def test_a_body_given_at_construction_is_given_again_after_a_server_restart_and_a_refused_one_raises():
    """The client gives its wearer's body first after every welcome (PROTOCOL.md §4.2): served from the first
    sample, and again on a restarted server; a body the server refuses raises at once and is given no more."""
    from egoposevr.model.runtime.body import bone_lengths_m
    from egoposevr.model.skeleton import joint_bone_lengths

    known = bone_lengths_m(np.full(22, 0.9))
    t_us, poses, valid = holding(User(height_scale=1.1), seconds=0.2)

    async def first_lengths(headset: HeadsetClient) -> np.ndarray:
        """Stream the samples -> the bone lengths (21,) of the first pose that answers one of them, m."""
        seqs = [
            await headset.send_hmd(int(t), p[0], p[1], p[2], v)
            for t, p, v in zip(t_us, poses, valid, strict=True)
        ]
        async for pose in headset.poses():
            if pose.seq in seqs:
                return joint_bone_lengths(np.asarray(pose.joints).reshape(22, 3))
        raise AssertionError("no pose")

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    with running_server(port=port) as server:
        headset = HeadsetClient(server.url, "kept", model="procedural", backoff_s=(0.05, 0.2), body=known)
        await headset.connect()
        assert np.allclose(await asyncio.wait_for(first_lengths(headset), 20), known, atol=2e-3)
    # A new server knows nothing of the session: the client gives the body again.
    with running_server(port=port):
        async with asyncio.timeout(10):
            while headset.reconnects == 0 or not headset.online:
                await asyncio.sleep(0.02)
        assert np.allclose(await asyncio.wait_for(first_lengths(headset), 20), known, atol=2e-3)
        giant = known.copy()
        giant[4] = 1.0  # a 1 m shin: within the wire's range, not a body's
        with pytest.raises(BodyRefused, match="bone 5"):
            await headset.set_body(giant, timeout_s=5)
        assert headset.given_body is None  # not given again at a reconnect
        session_body = await headset.get_body()  # the session's body stayed as it was
        assert session_body.given and np.allclose(session_body.bone_lengths_m, known, atol=1e-6)
        with pytest.raises(ValueError, match="21 positive finite"):
            await headset.set_body([0.2] * 20)
        await headset.close()
    with pytest.raises(ValueError, match="21 positive finite"):
        HeadsetClient("ws://127.0.0.1:1/ws", "x", body=[0.3] * 20 + [float("nan")])


async def _fake_server(replies: list[bytes]):
    """A server on loopback that answers a hello with ``replies`` (bytes as they are), then keeps the connection."""
    from websockets.asyncio.server import serve

    async def handler(ws):
        await ws.recv()  # the hello
        for reply in replies:
            await ws.send(reply)
        await ws.wait_closed()

    return await serve(handler, "127.0.0.1", 0)


@pytest.mark.asyncio
async def test_an_unreadable_server_message_is_skipped_and_counted_and_the_stream_goes_on():
    examples = example_messages()
    welcome, pose = encode(examples["welcome"]), encode(examples["pose"])
    damaged = [b"\x93\x01", welcome[:-3], encode(examples["pose"])[:40]]  # not a map, cut short twice
    async with await _fake_server([welcome, *damaged, pose]) as server:
        port = server.sockets[0].getsockname()[1]
        async with HeadsetClient(f"ws://127.0.0.1:{port}/ws", "bad-bytes") as headset:
            (received,) = await asyncio.wait_for(first_poses(headset, 1), 10)
            assert received == examples["pose"]
            assert (
                headset.counts == {"unreadable": len(damaged)} and headset.reconnects == 0 and headset.online
            )


@pytest.mark.asyncio
async def test_an_unreadable_answer_to_hello_is_a_clear_error():
    async with await _fake_server([b"\xc1"]) as server:  # 0xc1: never used by msgpack
        port = server.sockets[0].getsockname()[1]
        headset = HeadsetClient(f"ws://127.0.0.1:{port}/ws", "bad-hello", reconnect=False)
        with pytest.raises(InputClientError, match="answer to hello is unreadable"):
            await headset.connect()
