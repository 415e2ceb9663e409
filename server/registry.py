"""The servable models: the bundled zoo plus ``--models-dir``, loaded once, rescanned while running.

A model file that fails to load is remembered with its reason (``failures``), logged once and skipped; the
others keep serving. A file dropped into the models directory appears at the next ``rescan``; a changed file
is reloaded; a removed one disappears from the list (sessions that use it keep their loaded copy until they
switch). Files in the models directory win over bundled ones of the same name. Visual encoders are shared
between the models that use them.

Loading is blocking work (onnxruntime builds its graphs), so the app runs ``rescan`` in a worker thread. A
rescan builds a new ``models`` dict and swaps it in with one assignment: readers on the event loop see the old
registry or the new one, never a half-updated one.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Any

import numpy as np

from ..model.provenance import file_digest
from ..model.rig import head_joint_in_view_m
from ..model.runtime.loading import DEFAULT_PROVIDERS, LoadedModel, ModelError
from ..model.runtime.procedural import NAME as PROCEDURAL
from ..model.runtime.procedural import ProceduralModel
from ..model.weights import WEIGHTS_DIR, model_files
from ..protocol import ModelInfo as WireModelInfo

log = logging.getLogger("egoposevr.server")


@dataclasses.dataclass(frozen=True)
class _Stamp:
    """What identifies one version of a model file on disk."""

    path: Path
    mtime_ns: int
    size: int


def _wire_head_joint_m(head_offset_m: np.ndarray) -> list[float]:
    """A model's head offset (3,) as the ``models`` message gives it: the head joint in the view pose's frame (m;
    0.0 where it is -0.0)."""
    return [round(float(v), 6) + 0.0 for v in head_joint_in_view_m(head_offset_m)]


def _stamp(path: Path) -> _Stamp:
    stat = path.stat()
    return _Stamp(path, stat.st_mtime_ns, stat.st_size)


class ModelRegistry:
    """{name: LoadedModel} for every servable model; ``failures`` {path: reason} for files that would not load."""

    def __init__(
        self,
        models_dir: Path | None = None,
        bundled: bool = True,
        ort_threads: int = 1,
        providers: tuple[str, ...] = DEFAULT_PROVIDERS,
    ) -> None:
        self.models_dir, self.bundled, self.ort_threads = models_dir, bundled, ort_threads
        self.providers = providers
        # The procedural baseline has no file: it is always there, first, unless a file takes its name.
        self._builtin: dict[str, Any] = {PROCEDURAL: ProceduralModel()}
        self.models: dict[str, LoadedModel] = dict(self._builtin)
        self.failures: dict[Path, str] = {}
        self._stamps: dict[str, _Stamp] = {}  # the file version each model was loaded from
        self._failed: dict[Path, _Stamp] = {}  # not retried until the file changes
        self._shared: dict[Path, Any] = {}  # visual encoder sessions, by path
        # each cached encoder's file version and sha256, hashed once per version
        self._encoder_files: dict[Path, tuple[_Stamp, str]] = {}
        self._digests: dict[str, tuple[str, str | None]] = {}  # name -> (model file, encoder file) sha256

    def names(self) -> list[str]:
        return list(self.models)

    def active_providers(self) -> set[str]:
        """The execution providers the loaded models run on."""
        return {m.provider for m in self.models.values()} - {"none"}

    def file_names(self) -> list[str]:
        """The models loaded from files (the built-in procedural baseline not counted)."""
        return [n for n, m in self.models.items() if not isinstance(m, ProceduralModel)]

    def get(self, name: str) -> LoadedModel | None:
        return self.models.get(name)

    def wire_infos(self) -> list[WireModelInfo]:
        """The ``models`` message's list, with the digests of the files each model serves (PROTOCOL.md
        §model-digests): which weights answered a session, for a user's report; and where each hangs the body's
        head joint from the headset (§model-head-joint), which a model file records and a client cannot read."""
        infos = []
        for name, model in self.models.items():
            model_sha256, encoder_sha256 = self._digests.get(name, (None, None))
            infos.append(WireModelInfo(
                name=name, inputs=list(model.info.inputs), description=model.info.description[:1024],
                sha256=model_sha256, encoder_sha256=encoder_sha256,
                head_joint_m=_wire_head_joint_m(model.info.rig_offsets_m[0]),
            ))  # fmt: skip
        return infos

    def _candidates(self) -> dict[str, Path]:
        found = dict(model_files(WEIGHTS_DIR)) if self.bundled else {}
        if self.models_dir is not None and self.models_dir.is_dir():
            found |= model_files(self.models_dir)  # the user's files win
        return found

    def rescan(self) -> list[str]:
        """Load new and changed files, drop removed ones; returns what happened (also logged)."""
        events: list[str] = []
        candidates = self._candidates()
        stale_encoders = self._forget_changed_encoders()
        models = {n: m for n, m in self.models.items() if n not in self._builtin or n in candidates}
        for name in set(models) - set(candidates):
            del models[name], self._stamps[name]
            self._digests.pop(name, None)
            events.append(f"model {name} removed")
        for name, path in candidates.items():
            try:
                stamp = _stamp(path)
            except OSError:
                continue  # vanished between listing and stat: the next rescan sees it gone
            uses_stale = name in models and models[name].info.visual_path in stale_encoders
            if (self._stamps.get(name) == stamp and not uses_stale) or self._failed.get(path) == stamp:
                continue
            events.append(self._load(name, stamp, models))
        files = {n: models[n] for n in candidates if n in models}  # zoo order, then by name
        self.models = {n: m for n, m in self._builtin.items() if n not in files} | files
        for event in events:
            log.info("%s", event)
        return events

    def _forget_changed_encoders(self) -> set[Path]:
        """Drop cached visual encoders whose file changed or vanished; returns their paths."""
        stale = set()
        for path, (stamp, _) in list(self._encoder_files.items()):
            try:
                current = _stamp(path)
            except OSError:
                current = None
            if current != stamp:
                stale.add(path)
                self._shared.pop(path, None)
                del self._encoder_files[path]
        return stale

    def _load(self, name: str, stamp: _Stamp, models: dict[str, LoadedModel]) -> str:
        try:
            model = LoadedModel.load(
                stamp.path, threads=self.ort_threads, shared=self._shared, providers=self.providers
            )
        except (ModelError, OSError) as exc:
            self._failed[stamp.path], self.failures[stamp.path] = stamp, str(exc)
            models.pop(name, None)
            self._stamps.pop(name, None)
            log.warning("model %s failed to load: %s", name, exc)
            return f"model {name} failed: {exc}"
        encoder = model.info.visual_path
        if encoder is not None and encoder not in self._encoder_files:
            self._encoder_files[encoder] = (_stamp(encoder), file_digest(encoder))
        self._failed.pop(stamp.path, None)
        self.failures.pop(stamp.path, None)
        reloaded = name in models
        models[name], self._stamps[name] = model, stamp
        self._digests[name] = (
            file_digest(stamp.path),
            self._encoder_files[encoder][1] if encoder is not None else None,
        )
        action = "reloaded" if reloaded else "loaded"
        return f"model {name} {action} from {stamp.path} (sha256 {self._digests[name][0][:12]})"
