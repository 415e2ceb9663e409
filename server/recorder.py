"""``--record DIR``: every input connection's messages as one ``.egrec`` file, replayable later.

One file per input connection, ``<session>-<UTC time>-<n>.egrec``, holding the exact bytes of each valid
message the headset sent (hello, hmd, rgbd, select_model, calibrate) with its arrival time. Writes go through a buffered
file, so a write on the event loop costs a memory copy; files are flushed when the connection closes and at
shutdown. A write that fails (disk full) is logged once, counted (``egoposevr_recordings_failed_total``) and
that connection's recording stops; serving goes on. What reached the disk replays up to its last complete
record (``egoposevr replay`` warns and says how much was cut).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..recordings.egrec import EgrecWriter

log = logging.getLogger("egoposevr.server")


class Recorder:
    """Open recordings, one per input client."""

    def __init__(
        self, directory: Path, server_name: str = "", on_failure: Callable[[], None] = lambda: None
    ) -> None:
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.server_name = server_name
        self.on_failure = on_failure  # a recording stopped on an error (counted in /metrics)
        self._writers: dict[Any, tuple[EgrecWriter, int]] = {}  # client -> (writer, start ns)
        self._count = 0

    def open(self, client: Any, session_id: str) -> None:
        self._count += 1
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        path = self.directory / f"{session_id}-{stamp}-{self._count}.egrec"
        try:
            writer = EgrecWriter(path, session_id, source="server", recorded_by=self.server_name)
        except OSError as exc:
            log.warning("cannot record session %s to %s: %s", session_id, path, exc)
            self.on_failure()
            return
        self._writers[client] = (writer, time.perf_counter_ns())
        log.info("recording session %s to %s", session_id, path)

    def record(self, client: Any, data: bytes, recv_ns: int) -> None:
        entry = self._writers.get(client)
        if entry is None:
            return
        writer, start_ns = entry
        try:
            writer.message((recv_ns - start_ns) // 1000, data)
        except OSError as exc:
            log.warning("recording %s stopped: %s", writer.path, exc)
            self.on_failure()
            self._close(client)

    def close(self, client: Any) -> None:
        if client in self._writers:
            self._close(client)

    def _close(self, client: Any) -> None:
        writer, _ = self._writers.pop(client)
        try:
            writer.close()
        except OSError as exc:
            log.warning("recording %s did not close cleanly: %s", writer.path, exc)

    def close_all(self) -> None:
        for client in list(self._writers):
            self._close(client)

    @property
    def paths(self) -> list[Path]:
        return [w.path for w, _ in self._writers.values()]
