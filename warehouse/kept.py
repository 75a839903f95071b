"""Values computed from warehouse files, kept with the state of those files and served while it holds.

A read is named as the warehouse notes it (:func:`cadestate.lineage.note_read`): ``("files", table,
partition, ...)`` (``"*"``: every partition) or ``("partitions", table)``. Its state is a digest of
its files' (name, inode, size, modification time), or of the partitions listed with their folders'
modification times. Files are written whole, under new names or by an atomic rename (a new inode),
so an unchanged state means unchanged data.

A value is stored only when nothing it read was modified while it was computed: its state is the
same after as before, and, file times coming from a coarse clock, no file or folder it read changed
(written or renamed) later than the computation's start minus :data:`SETTLE_NS`. Storing is best effort (a read-only warehouse keeps
nothing). :mod:`tasks.inputs_memo` keeps the stages' input digests by these rules; :func:`kept_read`
keeps any value, in ``_cache/reads/<name>.json``: ``cadestate status`` its ``runs`` rows (those of
every clip, or of each clip it is given, ``runs/<clip>.json``: one file per clip, not one per set
of clips asked about), ``cadestate tables`` its row counts, each read again (DuckDB imported,
every file opened) only when a file came or went. :class:`KeptInMemory` keeps values in a
long-lived process's memory instead, each with the reads its computation made (recorded:
:func:`cadestate.lineage.recording_reads`): the annotation app's start page, each clip's tasks,
with a copy on disk (:class:`OnDisk`) that an app started again begins with.
"""

from __future__ import annotations

import contextlib
import json
import os
import threading
import time
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cadestate.atomic import atomic_write_bytes
from cadestate.lineage import digest, recording_reads
from warehouse.store import Warehouse, check_name

SETTLE_NS = 50_000_000
"""A read whose newest file is younger than the computation's start minus this may have changed
while it was read: what was computed from it is not stored."""
VERSION = "1"
"""Bump when what a kept value means changes: every one is then computed again."""


def read_state(wh: Warehouse, read: Sequence[str]) -> tuple[str, int]:
    """Digest of the current state of one read, and the newest modification time in it (ns)."""
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
            newest = max(newest, changed_ns(st))
    except FileNotFoundError:  # a file went away while it was listed (compacted): changing now
        return "changing", time.time_ns()
    return digest(*read, *lines), newest


def changed_ns(st: os.stat_result) -> int:
    """When a file or folder last changed: its data (modification time) or its place (a rename sets
    the status-change time only: a file written, flushed for a while, then renamed into a partition
    keeps the time its data was written; a folder swapped in keeps its own)."""
    return max(st.st_mtime_ns, st.st_ctime_ns)


def _states(wh: Warehouse, reads: Sequence[tuple[str, ...]]) -> tuple[str, int]:
    """The state of several reads as one digest, and the newest modification time in any."""
    states = [read_state(wh, r) for r in reads]
    return digest(*(s for s, _ in states)), max((n for _, n in states), default=0)


def kept_read(wh: Warehouse, name: str, reads: Sequence[tuple[str, ...]], compute: Callable[[], Any]) -> Any:
    """``compute()``, a JSON value made from the files of ``reads`` alone, kept in
    ``_cache/reads/<name>.json`` with their state and served while it holds (module docstring).
    ``name``: names joined by '/' (a folder of values, one per clip: ``runs/<clip>``)."""
    *folders, last = (check_name(part, "kept value") for part in name.split("/"))
    path = wh.root.joinpath("_cache", "reads", *folders, f"{last}.json")
    what = [list(r) for r in reads]
    state, _ = _states(wh, reads)
    with contextlib.suppress(OSError, ValueError, KeyError, TypeError):
        doc = json.loads(path.read_text(encoding="utf-8"))
        if doc["version"] == VERSION and doc["reads"] == what and doc["state"] == state:
            return doc["value"]
    started = time.time_ns()
    value = compute()
    after, newest = _states(wh, reads)
    if after == state and newest < started - SETTLE_NS:  # nothing came, went or changed while computing
        with contextlib.suppress(OSError):
            payload = json.dumps({"version": VERSION, "reads": what, "state": state, "value": value})
            atomic_write_bytes(path, payload.encode(), durable=False)
    return value


def _listing(folder: str) -> tuple[str, ...] | None:
    """The data files of a partition folder, sorted; None when it is missing."""
    try:
        return tuple(sorted(n for n in os.listdir(folder) if n.endswith(".parquet")))
    except FileNotFoundError:
        return None


def _settled(folder: str, started_ns: int) -> bool:
    """Whether ``folder`` (missing, or) last changed :data:`SETTLE_NS` before ``started_ns``."""
    try:
        return changed_ns(os.stat(folder)) < started_ns - SETTLE_NS
    except FileNotFoundError:
        return True


@dataclass(frozen=True)
class OnDisk:
    """Where a :class:`KeptInMemory` keeps a copy of each value it keeps, so that a process started
    later begins with them (the annotation app over 1,000 finished clips took 43 s to read every
    clip's tasks once): ``folder/<key>.json`` (keys that are not file names are not copied), valid
    for ``version`` (a digest of the code that computes the values: changed code computes them
    again); ``encode`` turns a value into JSON, ``decode`` back."""

    folder: Path
    version: str
    encode: Callable[[Any], Any]
    decode: Callable[[Any], Any]

    def load(self, root: Path, key: str) -> tuple[tuple[str, ...], tuple, Any] | None:
        """(folders, their listing, value) kept for ``key``; None when none is, or not for this
        version. Folders are kept relative to the warehouse ``root`` (a copy of the warehouse
        checks its own)."""
        with contextlib.suppress(OSError, ValueError, KeyError, TypeError):
            doc = json.loads((self.folder / f"{check_name(key, 'kept value')}.json").read_bytes())
            if doc["version"] == self.version:
                listing = tuple(None if names is None else tuple(names) for names in doc["listing"])
                return tuple(os.path.join(root, f) for f in doc["folders"]), listing, self.decode(doc["value"])
        return None

    def store(self, root: Path, key: str, folders: tuple[str, ...], listing: tuple, value: Any) -> None:
        """Keep a copy of ``value`` (best effort: a read-only warehouse keeps none)."""
        with contextlib.suppress(OSError, ValueError, TypeError):
            doc = {"version": self.version, "folders": [os.path.relpath(f, root) for f in folders], "listing": listing,
                   "value": self.encode(value)}
            atomic_write_bytes(self.folder / f"{check_name(key, 'kept value')}.json", json.dumps(doc).encode(), durable=False)


class KeptInMemory:
    """Values computed from warehouse files, each kept under a key while the partitions it read are
    unchanged; safe to share between threads. What a computation reads is recorded
    (:func:`cadestate.lineage.recording_reads`), and kept are those values that read named
    partitions only (``("files", table, partition, ...)``), with each partition's listing: the
    store never writes a name twice, so the same names are the same data, and a value is served
    again for one listing per partition (where :func:`read_state` stats every file too). A value
    computed again (a file came or went) is kept when its partitions list the same files before and
    after it was computed: no name comes back, so it saw that listing. The first value of a key
    (its partitions not known before) is kept, as above, when its folders last changed (written
    into or swapped in: :func:`changed_ns`) :data:`SETTLE_NS` before its computation; a folder time from a coarse clock
    may miss a change made meanwhile, and only that first value relies on it. With ``disk``
    (:class:`OnDisk`), a key not kept in memory is looked for there first, and what is kept is
    copied there."""

    def __init__(self, disk: OnDisk | None = None):
        self._kept: dict[str, tuple[tuple[str, ...], tuple | None, Any]] = {}
        self._flights: dict[str, threading.Lock] = {}  # held while a key's value is computed
        self._lock = threading.Lock()
        self._disk = disk

    def _served(self, wh: Warehouse, key: str) -> tuple[bool, tuple | None, tuple | None]:
        """(whether the value kept for ``key`` holds, what is kept, its folders' listing now)."""
        with self._lock:
            known = self._kept.get(key)  # (folders, their listing, value); listing None: folders only
        loaded = known is None and self._disk is not None
        if loaded:
            known = self._disk.load(wh.root, key)
        before = None if known is None else tuple(map(_listing, known[0]))
        if known is not None and known[1] is not None and before == known[1]:
            if loaded:  # kept in memory from now on (the warm path takes no second lock)
                with self._lock:
                    self._kept[key] = known
            return True, known, before
        return False, known, before

    def get(self, wh: Warehouse, key: str, compute: Callable[[], Any]) -> Any:
        """The value kept under ``key`` while what it read is unchanged, else ``compute()`` (kept so).
        A value is the one object kept: callers do not change it. Threads asking for one key while
        it is computed wait for that value (an app's first refreshes, each reading every clip, had
        computed each clip once per request in flight)."""
        hit, known, before = self._served(wh, key)
        if hit:
            return known[2]
        with self._lock:
            flight = self._flights.setdefault(key, threading.Lock())
        with flight:
            hit, known, before = self._served(wh, key)  # computed while this thread waited
            if hit:
                return known[2]
            return self._compute(wh, key, compute, known, before)

    def _compute(self, wh: Warehouse, key: str, compute: Callable[[], Any], known: tuple | None, before: tuple | None) -> Any:
        started = time.time_ns()
        with recording_reads() as noted:
            value = compute()
        if any(r[0] != "files" or "*" in r[2:] for r in noted):
            return value
        folders = tuple(dict.fromkeys(str(wh.partition_dir(r[1], p)) for r in noted for p in r[2:]))
        state = tuple(map(_listing, folders))
        if known is not None:
            keep = folders == known[0] and state == before
        else:
            keep = all(_settled(f, started) for f in folders)
        with self._lock:
            self._kept[key] = (folders, state, value) if keep else (folders, None, None)
        if keep and self._disk is not None:
            self._disk.store(wh.root, key, folders, state, value)
        return value

    def keep_only(self, keys: Collection[str]) -> None:
        """Drop the values of keys not in ``keys`` (a clip gone from the warehouse)."""
        wanted = set(keys)
        with self._lock:
            for key in [k for k in self._kept if k not in wanted]:
                del self._kept[key]
            for key in [k for k in self._flights if k not in wanted]:
                del self._flights[key]


def row_counts(wh: Warehouse) -> dict[str, int]:
    """Rows of each table (:func:`warehouse.catalog.row_counts`, which imports DuckDB and opens
    every file), kept while no file of any table came or went."""
    def count() -> dict[str, int]:
        from warehouse.catalog import row_counts as counted

        return counted(wh)

    return kept_read(wh, "row-counts", [("files", t, "*") for t in wh.info], count)
