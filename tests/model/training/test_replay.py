"""eval's replay of a dataset sequence: when the camera's frames arrive, and a stream's first samples waiting for
the first one, or with a low head for the net's visual window (PROTOCOL.md §first-frame), checked on a fake pipeline
that logs its calls."""

from __future__ import annotations

import types

import cv2
import numpy as np

from egoposevr.model.runtime.frames import FIRST_FRAME_WAIT_US, LOW_HEAD_M, LOW_HEAD_WAIT_US
from egoposevr.model.training.evaluate import CAMERA_LATENCY_US, replay_sequence


class LoggingPipeline:
    """Records ('hmd', t_us) and ('rgbd', t_us) in call order; answers every sample with zeros."""

    def __init__(self, camera: bool = True) -> None:
        self.model = types.SimpleNamespace(visual=object() if camera else None)
        self.visual_window = 3  # the net's visual window
        self.calls: list[tuple[str, int]] = []

    def reset(self) -> None:
        self.calls.clear()

    def push_rgbd(self, t_us, *_args) -> bool:
        self.calls.append(("rgbd", t_us))
        return True

    def push_hmd(self, t_us, *_args):
        self.calls.append(("hmd", t_us))
        return types.SimpleNamespace(joints=np.full((22, 3), t_us), local_rot=np.zeros((22, 3, 3)))

    def observe_hmd(self, t_us, *_args) -> None:
        self.calls.append(("observe", t_us))


def _sequence(hmd_hz: float, first_frame_us: int, n: int = 40, head_y_m: float = 1.6) -> dict:
    """``n`` headset samples at ``hmd_hz``, the head ``head_y_m`` up, and 30 Hz frames from ``first_frame_us``
    (tiny real images)."""
    jpeg = cv2.imencode(".jpg", np.zeros((2, 2, 3), np.uint8))[1].tobytes()
    png = cv2.imencode(".png", np.zeros((2, 2), np.uint16))[1].tobytes()
    cam_t_us = np.arange(first_frame_us, 2_000_000, 33_333)
    poses = np.zeros((n, 3, 7))
    poses[:, 0, 1] = head_y_m
    return {
        "hmd_t_us": np.round(np.arange(n) * 1e6 / hmd_hz).astype(np.int64),
        "hmd_poses": poses,
        "hmd_valid": np.ones((n, 3), bool),
        "cam_t_us": cam_t_us,
        "rgb_jpeg": [jpeg] * len(cam_t_us),
        "depth_png": [png] * len(cam_t_us),
        "camera": {"intrinsics": [1.0, 1.0, 1.0, 1.0], "cam_from_head": np.eye(4).ravel()},
    }


def test_the_first_samples_wait_for_the_first_frame_then_the_newest_is_answered_as_the_server_does():
    seq, pipeline = _sequence(90, first_frame_us=10_000), LoggingPipeline()
    joints, _ = replay_sequence(pipeline, seq)
    t_us = list(seq["hmd_t_us"])
    first = next(i for i, t in enumerate(t_us) if t >= 10_000 + CAMERA_LATENCY_US)  # the frame has arrived
    assert pipeline.calls[0] == ("rgbd", 10_000)  # before any sample is fed
    assert pipeline.calls[1 : first + 2] == [("observe", t) for t in t_us[:first]] + [("hmd", t_us[first])]
    assert [t for kind, t in pipeline.calls if kind == "hmd"] == t_us[first:]  # then one answer a sample
    assert len(joints) == len(t_us)  # every sample scored: the held ones with the first pose served
    np.testing.assert_array_equal(joints[: first + 1, 0, 0], [t_us[first]] * (first + 1))

    answered_at_once = LoggingPipeline()
    replay_sequence(answered_at_once, seq, first_frame_wait=False)
    assert answered_at_once.calls[0] == ("hmd", 0) and ("rgbd", 10_000) in answered_at_once.calls


def test_the_wait_runs_out_and_a_headset_without_the_camera_never_waits():
    late = _sequence(90, first_frame_us=FIRST_FRAME_WAIT_US + 100_000)  # the first frame comes too late
    pipeline = LoggingPipeline()
    replay_sequence(pipeline, late)
    answered = [t for kind, t in pipeline.calls if kind == "hmd"]
    assert (
        answered[0] >= FIRST_FRAME_WAIT_US and answered[0] - FIRST_FRAME_WAIT_US < 1e6 / 90
    )  # the wait ran out
    assert pipeline.calls.index(("hmd", answered[0])) < pipeline.calls.index(("rgbd", late["cam_t_us"][0]))
    for camera, send_frames in ((False, True), (True, False)):
        pipeline = LoggingPipeline(camera)
        replay_sequence(pipeline, late, send_frames=send_frames)
        assert [k for k, _ in pipeline.calls] == ["hmd"] * len(late["hmd_t_us"])


def _answered(pipeline: LoggingPipeline) -> list[int]:
    return [t for kind, t in pipeline.calls if kind == "hmd"]


def test_a_low_head_waits_for_the_nets_visual_window_and_only_with_the_option():
    seq = _sequence(90, first_frame_us=10_000, head_y_m=LOW_HEAD_M - 0.2)  # seated
    t_us = list(seq["hmd_t_us"])
    pipeline = LoggingPipeline()
    replay_sequence(pipeline, seq, low_head_wait=True)
    first = t_us.index(_answered(pipeline)[0])
    before = pipeline.calls[: pipeline.calls.index(("hmd", t_us[first]))]
    frames = [t for kind, t in before if kind == "rgbd"]
    assert len(frames) == pipeline.visual_window  # the window's frames, no more
    assert t_us[first - 1] < frames[-1] + CAMERA_LATENCY_US <= t_us[first]  # answered as the last one is in
    assert [t for kind, t in before if kind == "observe"] == t_us[:first]  # the held samples are its history

    standing = _sequence(90, first_frame_us=10_000, head_y_m=LOW_HEAD_M + 0.2)
    for sequence, option in ((standing, True), (seq, False)):  # the first frame only
        pipeline = LoggingPipeline()
        replay_sequence(pipeline, sequence, low_head_wait=option)
        assert _answered(pipeline)[0] == next(t for t in t_us if t >= 10_000 + CAMERA_LATENCY_US)


def test_a_low_heads_wait_runs_out_and_untracked_or_camera_less_streams_do_not_take_it():
    no_frames = _sequence(90, first_frame_us=5_000_000, n=150, head_y_m=1.0)  # the camera never sends
    pipeline = LoggingPipeline()
    replay_sequence(pipeline, no_frames, low_head_wait=True)
    first = _answered(pipeline)[0]
    assert LOW_HEAD_WAIT_US <= first < LOW_HEAD_WAIT_US + 1e6 / 90

    untracked = _sequence(90, first_frame_us=10_000, head_y_m=1.0)
    untracked["hmd_valid"][0, 0] = False  # no head height to judge by: the first frame's wait
    pipeline = LoggingPipeline()
    replay_sequence(pipeline, untracked, low_head_wait=True)
    assert _answered(pipeline)[0] < FIRST_FRAME_WAIT_US

    pipeline = LoggingPipeline(camera=False)
    replay_sequence(pipeline, no_frames, low_head_wait=True)
    assert _answered(pipeline)[0] == 0
