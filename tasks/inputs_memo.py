"""Input digests kept with what they read, so that ``cadestate status`` digests again only what changed.

A stage's ``clip_inputs`` (:meth:`tasks.registry.Stage.clip_inputs`: people's answers in force, the
CAD libraries' digest, ...) read warehouse tables, and digesting them costs the import of pyarrow
and the reads, for every stage of every clip on every ``status``. They depend on nothing but the
warehouse's files and the code, so each clip keeps them in ``_cache/inputs/<clip>.json``::

    {"version": ..., "stages": {stage: {"key": ..., "reads": [[...], ...], "states": [...], "inputs": [...]}}}

- ``key``: the memo's version, the stage and its code digest (other code, other digests);
- ``reads``: what the digests read, as the warehouse noted it (:func:`cadestate.lineage.note_read`):
  ``["files", table, partition, ...]`` (``"*"``: every partition) and ``["partitions", table]``;
- ``states``: per read, a digest of its files' (name, inode, size, modification time), or of the
  partitions listed with their folders' modification times.

An entry is used when its key matches and every read is in the same state: files are written
whole, under new names or by an atomic rename (a new inode), so unchanged states mean unchanged
data. An entry is stored only when nothing it read was modified while it was digested (else the
states could be newer than what was read), and storing is best effort: a read-only warehouse just
gets no memo. The flows store the digests they take before running a clip (:mod:`tasks.stage_chain`),
so a ``status`` after a run finds them.

:func:`kept_read` keeps any one read so, by the same rules: ``status`` keeps the ``runs`` rows it
shows in ``_cache/reads/``, and reads them again (DuckDB imported, every run file opened) only
when a run file came or went.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from cadestate.atomic import atomic_write_bytes
from cadestate.lineage import digest, one_reading, recording_reads
from tasks.registry import Stage
from warehouse import Warehouse
from warehouse.store import check_name

VERSION = "1"
"""Bump when what an entry means changes: every memo is then digested again."""

SETTLE_NS = 50_000_000
"""A read whose newest file is younger than the digest's start minus this (file times come from a
coarse clock) may have changed while it was read: its entry is not stored."""


def _state(wh: Warehouse, read: Sequence[str]) -> tuple[str, int]:
    """Digest of the current state of one noted read, and the newest modification time in it (ns)."""
    lines: list[str] = []
    newest = 0
    try:
        if read[0] == "files":
            parts = None if list(read[2:]) == ["*"] else list(read[2:])
            paths = wh.file_paths(read[1], parts)
        elif read[0] == "partitions":
            if not wh.table_dir(read[1]).is_dir():
                return digest(*read, "no table folder"), 0
            paths = [str(wh.table_dir(read[1]))] + [str(wh.partition_dir(read[1], p)) for p in wh.partitions(read[1])]
        else:
            return f"unknown read {read[0]!r}", time.time_ns()
        for path in paths:
            st = os.stat(path)
            lines.append(f"{os.path.basename(path)} {st.st_ino} {st.st_size} {st.st_mtime_ns}")
            newest = max(newest, st.st_mtime_ns)
    except FileNotFoundError:  # a file went away while it was listed (compacted): changing now
        return "changing", time.time_ns()
    return digest(*read, *lines), newest


class InputsMemo:
    """The memo of one clip (or library): :meth:`clip_inputs` of its stages, then :meth:`save`."""

    def __init__(self, wh: Warehouse, unit: str):
        self.wh = wh
        self.path = wh.root / "_cache" / "inputs" / f"{check_name(unit)}.json"
        self.unit = unit
        self.entries = self._load()
        self.changed = False
        self._states: dict[tuple[str, ...], tuple[str, int]] = {}
        self._since_ns: int | None = None

    @contextlib.contextmanager
    def reading(self) -> Iterator[None]:
        """A block in which the stages' digests are taken from one reading of the warehouse
        (:func:`cadestate.lineage.one_reading`: what several stages digest alike is computed once).
        An entry stored inside counts as taken when the block began: a value computed for an
        earlier stage must not be stored with the state of files changed since. The state of each
        read is taken once in the block, for every stage that read it."""
        self._since_ns = time.time_ns()
        self._states.clear()
        try:
            with one_reading():
                yield
        finally:
            self._since_ns = None

    def _load(self) -> dict[str, dict]:
        try:
            data = json.loads(self.path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return {}
        stages = data.get("stages") if isinstance(data, dict) and data.get("version") == VERSION else None
        return stages if isinstance(stages, dict) else {}

    def _state(self, read: tuple[str, ...]) -> tuple[str, int]:
        if read not in self._states:
            self._states[read] = _state(self.wh, read)
        return self._states[read]

    def clip_inputs(self, stage: Stage, fresh: bool = False) -> list[str]:
        """``stage.clip_inputs(wh, unit)``: from the memo when its entry holds (see the module), else
        digested again (always when ``fresh``) and kept."""
        if not stage.has("clip_inputs"):
            return []
        key = digest(VERSION, stage.name, stage.code_hash)
        entry = self.entries.get(stage.name)
        if not fresh and isinstance(entry, dict) and entry.get("key") == key and self._holds(entry):
            return list(entry["inputs"])
        started = self._since_ns or time.time_ns()
        with recording_reads() as noted:
            inputs = stage.clip_inputs(self.wh, self.unit)
        reads = list(dict.fromkeys(noted))
        if self._since_ns is None:  # what was read may have changed while the memo's other entries were checked
            self._states.clear()  # (in a reading, a state taken before a change is older than what was read, and
            # nothing read since the reading began is stored: the states are taken once for all its stages)
        states = [self._state(r) for r in reads]
        if all(newest < started - SETTLE_NS for _, newest in states):
            self.entries[stage.name] = {"key": key, "reads": [list(r) for r in reads],
                                        "states": [s for s, _ in states], "inputs": inputs}
            self.changed = True
        else:
            self.entries.pop(stage.name, None)
        return inputs

    def _holds(self, entry: dict) -> bool:
        try:
            reads = [tuple(str(x) for x in r) for r in entry["reads"]]
            return len(reads) == len(entry["states"]) and all(
                self._state(r)[0] == s for r, s in zip(reads, entry["states"]))
        except (KeyError, TypeError, IndexError):
            return False

    def save(self) -> None:
        """Write the memo if it changed (atomically; silently not when the warehouse is read-only)."""
        if self.changed:
            payload = json.dumps({"version": VERSION, "stages": self.entries}, sort_keys=True)
            with contextlib.suppress(OSError):
                atomic_write_bytes(self.path, payload.encode(), durable=False)  # a cache: lost, it is digested again
            self.changed = False


def kept_read(wh: Warehouse, name: str, read: tuple[str, ...], compute: Callable[[], Any]) -> Any:
    """``compute()``, a JSON value made from the files of ``read`` alone (a read as the memo notes
    one: ``("files", table, partition, ...)``), kept in ``_cache/reads/<name>.json`` with the state
    of those files and served while it holds (the rules of the module: stored only when nothing
    read was modified while it was computed, best effort)."""
    path = wh.root / "_cache" / "reads" / f"{check_name(name)}.json"
    state, _ = _state(wh, read)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        if doc["version"] == VERSION and doc["read"] == list(read) and doc["state"] == state:
            return doc["value"]
    except (OSError, ValueError, KeyError, TypeError):
        pass
    started = time.time_ns()
    value = compute()
    state, newest = _state(wh, read)
    if newest < started - SETTLE_NS:
        payload = json.dumps({"version": VERSION, "read": list(read), "state": state, "value": value})
        with contextlib.suppress(OSError):
            atomic_write_bytes(path, payload.encode(), durable=False)
    return value
