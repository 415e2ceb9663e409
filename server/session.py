"""One session: its clients, its model, the headset's pending work and the inference pipeline.

A state machine without sockets, threads or asyncio; its pipeline is made by the injected ``make_pipeline``
(tests use a fake). Threading contract: everything except :meth:`Session.begin`, :meth:`Session.finish` and
:meth:`Session.run` (= begin, the fusion net, finish) is called on the event loop; those are called in a
worker thread with a job from :meth:`Session.take_job`, one job at a time per session (the scheduler keeps at
most one in flight). Only they touch the pipeline, so model switches and resets travel inside the job.

Newest wins: headset samples that arrive while inference is busy wait in ``pending``; the next job answers
only the newest of them and feeds the older ones to the pipeline as history (``observe_hmd``), counting them
as skipped. Only the newest RGB-D frame is kept; a frame replaced before use is counted.

First frame (PROTOCOL.md §first-frame; ``first_frame_wait_ns`` 0 turns it off): for a model that reads the
camera, a stream's first samples (after a connect, a reconnect or a model switch) wait in ``pending`` until its
first frame is ready for a job, or until ``first_frame_wait_ns`` after the first of them
(:meth:`Session.holding_ns`): the stream's first answer, which the runtime's leg hold keeps, then has the camera's
measure of the legs. With ``low_head_wait_ns``, a stream whose first sample has the head low (seated) waits for the
net's visual window of frames instead, at most that long (frames.first_answer_wait decides from the stream's first
sample). The scheduler wakes the session when the wait runs out.

Frame lane (``frame_lane=True``, what the server runs): camera frames never ride on a headset job. The
scheduler takes the newest frame with :meth:`Session.take_frame` and runs :func:`encode_received_frames`
(image decode + visual encoder, stateless, several sessions' frames in one encoder call) on its low-priority
lane thread; the result comes back through :meth:`Session.offer_encoded`, and the next headset job adds it to
the pipeline's cache (:meth:`Pipeline.add_frame`, in capture order) before answering. One frame is in the
lane per session at a time; frames arriving meanwhile replace each other (counted). Without the lane
(``--no-frame-lane``), a job decodes and encodes its frames before its samples.
"""

from __future__ import annotations

import dataclasses
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from ..model.inputs import decode_rgbd
from ..model.runtime.body import bone_lengths_m, scale_of_lengths
from ..model.runtime.calibration import Calibration as MeasuredCalibration
from ..model.runtime.calibration import CalibrationCollector, CalibrationFailed
from ..model.runtime.frames import (
    DEFAULT_LOW_HEAD_WAIT_US,
    FIRST_FRAME_WAIT_US,
    EncodedFrame,
    FirstAnswerWait,
    check_frame,
    encode_frames,
    first_answer_wait,
)
from ..model.runtime.loading import LoadedModel
from ..model.runtime.pipeline import PendingPose, PoseResult, run_fusion
from ..model.runtime.procedural import pipeline_for
from ..protocol import (
    Body,
    Calibrate,
    Calibration,
    Error,
    ErrorCode,
    GetBody,
    Hmd,
    InputError,
    Pose,
    Ref,
    Rgbd,
    SetBody,
    encode,
)

# Older samples only feed the HMD history; beyond this many the oldest are dropped outright (counted).
MAX_PENDING_SAMPLES = 64
MAX_ENCODED_FRAMES = 8  # lane results waiting for a headset sample (a camera streaming without a headset)


@dataclasses.dataclass(frozen=True)
class Received:
    """A decoded client message with when it arrived (perf_counter ns) and how long decoding took."""

    msg: Any  # Hmd | Rgbd
    recv_ns: int
    decode_ns: int


@dataclasses.dataclass(frozen=True)
class Job:
    """What one ``run`` does: switch or reset first, push the frame, then the samples (the last answered)."""

    samples: tuple[Received, ...]
    frame: Received | None
    model: tuple[str, LoadedModel] | None
    reset: bool
    skipped: int  # samples not answered since the previous pose, these jobs' history ones included
    encoded: tuple[EncodedFrame, ...] = ()  # frames from the lane, added to the cache before the samples
    image_us: int | None = None  # the lane's image decoding time of those frames
    calibrate: tuple[Calibrate, ...] = ()  # calibrate requests, in arrival order, before the samples
    body: tuple[SetBody | GetBody, ...] = ()  # body requests, in arrival order, after the calibrate ones


@dataclasses.dataclass
class FrameResult:
    """What the frame lane produced from one ``rgbd`` message."""

    encoded: EncodedFrame | None = None
    errors: list[Error] = dataclasses.field(default_factory=list)
    image_us: int = 0


@dataclasses.dataclass
class RunResult:
    """What a run produced, for the loop to send and count."""

    pose: bytes | None = None
    model: str = ""  # the model that made the pose
    timing_us: dict[str, int] = dataclasses.field(default_factory=dict)
    errors: list[Error] = dataclasses.field(default_factory=list)
    stale_frame: bool = False
    # for every client of the session
    notices: list[Calibration | Body] = dataclasses.field(default_factory=list)


@dataclasses.dataclass
class Started:
    """A run between :meth:`Session.begin` and :meth:`Session.finish`."""

    started_ns: int  # perf_counter ns when the run began
    result: RunResult
    newest: Received | None = None  # the sample answered
    skipped: int = 0
    pending: PendingPose | None = None  # its pose up to the fusion net
    image_us: int | None = None


class TokenBucket:
    """The per-session message-rate cap: ``rate_hz`` sustained, ``burst`` at once."""

    def __init__(self, rate_hz: float, burst: int) -> None:
        self.rate_hz, self.burst = rate_hz, float(burst)
        self.tokens = float(burst)
        self.last_ns = time.perf_counter_ns()

    def allow(self, now_ns: int) -> bool:
        self.tokens = min(self.burst, self.tokens + (now_ns - self.last_ns) * 1e-9 * self.rate_hz)
        self.last_ns = now_ns
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False


class Session:
    """State of one session id; ``input`` and ``renders`` hold the app's client handles."""

    def __init__(
        self,
        session_id: str,
        model_name: str,
        model: LoadedModel,
        rate: TokenBucket,
        frame_lane: bool = False,
        make_pipeline: Callable[[Any], Any] = pipeline_for,
        first_frame_wait_ns: int = FIRST_FRAME_WAIT_US * 1000,
        low_head_wait_ns: int = DEFAULT_LOW_HEAD_WAIT_US * 1000,
    ) -> None:
        self.id = session_id
        self.model_name = model_name  # the active model as clients see it
        self.rate = rate
        self.input: Any = None
        self.renders: list[Any] = []
        self.pending: deque[Received] = deque()
        self.frame: Received | None = None
        self.frame_lane = frame_lane
        self._model = model  # the model the next job runs (a pending switch's), for the lane's encoder
        self._encoding = False  # a frame is in the lane
        self._encoded: deque[FrameResult] = deque(maxlen=MAX_ENCODED_FRAMES)
        self.skipped = 0  # since the last pose
        self.dropped_history = 0
        self.replaced_frames = 0
        self._next_model: tuple[str, LoadedModel] | None = None
        self._reset = False
        self._calibrate: list[Calibrate] = []  # requests for the next job
        self._body: list[SetBody | GetBody] = []  # requests for the next job
        self._make_pipeline = make_pipeline  # a model -> its per-session pipeline (tests inject a fake)
        self._pipeline = make_pipeline(model)  # run() only
        self._pipeline_model_name = model_name  # run() only: the model the pipeline runs
        self._previous_encode_us = 0
        self._collector: tuple[Calibrate, CalibrationCollector] | None = None  # run() only
        self.first_frame_wait_ns = first_frame_wait_ns
        self.low_head_wait_ns = low_head_wait_ns
        self._start_stream()

    # ------------------------------------------------------------------------------ event loop side
    @property
    def clients(self) -> list[Any]:
        return ([self.input] if self.input is not None else []) + self.renders

    def offer_hmd(self, received: Received) -> bool:
        """Queue a sample; returns True when the oldest pending one had to be dropped (counted as skipped)."""
        if self._first_answer_due and self._stream_start_ns is None:
            self._first_wait = self._wait_of(received)
            self._stream_start_ns = received.recv_ns
        dropped = len(self.pending) == MAX_PENDING_SAMPLES
        if dropped:
            self.pending.popleft()
            self.skipped += 1
            self.dropped_history += 1
        self.pending.append(received)
        return dropped

    def offer_rgbd(self, received: Received) -> bool:
        """Keep only the newest frame; returns False when an unused frame was replaced."""
        replaced = self.frame is not None
        self.replaced_frames += replaced
        self.frame = received
        if not self.frame_lane:
            self._stream_frames = 1  # it rides on the next job, before the samples
        return not replaced

    def holding_ns(self, now_ns: int) -> int | None:
        """How much longer the pending samples wait for what the stream's first answer needs (ns: its first frame,
        or with a low head the net's visual window of frames: frames.first_answer_wait), or None when they do not
        wait: the stream has answered or has what it needs, or its model reads no camera, or nothing is pending."""
        wait, start_ns = self._first_wait, self._stream_start_ns
        if not (self._first_answer_due and self.pending and wait is not None and start_ns is not None):
            return None
        if wait.met(self._stream_frames, (now_ns - start_ns) // 1000):
            return None
        return start_ns + wait.wait_us * 1000 - now_ns

    def _start_stream(self) -> None:
        """A new stream (a connect, a reconnect or a model switch): its first answer waits again."""
        self._first_answer_due = True  # this stream has answered nothing yet
        self._first_wait: FirstAnswerWait | None = None  # decided by its first sample
        self._stream_start_ns: int | None = None  # when its first sample arrived
        self._stream_frames = 0  # frames ready for it since
        if self.pending:  # a model switch with samples waiting: the new stream begins with them
            self._first_wait = self._wait_of(self.pending[0])
            self._stream_start_ns = self.pending[0].recv_ns

    def _wait_of(self, first: Received) -> FirstAnswerWait | None:
        """What the stream whose first sample is ``first`` waits for (None: its model reads no camera). Without
        the frame lane only the newest frame reaches a job, so no wait is for more than one."""
        if self._model.visual is None:
            return None
        low_head_wait_us = self.low_head_wait_ns // 1000 if self.frame_lane else 0
        return first_answer_wait(
            first.msg.head,
            first.msg.valid[0],
            self._model.info.config.visual_window,
            self.first_frame_wait_ns // 1000,
            low_head_wait_us,
        )

    def select(self, name: str, model: LoadedModel) -> None:
        """Switch model at the next job; the pipeline starts fresh (its caches belong to the old model)."""
        self.model_name = name
        self._next_model = (name, model)
        self._model = model
        self._encoded.clear()  # encoded by the previous model's encoder
        self._reset = False  # a new pipeline is a reset
        self._start_stream()

    def request_calibration(self, msg: Calibrate) -> None:
        """A ``calibrate`` request: the next job starts (or clears) it, with or without headset samples."""
        self._calibrate.append(msg)

    def request_body(self, msg: SetBody | GetBody) -> None:
        """A ``set_body`` or ``get_body`` request: the next job applies or answers it, with or without headset
        samples."""
        self._body.append(msg)

    def restart_stream(self) -> None:
        """A new input client: forget the previous headset's history at the next job; drop its leftovers."""
        self.pending.clear()
        self.frame = None
        self._encoded.clear()
        self._reset = self._next_model is None
        self._start_stream()

    @property
    def next_model(self) -> LoadedModel:
        """The model the next job runs (a pending switch's): the scheduler batches sessions by it."""
        return self._model

    @property
    def has_work(self) -> bool:
        requests = bool(self._calibrate) or bool(self._body)
        return self._samples_ready() or requests or (self.frame is not None and not self.frame_lane)

    def _samples_ready(self) -> bool:
        """Samples are pending and none waits for the stream's first answer's needs."""
        return bool(self.pending) and self.holding_ns(time.perf_counter_ns()) is None

    def take_job(self) -> Job | None:
        if not self.has_work:
            return None
        # A job for a calibration or a body request while the samples wait leaves them waiting.
        samples = tuple(self.pending) if self._samples_ready() else ()
        self.skipped += max(len(samples) - 1, 0)
        lane = list(self._encoded) if samples else []  # frames wait for a sample to be answered with
        job = Job(
            samples,
            None if self.frame_lane else self.frame,
            self._next_model,
            self._reset,
            self.skipped,
            encoded=tuple(r.encoded for r in lane if r.encoded is not None),
            image_us=sum(r.image_us for r in lane) if lane else None,
            calibrate=tuple(self._calibrate),
            body=tuple(self._body),
        )
        self._calibrate.clear()
        self._body.clear()
        if samples:
            self.pending.clear()
            self._encoded.clear()
            self._first_answer_due = False
        if not self.frame_lane:
            self.frame = None
        self._next_model, self._reset = None, False
        if samples:
            self.skipped = 0
        return job

    def take_frame(self) -> tuple[Received, LoadedModel] | None:
        """The newest frame and the encoder to run it with, for the lane; None if none, or one is in the lane
        already, or the model reads no camera (the frame is then dropped: decoding it would only cost)."""
        if not self.frame_lane or self.frame is None or self._encoding:
            return None
        frame, self.frame = self.frame, None
        if self._model.visual is None:
            return None
        self._encoding = True
        return frame, self._model

    def offer_encoded(self, result: FrameResult, model: LoadedModel) -> bool:
        """The lane's result for the frame :meth:`take_frame` gave out; kept for the next headset job unless
        the model changed meanwhile. Returns False when a frame was thrown away: this one (stale model) or,
        with no headset sample for a while, the oldest waiting one (the caller counts it as replaced)."""
        self._encoding = False
        if model is not self._model:
            return False
        overflow = len(self._encoded) == MAX_ENCODED_FRAMES
        self.replaced_frames += overflow
        self._encoded.append(result)
        if result.encoded is not None:
            self._stream_frames += 1
        return not overflow

    # ------------------------------------------------------------------------------ worker thread side
    def run(self, job: Job) -> RunResult:
        """Push the job through the pipeline; the newest sample's pose comes back encoded."""
        started = self.begin(job)
        return self.finish(started, run_fusion([started.pending])[0] if started.pending else None)

    def begin(self, job: Job) -> Started:
        """:meth:`run` up to the fusion net: switch or reset, calibration requests, frames, the history
        samples, then the newest sample's net inputs (``Started.pending``; None when nothing is answered).
        The scheduler runs several sessions' nets as one batch, then :meth:`finish` each."""
        started = Started(time.perf_counter_ns(), RunResult())
        result = started.result
        if job.model is not None:
            self._pipeline_model_name, model = job.model
            # the wearer's calibration and given body outlive the model
            calibration, given = self._pipeline.calibration, self._pipeline.given_body
            self._pipeline = self._make_pipeline(model)
            self._pipeline.calibrate(calibration)
            self._pipeline.give_body(given)
        elif job.reset:
            self._pipeline.reset()
            self._abandon_calibration("the input client reconnected", result)
        for request in job.calibrate:
            self._start_calibration(request, result)
        for request in job.body:
            self._body_request(request, result)
        started.image_us = (
            self._push_frame(job.frame, result) if job.frame is not None else job.image_us
        )  # µs or None
        for encoded in job.encoded:
            result.stale_frame |= not self._pipeline.add_frame(encoded)
        for received in job.samples[:-1]:
            self._observe(received.msg, result)
        if job.samples:
            started.newest, started.skipped = job.samples[-1], job.skipped
            started.pending = self._begin_pose(started.newest.msg, result)
        return started

    def finish(self, started: Started, sixd: np.ndarray | None) -> RunResult:
        """The rest of :meth:`run` from the fusion net's output for ``started.pending`` (None for a pipeline
        without a net, or when nothing is answered)."""
        result, newest = started.result, started.newest
        if started.pending is None:
            return result
        pose = self._finish_pose(started.pending, sixd, newest.msg, result)
        if pose is None:
            return result
        timing = {
            "decode": newest.decode_ns // 1000,
            "queue": max(started.started_ns - newest.recv_ns - newest.decode_ns, 0) // 1000,
            **({"image": started.image_us} if started.image_us is not None else {}),
            **pose.timing_us,
            "encode": self._previous_encode_us,
        }
        timing["total"] = (time.perf_counter_ns() - newest.recv_ns) // 1000
        before_encode_ns = time.perf_counter_ns()
        result.pose = encode_pose(pose, newest.msg, self._pipeline_model_name, timing, started.skipped)
        self._previous_encode_us = (time.perf_counter_ns() - before_encode_ns) // 1000
        result.timing_us, result.model = timing, self._pipeline_model_name
        return result

    def _push_frame(self, received: Received, result: RunResult) -> int | None:
        msg: Rgbd = received.msg
        if self._pipeline.model.visual is None:
            return None  # this model reads no camera: decoding the images would only cost time
        frame, error, image_us = _decode_frame(msg)
        if frame is None:
            result.errors.append(error)
            return image_us
        try:
            pushed = self._pipeline.push_rgbd(msg.t_us, *frame)
        except InputError as exc:
            result.errors.append(_error(ErrorCode.INVALID_FIELD, f"rgbd {msg.seq}: {exc}", msg))
            return image_us
        result.stale_frame = not pushed and self._pipeline.model.visual is not None
        return image_us

    # ------------------------------------------------------------------------------ calibration (run() only)
    def _start_calibration(self, request: Calibrate, result: RunResult) -> None:
        self._abandon_calibration("a newer calibrate replaced it", result)
        if request.clear:
            self._pipeline.calibrate(None)
            message = "calibration cleared; the body is estimated as the session goes"
            result.notices.append(Calibration(status="cleared", pose=request.pose, message=message))
            return
        offsets = self._pipeline.model.info.rig_offsets_m
        self._collector = (request, CalibrationCollector(request.pose, request.seconds, offsets))
        what = "arms out sideways, palms down" if request.pose == "tpose" else "arms relaxed"
        message = f"hold still for {request.seconds:g} s: standing straight, looking ahead, {what}"
        result.notices.append(Calibration(status="started", pose=request.pose, message=message))

    def _body_request(self, request: SetBody | GetBody, result: RunResult) -> None:
        """Apply a ``set_body`` (the hub has checked its lengths: :func:`check_set_body`), then tell every client
        the body served now."""
        if isinstance(request, SetBody):
            scale = None if request.clear else scale_of_lengths(np.asarray(request.bone_lengths_m))
            self._pipeline.give_body(scale)
        scale, measured = self._pipeline.served_body()
        lengths = [float(x) for x in bone_lengths_m(scale)]
        given = self._pipeline.given_body is not None
        result.notices.append(Body(bone_lengths_m=lengths, given=given, measured=measured))

    def _abandon_calibration(self, reason: str, result: RunResult) -> None:
        if self._collector is not None:
            pose = self._collector[0].pose
            result.notices.append(Calibration(status="failed", pose=pose, message=reason))
            self._collector = None

    def _collect(self, msg: Hmd, result: RunResult) -> None:
        """Feed the sample to a calibration in progress; when it completes, the pipeline takes it from this
        sample on."""
        if self._collector is None:
            return
        request, collector = self._collector
        try:
            measured = collector.push(msg.t_us, np.asarray(msg.poses()), np.asarray(msg.valid))
        except CalibrationFailed as exc:
            self._collector = None
            result.notices.append(Calibration(status="failed", pose=request.pose, message=str(exc)))
            return
        if measured is None:
            return
        self._collector = None
        self._pipeline.calibrate(measured)
        result.notices.append(_calibration_done(request, measured))

    def _observe(self, msg: Hmd, result: RunResult) -> None:
        self._collect(msg, result)
        try:
            self._pipeline.observe_hmd(msg.t_us, np.asarray(msg.poses()), np.asarray(msg.valid))
        except InputError as exc:
            result.errors.append(_error(ErrorCode.INVALID_FIELD, f"hmd {msg.seq}: {exc}", msg))

    def _begin_pose(self, msg: Hmd, result: RunResult) -> PendingPose | None:
        self._collect(msg, result)
        try:
            return self._pipeline.begin_hmd(msg.t_us, np.asarray(msg.poses()), np.asarray(msg.valid))
        except InputError as exc:
            result.errors.append(_error(ErrorCode.INVALID_FIELD, f"hmd {msg.seq}: {exc}", msg))
            return None

    def _finish_pose(
        self, pending: PendingPose, sixd: np.ndarray | None, msg: Hmd, result: RunResult
    ) -> PoseResult | None:
        pose = self._pipeline.finish_hmd(pending, sixd)
        if not (np.isfinite(pose.joints).all() and np.isfinite(pose.body_pose).all()):
            result.errors.append(
                _error(ErrorCode.INTERNAL, f"hmd {msg.seq}: the model produced non-finite numbers", msg)
            )
            return None
        return pose


def _calibration_done(request: Calibrate, measured: MeasuredCalibration) -> Calibration:
    """The ``calibration`` message announcing a finished measurement."""
    span = "" if measured.arm_span_m is None else f", arm span {measured.arm_span_m:.2f} m"
    return Calibration(
        status="done",
        pose=request.pose,
        message=f"calibrated: head joint {measured.head_height_m:.2f} m above the floor{span}",
        head_height_m=measured.head_height_m,
        arm_span_m=measured.arm_span_m,
        corrections=[float(v) for v in measured.correction_quats.reshape(-1)],
    )


def encode_received_frame(received: Received, model: LoadedModel) -> FrameResult:
    """The frame lane's work on one ``rgbd`` message: decode the images, run the visual encoder. Stateless
    (any thread); malformed frames come back as errors with the message's seq."""
    return encode_received_frames([(received, model)])[0]


def encode_received_frames(frames: list[tuple[Received, LoadedModel]]) -> list[FrameResult]:
    """:func:`encode_received_frame` on the new frames of several sessions: each is decoded on its own, and
    the well-formed ones of one model go through its encoder as one batch."""
    results = [FrameResult() for _ in frames]
    batches: dict[int, list[int]] = {}
    decoded: dict[int, tuple[Any, ...]] = {}
    for i, (received, model) in enumerate(frames):
        msg: Rgbd = received.msg
        frame, error, results[i].image_us = _decode_frame(msg)
        if frame is None:
            results[i].errors.append(error)
            continue
        try:
            check_frame(*frame)
        except InputError as exc:
            results[i].errors.append(_error(ErrorCode.INVALID_FIELD, f"rgbd {msg.seq}: {exc}", msg))
            continue
        decoded[i] = (msg.t_us, *frame)
        batches.setdefault(id(model), []).append(i)
    for indices in batches.values():
        encoded = encode_frames(frames[indices[0]][1], [decoded[i] for i in indices])
        for i, frame in zip(indices, encoded, strict=True):
            results[i].encoded = frame
    return results


def _decode_frame(msg: Rgbd) -> tuple[tuple[Any, ...] | None, Error | None, int]:
    """An rgbd message's images and geometry, as push_rgbd / encode_frame take them after t_us:
    ((rgb, depth, intrinsics, cam_from_head), None, decode µs), or (None, its image_decode error, µs)."""
    started = time.perf_counter_ns()
    try:
        rgb, depth = decode_rgbd(msg.rgb, msg.depth, expected_wh=(msg.width, msg.height))
    except InputError as exc:
        error = _error(ErrorCode.IMAGE_DECODE, f"rgbd {msg.seq}: {exc}", msg)
        return None, error, (time.perf_counter_ns() - started) // 1000
    image_us = (time.perf_counter_ns() - started) // 1000
    cam_from_head = None if msg.cam_from_head is None else np.reshape(msg.cam_from_head, (4, 4))
    return (rgb, depth, np.asarray(msg.intrinsics), cam_from_head), None, image_us


def error_about(
    code: ErrorCode, message: str, about: tuple[str | None, int | None] = (None, None), fatal: bool = False
) -> Error:
    """An ``error`` reply; ``about`` is the (type, seq) of the client message that caused it, where known:
    the type makes ``ref``, the seq goes into ``ref`` and ``seq`` (PROTOCOL.md §5)."""
    ref_type, seq = about
    ref = Ref(type=ref_type, seq=seq) if ref_type is not None else None
    return Error(code=code.value, message=message[:1024], fatal=fatal, seq=seq, ref=ref)


def check_set_body(msg: SetBody) -> str | None:
    """Why a ``set_body`` cannot be served (a bone outside body.GIVEN_SCALE_RANGE times the mean body's), or
    None. The hub asks before queueing it, so the error goes to the client that sent it."""
    if msg.clear:
        return None
    try:
        scale_of_lengths(np.asarray(msg.bone_lengths_m))
    except ValueError as exc:
        return f"set_body: {exc}"
    return None


def _error(code: ErrorCode, message: str, msg: Hmd | Rgbd) -> Error:
    return error_about(code, message, (msg.type, msg.seq))


def encode_pose(pose: PoseResult, sample: Hmd, model: str, timing_us: dict[str, int], skipped: int) -> bytes:
    """The wire ``pose`` answering ``sample``. Built without re-validation: the values come from the pipeline
    (finite, checked by the caller) and the validated sample, and the shapes are fixed by them."""
    message = Pose.model_construct(
        seq=sample.seq,
        t_us=pose.t_us,
        model=model,
        global_orient=pose.global_orient.tolist(),
        body_pose=pose.body_pose.tolist(),
        transl=pose.transl.tolist(),
        joints=pose.joints.reshape(-1).tolist(),
        timing_us=timing_us,
        camera=pose.camera,
        skipped=skipped,
        truth=sample.truth,
        planted=None if pose.planted is None else list(pose.planted),
        floor_y_m=pose.floor_y_m,
    )
    return encode(message)
