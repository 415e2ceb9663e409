"""The server over a real loopback socket: sessions, broadcast, model switches, reconnects, HTTP, recording."""

from __future__ import annotations

import shutil
import statistics
import threading
import time

import pytest
from loopback import Client, raw_client, recorded_messages, replay, replay_until, running_server
from websockets.sync.client import connect

from egoposevr.clients.bench import STAGES
from egoposevr.model.weights import WEIGHTS_DIR
from egoposevr.protocol import ListModels, Ping, SelectModel, decode
from egoposevr.recordings.egrec import KIND_CLIENT, read_header, read_records

WALK_5S = recorded_messages("walk-0000")  # the whole walk: 450 hmd samples + 150 frames
WALK = WALK_5S[:400]  # ~3.3 s: 300 hmd samples at 90 Hz + 100 frames
SQUAT = recorded_messages("squat-0001", limit=400)


def test_http_endpoints(server):
    assert server.get("/healthz") == (200, "ok\n")
    assert server.get("/readyz") == (200, "ready\n")
    status, body = server.get("/metrics")
    assert status == 200 and "egoposevr_sessions" in body and "egoposevr_stage_seconds" in body
    assert server.get("/nope")[0] == 404


def test_headsets_and_viewers_each_get_their_sessions_poses(server):
    clients = {}
    for session in ("walker", "squatter"):
        headset = Client(server.url, session)
        headset.hello("input", session, model="hmd")
        viewers = [Client(server.url, session) for _ in range(2)]
        for v in viewers:
            v.hello("render", session)
        clients[session] = (headset.collect(), [v.collect() for v in viewers])
    sent = {}
    threads = [
        threading.Thread(target=lambda s=s, m=m: sent.__setitem__(s, replay(clients[s][0], m)))
        for s, m in (("walker", WALK), ("squatter", SQUAT))
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for session, (headset, viewers) in clients.items():
        headset.wait_for(lambda h=headset, s=session: _accounted(h, sent[s]))
        seqs = {p.seq for p in headset.poses()}
        # Its own samples only, and the newest always answered (§newest-wins). How many older ones a busy
        # machine skips is a speed, which the bench measures, not this test (147 of 300 answered once, on a loaded machine).
        assert seqs <= set(sent[session]) and max(sent[session]) in seqs
        for viewer in viewers:
            count = len(seqs)
            viewer.wait_for(lambda v=viewer, n=count: len(v.poses()) >= n)
            assert {p.seq for p in viewer.poses()} == seqs  # every pose of its session, no other session's
            assert all(p.model == "hmd" for p in viewer.poses())
        for c in (headset, *viewers):
            c.close()


def _accounted(headset: Client, sent: dict[int, float]) -> bool:
    """Every sample sent got a pose or was reported skipped."""
    poses = headset.poses()
    return len(poses) + sum(p.skipped or 0 for p in poses) == len(sent)


def test_pose_carries_stage_timings_and_camera_flag(server):
    with Client(server.url, "timed") as headset:
        headset.hello("input", "timed")  # the default model reads the camera
        headset.collect()
        assert replay_until(headset, WALK, lambda: any(p.camera for p in headset.poses()), timeout=20)
    pose = next(p for p in headset.poses() if p.camera)
    assert pose.model == "egoposevr"
    assert set(STAGES) - {"image"} <= set(pose.timing_us)  # image: only after a new frame
    assert pose.timing_us["total"] >= pose.timing_us["fusion"]


def test_a_stalled_viewer_does_not_hold_back_the_headset_or_other_viewers():
    with running_server(send_buffer_bytes=8192) as server:
        _stalled_viewer_case(server)


def _stalled_viewer_case(server):
    session = "stalled"
    headset = Client(server.url, session)
    headset.hello("input", session, model="hmd")
    healthy = Client(server.url, session)
    healthy.hello("render", session)
    headset.collect()
    healthy.collect()
    baseline = replay(headset, WALK_5S[:120])  # no stalled viewer yet
    baseline_ms = _median_latency_ms(headset, baseline)
    baseline_answered = len(headset.poses()) / len(baseline)
    stalled = raw_client(server.url, session, receive_buffer=4096)  # never reads
    try:
        dropped_before = server.metric("egoposevr_dropped_poses_total", role="render")
        # How many samples a shared machine answers in real time, and how fast, is a speed: a stretch that a
        # pause of the machine's own spoils (CI once answered 80 of 210, another run 174) is tried again on the
        # walk's next stretch. A server that waited on the stalled viewer fails every stretch, since the viewer
        # stays stalled throughout: it would stop answering once the viewer's 8 KiB buffers filled, a few poses
        # in, or, if it sent to the viewer first, add its wait to each answer.
        for stretch in (WALK_5S[120:280], WALK_5S[280:440], WALK_5S[440:]):
            headset.received.clear()
            sent = replay(headset, stretch)
            headset.wait_for(lambda s=sent: _accounted(headset, s))
            answered = headset.poses()
            share = len(answered) / len(sent)
            median_ms = _median_latency_ms(headset, sent)
            if share >= 0.5 * baseline_answered and median_ms < 2 * baseline_ms + 3:
                break
        assert share >= 0.5 * baseline_answered, (len(answered), len(sent), baseline_answered)
        assert median_ms < 2 * baseline_ms + 3, (median_ms, baseline_ms)
        healthy.wait_for(lambda: len([p for p in healthy.poses() if p.seq in sent]) >= len(answered))
        assert server.metric("egoposevr_dropped_poses_total", role="render") > dropped_before
    finally:  # a failure here must not leave sockets open for the next test's warnings to trip on
        for c in (headset, healthy):
            c.close()
        stalled.close()


def _median_latency_ms(headset: Client, sent: dict[int, float]) -> float:
    headset.wait_for(lambda: _accounted(headset, sent))
    return 1e3 * statistics.median(
        t - sent[m.seq] for t, m in headset.received if m.type == "pose" and m.seq in sent
    )


def test_model_switch_mid_session_resets_cleanly(server):
    with Client(server.url, "switch") as headset:
        headset.hello("input", "switch", model="hmd")
        viewer = Client(server.url, "switch")
        viewer.hello("render", "switch")
        headset.collect()
        viewer.collect()
        replay(headset, WALK[:100])
        headset.send(SelectModel(model="hmd-rgbd"))
        headset.wait_for(
            lambda: any(m.type == "models" and m.active == "hmd-rgbd" for _, m in headset.received)
        )
        viewer.wait_for(
            lambda: any(m.type == "models" and m.active == "hmd-rgbd" for _, m in viewer.received)
        )
        assert replay_until(
            headset, WALK[100:], lambda: any(p.model == "hmd-rgbd" and p.camera for p in headset.poses()), 20
        )
        models = [p.model for p in headset.poses()]
        switched = models.index("hmd-rgbd")
        assert set(models[:switched]) == {"hmd"} and set(models[switched:]) == {"hmd-rgbd"}
        viewer.close()


def test_the_procedural_baseline_is_served_like_any_model(server):
    with Client(server.url, "baseline") as headset:
        headset.hello("input", "baseline", model="procedural")
        headset.collect()
        replay(headset, WALK[:60])
        headset.wait_for(lambda: len(headset.poses()) >= 40)
        poses = headset.poses()
        assert {p.model for p in poses} == {"procedural"} and all(p.camera is None for p in poses)
        assert min(min(p.joints[31], p.joints[34]) for p in poses) > 0.0  # both feet above the floor


def test_headset_reconnects_and_viewers_keep_their_subscription(server):
    viewer = Client(server.url, "again")
    viewer.hello("render", "again")
    viewer.collect()
    for attempt in range(2):
        with Client(server.url, "again") as headset:
            assert headset.hello("input", "again", model="hmd").type == "welcome"
            sent = replay(headset, WALK[attempt * 100 : attempt * 100 + 60])
            headset.collect()
            viewer.wait_for(lambda s=sent: set(s) & {p.seq for p in viewer.poses()} != set())
        # a second input while the first is still connected is refused (tested in test_server_limits)
    seqs = {p.seq for p in viewer.poses()}
    assert min(seqs) < 100 <= max(seqs)  # poses from both connections
    viewer.close()


def test_select_and_list_models(server):
    with Client(server.url, "lister") as headset:
        headset.hello("input", "lister")
        headset.send(ListModels())
        models = headset.recv_type("models")
        assert models.active == "egoposevr"
        assert [m.name for m in models.models][:8] == [
            "procedural", "hmd", "hmd-rgb1", "hmd-rgb", "hmd-rgbd", "egoposevr", "hmd-rgbd-concat",
            "egoposevr-lite",
        ]  # fmt: skip
        headset.send(Ping(nonce=7, t_us=5))
        pong = headset.recv_type("pong")
        assert (pong.nonce, pong.t_us) == (7, 5) and pong.server_t_us > 0


def test_a_model_dropped_into_the_models_dir_appears_and_a_broken_one_is_reported(tmp_path):
    with running_server(models_dir=tmp_path) as server, Client(server.url, "hot") as headset:
        headset.hello("input", "hot")
        shutil.copy(WEIGHTS_DIR / "hmd.onnx", tmp_path / "mine.onnx")
        (tmp_path / "broken.onnx").write_bytes(b"not an onnx graph")
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            headset.send(ListModels())
            names = [m.name for m in headset.recv_type("models").models]
            if "mine" in names and server.metric("egoposevr_model_failures") == 1:
                break
            time.sleep(0.1)
        assert "mine" in names and "broken" not in names
        assert server.metric("egoposevr_model_failures") == 1
        headset.send(SelectModel(model="mine"))
        assert headset.recv_type("models").active == "mine"
        headset.collect()
        replay(headset, WALK[:30])
        headset.wait_for(lambda: any(p.model == "mine" for p in headset.poses()))


def test_recording_writes_a_replayable_egrec(tmp_path):
    with running_server(record=tmp_path) as server, Client(server.url, "rec") as headset:
        headset.hello("input", "rec", model="hmd")
        replay(headset, WALK[:40])
        headset.collect()
        time.sleep(0.2)
    (path,) = tmp_path.glob("rec-*.egrec")
    assert read_header(path)["session"] == "rec"
    kinds = [decode(r.payload).type for r in read_records(path) if r.kind == KIND_CLIENT]
    assert kinds[0] == "hello" and kinds[1:] == [k for _, k, _ in WALK[:40]]


def test_metrics_count_what_happened(server):
    before_hmd = server.metric("egoposevr_messages_total", type="hmd")
    before_err = server.metric("egoposevr_errors_total", code="unknown_model")
    with Client(server.url, "counted") as headset:
        headset.hello("input", "counted", model="hmd")
        headset.send(SelectModel(model="nope"))
        assert headset.recv_type("error").code == "unknown_model"
        headset.collect()
        sent = replay(headset, WALK[:50])
        headset.wait_for(lambda: _accounted(headset, sent))
        assert server.metric("egoposevr_sessions") >= 1
    assert server.metric("egoposevr_messages_total", type="hmd") - before_hmd == len(sent)
    assert server.metric("egoposevr_errors_total", code="unknown_model") - before_err == 1
    assert server.metric("egoposevr_stage_seconds_count", stage="fusion") >= len(headset.poses())


def test_origin_allow_list_refuses_other_browsers():
    with running_server(origins=("http://good.example",)) as server:
        with Client(server.url, "o", origin="http://good.example") as ok:
            assert ok.hello("render", "o").type == "welcome"
        with Client(server.url, "o") as no_origin:  # headsets and scripts send no Origin
            assert no_origin.hello("render", "o").type == "welcome"
        with pytest.raises(Exception, match="403"):
            connect(server.url, origin="http://evil.example", open_timeout=5)
