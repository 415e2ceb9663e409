"""Recordings that survive: a file cut by a crash, SIGKILL or a full disk replays up to its last complete
record, with a warning that says how much was cut; ``--strict`` keeps refusing it."""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any
from unittest import mock

import pytest
from loopback import RECORDINGS, Client, recorded_messages, replay, running_server

from egoposevr.cli.main import main
from egoposevr.recordings import egrec
from egoposevr.recordings.egrec import Cut, EgrecError, read_records

WALK = RECORDINGS / "walk-0000.egrec"


def _cut(tmp_path: Path, fraction: float, garbage: bytes = b"") -> Path:
    data = WALK.read_bytes()
    path = tmp_path / "cut.egrec"
    path.write_bytes(data[: int(len(data) * fraction)] + garbage)
    return path


def test_a_cut_file_gives_its_complete_records_and_says_where_it_stopped(tmp_path):
    whole = list(read_records(WALK))
    for garbage in (b"", b"\xc1\xc1\xc1"):  # cut mid-record; a corrupt tail
        path = _cut(tmp_path, 0.5, garbage)
        with pytest.raises(EgrecError, match=r"truncated|corrupt"):
            list(read_records(path))
        cut = Cut()
        records = list(read_records(path, strict=False, cut=cut))
        assert cut.happened and cut.records == len(records) and 0 < len(records) < len(whole)
        assert records == whole[: len(records)]
        assert cut.bytes_read < cut.bytes_total == path.stat().st_size
        assert f"cut after record {len(records)}" in cut.describe()
    intact = Cut()
    assert len(list(read_records(WALK, strict=False, cut=intact))) == len(whole) and not intact.happened


def test_replay_plays_the_good_part_with_a_warning_and_strict_refuses(tmp_path, capsys):
    path = _cut(tmp_path, 0.4)
    report = tmp_path / "report.json"
    assert main(["replay", str(path), "--strict"]) == 2
    assert "truncated" in capsys.readouterr().err
    with running_server() as server:
        code = main(["replay", str(path), "--url", server.url, "--model", "hmd", "--json", str(report), "--quiet"])  # fmt: skip
    assert code == 0
    assert "warning" in capsys.readouterr().err
    result = json.loads(report.read_text())
    assert result["answered"] > 100 and result["recording_cut"]["records_read"] > 100
    assert result["recording_cut"]["bytes_read"] < result["recording_cut"]["bytes_total"]


def test_render_draws_the_good_part_with_a_warning_and_strict_refuses(tmp_path, capsys):
    path = _cut(tmp_path, 0.2)
    video = tmp_path / "cut.mp4"
    assert main(["render", str(path), "--out", str(video), "--model", "hmd", "--strict"]) == 1
    assert "truncated" in capsys.readouterr().err and not video.exists()
    assert main(["render", str(path), "--out", str(video), "--model", "hmd", "--size", "64x48"]) == 0
    err = capsys.readouterr().err
    assert "warning" in err and "cut after record" in err and "rendering the" in err
    assert video.stat().st_size > 0


def test_bench_says_which_recording_it_cannot_replay_before_starting_a_server(tmp_path, capsys):
    garbage = tmp_path / "garbage.egrec"
    garbage.write_bytes(b"not a recording")
    with mock.patch("egoposevr.clients.bench.serving") as serving:
        assert main(["bench", "--recordings", str(garbage), "--seconds", "1"]) == 2
    assert "garbage.egrec: not an .egrec file" in capsys.readouterr().err
    serving.assert_not_called()
    cut = _cut(tmp_path, 0.4)
    with mock.patch("egoposevr.clients.bench.serving", side_effect=OSError("stop here")):
        assert main(["bench", "--recordings", str(cut), "--seconds", "1"]) == 1
    err = capsys.readouterr().err
    assert "cut.egrec was cut after record" in err and "stop here" in err


class _FullDisk:
    """A file that takes ``room`` more bytes, writes part of the next chunk, then fails like a full disk."""

    def __init__(self, file: Any, room: int) -> None:
        self.file, self.room = file, room

    def write(self, data: bytes) -> int:
        if len(data) > self.room:
            self.file.write(data[: self.room])
            self.room = 0
            raise OSError(errno.ENOSPC, "No space left on device")
        self.room -= len(data)
        return self.file.write(data)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.file, name)


def test_a_full_disk_stops_the_recording_counts_it_and_serving_goes_on(tmp_path):
    original = egrec.EgrecWriter.__init__

    def small_disk(self: Any, *args: Any, **kwargs: Any) -> None:
        original(self, *args, **kwargs)
        self._file = _FullDisk(self._file, room=40_000)

    with (
        mock.patch.object(egrec.EgrecWriter, "__init__", small_disk),
        running_server(record=tmp_path, default_model="hmd") as server,
        Client(server.url, "full") as headset,
    ):
        headset.hello("input", "full")
        headset.collect()
        sent = replay(headset, recorded_messages("walk-0000", limit=200), speed=4.0)
        headset.wait_for(lambda: max((p.seq for p in headset.poses()), default=-1) == max(sent))
        assert server.metric("egoposevr_recordings_failed_total") == 1
    (recording,) = tmp_path.glob("full-*.egrec")
    assert 0 < recording.stat().st_size <= 40_000 + 200  # the header went in before the disk filled
    cut = Cut()
    records = list(read_records(recording, strict=False, cut=cut))
    assert len(records) > 10  # the hello and the first messages, up to the last complete record


def test_a_recording_of_a_server_killed_with_sigkill_replays(tmp_path, capsys):
    process = subprocess.Popen(
        [sys.executable, "-m", "egoposevr.cli.main", "serve", "--port", "0", "--record", str(tmp_path),
         "--default-model", "hmd"],
        stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        url = _listening_url(process)
        with Client(url, "killed") as headset:
            headset.hello("input", "killed")
            replay(headset, recorded_messages("walk-0000", limit=300), speed=4.0)
            time.sleep(0.3)
            os.kill(process.pid, signal.SIGKILL)
            process.wait(10)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(10)
        process.stderr.close()
    (recording,) = tmp_path.glob("killed-*.egrec")
    with running_server() as server:
        report = tmp_path / "report.json"
        code = main(["replay", str(recording), "--url", server.url, "--json", str(report), "--quiet"])
    assert code == 0 and json.loads(report.read_text())["answered"] > 0


def _listening_url(process: subprocess.Popen) -> str:
    import re

    deadline = time.monotonic() + 60
    for line in process.stderr:
        if match := re.search(r"on (ws://\S+)", line):
            return match.group(1)
        assert time.monotonic() < deadline
    raise AssertionError("the server did not start")
