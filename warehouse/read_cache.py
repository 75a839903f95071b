"""Results of warehouse reads kept while their files stay the same files.

A process that reads the same small tables again and again (the annotation app serving a clip's
tasks, a unit's input digests before its stages run) reads each file set once. An entry is keyed by
the table, the columns and the identity of every file read: path, inode, size and modification
time, taken by ``stat`` on every read. Files are written whole, under new names or by an atomic
rename (a new inode), so the same identities hold the same rows, and a write, a compaction or a
removal changes the key. The least recently used entries go first.
"""

from __future__ import annotations

import os
import threading
from collections import OrderedDict
from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import pyarrow as pa


class ReadCache:
    """At most ``entries`` read results (module docstring); safe to share between threads."""

    def __init__(self, entries: int = 64):
        self.entries = entries
        self._kept: OrderedDict[tuple, pa.Table] = OrderedDict()
        self._lock = threading.Lock()

    @staticmethod
    def key(table: str, files: Sequence[str], columns: Sequence[str] | None, filters: object = None) -> tuple | None:
        """The identity of a read of ``files`` with ``columns`` and ``filters`` (None, or DNF tuples as
        :meth:`warehouse.store.Warehouse.read` takes them); None when it is not kept: a file is gone,
        or the filter is an expression (read it, keep nothing)."""
        if filters is not None and not isinstance(filters, list):
            return None
        try:
            ids = tuple((f, st.st_ino, st.st_size, st.st_mtime_ns) for f in files for st in [os.stat(f)])
            rows = tuple(tuple(tuple(v) if isinstance(v, list) else v for v in f) for f in filters) if filters else None
            hash(rows)
        except (FileNotFoundError, TypeError):  # a file gone; a filter value that cannot be hashed
            return None
        return table, ids, tuple(columns) if columns else None, rows

    def get(self, key: tuple) -> pa.Table | None:
        with self._lock:
            hit = self._kept.get(key)
            if hit is not None:
                self._kept.move_to_end(key)
            return hit

    def put(self, key: tuple, result: pa.Table) -> None:
        with self._lock:
            self._kept[key] = result
            while len(self._kept) > self.entries:
                self._kept.popitem(last=False)
