"""msgpack codec: ``encode(msg) -> bytes`` and ``decode(data) -> Message``. Pure: no I/O, no state.

Every way ``decode`` can fail ends in one :class:`ProtocolError` whose ``code`` says which rule broke.
"""

from __future__ import annotations

from typing import Any, get_args

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

    ``max_bytes`` bounds the whole message; it is checked before any parsing. Once the bytes are one msgpack
    map, the error carries the message's ``type`` and ``seq`` where they are readable (``ref_type``,
    ``ref_seq``), so that a client learns which of its messages was refused.
    """
    if not isinstance(data, bytes | bytearray | memoryview):
        raise ProtocolError(ErrorCode.MALFORMED, f"expected binary data, got {type(data).__name__}")
    if len(data) > max_bytes:
        raise ProtocolError(ErrorCode.TOO_LARGE, f"message is {len(data)} bytes, limit is {max_bytes}")
    obj = _unpack(data, max_bytes)
    ref_type, ref_seq = _readable_ref(obj)
    try:
        cls = _message_class(obj)
        return cls.model_validate(obj)
    except ValidationError as exc:
        error = _protocol_error(cls.TYPE, exc)
    except ProtocolError as exc:
        error = exc
    error.ref_type, error.ref_seq = ref_type, ref_seq
    raise error


def decode_from_server(
    data: bytes | bytearray | memoryview, *, max_bytes: int = DEFAULT_MAX_MESSAGE_BYTES
) -> Message | None:
    """``decode`` for clients: None for a message type this version does not know, which a client must ignore
    (PROTOCOL.md §9: later v1 servers may send new types); every other problem raises as ``decode`` does."""
    try:
        return decode(data, max_bytes=max_bytes)
    except ProtocolError as exc:
        if exc.code is ErrorCode.UNKNOWN_TYPE:
            return None
        raise


def _readable_ref(obj: Any) -> tuple[str | None, int | None]:
    """The message's ``type`` (a string of at most 64 characters) and ``seq`` (0 <= seq < 2^63), if readable."""
    if not isinstance(obj, dict):
        return None, None
    msg_type, seq = obj.get("type"), obj.get("seq")
    ref_type = msg_type if isinstance(msg_type, str) and 0 < len(msg_type) <= 64 else None
    ref_seq = seq if type(seq) is int and 0 <= seq < 2**63 else None
    return ref_type, ref_seq


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
        raise ProtocolError(ErrorCode.MALFORMED, f"not one msgpack value: {_unpack_reason(exc)}") from None


def _unpack_reason(exc: Exception) -> str:
    """What msgpack's exception means, in words (several of them carry no text)."""
    name = type(exc).__name__
    if "incomplete input" in str(exc):
        return "the data ends in the middle of a value (truncated)"
    reasons = {
        "ExtraData": "bytes follow the end of the message (send one map per WebSocket frame)",
        "OutOfData": "the data ends in the middle of a value (truncated)",
        "FormatError": "a byte that starts no msgpack value (corrupt or not msgpack)",
        "StackError": "values nested too deeply",
        "UnicodeDecodeError": "a string that is not UTF-8",
    }
    detail = str(exc).strip()
    if name in reasons:
        return reasons[name]
    if "ExtType" in detail or "ext" in detail.lower():
        return "an extension type (msgpack ext/timestamp values are not allowed)"
    return f"{detail} ({name})" if detail else name


def _message_class(obj: Any) -> type[Message]:
    if not isinstance(obj, dict):
        raise ProtocolError(ErrorCode.NOT_A_MAP, f"expected a msgpack map, got {_kind(obj)}")
    msg_type = obj.get("type")
    if not isinstance(msg_type, str):
        raise ProtocolError(
            ErrorCode.MISSING_TYPE, f"expected a string field 'type' first in the map, got {_value(msg_type)}"
        )
    cls = MESSAGE_TYPES.get(msg_type)
    if cls is None:
        known = ", ".join(sorted(MESSAGE_TYPES))
        raise ProtocolError(
            ErrorCode.UNKNOWN_TYPE, f"unknown message type {_value(msg_type)}; v1 has {known}"
        )
    version = obj.get("v")
    if type(version) is not int or version != PROTOCOL_VERSION:
        raise ProtocolError(
            ErrorCode.UNSUPPORTED_VERSION,
            f"{msg_type}.v: expected the integer {PROTOCOL_VERSION}, got {_value(version)}",
        )
    return cls


def _protocol_error(msg_type: str, exc: ValidationError) -> ProtocolError:
    """The first validation failure, as a ProtocolError naming the field as PROTOCOL.md does, what was
    expected and what came."""
    first = exc.errors(include_url=False)[0]
    code = _CODE_BY_PYDANTIC_TYPE.get(first["type"], ErrorCode.INVALID_FIELD)
    where = _field_path(first["loc"])
    # Our own checks across fields have no location: their text starts with the field's name.
    text = f"{msg_type}.{first['msg']}" if not where else f"{msg_type}.{where}: {_expected(first, msg_type)}"
    more = exc.error_count() - 1
    return ProtocolError(code, text + (f" ({more} more problem{'s' * (more > 1)})" if more else ""))


def _field_path(loc: tuple[Any, ...]) -> str:
    """('head', 5) -> 'head[5]'; ('models', 0, 'name') -> 'models[0].name'."""
    path = ""
    for part in loc:
        path += f"[{part}]" if isinstance(part, int) else (f".{part}" if path else str(part))
    return path


_EXPECTED: dict[str, str] = {
    "float_type": "expected a number (float32, float64 or an integer)",
    "int_type": "expected an integer",
    "bool_type": "expected true or false",
    "string_type": "expected a string",
    "bytes_type": "expected binary data (msgpack bin, not str)",
    "list_type": "expected an array",
    "dict_type": "expected a map",
    "finite_number": "expected a finite number",
    "string_pattern_mismatch": "expected a name of letters, digits and _ . : - (1 to 64 characters)",
}


def _length_bounds(msg_type: str, loc: tuple[Any, ...]) -> tuple[int | None, int | None]:
    """(min, max) length a top-level field of ``msg_type`` allows, from its declaration (optional or not)."""
    field = MESSAGE_TYPES[msg_type].model_fields.get(str(loc[0])) if loc else None
    if field is None:
        return None, None
    low = high = None
    todo: list[Any] = [*field.metadata, field.annotation]
    while todo:
        item = todo.pop()
        low = getattr(item, "min_length", low) if not isinstance(item, type) else low
        high = getattr(item, "max_length", high) if not isinstance(item, type) else high
        todo += [a for a in get_args(item) if a is not None]
        todo += list(getattr(item, "__metadata__", ()))
    return low, high


def _expected(error: dict[str, Any], msg_type: str) -> str:
    """'expected ..., got ...' for one pydantic error, in the words of PROTOCOL.md."""
    kind, ctx, value = error["type"], error.get("ctx") or {}, error.get("input")
    if kind == "missing":
        return "required, but absent"
    if kind in ("too_short", "too_long", "string_too_short", "string_too_long"):
        low, high = _length_bounds(msg_type, error["loc"]) if len(error["loc"]) == 1 else (None, None)
        low, high = ctx.get("min_length", low), ctx.get("max_length", high)
        want = f"exactly {low}" if low == high else f"{low or 0} to {high}" if high else f"at least {low}"
        unit = "characters" if kind.startswith("string") else "items"
        return f"expected {want} {unit}, got {ctx.get('actual_length', len(value) if hasattr(value, '__len__') else '?')}"
    if kind == "bytes_too_short":
        return "expected at least one byte, got none"
    if kind == "literal_error":
        return f"expected one of {ctx.get('expected')}, got {_value(value)}"
    bounds = {"greater_than": ">", "greater_than_equal": ">=", "less_than": "<", "less_than_equal": "<="}
    if kind in bounds:
        limit = next(iter(ctx.values()), "?")
        return f"expected a value {bounds[kind]} {limit}, got {_value(value)}"
    return f"{_EXPECTED.get(kind, error['msg'])}, got {_value(value)}"


def _kind(value: Any) -> str:
    names = {bool: "a boolean", int: "an integer", float: "a float", str: "a string", bytes: "binary data"}
    names |= {list: "an array", dict: "a map", type(None): "nil"}
    return names.get(type(value), type(value).__name__)


def _value(value: Any) -> str:
    """A short description of what came: its msgpack kind and, when short, its value."""
    if isinstance(value, bytes | bytearray):
        return f"{len(value)} bytes of binary data"
    if isinstance(value, dict):
        return f"a map of {len(value)} keys"
    if isinstance(value, list):
        return f"an array of {len(value)} items"
    if value is None:
        return "nil"
    text = repr(value)
    return f"{_kind(value)} {text if len(text) <= 60 else text[:57] + '...'}"
