"""The scheduler: cross-session batching, its window, fairness and isolation, with a fake pipeline (no
sockets, no ONNX); and a batched answer against the unbatched one with the real bundled models."""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
from loopback import recorded_messages

from egoposevr.model.runtime.pipeline import PendingPose, PoseResult
from egoposevr.protocol import decode
from egoposevr.protocol.examples import example_messages
from egoposevr.server.broadcast import Outbox
from egoposevr.server.metrics import Metrics
from egoposevr.server.registry import ModelRegistry
from egoposevr.server.scheduler import Scheduler, run_batch
from egoposevr.server.session import Received, Session, TokenBucket

HMD = example_messages()["hmd"]


class FakeNet:
    """A fusion net that records the batch size of every call and answers each row with its own input."""

    def __init__(self, delay_s: float = 0.0) -> None:
        self.batches: list[int] = []
        self.delay_s = delay_s
        self.lock = threading.Lock()

    def run(self, _outputs, feed):
        with self.lock:
            self.batches.append(len(feed["hmd"]))
        time.sleep(self.delay_s)
        return [np.repeat(feed["hmd"][:, :, :1], 6, axis=2).repeat(22, axis=1)]


class FakeModel:
    visual = None

    def __init__(self, net: FakeNet, batchable: bool = True) -> None:
        self.fusion, self.batchable = net, batchable


class FakePipeline:
    """Answers sample t with joints all equal to t (seconds), through the net."""

    calibration = None

    def __init__(self, model: FakeModel) -> None:
        self.model = model

    def begin_hmd(self, t_us, poses, valid) -> PendingPose:
        hmd = np.full((1, 1, 1), t_us * 1e-6, dtype=np.float32)
        return PendingPose(int(t_us), valid, np.zeros((3, 3)), np.eye(3), None, {}, self.model, {"hmd": hmd})

    def finish_hmd(self, pending: PendingPose, sixd: np.ndarray) -> PoseResult:
        joints = np.full((22, 3), float(sixd[0, 0]))
        zeros = np.zeros(3)
        return PoseResult(pending.t_us, "fake", zeros, np.zeros(63), zeros, joints, np.zeros((22, 3, 3)), None,
                          dict(pending.timing_us))  # fmt: skip

    def observe_hmd(self, *args) -> None:
        pass


class FakeClient:
    def __init__(self, capacity: int = 64) -> None:
        self.outbox = Outbox(capacity)
        self.role = "input"

    def poses(self) -> list:
        out = []
        while (data := self.outbox.take()) is not None:
            out.append(decode(data))
        return [m for m in out if m.type == "pose"]


def fake_session(name: str, model: FakeModel) -> Session:
    session = Session(
        name, "fake", model, TokenBucket(1e6, 1000), frame_lane=True, make_pipeline=FakePipeline
    )
    session.input = FakeClient()
    return session


def offer(session: Session, seq: int, t_us: int) -> None:
    session.offer_hmd(Received(HMD.model_copy(update={"seq": seq, "t_us": t_us}), time.perf_counter_ns(), 0))


@contextlib.contextmanager
def running_scheduler(**kwargs) -> Iterator[Scheduler]:
    scheduler = Scheduler(Metrics(), **kwargs)
    try:
        yield scheduler
    finally:
        scheduler.close()


async def until(predicate, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        await asyncio.sleep(0.001)


@pytest.mark.asyncio
async def test_ready_sessions_on_one_model_run_as_one_net_call_and_each_gets_its_own_answer():
    net = FakeNet()
    model = FakeModel(net)
    sessions = [fake_session(f"s{i}", model) for i in range(5)]
    with running_scheduler(workers=2, batch_window_s=0.05) as scheduler:
        for i, session in enumerate(sessions):
            offer(session, 1, 1_000_000 * (i + 1))
            scheduler.wake(session)
        received = {s.id: [] for s in sessions}
        await until(lambda: all(received[s.id] or received[s.id].extend(s.input.poses()) for s in sessions))
    assert net.batches == [5]
    for i, session in enumerate(sessions):
        [pose] = received[session.id]
        assert pose.joints[0] == pytest.approx(i + 1)  # its own sample, not a neighbour's


@pytest.mark.asyncio
async def test_window_zero_runs_every_job_alone():
    net = FakeNet()
    model = FakeModel(net)
    sessions = [fake_session(f"s{i}", model) for i in range(4)]
    with running_scheduler(workers=1, batch_window_s=0.0) as scheduler:
        for session in sessions:
            offer(session, 1, 1000)
            scheduler.wake(session)
        await until(lambda: len(net.batches) == 4)
    assert net.batches == [1, 1, 1, 1]


@pytest.mark.asyncio
async def test_graphs_without_a_batch_axis_and_other_models_are_not_mixed():
    fixed_net, shared_net = FakeNet(), FakeNet()
    fixed, shared = FakeModel(fixed_net, batchable=False), FakeModel(shared_net)
    sessions = [fake_session("f0", fixed), fake_session("f1", fixed), fake_session("s0", shared)]
    sessions.append(fake_session("s1", shared))
    with running_scheduler(workers=2, batch_window_s=0.05) as scheduler:
        for session in sessions:
            offer(session, 1, 1000)
            scheduler.wake(session)
        await until(lambda: len(fixed_net.batches) == 2 and len(shared_net.batches) == 1)
    assert fixed_net.batches == [1, 1] and shared_net.batches == [2]


@pytest.mark.asyncio
async def test_a_lone_ready_job_waits_at_most_the_window_for_idle_sessions():
    net = FakeNet()
    model = FakeModel(net)
    streaming = [fake_session(f"s{i}", model) for i in range(3)]
    with running_scheduler(workers=2, batch_window_s=0.03) as scheduler:
        for session in streaming[1:]:  # streaming but idle: they could join, so the first one waits
            scheduler.wake(session)
        offer(streaming[0], 1, 1000)
        started = time.perf_counter()
        scheduler.wake(streaming[0])
        await until(lambda: bool(net.batches))
        waited_s = time.perf_counter() - started
    assert net.batches == [1]
    assert 0.02 <= waited_s < 0.03 + 0.05  # the window, and not much more (a noisy machine's loop)


@pytest.mark.asyncio
async def test_a_session_that_sends_fast_does_not_starve_the_others():
    """Oldest ready first and one job in flight per session: a flooding session gets one answer per round,
    newest wins, and every other session is answered in between."""
    net = FakeNet(delay_s=0.002)
    model = FakeModel(net)
    flood, calm = fake_session("flood", model), fake_session("calm", model)
    calm_answers: list = []
    with running_scheduler(workers=1, batch_window_s=0.0) as scheduler:
        for round_ in range(20):
            for k in range(10):
                offer(flood, round_ * 10 + k, (round_ * 10 + k + 1) * 1000)
            scheduler.wake(flood)
            offer(calm, round_, (round_ + 1) * 1000)
            scheduler.wake(calm)
            await asyncio.sleep(0.005)
            calm_answers += calm.input.poses()
        await until(lambda: not flood.has_work and not calm.has_work and not scheduler._running)
        calm_answers += calm.input.poses()
    assert len(calm_answers) >= 15  # at 5 ms a round against 2 ms a job: nearly every round answered


@pytest.mark.asyncio
async def test_a_slow_or_gone_client_never_delays_another_session():
    net = FakeNet()
    model = FakeModel(net)
    stuck, gone, good = (fake_session(name, model) for name in ("stuck", "gone", "good"))
    stuck.input = FakeClient(capacity=1)  # never read: its queue is full after one pose
    answered = []
    with running_scheduler(workers=2, batch_window_s=0.002) as scheduler:
        for k in range(30):
            for session in (stuck, gone, good):
                offer(session, k, (k + 1) * 11_111)
                scheduler.wake(session)
            if k == 10:
                scheduler.forget(gone)  # its clients left while its job may be in flight
                gone.input = None
            await asyncio.sleep(0.004)
            answered += good.input.poses()
        await until(lambda: not scheduler._running)
        answered += good.input.poses()
    assert len(answered) >= 25
    assert stuck.input.outbox.dropped_poses >= 20  # the stuck client lost its oldest poses, nothing waited


@pytest.mark.asyncio
async def test_a_failing_run_is_the_sessions_internal_error_and_the_others_go_on(caplog):
    net = FakeNet()
    model = FakeModel(net)
    broken, fine = fake_session("broken", model), fake_session("fine", model)

    def explode(*args):
        raise RuntimeError("injected fault")

    broken._pipeline.begin_hmd = explode
    with running_scheduler(workers=1, batch_window_s=0.05) as scheduler:
        for k in range(2):
            for session in (broken, fine):
                offer(session, k, (k + 1) * 1000)
                scheduler.wake(session)
            await until(lambda: not scheduler._running and not broken.has_work and not fine.has_work)
        await asyncio.sleep(0.01)
    errors = [decode(d) for d in broken.input.outbox.control]
    assert [e.code for e in errors] == ["internal", "internal"]
    assert len(fine.input.poses()) == 2
    assert sum("injected fault" in r.getMessage() or r.exc_info is not None for r in caplog.records) == 1


@pytest.fixture(scope="module")
def registry():
    registry = ModelRegistry()
    registry.rescan()
    return registry


@pytest.mark.parametrize("model", ["egoposevr", "hmd"])
def test_a_batched_answer_equals_the_unbatched_one_for_every_session(registry, model):
    """Eight sessions replaying different stretches of the bundled recordings, run once batched (one net
    call per step) and once alone: every pose agrees within 1e-5."""
    loaded = registry.get(model)
    if not loaded.batchable:
        pytest.skip(f"{model}.onnx has no batch axis")
    messages = [decode(d) for _, kind, d in recorded_messages("walk-0000", limit=1200) if kind == "hmd"]
    streams = [messages[i * 40 : i * 40 + 60] for i in range(8)]

    def replay(batched: bool) -> list[list[np.ndarray]]:
        sessions = [
            Session(f"s{i}", model, loaded, TokenBucket(1e6, 1000), first_frame_wait_ns=0) for i in range(8)
        ]  # every sample answered as it comes, camera or not
        joints: list[list[np.ndarray]] = [[] for _ in sessions]
        for step in range(60):
            jobs = []
            for session, stream in zip(sessions, streams, strict=True):
                session.offer_hmd(Received(stream[step], time.perf_counter_ns(), 0))
                jobs.append((session, session.take_job()))
            results = run_batch(jobs) if batched else [s.run(j) for s, j in jobs]
            for out, result in zip(joints, results, strict=True):
                out.append(np.reshape(decode(result.pose).joints, (22, 3)))
        return joints

    batched, alone = replay(True), replay(False)
    worst = max(
        float(np.abs(a - b).max())
        for sa, sb in zip(batched, alone, strict=True)
        for a, b in zip(sa, sb, strict=True)
    )
    assert worst <= 1e-5
