"""The OpenCV renderer: a recording through a model to MP4, and a live session watched as a viewer."""

from __future__ import annotations

import threading

import cv2
import numpy as np
from loopback import RECORDINGS, Client, recorded_messages, replay, running_server

from egoposevr.cli.main import main

WALK = RECORDINGS / "walk-0000.egrec"


def read_frames(path) -> list[np.ndarray]:
    capture = cv2.VideoCapture(str(path))
    frames = []
    while (frame := capture.read())[0]:
        frames.append(frame[1])
    return frames


def test_a_recording_becomes_a_video_where_the_body_moves(tmp_path, capsys):
    out = tmp_path / "walk.mp4"
    assert (
        main(["render", str(WALK), "--model", "hmd", "--out", str(out), "--fps", "20", "--size", "320x240"])
        == 0
    )
    assert "wrote" in capsys.readouterr().out
    frames = read_frames(out)
    assert len(frames) >= 90 and frames[0].shape == (240, 320, 3)  # 5 s at 20 fps
    moving = np.abs(frames[10].astype(int) - frames[60].astype(int)).sum(-1) > 60
    assert moving.sum() > 200  # the skeleton moved between the two frames
    assert frames[30].reshape(-1, 3).max(0).min() > 200  # bright skeleton pixels are drawn


def test_a_live_session_is_watched_as_a_viewer(tmp_path):
    out = tmp_path / "live.mp4"
    with running_server() as server, Client(server.url, "live") as headset:
        headset.hello("input", "live", model="hmd")
        headset.collect()
        streamer = threading.Thread(target=replay, args=(headset, recorded_messages("walk-0000", limit=300)))
        streamer.start()
        code = main(["render", "--url", server.url, "--session", "live", "--seconds", "2", "--out", str(out)])
        streamer.join()
    assert code == 0
    assert len(read_frames(out)) >= 30


def test_render_refuses_bad_requests(tmp_path, capsys):
    assert main(["render", "--out", str(tmp_path / "x.mp4")]) == 2
    assert main(["render", str(WALK), "--model", "nope", "--out", str(tmp_path / "x.mp4")]) == 2
    assert main(["render", str(WALK), "--size", "big", "--out", str(tmp_path / "x.mp4")]) == 2
    assert "nope" in capsys.readouterr().err
