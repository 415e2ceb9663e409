"""Where a trained file came from beyond its flags: the command that made it, the code and the machine that ran
it, digests of the bytes it read (the data's shards, the file it started from, the encoder it read), and those
files' own records.

A checkpoint's ``runs`` list holds one :func:`run_record` per ``egoposevr train`` invocation that advanced it
(a resumed run adds one); ``blend``, ``export`` and ``fit-body`` add their own. A file started from or read by
a net travels with it as an entry of ``ancestors`` (:func:`ancestry`, gathered at the record's root by
:func:`hoist_ancestors`), so a file keeps its lineage after those files are replaced. Training is deterministic
for a given seed, data, code and thread count (the tests train twice and compare the bits), so these say what
is needed to make a file again: :func:`describe` prints a record for people (``egoposevr models --training``)
and :func:`recipe` the commands (``--recipe``). Files made before these were recorded (MODEL_CARD.md names
them) say so instead; a record of another shape is a :class:`RecordError`.

No torch and no numpy here: the serving side prints records too.
"""

from __future__ import annotations

import datetime
import functools
import hashlib
import os
import platform
import shlex
import subprocess
from collections.abc import Callable, Iterable, Sequence
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any, Final


class RecordError(ValueError):
    """A training record that is not of the shape this version writes (a damaged or foreign file)."""


_SOURCE_DIR: Final = Path(__file__).resolve().parent  # the package's model/; a git work tree when editable
_GIT_TIMEOUT_S: Final = 5.0
_CHUNK_BYTES: Final = 1 << 20


def file_digest(path: str | Path) -> str:
    """sha256 (hex) of one file's bytes."""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def data_digest(data_dirs: Sequence[Path], split: str = "train") -> str:
    """sha256 (hex) of the named split's shards of the dataset folders, in the order given: one folder's
    :func:`folder_digest`, several folders' the digest of theirs in order."""
    digests = [folder_digest(d, split) for d in data_dirs]
    if len(digests) == 1:
        return digests[0]
    return hashlib.sha256("".join(f"{k}:{d}\n" for k, d in enumerate(digests)).encode()).hexdigest()


def folder_digest(data_dir: Path, split: str = "train") -> str:
    """sha256 (hex) over one dataset folder's split shards: each shard's name and bytes, in name order. A set
    re-rendered by the same command gives the same digest (shards are written with fixed timestamps:
    model/synth/archive.py), wherever its folder lies; ``egoposevr synth`` writes it in the manifest."""
    return _folder_digest(_shard_stamps(Path(data_dir), split))


def _shard_stamps(data_dir: Path, split: str) -> tuple[tuple[str, int, int], ...]:
    """(path, size, mtime_ns) of a folder's split shards, sorted: the cache key of their digest."""
    shards = sorted((data_dir / split).glob("shard-*.npz"))
    return tuple((str(p.resolve()), (s := p.stat()).st_size, s.st_mtime_ns) for p in shards)


@functools.lru_cache(maxsize=32)
def _folder_digest(shards: tuple[tuple[str, int, int], ...]) -> str:
    """The digest of :func:`folder_digest`, once per set of unchanged files (a zoo's nets read the same data)."""
    digest = hashlib.sha256()
    for path, _, _ in shards:
        digest.update(f"{Path(path).name}\n".encode())
        with open(path, "rb") as f:
            while chunk := f.read(_CHUNK_BYTES):
                digest.update(chunk)
    return digest.hexdigest()


def package_version() -> str:
    """The installed package's version; ``0+unknown`` from a source tree that was never installed."""
    try:
        return version("egoposevr")
    except PackageNotFoundError:
        return "0+unknown"


_code_at_start: dict[str, Any] | None = None  # remember_code's answer, for a process's whole run


def remember_code() -> None:
    """Read the code's version now, at a process's start, for :func:`code_version` to give all along: a run
    loads its data for minutes, and a commit made meanwhile is not the code it imported."""
    global _code_at_start
    _code_at_start = None
    _code_at_start = code_version()


def code_version() -> dict[str, Any]:
    """The code that runs: the package's version and, when it runs from a git work tree (an editable
    install), the commit and whether tracked files differ from it; ``None`` for either where git cannot
    tell. What :func:`remember_code` read, where a process called it."""
    if _code_at_start is not None:
        return dict(_code_at_start)
    commit = _git("rev-parse", "HEAD")
    changed = _git("status", "--porcelain", "--untracked-files=no") if commit else None
    return {
        "version": package_version(),
        "commit": commit,
        "dirty": None if changed is None else bool(changed),
    }


def _git(*args: str) -> str | None:
    """git's trimmed output run in the package's folder; None where that is not a work tree or git fails."""
    try:
        done = subprocess.run(
            ["git", "-C", str(_SOURCE_DIR), *args],
            capture_output=True, text=True, timeout=_GIT_TIMEOUT_S, check=False,
        )  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def machine(device: str, threads: int, libraries: dict[str, str] | None = None) -> dict[str, Any]:
    """The machine a run trains on: platform, CPU model and count, Python, the training device and thread
    count (results depend on it: reductions split otherwise; 0 for a library's default), and the libraries'
    versions (or a GPU's name) given."""
    return {
        "platform": platform.platform(),
        "cpu": _cpu_model(),
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "device": device,
        "threads": threads,
        **(libraries or {}),
    }


def _cpu_model() -> str:
    """The CPU's model name (Linux's /proc/cpuinfo; else what platform says)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def run_record(command: Sequence[str] | None, code: dict[str, Any], host: dict[str, Any]) -> dict[str, Any]:
    """One invocation's record: its command line (None when not run from the command line) and the folder it
    ran in (the command's relative paths are from there), when it began (UTC), the code and the machine."""
    return {
        "command": shlex.join(command) if command is not None else None,
        "cwd": os.getcwd(),
        "started_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "code": code,
        "machine": host,
    }


def ancestry(digest: str, record: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """A file's record as an entry of the ``ancestors`` map of what was made from it: {its digest: its record}
    plus the files it was made from, flat (each file once, however many nets started from it)."""
    own = {key: value for key, value in record.items() if key != "ancestors"}
    return {digest: own, **record.get("ancestors", {})}


def hoist_ancestors(record: dict[str, Any]) -> dict[str, Any]:
    """A record tree (an ensemble's or a blend's nets nested) with every net's ``ancestors`` gathered into one
    map at its root, so that a file made from one start many times records that start once."""
    gathered: dict[str, dict[str, Any]] = {}

    def gather(node: dict[str, Any]) -> dict[str, Any]:
        gathered.update(node.get("ancestors", {}))
        node = {key: value for key, value in node.items() if key != "ancestors"}
        if "ensemble" in node:
            node["ensemble"] = [gather(net) for net in node["ensemble"]]
        if "nets" in node.get("blend", {}):
            node["blend"] = {**node["blend"], "nets": [gather(net) for net in node["blend"]["nets"]]}
        return node

    root = gather(record)
    return root | ({"ancestors": gathered} if gathered else {})


def describe(record: dict[str, Any], indent: str = "  ") -> list[str]:
    """A model file's ``training`` record as lines for people: an ensemble's and a blend's nets nested under
    them, each net's steps, seed, data, start, encoder and runs, and the record of each file it started from
    or read keypoints from (its ``ancestors``) under the line that names it, once. RecordError for a record
    of another shape."""
    return _readable(lambda: list(_describe(record, indent, 0, _Ancestors(record.get("ancestors", {})))))


def _readable(read: Callable[[], list[str]]) -> list[str]:
    """What ``read`` makes of a record, or RecordError where the record is not of the shape it reads."""
    try:
        return read()
    except (AttributeError, TypeError, KeyError, ValueError) as error:
        raise RecordError(
            f"the training record is not one this version reads ({type(error).__name__}: {error})"
        ) from error


class _Ancestors:
    """The ancestors map of the root record, and which of them have been printed."""

    def __init__(self, records: dict[str, dict[str, Any]]) -> None:
        self.records, self.shown = records, set()

    def take(self, digest: str | None) -> dict[str, Any] | None:
        """An ancestor's record the first time it is asked for; None after, or if it is not recorded."""
        if digest is None or digest in self.shown or digest not in self.records:
            return None
        self.shown.add(digest)
        return self.records[digest]


def recipe(record: dict[str, Any]) -> list[str]:
    """The commands that made a file, in the order they ran: each file it started from or read keypoints from
    first (its ``ancestors``), then each net's training, each blend and the export; one line each, with the
    folder it ran in, the commit and the thread count as a comment, and a comment where a step was not
    recorded. A command that made several files (the encoder and the net of one ``train``) is listed once.
    RecordError for a record of another shape."""
    return _readable(lambda: _recipe(record))


def _recipe(record: dict[str, Any]) -> list[str]:
    ancestors = record.get("ancestors", {})
    lines: list[str] = []
    listed: set[tuple[Any, ...]] = set()
    made: set[str] = set()

    def runs(entries: list[dict[str, Any]], what: str) -> None:
        if not entries:
            lines.append(f"# {what}: not recorded")
        for run in entries:
            key = (run.get("command"), run.get("cwd"), run.get("started_utc"))
            if run.get("recorded") is False or run.get("command") is None:
                lines.append(f"# {what}: not recorded")
            elif key not in listed:
                listed.add(key)
                lines.append(_recipe_line(run))

    def from_file(digest: str | None) -> None:
        if digest in ancestors and digest not in made:
            made.add(digest)
            node(ancestors[digest])

    def node(r: dict[str, Any]) -> None:
        for net in r.get("ensemble", []):
            node(net)
        if "blend" in r:
            for net in r["blend"].get("nets", []):
                node(net)
            runs([r["blend"]["run"]] if "run" in r["blend"] else [], "a blend")
        elif "ensemble" not in r:
            from_file((r.get("init") or {}).get("sha256"))
            for encoder in r.get("encoders", []):
                from_file(encoder.get("sha256"))
            runs(r.get("runs", []), f"{r.get('steps')} steps, seed {r.get('seed')}")
        if "export" in r:
            runs([r["export"]], "the export")
        if r.get("mirror_averaged"):  # rewritten in place to serve each answer's mean with the mirrored one's
            runs([r["mirror_run"]] if "mirror_run" in r else [], "the mirror averaging")

    node(record)
    return lines


def short_commit(code: dict[str, Any]) -> str:
    """A :func:`code_version` record as people read it: the commit's first 12 digits, and whether it had local
    changes."""
    return (code.get("commit") or "unknown commit")[:12] + (
        " with local changes" if code.get("dirty") else ""
    )


def _recipe_line(run: dict[str, Any]) -> str:
    """One recorded invocation as a shell line: into its folder, its command, and what else decides its bits."""
    host = run.get("machine") or {}
    commit = short_commit(run.get("code") or {})
    where = f"cd {shlex.quote(run['cwd'])} && " if run.get("cwd") else ""
    return f"{where}{run['command']}  # code {commit}; {host.get('threads')} threads on {host.get('device')}"


def describe_fit(record: dict[str, Any]) -> list[str]:
    """A body regressor's record (``egoposevr fit-body``) as lines for people: its data and its run.
    RecordError for a record of another shape."""
    return _readable(lambda: _fit_lines(record))


def _fit_lines(record: dict[str, Any]) -> list[str]:
    dirs = " ".join(record.get("data") or [])
    lines = [
        f"fitted on {dirs} ({record.get('sequences')} sequences of {record.get('split')}), "
        f"sha256 {_short(record.get('data_sha256'))}"
    ]
    return lines + list(_runs("ran", [record["run"]] if "run" in record else [], ""))


def _describe(record: dict[str, Any], indent: str, depth: int, ancestors: _Ancestors) -> Iterable[str]:
    pad = indent * depth
    if "ensemble" in record:
        nets = record["ensemble"]
        yield f"{pad}the mean of {len(nets)} nets:"
        for k, net in enumerate(nets, 1):
            yield f"{pad}{indent}net {k}:"
            yield from _describe(net, indent, depth + 2, ancestors)
    elif "blend" in record:
        blend = record["blend"]
        weights = ", ".join(f"{w:.2f}" for w in blend.get("weights", []))
        yield f"{pad}a weight-space blend ({weights}) of:"
        nets = blend.get("nets") or [None] * len(blend.get("from", []))
        for source, net in zip(blend.get("from", []), nets, strict=False):
            yield f"{pad}{indent}{source}:"
            if net is None:  # the first blends kept only their files' names
                yield f"{pad}{indent * 2}its record was not kept"
                continue
            yield from _describe(net, indent, depth + 2, ancestors)
        yield from _runs("blended", [blend["run"]] if "run" in blend else [], pad)
    else:
        yield from _net_lines(record, indent, depth, ancestors)
    if checkpoint := record.get("checkpoint"):
        yield f"{pad}checkpoint {checkpoint.get('from')}, sha256 {_short(checkpoint.get('sha256'))}"
    if "export" in record:
        yield from _runs("exported", [record["export"]], pad)
    if record.get("mirror_averaged"):
        yield from _runs("mirror-averaged", [record["mirror_run"]] if "mirror_run" in record else [], pad)


def _net_lines(record: dict[str, Any], indent: str, depth: int, ancestors: _Ancestors) -> Iterable[str]:
    """One trained net: what it read (with the record of a file it started from or read, nested) and how it
    ran."""
    pad = indent * depth
    yield f"{pad}{record.get('steps')} steps, seed {record.get('seed')}"
    data = record.get("data") or {}
    dirs = data.get("dir")
    dirs = " ".join(dirs) if isinstance(dirs, list) else dirs
    yield f"{pad}data {dirs} ({data.get('sequences')} sequences), sha256 {_short(data.get('sha256'))}"
    if len(each := data.get("folders_sha256") or []) > 1:  # to match each folder's manifest
        yield f"{pad}  each folder's shards: {', '.join(_short(d) for d in each)}"
    if held := data.get("held_out_fold"):
        yield f"{pad}people of fold {held} left out"
    if kept := data.get("trained_fold"):
        yield f"{pad}only the people of fold {kept}"
    if init := record.get("init"):
        member = f" member {init['member']}" if "member" in init else ""
        yield f"{pad}started from {init.get('from')}{member}, sha256 {_short(init.get('sha256'))}"
        if (made := ancestors.take(init.get("sha256"))) is not None:
            yield from _describe(made, indent, depth + 1, ancestors)
    for teacher in record.get("teacher_files", []):
        yield f"{pad}taught by {teacher.get('from')}, sha256 {_short(teacher.get('sha256'))}"
    for encoder in record.get("encoders", []):
        yield f"{pad}keypoints from {encoder.get('from')}, sha256 {_short(encoder.get('sha256'))}"
        if (made := ancestors.take(encoder.get("sha256"))) is not None:
            yield from _describe(made, indent, depth + 1, ancestors)
    yield from _runs("ran", record.get("runs", []), pad)


def _runs(verb: str, runs: list[dict[str, Any]], pad: str) -> Iterable[str]:
    """A record's invocations, or that none were recorded."""
    if not runs:
        yield f"{pad}{verb}: not recorded (made before runs were recorded)"
    for run in runs:
        code, host = run.get("code") or {}, run.get("machine") or {}
        steps = f" steps {run['from_step']}-{run.get('to_step')}" if "from_step" in run else ""
        if run.get("recorded") is False:
            yield f"{pad}{verb}{steps}: not recorded (run before runs were recorded)"
            continue
        commit = code.get("commit") or "unknown commit"
        dirty = " (with local changes)" if code.get("dirty") else ""
        command = run.get("command") or "(not from the command line)"
        yield f"{pad}{verb}{steps} on {run.get('started_utc')} in {run.get('cwd')}: {command}"
        yield f"{pad}  code {code.get('version')} {commit}{dirty}"
        gpu = f" ({host['gpu']})" if host.get("gpu") else ""
        yield (
            f"{pad}  machine {host.get('cpu')} ({host.get('cpus')} CPUs), device {host.get('device')}{gpu}, "
            f"{host.get('threads')} threads, {host.get('platform')}"
        )


def _short(digest: str | None) -> str:
    """A digest as people compare it (the first 16 hex digits), or that it was not recorded."""
    return digest[:16] if digest else "not recorded"
