"""``.egrec`` recorded sessions: the wire messages a client sent, with their send times, plus ground truth.

A file is a stream of msgpack values (DATA.md has the full layout):

1. a header map: ``{"format": "egrec", "version": 1, "session": str, ...metadata}``;
2. records, each an array ``[t_us, kind, payload]``: ``t_us`` is the send time in microseconds from the
   start of the recording (non-decreasing); ``kind`` is ``"c2s"`` (payload: the exact bytes of one protocol
   v1 message, client to server) or ``"gt"`` (payload: a map with the ground-truth body for the ``hmd``
   sample with the same ``seq``: ``seq``, ``t_us``, ``global_orient`` [3], ``body_pose`` [63], ``transl``
   [3], ``joints`` [66]).

The synthesis engine writes these, the server's ``--record`` writes them for live sessions, and the mock
headset replays them. Readers ignore unknown header keys and unknown record kinds (forward compatible).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO, Final

import msgpack

FORMAT: Final = "egrec"
VERSION: Final = 1
KIND_CLIENT: Final = "c2s"
KIND_TRUTH: Final = "gt"
MAX_RECORD_BYTES: Final = 16 * 1024 * 1024


class EgrecError(ValueError):
    """A file that is not a readable .egrec; the message says where and why."""


@dataclasses.dataclass(frozen=True)
class Record:
    t_us: int
    kind: str
    payload: Any


class EgrecWriter:
    """Appends records to a new .egrec file; use as a context manager (or call :meth:`close`)."""

    def __init__(self, path: str | Path, session: str, **metadata: Any) -> None:
        self.path = Path(path)
        self._file: BinaryIO = self.path.open("wb")
        self._packer = msgpack.Packer(use_bin_type=True)
        self._last_t_us = 0
        self.records = 0
        header = {"format": FORMAT, "version": VERSION, "session": session, **metadata}
        self._file.write(self._packer.pack(header))

    def write(self, t_us: int, kind: str, payload: Any) -> None:
        t_us = max(int(t_us), self._last_t_us)  # send times never run backwards
        self._last_t_us = t_us
        self._file.write(self._packer.pack([t_us, kind, payload]))
        self.records += 1

    def message(self, t_us: int, data: bytes) -> None:
        """One client-to-server message, as the exact bytes on the wire."""
        self.write(t_us, KIND_CLIENT, bytes(data))

    def truth(self, t_us: int, body: dict[str, Any]) -> None:
        self.write(t_us, KIND_TRUTH, body)

    def flush(self) -> None:
        self._file.flush()

    def close(self) -> None:
        if not self._file.closed:
            self._file.close()

    def __enter__(self) -> EgrecWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _unpacker(file: BinaryIO) -> msgpack.Unpacker:
    return msgpack.Unpacker(
        file,
        raw=False,
        strict_map_key=True,
        max_buffer_size=MAX_RECORD_BYTES,
        max_bin_len=MAX_RECORD_BYTES,
        max_str_len=1 << 20,
        max_array_len=1 << 20,
        max_map_len=1 << 16,
    )


def read_header(path: str | Path) -> dict[str, Any]:
    """The header map of a recording. Raises :class:`EgrecError`."""
    with Path(path).open("rb") as file:
        return _header(_unpacker(file), path)


def _header(unpacker: msgpack.Unpacker, path: str | Path) -> dict[str, Any]:
    try:
        header = next(unpacker)
    except StopIteration:
        raise EgrecError(f"{path}: empty file") from None
    except (ValueError, msgpack.UnpackException) as error:
        raise EgrecError(f"{path}: not msgpack ({error})") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise EgrecError(f"{path}: not an .egrec file (no {{'format': 'egrec'}} header)")
    if header.get("version") != VERSION:
        raise EgrecError(f"{path}: .egrec version {header.get('version')!r}; this reader knows {VERSION}")
    return header


@dataclasses.dataclass
class Cut:
    """Where a recording cut short (a crash, SIGKILL, a full disk) stopped being readable.

    records: complete records read; bytes_read / bytes_total: how far into the file they reach; reason:
    what was wrong after them. Filled in by :func:`read_records` when ``strict`` is False.
    """

    records: int = 0
    bytes_read: int = 0
    bytes_total: int = 0
    reason: str = ""

    @property
    def happened(self) -> bool:
        return bool(self.reason)

    def describe(self) -> str:
        lost = self.bytes_total - self.bytes_read
        return f"cut after record {self.records} ({self.reason}; {lost} of {self.bytes_total} bytes unread)"


def read_records(path: str | Path, *, strict: bool = True, cut: Cut | None = None) -> Iterator[Record]:
    """Every record after the header, in file order.

    strict: a truncated or corrupt record raises :class:`EgrecError`. Otherwise reading stops at the last
    complete record and ``cut`` (if given) says where and why: a recording cut by a crash or a full disk
    replays its good part. A bad header raises either way (nothing after it can be trusted).
    """
    size = Path(path).stat().st_size
    cut = cut if cut is not None else Cut()
    cut.bytes_total = size
    with Path(path).open("rb") as file:
        unpacker = _unpacker(file)
        _header(unpacker, path)
        index = 0
        while True:
            good_until = unpacker.tell()
            problem = None
            try:
                item = next(unpacker)
            except StopIteration:
                if unpacker.tell() < size:  # msgpack stops quietly at a cut record; say so
                    problem = f"truncated after record {index}"
                else:
                    cut.records, cut.bytes_read = index, size
                    return
            except (ValueError, msgpack.UnpackException) as error:
                problem = f"record {index} is corrupt ({error})"
            else:
                problem = _record_problem(item, index)
            if problem is not None:
                if strict:
                    raise EgrecError(f"{path}: {problem}")
                cut.records, cut.bytes_read, cut.reason = index, good_until, problem
                return
            yield Record(item[0], item[1], item[2])
            index += 1


def _record_problem(item: Any, index: int) -> str | None:
    if (
        not isinstance(item, list)
        or len(item) != 3
        or not isinstance(item[0], int)
        or not isinstance(item[1], str)
    ):
        return f"record {index} is not [t_us, kind, payload]"
    if item[1] == KIND_CLIENT and not isinstance(item[2], bytes):
        return f"record {index} (c2s) holds no message bytes"
    return None
