"""Bad input over a real socket: each kind gets its error code, the connection survives unless the error is
fatal, and the server keeps serving everyone else. Plus hypothesis fuzzing of raw frames."""

from __future__ import annotations

import threading
import time

import cv2
import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from loopback import Client, example_with, pack, recorded_messages, replay, running_server
from websockets.exceptions import ConnectionClosed

from egoposevr.protocol import Hello, Ping, SelectModel, decode, encode
from egoposevr.protocol.examples import example_messages

EXAMPLES = example_messages()


def _jpeg(w: int, h: int) -> bytes:
    return cv2.imencode(".jpg", np.zeros((h, w, 3), np.uint8))[1].tobytes()


def _png(w: int, h: int) -> bytes:
    return cv2.imencode(".png", np.full((h, w), 1500, np.uint16))[1].tobytes()


def _huge_png_header() -> bytes:
    png = bytearray(_png(4, 2))
    png[16:24] = (60000).to_bytes(4, "big") * 2  # the header claims 60000 × 60000 pixels
    return bytes(png)


HEAD_NAN = [0.0, float("nan"), 0.0, 0.0, 0.0, 0.0, 1.0]
NOT_RIGID = [2.0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]

# (what, frame sent by the input client, expected code). None of these is fatal.
NON_FATAL = [
    ("not msgpack", b"\xc1", "malformed"),
    ("trailing bytes", encode(Ping()) + b"\x00", "malformed"),
    ("text frame", "hello", "malformed"),
    ("ext type", pack(msgpack.ExtType(1, b"x")), "malformed"),
    ("array", pack([1, 2, 3]), "not_a_map"),
    ("no type", pack({"v": 1}), "missing_type"),
    ("unknown type", pack({"type": "dance", "v": 1}), "unknown_type"),
    ("version 2", pack({"type": "ping", "v": 2}), "unsupported_version"),
    ("hmd without head", example_with("hmd", head=None), "missing_field"),
    ("head as text", example_with("hmd", head="up"), "invalid_field"),
    ("bool as float", example_with("hmd", head=[True] * 7), "invalid_field"),
    ("six numbers", example_with("hmd", head=[0.0] * 6), "wrong_length"),
    ("NaN", example_with("hmd", head=HEAD_NAN), "non_finite"),
    ("negative seq", example_with("hmd", seq=-1), "out_of_range"),
    ("100 km away", example_with("hmd", head=[1e5, 0, 0, 0, 0, 0, 1.0]), "out_of_range"),
    ("non-unit quaternion", example_with("hmd", head=[0, 1.6, 0, 0, 0, 0, 2.0]), "bad_quaternion"),
    ("camera not rigid", example_with("rgbd", cam_from_head=NOT_RIGID), "bad_transform"),
    ("rgb not JPEG", example_with("rgbd", rgb=b"GIF89a"), "bad_image"),
    ("width 0", example_with("rgbd", width=0), "out_of_range"),
    ("JPEG that does not decode", example_with("rgbd", rgb=b"\xff\xd8\xff" + b"\x00" * 64), "image_decode"),
    ("size disagrees", example_with("rgbd", rgb=_jpeg(8, 6), depth=_png(8, 6)), "image_decode"),
    ("header claims 60000²", example_with("rgbd", depth=_huge_png_header()), "image_decode"),
    ("a server message", encode(EXAMPLES["pose"]), "unexpected_message"),
    ("second hello", encode(Hello(role="input", session="bad")), "already_greeted"),
    ("unknown model", encode(SelectModel(model="nope")), "unknown_model"),
]


def test_every_kind_of_bad_input_gets_its_error_and_the_connection_survives(server):
    with Client(server.url, "bad") as headset:
        headset.hello("input", "bad", model="hmd-rgbd")
        for what, frame, code in NON_FATAL:
            headset.send(frame)
            error = headset.recv_type("error")
            assert (error.code, error.fatal) == (code, False), what
            assert error.message, what
            headset.send(Ping(nonce=1))
            assert headset.recv_type("pong").nonce == 1, what  # still connected
        # after all that, the session still answers
        headset.collect()
        sent = replay(headset, recorded_messages("walk-0000", limit=40))
        headset.wait_for(lambda: {p.seq for p in headset.poses()} & set(sent))


def test_errors_name_the_offending_seq_and_count_in_metrics(server):
    before = server.metric("egoposevr_errors_total", code="image_decode")
    with Client(server.url, "seqs") as headset:
        headset.hello("input", "seqs", model="hmd-rgbd")
        headset.send(example_with("rgbd", seq=77, rgb=_jpeg(8, 6), depth=_png(8, 6)))
        error = headset.recv_type("error")
        assert (error.code, error.seq) == ("image_decode", 77)
        assert "8x6" in error.message and "4x2" in error.message
    assert server.metric("egoposevr_errors_total", code="image_decode") == before + 1


def test_a_render_client_may_not_send_headset_data_but_may_switch_models(server):
    with Client(server.url, "roles") as viewer:
        viewer.hello("render", "roles")
        for msg in (EXAMPLES["hmd"], EXAMPLES["rgbd"]):
            viewer.send(msg)
            assert viewer.recv_type("error").code == "wrong_role"
        viewer.send(SelectModel(model="hmd"))
        assert viewer.recv_type("models").active == "hmd"
        viewer.send(Ping(nonce=2))
        assert viewer.recv_type("pong").nonce == 2


def _fatal(client: Client, code: str, close_code: int) -> None:
    error = client.recv_type("error")
    assert (error.code, error.fatal) == (code, True)
    with pytest.raises(ConnectionClosed) as closed:
        client.recv(timeout=5)
    assert closed.value.rcvd.code == close_code


def test_fatal_faults_close_with_their_code(server):
    with Client(server.url, "fatal") as first:
        first.send(Ping())
        _fatal(first, "handshake_required", 1008)
    with Client(server.url, "fatal") as garbage_first:
        garbage_first.send(b"\xc1")
        _fatal(garbage_first, "handshake_required", 1008)
    with Client(server.url, "elsewhere") as mismatch:
        mismatch.send(Hello(role="render", session="fatal"))
        _fatal(mismatch, "invalid_field", 1008)
    with Client(server.url, "busy") as one, Client(server.url, "busy") as two:
        one.hello("input", "busy")
        two.send(Hello(role="input", session="busy"))
        _fatal(two, "session_busy", 1008)
    with Client(server.url, "big") as big:
        big.hello("input", "big")
        big.send(example_with("rgbd", rgb=b"\xff\xd8\xff" + bytes(server.config.max_message_bytes)))
        _fatal(big, "too_large", 1009)


def test_limits_token_sessions_rate_and_hello_timeout():
    config = {
        "token": "s3cret",
        "max_sessions": 1,
        "rate_limit_hz": 50,
        "rate_burst": 10,
        "hello_timeout_s": 0.3,
    }
    with running_server(**config) as server:
        with Client(server.url) as intruder:
            intruder.send(Hello(role="input", session="a", token="guess"))
            _fatal(intruder, "auth_failed", 1008)
        with Client(server.url) as slow:
            time.sleep(0.5)
            _fatal(slow, "handshake_required", 1008)
        with Client(server.url) as first, Client(server.url) as second:
            first.hello("input", "a", token="s3cret")
            second.send(Hello(role="input", session="b", token="s3cret"))
            _fatal(second, "server_full", 1013)
            for _ in range(40):  # a flood: 40 at once against a burst of 10
                first.send(Ping())
            assert first.recv_type("error").code == "rate_limited"
            assert server.metric("egoposevr_rate_limited_messages_total") >= 25
            time.sleep(0.3)  # the bucket refills
            first.send(Ping(nonce=9))
            assert first.recv_type("pong").nonce == 9


def test_bad_clients_do_not_disturb_a_good_headset(server):
    """A headset streams while another connection sprays garbage: every one of its samples is answered, in
    order, and none of the sprayer's errors reaches it. The headset sends in lockstep (the next sample once the
    last is answered) so that the server never has a reason to skip one; how fast a loaded machine answers is
    the bench's business, not this test's."""
    stop = threading.Event()
    spray_errors = []

    def spray() -> None:
        with Client(server.url, "spray") as bad:
            bad.hello("input", "spray")
            bad.collect()
            frames = [f for _, f, _ in NON_FATAL]
            while not stop.is_set():
                for frame in frames:
                    bad.send(frame)
                time.sleep(0.01)
            spray_errors.extend(m for _, m in bad.received if m.type == "error")

    sprayer = threading.Thread(target=spray)
    sprayer.start()
    try:
        with Client(server.url, "good") as headset:
            headset.hello("input", "good", model="hmd")
            headset.collect()
            sent = []

            def all_answered() -> bool:
                return len(headset.poses()) >= len(sent)

            for _, kind, data in recorded_messages("walk-0000", limit=200):
                headset.send(data)
                if kind == "hmd":
                    sent.append(decode(data).seq)
                    headset.wait_for(all_answered, timeout=10.0)
            assert [p.seq for p in headset.poses()] == sent
            assert not any(p.skipped for p in headset.poses())
            assert [m for _, m in headset.received if m.type == "error"] == []
    finally:
        stop.set()
        sprayer.join()
    assert spray_errors, "the sprayer was answered with errors while the headset streamed"


@pytest.fixture(scope="module")
def fuzz_client(server):
    with Client(server.url, "fuzz") as client:
        client.hello("input", "fuzz", model="hmd")
        yield client


msgpack_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats()
    | st.text(max_size=20)
    | st.binary(max_size=40),
    lambda inner: st.lists(inner, max_size=8) | st.dictionaries(st.text(max_size=10), inner, max_size=8),
    max_leaves=30,
)
message_like = st.fixed_dictionaries(
    {"type": st.sampled_from(["hmd", "rgbd", "ping", "hello", "select_model", "pose", "list_models"]),
     "v": st.sampled_from([1, 1, 2])},
    optional={"seq": msgpack_values, "t_us": msgpack_values, "head": msgpack_values, "valid": msgpack_values,
              "rgb": msgpack_values, "width": msgpack_values, "model": msgpack_values},
)  # fmt: skip


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(frame=st.binary(max_size=200) | message_like.map(pack) | msgpack_values.map(pack))
def test_fuzzed_frames_never_break_the_connection(fuzz_client, frame):
    fuzz_client.send(frame)
    fuzz_client.send(Ping(nonce=123))
    deadline = time.monotonic() + 5
    while True:  # whatever the frame caused (an error, a pose, models), the pong must follow
        msg = fuzz_client.recv(max(deadline - time.monotonic(), 0.01))
        assert not (msg.type == "error" and msg.fatal), msg
        if msg.type == "pong" and msg.nonce == 123:
            break
