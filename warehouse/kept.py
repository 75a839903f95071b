"""Values computed from warehouse files, kept with the state of those files and served while it holds.

A read is named as the warehouse notes it (:func:`cadestate.lineage.note_read`): ``("files", table,
partition, ...)`` (``"*"``: every partition) or ``("partitions", table)``. Its state is a digest of
its files' (name, inode, size, modification time), or of the partitions listed with their folders'
modification times. Files are written whole, under new names or by an atomic rename (a new inode),
so an unchanged state means unchanged data.

A value is stored only when nothing it read was modified while it was computed: file times come
from a coarse clock, so a read whose newest file is younger than the computation's start minus
:data:`SETTLE_NS` may have changed meanwhile. Storing is best effort (a read-only warehouse keeps
nothing). :mod:`tasks.inputs_memo` keeps the stages' input digests by these rules; :func:`kept_read`
keeps any value, in ``_cache/reads/<name>.json``: ``cadestate status`` its ``runs`` rows (those of
every clip, or of each clip it is given, ``runs/<clip>.json``: one file per clip, not one per set
of clips asked about), ``cadestate tables`` its row counts, each read again (DuckDB imported,
every file opened) only when a file came or went.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
from collections.abc import Callable, Sequence
from typing import Any

from cadestate.atomic import atomic_write_bytes
from cadestate.lineage import digest
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
            newest = max(newest, st.st_mtime_ns)
    except FileNotFoundError:  # a file went away while it was listed (compacted): changing now
        return "changing", time.time_ns()
    return digest(*read, *lines), newest


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
    state, newest = _states(wh, reads)
    if newest < started - SETTLE_NS:
        with contextlib.suppress(OSError):
            payload = json.dumps({"version": VERSION, "reads": what, "state": state, "value": value})
            atomic_write_bytes(path, payload.encode(), durable=False)
    return value


def row_counts(wh: Warehouse) -> dict[str, int]:
    """Rows of each table (:func:`warehouse.catalog.row_counts`, which imports DuckDB and opens
    every file), kept while no file of any table came or went."""
    def count() -> dict[str, int]:
        from warehouse.catalog import row_counts as counted

        return counted(wh)

    return kept_read(wh, "row-counts", [("files", t, "*") for t in wh.info], count)
