"""The project's error root, the wire protocol's error type, and the vocabulary of error codes.

Exception tree (the protocol is the lowest package, so the root lives here)::

    Exception
    └── EgoPoseError           the project's own errors
        └── InputError         (also a ValueError) what a client sent cannot be used: the client's fault.
            │                  The server answers it with an ``error`` reply and goes on; anything else
            │                  that escapes a run is ours: logged once with its traceback, ``internal``.
            └── ProtocolError  .code: ErrorCode, .message: str, .fatal: bool
                               raised by decode() for anything malformed; the server turns it into an
                               ``error`` message with the same code, so clients see one vocabulary.

Codes the protocol itself raises are marked (P) below; the rest are raised by the server (issue: server) and
live here so that there is exactly one table, mirrored in PROTOCOL.md.
"""

from __future__ import annotations

from enum import StrEnum


class ErrorCode(StrEnum):
    """Machine-readable error codes carried by ``error`` messages (see PROTOCOL.md §Errors)."""

    # -- raised by decode() (P) --
    TOO_LARGE = "too_large"  # (P) the message exceeds the size limit
    MALFORMED = "malformed"  # (P) the bytes are not one msgpack value
    NOT_A_MAP = "not_a_map"  # (P) the top-level value is not a map with string keys
    MISSING_TYPE = "missing_type"  # (P) no "type" string
    UNKNOWN_TYPE = "unknown_type"  # (P) "type" names no v1 message
    UNSUPPORTED_VERSION = "unsupported_version"  # (P) "v" is missing or not 1
    MISSING_FIELD = "missing_field"  # (P) a required field is absent
    INVALID_FIELD = "invalid_field"  # (P) a field has the wrong type
    WRONG_LENGTH = "wrong_length"  # (P) an array or string has the wrong length
    NON_FINITE = "non_finite"  # (P) a float is NaN or infinite
    OUT_OF_RANGE = "out_of_range"  # (P) a number is outside its allowed range
    BAD_QUATERNION = "bad_quaternion"  # (P) a tracked device's quaternion is far from unit length
    BAD_TRANSFORM = "bad_transform"  # (P) cam_from_head is not a rigid transform
    BAD_IMAGE = "bad_image"  # (P) rgb is not JPEG or depth is not PNG (by signature)
    # -- raised by the server --
    HANDSHAKE_REQUIRED = "handshake_required"  # the first message was not hello
    ALREADY_GREETED = "already_greeted"  # a second hello on the same connection
    AUTH_FAILED = "auth_failed"  # missing or wrong token (fatal)
    WRONG_ROLE = "wrong_role"  # e.g. a render client sent hmd
    SESSION_BUSY = "session_busy"  # the session already has an input client (fatal)
    SERVER_FULL = "server_full"  # max sessions reached (fatal)
    UNKNOWN_MODEL = "unknown_model"  # select_model / hello named no loaded model
    IMAGE_DECODE = "image_decode"  # JPEG/PNG did not decode, or its size disagrees with width/height
    RATE_LIMITED = "rate_limited"  # the per-session message-rate cap was exceeded
    UNEXPECTED_MESSAGE = "unexpected_message"  # a server-to-client type sent by a client
    INTERNAL = "internal"  # a bug on the server; the message says what was being done
    SHUTTING_DOWN = "shutting_down"  # the server is stopping (fatal)


class EgoPoseError(Exception):
    """The root of the project's own errors."""


class InputError(EgoPoseError, ValueError):
    """Input that cannot be used (a wrong shape, a non-finite number, an image that does not decode): the
    sender's fault, reported to it. A ValueError too, so library callers can catch it as one."""


class ProtocolError(InputError):
    """A message that does not follow protocol v1.

    ``code`` is machine-readable (an :class:`ErrorCode`), ``message`` says what was expected and what came.
    ``ref_type`` / ``ref_seq``: the offending message's ``type`` and ``seq`` where they could be read (a
    message refused for one bad field still says which message it was), else None.
    """

    def __init__(
        self,
        code: ErrorCode,
        message: str,
        *,
        fatal: bool = False,
        ref_type: str | None = None,
        ref_seq: int | None = None,
    ) -> None:
        super().__init__(f"{code}: {message}")
        self.code = ErrorCode(code)
        self.message = message
        self.fatal = fatal
        self.ref_type = ref_type
        self.ref_seq = ref_seq
