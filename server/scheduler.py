"""Where every session's work runs: the inference worker pool, the frame lane and cross-session batching.

One way through::

    hub.receive ─ Session.offer_* ─> Scheduler.wake(session)
        ready sessions ─(batch window)─> one batch per model ─> worker thread: run_batch
            Session.begin (each) ─> run_fusion (one net call per batch) ─> Session.finish (each)
        ─> broadcast.publish(session, result) ─> the session's clients' outboxes

    new camera frames of every session ─> frame lane thread: encode_received_frames (one encoder call per
        model) ─> Session.offer_encoded ─> the session's next headset job adds them to its cache

Nothing calls back up: the hub only routes messages into sessions and wakes the scheduler; the scheduler
delivers results straight to the clients' outboxes (:func:`~egoposevr.server.broadcast.publish`).

Batching (``batch_window_s`` > 0): a headset job that is ready while a worker is free waits at most the
window for the jobs of other sessions on the same model, then they all run as one fusion-net call; jobs
that piled up while every worker was busy join the next batch without waiting. The per-session arithmetic
(features, FK, filter, KPO, rotations) stays per session, in compiled kernels that release the GIL. ``0``
turns batching off: every job runs alone, as soon as a worker is free. Each session has at most one job in
flight, and sessions are served oldest-ready first, so a busy session cannot starve another.

Errors: a client's bad input comes back inside the run's result (``invalid_field`` and friends, from the
session). Anything else a run raises is ours: it is logged once per session with its traceback, the
session's input client gets ``internal``, and the session goes on with its next job.

Threading: every method runs on the event loop; ``run_batch`` and the lane's work run in threads.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from ..model.runtime.pipeline import run_fusion
from ..protocol import ErrorCode
from .broadcast import publish
from .metrics import Metrics
from .session import FrameResult, Job, RunResult, Session, Started, encode_received_frames, error_about

log = logging.getLogger("egoposevr.server")
FRAME_LANE_NICE = 10  # CFS gives a nice-10 thread ~1/10 of a core against a busy nice-0 one


def run_batch(batch: list[tuple[Session, Job]]) -> list[RunResult | Exception]:
    """Run the jobs of several sessions (worker thread): each session's :meth:`~Session.begin`, one
    :func:`~egoposevr.model.runtime.pipeline.run_fusion` over all their pending poses, each
    :meth:`~Session.finish`. A session whose run raises gets its exception back in its slot; the others
    are not affected (an exception in the shared net call is every one of its sessions')."""
    started: list[Started | Exception] = []
    for session, job in batch:
        try:
            started.append(session.begin(job))
        except Exception as exc:  # ours: reported by the scheduler
            started.append(exc)
    waiting = [i for i, s in enumerate(started) if isinstance(s, Started) and s.pending is not None]
    outputs: dict[int, Any] = {}
    try:
        outputs = dict(zip(waiting, run_fusion([started[i].pending for i in waiting]), strict=True))
    except Exception as exc:
        for i in waiting:
            started[i] = exc
    results: list[RunResult | Exception] = []
    for i, (session, _) in enumerate(batch):
        begun = started[i]
        if isinstance(begun, Exception):
            results.append(begun)
            continue
        try:
            results.append(session.finish(begun, outputs.get(i)))
        except Exception as exc:
            results.append(exc)
    return results


class Scheduler:
    """Runs the sessions' jobs; see the module docstring. ``close`` stops it."""

    def __init__(
        self,
        metrics: Metrics,
        workers: int,
        batch_window_s: float,
        max_batch: int = 16,
    ) -> None:
        self.metrics, self.workers = metrics, workers
        self.batch_window_s, self.max_batch = batch_window_s, max_batch
        self._pool = ThreadPoolExecutor(workers, thread_name_prefix="egoposevr-infer")
        # Camera frames run on their own thread at a lower OS priority, so that on a busy machine the
        # headset jobs of every session get the cores first.
        self._lane = ThreadPoolExecutor(1, thread_name_prefix="egoposevr-frames", initializer=_lower_priority)
        self._sessions: set[Session] = set()  # sessions with an input client, or work
        self._ready: dict[Session, float] = {}  # session -> loop time it became ready; oldest first
        self._running: set[Session] = set()
        self._idle_workers = workers
        self._lane_busy = False
        self._logged: set[str] = set()  # session ids whose failure was logged
        self._wakeup = asyncio.Event()
        # sessions whose samples wait for what their stream's first answer needs (Session.holding_ns)
        self._holds: dict[Session, asyncio.TimerHandle] = {}
        self._dispatcher: asyncio.Task[None] | None = None
        self._closed = False

    # ------------------------------------------------------------------------------ from the hub
    def wake(self, session: Session) -> None:
        """``session`` may have new work (a sample, a frame, a calibration request)."""
        if self._closed:
            return
        self._sessions.add(session)
        self._mark_ready(session)
        self._start_frames()
        if self._dispatcher is None:
            self._dispatcher = asyncio.get_running_loop().create_task(self._dispatch_forever())
        self._wakeup.set()

    def forget(self, session: Session) -> None:
        """The session ended: nothing more of it runs (a job in flight finishes; nobody is left to tell)."""
        self._sessions.discard(session)
        self._ready.pop(session, None)
        self._logged.discard(session.id)
        if (hold := self._holds.pop(session, None)) is not None:
            hold.cancel()

    def close(self) -> None:
        self._closed = True
        for hold in self._holds.values():
            hold.cancel()
        if self._dispatcher is not None:
            self._dispatcher.cancel()
        self._pool.shutdown(wait=False, cancel_futures=True)
        self._lane.shutdown(wait=False, cancel_futures=True)

    # ------------------------------------------------------------------------------ headset jobs
    def _mark_ready(self, session: Session) -> None:
        if session not in self._sessions or session in self._running:
            return
        loop = asyncio.get_running_loop()
        if session.has_work:
            self._ready.setdefault(session, loop.time())
        elif (left_ns := session.holding_ns(time.perf_counter_ns())) is not None:
            # its samples wait for what the stream's first answer needs: look again when the wait runs out (an
            # earlier stream's later timer, after a reconnect, is replaced)
            held = self._holds.get(session)
            if held is not None and held.when() <= loop.time() + left_ns / 1e9:
                return
            if held is not None:
                held.cancel()
            self._holds[session] = loop.call_later(left_ns / 1e9, self._hold_over, session)

    def _hold_over(self, session: Session) -> None:
        self._holds.pop(session, None)
        if not self._closed:
            self.wake(session)

    async def _dispatch_forever(self) -> None:
        while True:
            await self._wakeup.wait()
            self._wakeup.clear()
            try:
                while self._ready and self._idle_workers > 0:
                    if self.batch_window_s > 0:
                        await self._gather()
                    batch = self._take_batch()
                    if batch:
                        self._submit(batch)
            except Exception:  # a bug here must not stop every session's inference
                log.exception("the scheduler's dispatch failed; it goes on")

    async def _gather(self) -> None:
        """Wait until every idle session is ready or the oldest ready job has waited the window."""
        loop = asyncio.get_running_loop()
        deadline = min(self._ready.values(), default=loop.time()) + self.batch_window_s
        while self._ready and len(self._ready) < self._could_join():
            remaining = deadline - loop.time()
            if remaining <= 0:
                return
            self._wakeup.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._wakeup.wait(), remaining)

    def _could_join(self) -> int:
        """Sessions that could be ready now: streaming (an input client) and not running."""
        return sum(1 for s in self._sessions if s.input is not None and s not in self._running)

    def _take_batch(self) -> list[tuple[Session, Job]]:
        """The oldest ready session's job and, batching, those of the ready sessions on the same model."""
        if not self._ready:
            return []
        first = next(iter(self._ready))
        members = [first]
        if self.batch_window_s > 0 and first.next_model.batchable:
            same = [s for s in self._ready if s is not first and s.next_model is first.next_model]
            members += same[: self.max_batch - 1]
        batch = []
        for session in members:
            del self._ready[session]
            job = session.take_job()
            if job is None:
                continue
            if len(job.samples) > 1:
                self.metrics.skipped_samples.inc(len(job.samples) - 1)
            self._running.add(session)
            batch.append((session, job))
        return batch

    def _submit(self, batch: list[tuple[Session, Job]]) -> None:
        self._idle_workers -= 1
        self.metrics.batch_size.observe(len(batch))
        future = asyncio.get_running_loop().run_in_executor(self._pool, run_batch, batch)
        future.add_done_callback(lambda done: self._batch_done(batch, done))

    def _batch_done(self, batch: list[tuple[Session, Job]], done: asyncio.Future[list[Any]]) -> None:
        self._idle_workers += 1
        if done.cancelled():
            return
        exc = done.exception()
        results = [exc] * len(batch) if exc is not None else done.result()
        for (session, job), result in zip(batch, results, strict=True):
            self._running.discard(session)
            if session not in self._sessions:
                continue  # ended while running
            if isinstance(result, BaseException):
                result = self._internal_error(session, job, result)
            publish(session, result, self.metrics)
            self._mark_ready(session)
        # The poses' senders were just woken: let them write before a frame or the next batch takes the GIL.
        asyncio.get_running_loop().call_soon(self._after_publish)

    def _after_publish(self) -> None:
        self._start_frames()
        self._wakeup.set()

    def _internal_error(self, session: Session, job: Job, exc: BaseException) -> RunResult:
        if session.id not in self._logged:  # a model that fails tends to fail every time: logged once
            self._logged.add(session.id)
            log.error("inference failed in session %s", session.id, exc_info=exc)
        newest = job.samples[-1].msg if job.samples else None
        about = (newest.type, newest.seq) if newest is not None else (None, None)
        message = "server error while running the model; the session goes on"
        return RunResult(errors=[error_about(ErrorCode.INTERNAL, message, about)])

    # ------------------------------------------------------------------------------ camera frames
    def _start_frames(self) -> None:
        """Send the newest frames of the sessions whose headset work is done to the lane as one batch,
        unless the lane is busy. A session's frame goes into the gap after its pose, not beside its run."""
        if self._lane_busy or self._closed:
            return
        idle = [s for s in self._sessions if s not in self._running and s not in self._ready]
        taken = [(s, *t) for s in idle if (t := s.take_frame()) is not None]
        if not taken:
            return
        self._lane_busy = True
        frames = [(received, model) for _, received, model in taken]
        future = asyncio.get_running_loop().run_in_executor(self._lane, encode_received_frames, frames)
        future.add_done_callback(lambda done: self._frames_done(taken, done))

    def _frames_done(
        self, taken: list[tuple[Session, Any, Any]], done: asyncio.Future[list[FrameResult]]
    ) -> None:
        """Back on the loop: errors go to the input client now; each frame waits for its session's next
        headset job."""
        self._lane_busy = False
        if done.cancelled():
            return
        if (exc := done.exception()) is not None:
            log.error("frame encoding failed", exc_info=exc)
            message = "server error encoding a frame"
            results = [FrameResult(errors=[error_about(ErrorCode.INTERNAL, message)]) for _ in taken]
        else:
            results = done.result()
        for (session, _, model), result in zip(taken, results, strict=True):
            if not session.offer_encoded(result, model):
                self.metrics.replaced_frames.inc()
            if session in self._sessions:
                publish(session, RunResult(errors=result.errors), self.metrics)
                self._mark_ready(session)  # samples that waited for this stream's first frame
        self._wakeup.set()
        self._start_frames()  # newer frames may be waiting


def _lower_priority() -> None:
    with contextlib.suppress(OSError, AttributeError):  # Linux: a thread is a task with its own nice value
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), FRAME_LANE_NICE)
