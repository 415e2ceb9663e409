"""The .egrec format: written by synthesis, read back as valid protocol v1 messages with ground truth."""

import msgpack
import numpy as np
import pytest

from egoposevr.model.synth.headset import CameraModel
from egoposevr.model.synth.pipeline import SynthConfig, synthesize_sequence, write_session
from egoposevr.model.synth.procedural import generate
from egoposevr.model.synth.render import Renderer
from egoposevr.protocol import Hmd, Rgbd, decode
from egoposevr.recordings import EgrecError, EgrecWriter, bundled, read_header, read_records


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    cam = CameraModel(width=64, height=48)
    cfg = SynthConfig(hmd_rate_hz=90.0, camera=cam)
    rng = np.random.default_rng(1)
    seq = synthesize_sequence(generate("squat", 2.0, 60.0, rng), cfg, rng, Renderer(cam))
    path = tmp_path_factory.mktemp("rec") / "s.egrec"
    write_session(seq, path, cfg)
    return path


def _check_recording(path, hmd_rate=None, camera_rate=30.0):
    header = read_header(path)
    assert header["has_ground_truth"] is True
    records = list(read_records(path))
    times = [r.t_us for r in records]
    assert times == sorted(times)
    messages = [decode(r.payload) for r in records if r.kind == "c2s"]
    hmd = [m for m in messages if isinstance(m, Hmd)]
    rgbd = [m for m in messages if isinstance(m, Rgbd)]
    truth = {r.payload["seq"]: r.payload for r in records if r.kind == "gt"}
    assert len(messages) == len(hmd) + len(rgbd)
    span_s = (hmd[-1].t_us - hmd[0].t_us) / 1e6
    assert len(hmd) / span_s == pytest.approx(hmd_rate or header["hmd_rate_hz"], rel=0.03)
    assert len(rgbd) / span_s == pytest.approx(camera_rate, rel=0.1)
    assert sorted(truth) == [m.seq for m in hmd]
    for m in hmd[:: max(1, len(hmd) // 10)]:
        gt = truth[m.seq]
        assert gt["t_us"] == m.t_us and len(gt["body_pose"]) == 63 and len(gt["joints"]) == 66
        head_joint = np.array(gt["joints"]).reshape(22, 3)[15]
        assert np.linalg.norm(np.array(m.head[:3]) - head_joint) < 0.2  # the headset is on that head
    return header, hmd, rgbd


def test_synthesised_session_replays_as_protocol_messages(session):
    _, hmd, rgbd = _check_recording(session, hmd_rate=90.0)
    assert rgbd[0].width == 64 and rgbd[0].cam_from_head is not None
    assert [m.seq for m in hmd] == list(range(len(hmd)))


def test_bundled_recordings_are_small_procedural_and_complete():
    paths = bundled()
    assert 2 <= len(paths) <= 3
    assert sum(p.stat().st_size for p in paths) < 10 * 1024 * 1024
    for path in paths:
        header, hmd, _ = _check_recording(path)
        assert header["source"].startswith("procedural:")  # no motion capture inside the package
        assert (hmd[-1].t_us - hmd[0].t_us) / 1e6 <= 15.0


def test_writer_keeps_send_times_monotonic(tmp_path):
    with EgrecWriter(tmp_path / "w.egrec", session="x") as writer:
        writer.message(100, b"\x80")
        writer.message(50, b"\x80")
    assert [r.t_us for r in read_records(tmp_path / "w.egrec")] == [100, 100]


@pytest.mark.parametrize(
    ("content", "needle"),
    [
        (b"", "empty file"),
        (msgpack.packb({"format": "other"}), "not an .egrec"),
        (msgpack.packb({"format": "egrec", "version": 9}), "version 9"),
        (msgpack.packb({"format": "egrec", "version": 1}) + msgpack.packb([1, "c2s"]), "record 0"),
        (
            msgpack.packb({"format": "egrec", "version": 1}) + msgpack.packb([1, "c2s", "text"]),
            "no message bytes",
        ),
        (msgpack.packb({"format": "egrec", "version": 1}) + b"\xc1", "corrupt"),
    ],
)
def test_bad_files_get_a_clear_error(tmp_path, content, needle):
    path = tmp_path / "bad.egrec"
    path.write_bytes(content)
    with pytest.raises(EgrecError, match=needle):
        list(read_records(path))


def test_truncated_recording_fails_at_the_cut(session, tmp_path):
    data = session.read_bytes()
    cut = tmp_path / "cut.egrec"
    cut.write_bytes(data[: len(data) // 2])
    records = read_records(cut)
    delivered = [next(records) for _ in range(10)]  # everything before the cut is delivered
    assert len(delivered) == 10
    with pytest.raises(EgrecError, match="truncated"):
        list(records)
