"""Fuzzing: whatever bytes arrive, decode returns a Message or raises ProtocolError — nothing else."""

import msgpack
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from egoposevr.protocol import MESSAGE_TYPES, Hmd, Message, ProtocolError, decode, encode
from egoposevr.protocol.examples import example_messages

GOLDEN_BYTES = [encode(m) for m in example_messages().values()]
FUZZ = settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def decode_or_protocol_error(data: bytes) -> None:
    try:
        assert isinstance(decode(data), Message)
    except ProtocolError as exc:
        assert exc.message


@FUZZ
@given(st.binary(max_size=512))
def test_random_bytes(data):
    decode_or_protocol_error(data)


@st.composite
def mutated_golden(draw):
    data = bytearray(draw(st.sampled_from(GOLDEN_BYTES)))
    for _ in range(draw(st.integers(1, 8))):
        op = draw(st.sampled_from(["flip", "insert", "delete", "truncate"]))
        pos = draw(st.integers(0, max(len(data) - 1, 0)))
        if op == "flip" and data:
            data[pos] ^= draw(st.integers(1, 255))
        elif op == "insert":
            data[pos:pos] = draw(st.binary(min_size=1, max_size=4))
        elif op == "delete" and data:
            del data[pos]
        else:
            data = data[:pos]
    return bytes(data)


@FUZZ
@given(mutated_golden())
def test_mutated_golden_messages(data):
    decode_or_protocol_error(data)


msgpack_values = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats() | st.text(max_size=8)
    | st.binary(max_size=8),
    lambda children: st.lists(children, max_size=8) | st.dictionaries(st.text(max_size=8), children, max_size=6),
    max_leaves=30,
)  # fmt: skip


@FUZZ
@given(
    st.sampled_from(sorted(MESSAGE_TYPES)), st.dictionaries(st.text(max_size=12), msgpack_values, max_size=10)
)
def test_well_framed_maps_with_random_fields(msg_type, fields):
    decode_or_protocol_error(msgpack.packb({"type": msg_type, "v": 1, **fields}, use_bin_type=True))


f32 = st.floats(-100, 100, width=32)


@st.composite
def hmd_messages(draw):
    def device():
        quat = draw(st.lists(st.floats(-1, 1, width=32), min_size=4, max_size=4))
        norm = sum(q * q for q in quat) ** 0.5
        quat = [0.0, 0.0, 0.0, 1.0] if norm < 0.5 else [q / norm for q in quat]
        return [*draw(st.lists(f32, min_size=3, max_size=3)), *quat]

    return Hmd(
        seq=draw(st.integers(0, 2**63 - 1)), t_us=draw(st.integers(0, 2**63 - 1)),
        head=device(), left=device(), right=device(), valid=draw(st.lists(st.booleans(), min_size=3, max_size=3)),
    )  # fmt: skip


@FUZZ
@given(hmd_messages())
def test_hmd_round_trip(msg):
    back = decode(encode(msg))
    # Positions are float32-exact by construction; normalised quaternions lose their float64 tail.
    assert back.seq == msg.seq and back.t_us == msg.t_us and back.valid == msg.valid
    for a, b in zip(back.poses(), msg.poses(), strict=True):
        assert a[:3] == b[:3]
        assert max(abs(x - y) for x, y in zip(a[3:], b[3:], strict=True)) < 1e-7
