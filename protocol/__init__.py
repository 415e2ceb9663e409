"""EgoPoseVR wire protocol v1: message models, msgpack codec, errors. Pure: no I/O, no asyncio, no numpy.

>>> from egoposevr.protocol import Ping, decode, encode
>>> decode(encode(Ping(nonce=1))).nonce
1
"""

from .codec import DEFAULT_MAX_MESSAGE_BYTES, decode, decode_from_server, encode
from .errors import EgoPoseError, ErrorCode, InputError, ProtocolError
from .messages import (
    CLIENT_MESSAGES,
    MESSAGE_TYPES,
    PROTOCOL_VERSION,
    SERVER_MESSAGES,
    Body,
    Calibrate,
    Calibration,
    Error,
    GetBody,
    Hello,
    Hmd,
    ListModels,
    Message,
    ModelInfo,
    Models,
    Ping,
    Pong,
    Pose,
    Ref,
    Rgbd,
    SelectModel,
    SessionStatus,
    SetBody,
    Welcome,
)

__all__ = [
    "CLIENT_MESSAGES",
    "DEFAULT_MAX_MESSAGE_BYTES",
    "MESSAGE_TYPES",
    "PROTOCOL_VERSION",
    "SERVER_MESSAGES",
    "Body",
    "Calibrate",
    "Calibration",
    "EgoPoseError",
    "Error",
    "ErrorCode",
    "GetBody",
    "Hello",
    "Hmd",
    "InputError",
    "ListModels",
    "Message",
    "ModelInfo",
    "Models",
    "Ping",
    "Pong",
    "Pose",
    "ProtocolError",
    "Ref",
    "Rgbd",
    "SelectModel",
    "SessionStatus",
    "SetBody",
    "Welcome",
    "decode",
    "decode_from_server",
    "encode",
]
