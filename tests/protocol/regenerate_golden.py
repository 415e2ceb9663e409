"""Rewrite the golden fixtures from protocol/examples.py. Run only when the wire format changes on purpose,
and say so in PROTOCOL.md's change log: every client in the field reads these bytes."""

from pathlib import Path

from egoposevr.protocol import encode
from egoposevr.protocol.examples import example_messages, openxr_examples

GOLDEN = Path(__file__).parent / "golden"
OPENXR = Path(__file__).parent / "openxr"

if __name__ == "__main__":
    GOLDEN.mkdir(exist_ok=True)
    for name, msg in example_messages().items():
        (GOLDEN / f"{name}.msgpack").write_bytes(encode(msg))
        print(GOLDEN / f"{name}.msgpack")
    OPENXR.mkdir(exist_ok=True)
    for name, msg in openxr_examples().items():
        (OPENXR / f"{name}.msgpack").write_bytes(encode(msg))
        print(OPENXR / f"{name}.msgpack")
