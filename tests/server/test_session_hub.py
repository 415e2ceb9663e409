"""The socket-free core: Session (newest wins, history, frames, model switches) and Hub (handshake, roles,
routing, broadcast, shutdown), driven directly without a network."""

from __future__ import annotations

import time

import numpy as np
import pytest
from loopback import recorded_messages, server_config

from egoposevr.model.runtime.frames import LOW_HEAD_M
from egoposevr.model.runtime.pipeline import Pipeline
from egoposevr.protocol import GetBody, Hello, Ping, SelectModel, decode, encode
from egoposevr.protocol.examples import example_messages
from egoposevr.server.broadcast import publish
from egoposevr.server.hub import Hub
from egoposevr.server.metrics import Metrics
from egoposevr.server.registry import ModelRegistry
from egoposevr.server.session import (
    MAX_ENCODED_FRAMES,
    MAX_PENDING_SAMPLES,
    Received,
    Session,
    TokenBucket,
    encode_received_frame,
)


@pytest.fixture(scope="module")
def registry():
    registry = ModelRegistry()
    registry.rescan()
    return registry


@pytest.fixture(scope="module")
def samples():
    return [decode(data) for _, kind, data in recorded_messages("walk-0000", limit=200) if kind == "hmd"]


def received(msg) -> Received:
    return Received(msg, time.perf_counter_ns(), 1000)


def new_session(
    registry, model="hmd", frame_lane=False, first_frame_wait_ns=0, low_head_wait_ns=0
) -> Session:
    """A session whose samples, unless a test asks otherwise, never wait for a first frame or a visual window."""
    return Session(
        "s", model, registry.get(model), TokenBucket(1000, 100), frame_lane=frame_lane,
        first_frame_wait_ns=first_frame_wait_ns, low_head_wait_ns=low_head_wait_ns,
    )  # fmt: skip


def with_head_at(sample, head_y_m: float):
    """``sample`` with its headset ``head_y_m`` above the floor."""
    head = list(sample.head)
    head[1] = head_y_m
    return sample.model_copy(update={"head": head})


def camera_frame(sample, seq: int):
    """The example rgbd message, captured with ``sample``."""
    return example_messages()["rgbd"].model_copy(update={"seq": seq, "t_us": sample.t_us})


def test_the_newest_sample_wins_and_older_ones_feed_the_history(registry, samples):
    session = new_session(registry)
    for msg in samples[:5]:
        session.offer_hmd(received(msg))
    job = session.take_job()
    assert len(job.samples) == 5 and job.skipped == 4
    result = session.run(job)
    pose = decode(result.pose)
    assert (pose.seq, pose.skipped, pose.model) == (samples[4].seq, 4, "hmd")
    reference = Pipeline(registry.get("hmd"))
    for msg in samples[:5]:
        reference.push_hmd(msg.t_us, np.asarray(msg.poses()), np.asarray(msg.valid))
    assert np.allclose(session._pipeline.hmd_window, reference.hmd_window)  # no sample lost from the window
    session.offer_hmd(received(samples[5]))
    assert decode(session.run(session.take_job()).pose).skipped == 0


def test_pending_samples_are_bounded(registry, samples):
    session = new_session(registry)
    for msg in samples[: MAX_PENDING_SAMPLES + 3]:
        session.offer_hmd(received(msg))
    assert len(session.pending) == MAX_PENDING_SAMPLES and session.dropped_history == 3
    assert session.take_job().skipped == MAX_PENDING_SAMPLES + 2


def test_only_the_newest_frame_is_kept_and_a_bad_one_is_reported_with_its_seq(registry, samples):
    session = new_session(registry, "hmd-rgbd")
    rgbd = example_messages()["rgbd"]
    assert session.offer_rgbd(received(rgbd))
    bad = rgbd.model_copy(update={"seq": 9, "width": 8})
    assert not session.offer_rgbd(received(bad))  # replaced the unused one
    assert session.replaced_frames == 1
    session.offer_hmd(received(samples[0]))
    result = session.run(session.take_job())
    assert [(e.code, e.seq) for e in result.errors] == [("image_decode", 9)]
    assert decode(result.pose).camera is False  # the sample was still answered, from the headset alone


def test_a_model_switch_starts_a_fresh_pipeline(registry, samples):
    session = new_session(registry)
    session.offer_hmd(received(samples[0]))
    session.run(session.take_job())
    session.select("hmd-rgbd", registry.get("hmd-rgbd"))
    assert session.model_name == "hmd-rgbd"
    session.offer_hmd(received(samples[1]))
    job = session.take_job()
    assert job.model[0] == "hmd-rgbd"
    result = session.run(job)
    assert decode(result.pose).model == result.model == "hmd-rgbd"
    assert session._pipeline.model is registry.get("hmd-rgbd")


def test_frame_lane_keeps_frames_off_the_headset_job_and_feeds_the_next_one(registry, samples):
    session = new_session(registry, "hmd-rgbd", frame_lane=True)
    session.offer_hmd(received(samples[0]))
    session.offer_rgbd(received(camera_frame(samples[0], 1)))
    job = session.take_job()
    assert job.frame is None and job.encoded == ()  # the headset is answered first, from the cache
    assert decode(session.run(job).pose).camera is False
    frame, model = session.take_frame()
    assert session.take_frame() is None  # one frame per session in the lane
    result = encode_received_frame(frame, model)
    assert result.errors == [] and result.encoded is not None
    session.offer_encoded(result, model)
    assert session.take_job() is None  # an encoded frame waits for a sample
    session.offer_hmd(received(samples[1]))
    job = session.take_job()
    assert len(job.encoded) == 1 and job.image_us == result.image_us
    run = session.run(job)
    pose = decode(run.pose)
    assert pose.camera is True and "image" in pose.timing_us


def test_a_streams_first_samples_wait_for_its_first_frame_then_the_newest_is_answered_with_it(
    registry, samples
):
    """PROTOCOL.md §first-frame: nothing is answered before the stream's first frame is encoded; then the newest
    sample is, with the camera, the older ones its history; later samples never wait again."""
    session = new_session(registry, "egoposevr", frame_lane=True, first_frame_wait_ns=10**12)
    for msg in samples[:3]:
        session.offer_hmd(received(msg))
    session.offer_rgbd(received(camera_frame(samples[0], 1)))
    assert (
        not session.has_work and session.take_job() is None and session.holding_ns(time.perf_counter_ns()) > 0
    )
    frame, model = session.take_frame()
    assert not session.has_work  # still in the lane
    session.offer_encoded(encode_received_frame(frame, model), model)
    job = session.take_job()
    assert len(job.samples) == 3 and len(job.encoded) == 1
    pose = decode(session.run(job).pose)
    assert (pose.seq, pose.skipped, pose.camera) == (samples[2].seq, 2, True)
    session.offer_hmd(received(samples[3]))  # no newer frame: answered at once, the cached frame still young
    assert session.has_work and decode(session.run(session.take_job()).pose).seq == samples[3].seq


def test_the_first_frame_wait_runs_out_and_is_armed_again_by_a_new_stream_or_model(registry, samples):
    session = new_session(registry, "egoposevr", first_frame_wait_ns=20_000_000)  # 20 ms
    session.offer_hmd(received(samples[0]))
    session.offer_hmd(received(samples[1]))
    assert not session.has_work
    time.sleep(0.03)
    assert session.has_work and session.holding_ns(time.perf_counter_ns()) is None
    pose = decode(session.run(session.take_job()).pose)
    assert (pose.seq, pose.skipped, pose.camera) == (samples[1].seq, 1, False)
    session.offer_hmd(received(samples[2]))
    assert session.has_work  # the stream has answered: no wait
    session.run(session.take_job())
    session.restart_stream()  # a new input client
    session.offer_hmd(received(samples[3]))
    assert not session.has_work
    session.select("hmd", registry.get("hmd"))  # a model that reads no camera never waits
    assert session.has_work
    session.run(session.take_job())
    session.select("egoposevr", registry.get("egoposevr"))
    session.offer_hmd(received(samples[4]))
    assert not session.has_work


def test_a_low_heads_first_answer_waits_for_the_nets_visual_window(registry, samples):
    """PROTOCOL.md §first-frame: a stream that begins with the head low (seated) is first answered once the net's
    visual window of frames is in; a standing one once its first frame is."""
    visual_window = registry.get("egoposevr").info.config.visual_window
    seated = [with_head_at(m, LOW_HEAD_M - 0.25) for m in samples[: visual_window + 2]]
    session = new_session(
        registry, "egoposevr", frame_lane=True, first_frame_wait_ns=10**12, low_head_wait_ns=10**12
    )
    for i, msg in enumerate(seated):
        session.offer_hmd(received(msg))
        if 3 <= i < 3 + visual_window - 1:  # the camera's frames begin later than the headset's samples
            session.offer_rgbd(received(camera_frame(msg, i)))
            frame, model = session.take_frame()
            session.offer_encoded(encode_received_frame(frame, model), model)
        assert not session.has_work and session.holding_ns(time.perf_counter_ns()) > 0
    session.offer_rgbd(received(camera_frame(seated[-1], 99)))  # the window's last frame
    frame, model = session.take_frame()
    session.offer_encoded(encode_received_frame(frame, model), model)
    job = session.take_job()
    assert (len(job.samples), len(job.encoded)) == (len(seated), visual_window)
    pose = decode(session.run(job).pose)
    assert (pose.seq, pose.skipped, pose.camera) == (seated[-1].seq, len(seated) - 1, True)

    session.restart_stream()  # a standing stream: its first frame is enough
    session.offer_hmd(received(with_head_at(samples[0], LOW_HEAD_M + 0.25)))
    session.offer_rgbd(received(camera_frame(samples[0], 100)))
    frame, model = session.take_frame()
    session.offer_encoded(encode_received_frame(frame, model), model)
    assert session.has_work


def test_a_low_heads_wait_runs_out_and_needs_the_frame_lane(registry, samples):
    low = [with_head_at(m, LOW_HEAD_M - 0.25) for m in samples[:3]]
    session = new_session(
        registry, "egoposevr", frame_lane=True, first_frame_wait_ns=1, low_head_wait_ns=20_000_000
    )
    session.offer_hmd(received(low[0]))
    assert not session.has_work
    time.sleep(0.03)  # the low head's wait (20 ms) runs out; a standing stream's (1 ns) would have at once
    assert session.has_work and len(session.take_job().samples) == 1
    session.offer_hmd(received(low[1]))
    assert session.has_work  # the stream has answered
    session.select("egoposevr", registry.get("egoposevr"))  # a switch with a sample waiting: it waits again
    assert not session.has_work
    time.sleep(0.03)
    assert session.has_work

    session = new_session(
        registry, "egoposevr", first_frame_wait_ns=10**12, low_head_wait_ns=10**12
    )  # no lane
    session.offer_hmd(received(low[2]))
    session.offer_rgbd(received(camera_frame(low[2], 1)))  # rides on the job: the only frame a job can have
    assert session.has_work


def test_a_request_while_the_samples_wait_is_answered_and_leaves_them_waiting(registry, samples):
    session = new_session(registry, "egoposevr", first_frame_wait_ns=10**12)
    session.offer_hmd(received(samples[0]))
    session.request_body(GetBody())
    job = session.take_job()
    assert job.samples == () and len(job.body) == 1
    assert [n.type for n in session.run(job).notices] == ["body"]
    assert len(session.pending) == 1 and not session.has_work
    session.offer_rgbd(received(camera_frame(samples[0], 1)))  # without the lane: the frame rides on the job
    job = session.take_job()
    assert len(job.samples) == 1 and job.frame is not None
    assert decode(session.run(job).pose).camera is True


def test_frame_lane_reports_bad_frames_and_drops_results_of_a_replaced_model(registry, samples):
    session = new_session(registry, "hmd-rgbd", frame_lane=True)
    session.offer_rgbd(received(camera_frame(samples[0], 9).model_copy(update={"width": 8})))
    frame, model = session.take_frame()
    result = encode_received_frame(frame, model)
    assert [(e.code, e.seq) for e in result.errors] == [("image_decode", 9)]
    session.offer_encoded(result, model)
    session.offer_rgbd(received(camera_frame(samples[0], 10)))
    frame, model = session.take_frame()
    session.select("egoposevr", registry.get("egoposevr"))  # switched while the frame was in the lane
    session.offer_encoded(encode_received_frame(frame, model), model)
    session.offer_hmd(received(samples[1]))
    assert session.take_job().encoded == ()


def test_frame_lane_results_without_a_headset_are_bounded_and_counted(registry, samples):
    session = new_session(registry, "hmd-rgbd", frame_lane=True)
    kept = []
    for k in range(MAX_ENCODED_FRAMES + 2):  # a camera streaming while the headset is silent
        session.offer_rgbd(
            received(camera_frame(samples[0], k).model_copy(update={"t_us": samples[0].t_us + k}))
        )
        frame, model = session.take_frame()
        kept.append(session.offer_encoded(encode_received_frame(frame, model), model))
    assert kept.count(False) == 2 and session.replaced_frames == 2
    session.offer_hmd(received(samples[1]))
    assert len(session.take_job().encoded) == MAX_ENCODED_FRAMES


def test_frame_lane_drops_frames_for_a_model_without_a_camera(registry, samples):
    session = new_session(registry, "hmd", frame_lane=True)
    session.offer_rgbd(received(camera_frame(samples[0], 1)))
    assert session.take_frame() is None and session.frame is None


class RecordingScheduler:
    """What the hub hands to the scheduler, recorded."""

    def __init__(self) -> None:
        self.woken, self.forgotten = [], []

    def wake(self, session) -> None:
        self.woken.append(session)

    def forget(self, session) -> None:
        self.forgotten.append(session)


def hub_with(registry, **config) -> tuple[Hub, list, list]:
    scheduler = RecordingScheduler()
    hub = Hub(server_config(**config), registry, Metrics(), scheduler)
    hub.ready = True
    return hub, scheduler.woken, scheduler.forgotten


def sent(client) -> list:
    out = []
    while (data := client.outbox.take()) is not None:
        out.append(decode(data))
    return out


def test_hello_then_routing(registry, samples):
    hub, woken, ended = hub_with(registry)
    viewer = hub.connect("v")
    hub.receive(viewer, encode(Hello(role="render", session="s")), time.perf_counter_ns())
    replies = sent(viewer)
    assert [m.type for m in replies] == ["welcome", "models", "session"]
    assert (replies[2].event, replies[2].input, replies[2].renders) == ("joined", False, 1)
    headset = hub.connect("h")
    hub.receive(headset, encode(Hello(role="input", session="s", model="nope")), time.perf_counter_ns())
    replies = sent(headset)
    assert [m.type for m in replies] == ["welcome", "error", "models"]
    assert replies[1].code == "unknown_model" and replies[2].active == "egoposevr"
    assert replies[1].ref.type == "hello"
    [status] = sent(viewer)
    assert (status.type, status.event, status.input) == ("session", "input_joined", True)
    hub.receive(headset, encode(samples[0]), time.perf_counter_ns())
    assert woken == [hub.sessions["s"]]
    hub.receive(viewer, encode(samples[1]), time.perf_counter_ns())
    error = sent(viewer)[0]
    assert error.code == "wrong_role" and (error.ref.type, error.ref.seq, error.seq) == ("hmd", 1, 1)
    hub.disconnect(headset)
    [status] = sent(viewer)
    assert (status.event, status.input) == ("input_left", False)
    assert "s" in hub.sessions and not ended
    hub.disconnect(viewer)
    assert "s" not in hub.sessions and len(ended) == 1


def test_publish_reaches_every_client_and_a_full_queue_drops_the_oldest(registry, samples):
    hub, _, _ = hub_with(registry, pose_queue=2)
    clients = [hub.connect(str(i)) for i in range(3)]
    for client, role in zip(clients, ("input", "render", "render"), strict=True):
        hub.receive(client, encode(Hello(role=role, session="s", model="hmd")), time.perf_counter_ns())
        sent(client)
    session = hub.sessions["s"]
    for msg in samples[:3]:
        hub.receive(clients[0], encode(msg), time.perf_counter_ns())
        publish(session, session.run(session.take_job()), hub.metrics)
    for client in clients:
        assert [m.seq for m in sent(client)] == [
            s.seq for s in samples[1:3]
        ]  # queue of 2: the oldest dropped
        assert client.outbox.dropped_poses == 1


def test_handshake_rules_and_shutdown(registry):
    hub, _, _ = hub_with(registry)
    early = hub.connect("e")
    hub.receive(early, encode(Ping()), time.perf_counter_ns())
    assert sent(early)[0].code == "handshake_required" and early.outbox.close_code == 1008
    hub.ready = False
    loading = hub.connect("l")
    hub.receive(loading, encode(Hello(role="input", session="x")), time.perf_counter_ns())
    assert sent(loading)[0].code == "server_full" and loading.outbox.close_code == 1013
    hub.ready = True
    member = hub.connect("m")
    hub.receive(member, encode(Hello(role="input", session="x")), time.perf_counter_ns())
    hub.receive(member, encode(SelectModel(model="hmd")), time.perf_counter_ns())
    assert [m.type for m in sent(member)] == ["welcome", "models", "models"]
    hub.shutdown()
    error = sent(member)[0]
    assert (error.code, error.fatal, member.outbox.close_code) == ("shutting_down", True, 1001)
    late = hub.connect("late")
    hub.receive(late, encode(Hello(role="input", session="y")), time.perf_counter_ns())
    assert sent(late)[0].code == "shutting_down"
