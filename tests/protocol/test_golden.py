"""The golden fixtures pin the v1 wire bytes: every message type encodes to, and decodes from, its file."""

from pathlib import Path

import pytest

from egoposevr.protocol import MESSAGE_TYPES, decode, encode
from egoposevr.protocol.examples import example_messages

GOLDEN = Path(__file__).parent / "golden"
EXAMPLES = example_messages()


def test_every_message_type_has_an_example_and_a_fixture():
    assert set(EXAMPLES) == set(MESSAGE_TYPES)
    assert {p.stem for p in GOLDEN.glob("*.msgpack")} == set(MESSAGE_TYPES)


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_encode_reproduces_the_golden_bytes(name):
    assert encode(EXAMPLES[name]) == (GOLDEN / f"{name}.msgpack").read_bytes()


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_decode_of_the_golden_bytes_gives_the_example(name):
    decoded = decode((GOLDEN / f"{name}.msgpack").read_bytes())
    assert decoded == EXAMPLES[name]
    assert type(decoded) is MESSAGE_TYPES[name]


def test_type_is_the_first_key_and_floats_are_float32():
    data = (GOLDEN / "hmd.msgpack").read_bytes()
    assert data.startswith(b"\x88\xa4type\xa3hmd\xa1v\x01")
    assert b"\xcb" not in data  # no float64 marker anywhere in a pose-carrying message
