"""decode accepts what clients in other languages send and refuses bad input with a precise code."""

import math

import msgpack
import pytest

from egoposevr.protocol import ErrorCode, Hmd, Pose, ProtocolError, decode, encode
from egoposevr.protocol.examples import EXAMPLE_DEPTH_PNG, EXAMPLE_JPEG, example_messages

EX = example_messages()


def pack(obj) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def as_map(name: str, **changes) -> dict:
    """The example message `name` as a plain map, with fields changed (None deletes)."""
    obj = msgpack.unpackb(encode(EX[name]), raw=False)
    for key, value in changes.items():
        if value is None:
            obj.pop(key, None)
        else:
            obj[key] = value
    return obj


def test_integers_and_float64_are_accepted_in_float_fields():
    # JavaScript msgpack encoders write 1.0 as the integer 1; C# may write doubles.
    obj = as_map("hmd", head=[0, 2, 0, 0, 0, 0, 1], left=[0.5, 1.0, 0.1, 0.0, 0.0, 0.0, 1.0])
    msg = decode(msgpack.packb(obj, use_single_float=False))
    assert isinstance(msg, Hmd)
    assert msg.head == [0.0, 2.0, 0.0, 0.0, 0.0, 0.0, 1.0]
    assert msg.left[2] == 0.1


def test_unknown_fields_are_ignored_and_optional_fields_may_be_nil():
    msg = decode(
        pack(as_map("hello", extra_field={"anything": [1, 2]}, model=None, token=None) | {"client": None})
    )
    assert msg.model is None
    assert msg.client is None


def test_encode_omits_absent_optionals():
    obj = msgpack.unpackb(encode(EX["hello"].model_copy(update={"token": None})), raw=False)
    assert "token" not in obj


def test_memoryview_and_bytearray_inputs_decode():
    data = encode(EX["pose"])
    assert decode(memoryview(data)) == decode(bytearray(data)) == EX["pose"]


def test_untracked_device_may_carry_a_zero_quaternion():
    msg = decode(pack(as_map("hmd", right=[0.0] * 7)))
    assert msg.valid[2] is False


def test_pose_round_trip_keeps_float32_values_exactly():
    pose = Pose(
        seq=1, t_us=2, model="hmd", global_orient=[0.1, 0.2, 0.3], body_pose=[0.0] * 63,
        transl=[0.0, 0.9, 0.0], joints=[0.5] * 66, timing_us={"total": 1},
    )  # fmt: skip
    back = decode(encode(pose))
    assert back.global_orient == pytest.approx([0.1, 0.2, 0.3], rel=1e-7)  # float32 on the wire
    assert back.joints == pose.joints


BAD_INPUTS = {
    "empty bytes": (b"", ErrorCode.MALFORMED),
    "truncated msgpack": (encode(EX["hmd"])[:-5], ErrorCode.MALFORMED),
    "trailing garbage": (encode(EX["ping"]) + b"\x00", ErrorCode.MALFORMED),
    "invalid utf-8 string": (b"\x81\xa4type\xa2\xff\xfe", ErrorCode.MALFORMED),
    "extension type": (b"\x81\xa4type\xd4\x01\x00", ErrorCode.MALFORMED),
    "top-level array": (pack([1, 2, 3]), ErrorCode.NOT_A_MAP),
    "top-level int": (pack(5), ErrorCode.NOT_A_MAP),
    "integer map keys": (b"\x81\x01\x02", ErrorCode.MALFORMED),
    "no type": (pack({"v": 1}), ErrorCode.MISSING_TYPE),
    "type not a string": (pack({"type": 3, "v": 1}), ErrorCode.MISSING_TYPE),
    "unknown type": (pack({"type": "teleport", "v": 1}), ErrorCode.UNKNOWN_TYPE),
    "version 2": (pack(as_map("hmd", v=2)), ErrorCode.UNSUPPORTED_VERSION),
    "version missing": (pack(as_map("hmd", v=None)), ErrorCode.UNSUPPORTED_VERSION),
    "version as bool": (pack(as_map("hmd", v=True)), ErrorCode.UNSUPPORTED_VERSION),
    "missing seq": (pack(as_map("hmd", seq=None)), ErrorCode.MISSING_FIELD),
    "head too short": (pack(as_map("hmd", head=[0.0] * 6)), ErrorCode.WRONG_LENGTH),
    "joints too long": (pack(as_map("pose", joints=[0.0] * 67)), ErrorCode.WRONG_LENGTH),
    "NaN position": (pack(as_map("hmd", head=[math.nan, 1, 0, 0, 0, 0, 1])), ErrorCode.NON_FINITE),
    "infinite joint": (pack(as_map("pose", joints=[math.inf] + [0.0] * 65)), ErrorCode.NON_FINITE),
    "string in a float array": (pack(as_map("hmd", head=["0", 1, 0, 0, 0, 0, 1])), ErrorCode.INVALID_FIELD),
    "bool in a float array": (pack(as_map("hmd", head=[True, 1, 0, 0, 0, 0, 1])), ErrorCode.INVALID_FIELD),
    "valid flags as ints": (pack(as_map("hmd", valid=[1, 1, 1])), ErrorCode.INVALID_FIELD),
    "negative seq": (pack(as_map("hmd", seq=-1)), ErrorCode.OUT_OF_RANGE),
    "seq beyond int63": (pack(as_map("hmd", seq=2**64 - 1)), ErrorCode.OUT_OF_RANGE),
    "float seq": (pack(as_map("hmd", seq=1.5)), ErrorCode.INVALID_FIELD),
    "position 1e6 m away": (pack(as_map("hmd", head=[1e6, 1, 0, 0, 0, 0, 1])), ErrorCode.OUT_OF_RANGE),
    "zero quaternion on a tracked head": (pack(as_map("hmd", head=[0, 1, 0, 0, 0, 0, 0])), ErrorCode.BAD_QUATERNION),
    "unknown role": (pack(as_map("hello", role="admin")), ErrorCode.INVALID_FIELD),
    "session with a slash": (pack(as_map("hello", session="../etc")), ErrorCode.INVALID_FIELD),
    "empty session": (pack(as_map("hello", session="")), ErrorCode.WRONG_LENGTH),
    "rgb sent as str": (pack(as_map("rgbd", rgb="not bytes")), ErrorCode.INVALID_FIELD),
    "rgb is a PNG": (pack(as_map("rgbd", rgb=EXAMPLE_DEPTH_PNG)), ErrorCode.BAD_IMAGE),
    "depth is a JPEG": (pack(as_map("rgbd", depth=EXAMPLE_JPEG)), ErrorCode.BAD_IMAGE),
    "empty rgb": (pack(as_map("rgbd", rgb=b"")), ErrorCode.WRONG_LENGTH),
    "width 0": (pack(as_map("rgbd", width=0)), ErrorCode.OUT_OF_RANGE),
    "width 100000": (pack(as_map("rgbd", width=100_000)), ErrorCode.OUT_OF_RANGE),
    "negative focal length": (pack(as_map("rgbd", intrinsics=[-2.0, 2.0, 2.0, 1.0])), ErrorCode.OUT_OF_RANGE),
    "cam_from_head not rigid": (pack(as_map("rgbd", cam_from_head=[2.0] + [0.0] * 14 + [1.0])), ErrorCode.BAD_TRANSFORM),
    "timing value negative": (pack(as_map("pose", timing_us={"total": -1})), ErrorCode.OUT_OF_RANGE),
    "huge array header": (b"\x81\xa4type\xdd\xff\xff\xff\xff", ErrorCode.MALFORMED),
    "deep nesting": (b"\x91" * 5000, ErrorCode.MALFORMED),
}  # fmt: skip


@pytest.mark.parametrize("name", sorted(BAD_INPUTS))
def test_bad_input_raises_protocol_error_with_its_code(name):
    data, code = BAD_INPUTS[name]
    with pytest.raises(ProtocolError) as info:
        decode(data)
    assert info.value.code == code, info.value.message
    assert info.value.message  # says what was expected


def test_oversized_message_is_refused_before_parsing():
    with pytest.raises(ProtocolError) as info:
        decode(b"\x00" * 101, max_bytes=100)
    assert info.value.code == ErrorCode.TOO_LARGE
    assert "101" in info.value.message and "100" in info.value.message


def test_non_bytes_input_is_refused():
    with pytest.raises(ProtocolError) as info:
        decode("a string")  # type: ignore[arg-type]
    assert info.value.code == ErrorCode.MALFORMED


def test_error_message_names_the_field_and_the_value():
    with pytest.raises(ProtocolError) as info:
        decode(pack(as_map("hmd", left=[0.0, 1.0, 0.0, 0.0, 0.0, math.nan, 1.0])))
    assert (
        info.value.message
        == "hmd.left[5]: expected a finite number for a tracked device (valid is true), got nan"
    )
    assert (info.value.ref_type, info.value.ref_seq) == ("hmd", 42)


def test_pose_camera_flag_is_optional_and_round_trips():
    from egoposevr.protocol import decode, encode
    from egoposevr.protocol.examples import example_messages

    pose = example_messages()["pose"]
    assert pose.camera is None and b"camera" not in encode(pose)  # v1 bytes unchanged when absent
    for flag in (True, False):
        assert decode(encode(pose.model_copy(update={"camera": flag}))).camera is flag
