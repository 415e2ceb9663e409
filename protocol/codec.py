"""msgpack codec: ``encode(msg) -> bytes`` and ``decode(data) -> Message``. Pure: no I/O, no state.

Every way ``decode`` can fail ends in one :class:`ProtocolError` whose ``code`` says which rule broke.
"""

from __future__ import annotations

from typing import Any

import msgpack
from pydantic import ValidationError

from .errors import ErrorCode, ProtocolError
from .messages import MESSAGE_TYPES, PROTOCOL_VERSION, Message

DEFAULT_MAX_MESSAGE_BYTES = 8 * 1024 * 1024
MAX_ARRAY_ITEMS = 4096  # the longest array in v1 has 256 items; anything far beyond is hostile
MAX_MAP_ITEMS = 256
MAX_STR_BYTES = 64 * 1024

# pydantic error types -> protocol error codes; anything unlisted is INVALID_FIELD.
_CODE_BY_PYDANTIC_TYPE: dict[str, ErrorCode] = {
    "missing": ErrorCode.MISSING_FIELD,
    "too_short": ErrorCode.WRONG_LENGTH,
    "too_long": ErrorCode.WRONG_LENGTH,
    "string_too_short": ErrorCode.WRONG_LENGTH,
    "string_too_long": ErrorCode.WRONG_LENGTH,
    "bytes_too_short": ErrorCode.WRONG_LENGTH,
    "finite_number": ErrorCode.NON_FINITE,
    "greater_than": ErrorCode.OUT_OF_RANGE,
    "greater_than_equal": ErrorCode.OUT_OF_RANGE,
    "less_than": ErrorCode.OUT_OF_RANGE,
    "less_than_equal": ErrorCode.OUT_OF_RANGE,
    "out_of_range": ErrorCode.OUT_OF_RANGE,
    "bad_quaternion": ErrorCode.BAD_QUATERNION,
    "bad_transform": ErrorCode.BAD_TRANSFORM,
    "bad_image": ErrorCode.BAD_IMAGE,
}


def encode(msg: Message) -> bytes:
    """Serialise ``msg`` as one msgpack map: floats as float32, bytes as bin, absent optionals omitted."""
    return msgpack.packb(msg.model_dump(exclude_none=True), use_bin_type=True, use_single_float=True)


def decode(data: bytes | bytearray | memoryview, *, max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES) -> Message:
    """Parse and validate one message; raise :class:`ProtocolError` for anything that is not v1.

    ``max_bytes`` bounds the whole message; it is checked before any parsing.
    """
    if not isinstance(data, bytes | bytearray | memoryview):
        raise ProtocolError(ErrorCode.MALFORMED, f"expected binary data, got {type(data).__name__}")
    if len(data) > max_bytes:
        raise ProtocolError(ErrorCode.TOO_LARGE, f"message is {len(data)} bytes, limit is {max_bytes}")
    obj = _unpack(data, max_bytes)
    cls = _message_class(obj)
    try:
        return cls.model_validate(obj)
    except ValidationError as exc:
        raise _protocol_error(cls.TYPE, exc) from None


def _unpack(data: bytes | bytearray | memoryview, max_bytes: int) -> Any:
    try:
        return msgpack.unpackb(
            data,
            raw=False,
            strict_map_key=True,
            use_list=True,
            max_bin_len=max_bytes,
            max_str_len=MAX_STR_BYTES,
            max_array_len=MAX_ARRAY_ITEMS,
            max_map_len=MAX_MAP_ITEMS,
            max_ext_len=0,
        )
    # msgpack signals bad input with several unrelated exception types (ExtraData, FormatError, StackError,
    # ValueError, UnicodeDecodeError, TypeError, ...); every one of them means "not one msgpack value".
    except Exception as exc:
        raise ProtocolError(
            ErrorCode.MALFORMED, f"not a msgpack message: {type(exc).__name__}: {exc}"
        ) from None


def _message_class(obj: Any) -> type[Message]:
    if not isinstance(obj, dict):
        raise ProtocolError(ErrorCode.NOT_A_MAP, f"expected a msgpack map, got {type(obj).__name__}")
    msg_type = obj.get("type")
    if not isinstance(msg_type, str):
        raise ProtocolError(ErrorCode.MISSING_TYPE, f"expected a string field 'type', got {msg_type!r:.60}")
    cls = MESSAGE_TYPES.get(msg_type)
    if cls is None:
        known = ", ".join(sorted(MESSAGE_TYPES))
        raise ProtocolError(ErrorCode.UNKNOWN_TYPE, f"unknown message type {msg_type!r:.60}; v1 has {known}")
    version = obj.get("v")
    if type(version) is not int or version != PROTOCOL_VERSION:
        raise ProtocolError(
            ErrorCode.UNSUPPORTED_VERSION,
            f"{msg_type}: protocol version must be {PROTOCOL_VERSION}, got {version!r:.60}",
        )
    return cls


def _protocol_error(msg_type: str, exc: ValidationError) -> ProtocolError:
    """The first validation failure, as a ProtocolError naming the field, the rule and the value."""
    first = exc.errors(include_url=False)[0]
    code = _CODE_BY_PYDANTIC_TYPE.get(first["type"], ErrorCode.INVALID_FIELD)
    where = ".".join(str(part) for part in first["loc"]) or "message"
    got = "" if first["type"] == "missing" else f" (got {_short_repr(first.get('input'))})"
    more = f"; {exc.error_count() - 1} more" if exc.error_count() > 1 else ""
    return ProtocolError(code, f"{msg_type}.{where}: {first['msg']}{got}{more}")


def _short_repr(value: Any) -> str:
    if isinstance(value, bytes | bytearray):
        return f"{len(value)} bytes"
    if isinstance(value, dict):
        return f"a map of {len(value)} keys"
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."
