"""Results of warehouse reads kept while their files stay the same files.

A process that reads the same small tables again and again (the annotation app serving a clip's
tasks, a unit's input digests before its stages run) reads each file set once, and each file once:
a read of a table one file of which is new reads that file alone (the others' rows are kept file by
file, within ``file_bytes``), and a file the process wrote itself is kept as written. An entry is keyed by
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


FILE_BYTES = 256 * 2**20
"""Default bound on the rows kept file by file, and on the read results kept (Arrow bytes each): a
long-lived process whose stages read large tables through the cache stays within ~0.5 GB for it."""


class ReadCache:
    """At most ``entries`` read results, of ``file_bytes`` at most together, and files' rows of
    ``file_bytes`` at most (module docstring); safe to share between threads."""

    def __init__(self, entries: int = 64, file_bytes: int = FILE_BYTES):
        self.entries = entries
        self.file_bytes = file_bytes
        self._kept: OrderedDict[tuple, pa.Table] = OrderedDict()
        self._kept_total = 0
        self._files: OrderedDict[tuple, pa.Table] = OrderedDict()
        self._file_total = 0
        self._lock = threading.Lock()

    @staticmethod
    def key(table: str, files: Sequence[str], columns: Sequence[str] | None, filters: object = None) -> tuple | None:
        """The identity of a read of ``files`` with ``columns`` and ``filters`` (None, or DNF tuples as
        :meth:`warehouse.store.Warehouse.read` takes them); None when it is not kept: a file is gone,
        or the filter is an expression (read it, keep nothing)."""
        if filters is not None and not isinstance(filters, list):
            return None
        ids = tuple(ReadCache.file_identity(f) for f in files)
        if None in ids:  # a file gone
            return None
        try:
            rows = tuple(tuple(tuple(v) if isinstance(v, list) else v for v in f) for f in filters) if filters else None
            hash(rows)
        except TypeError:  # a filter value that cannot be hashed
            return None
        return table, ids, tuple(columns) if columns else None, rows

    def get(self, key: tuple) -> pa.Table | None:
        with self._lock:
            hit = self._kept.get(key)
            if hit is not None:
                self._kept.move_to_end(key)
            return hit

    @staticmethod
    def file_identity(path: str) -> tuple | None:
        """The identity of one data file: path, inode, size and modification time (None: it is gone)."""
        try:
            st = os.stat(path)
        except FileNotFoundError:
            return None
        return path, st.st_ino, st.st_size, st.st_mtime_ns

    def get_file(self, identity: tuple, schema: pa.Schema, names: tuple[str, ...] | None = None) -> pa.Table | None:
        """The rows of the file ``identity`` as ``schema`` (the table's schema or some of its columns;
        ``names``: its column names, when the caller reads many files as one schema): kept as read
        with those columns, or cut from the whole file's rows when those are kept (and kept so)."""
        import pyarrow as pa

        wanted = names if names is not None else tuple(schema.names)
        with self._lock:
            for key in ((identity, wanted), (identity, None)):
                hit = self._files.get(key)
                if hit is not None:
                    self._files.move_to_end(key)
                    break
        if hit is None or key[1] is not None:
            return hit
        if hit.schema.equals(schema, check_metadata=True):  # the whole file's rows, as kept
            return hit
        if not set(wanted) <= set(hit.column_names):
            return None
        cut = pa.Table.from_arrays([hit.column(n) for n in wanted], schema=schema)
        self.put_file(identity, cut)  # the next read of these columns takes it as is (its columns are the whole's)
        return cut

    def put_file(self, identity: tuple, part: pa.Table, whole: bool = False) -> None:
        """Keep one file's rows (``whole``: every column of its table, which any read of some of
        them can be cut from); the least recently used go while the kept rows exceed ``file_bytes``."""
        key = (identity, None if whole else tuple(part.column_names))
        with self._lock:
            if key in self._files:
                return
            self._files[key] = part
            self._file_total += part.nbytes
            while self._file_total > self.file_bytes and len(self._files) > 1:
                _, gone = self._files.popitem(last=False)
                self._file_total -= gone.nbytes

    def written(self, path: str, table: pa.Table) -> None:
        """A file this process has just written with ``table`` (every column of its table, cast to
        its schema): kept, so that the next read of it reads nothing (a reader of the same warehouse
        finds what a writer of it left)."""
        identity = self.file_identity(path)
        if identity is not None:
            self.put_file(identity, table, whole=True)

    def put(self, key: tuple, result: pa.Table) -> None:
        with self._lock:
            if key in self._kept:
                self._kept_total -= self._kept.pop(key).nbytes
            self._kept[key] = result
            self._kept_total += result.nbytes
            while self._kept and (len(self._kept) > self.entries or self._kept_total > self.file_bytes):
                _, gone = self._kept.popitem(last=False)
                self._kept_total -= gone.nbytes
