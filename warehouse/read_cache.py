"""Results of warehouse reads kept while their files stay the same files.

A process that reads the same small tables again and again (the annotation app serving a clip's
tasks, a unit's input digests before its stages run) reads each file set once, and each file once:
a read of a table one file of which is new reads that file alone (the others' rows are kept file by
file, within ``file_bytes``), and a file the process wrote itself is kept as written. An entry is keyed by
the table, the columns and the path of every file read. The store never writes a name twice (a file
is named ``<time>-<id>.parquet`` once written; a replace-mode write or a compaction swaps in a
folder of new names: :mod:`warehouse.store`), so a path holds one content for good, and a write, a
compaction or a removal changes the listing a read takes, and so its key. (It stat-ed every file of
every read before: on a clip with 30-60 files in its label and run partitions, about 800 calls a
label round.) The least recently used entries go first.
"""

from __future__ import annotations

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
        """The identity of a read of ``files`` (paths, as listed) with ``columns`` and ``filters`` (None,
        or DNF tuples as :meth:`warehouse.store.Warehouse.read` takes them); None when it is not kept:
        the filter is an expression (read it, keep nothing)."""
        if filters is not None and not isinstance(filters, list):
            return None
        try:
            rows = tuple(tuple(tuple(v) if isinstance(v, list) else v for v in f) for f in filters) if filters else None
            hash(rows)
        except TypeError:  # a filter value that cannot be hashed
            return None
        return table, tuple(files), tuple(columns) if columns else None, rows

    def get(self, key: tuple) -> pa.Table | None:
        with self._lock:
            hit = self._kept.get(key)
            if hit is not None:
                self._kept.move_to_end(key)
            return hit

    def get_file(self, path: str, schema: pa.Schema, names: tuple[str, ...] | None = None) -> pa.Table | None:
        """The rows of the file ``path`` as ``schema`` (the table's schema or some of its columns;
        ``names``: its column names, when the caller reads many files as one schema): kept as read
        with those columns, or cut from the whole file's rows when those are kept (and kept so)."""
        import pyarrow as pa

        wanted = names if names is not None else tuple(schema.names)
        with self._lock:
            for key in ((path, wanted), (path, None)):
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
        self.put_file(path, cut)  # the next read of these columns takes it as is (its columns are the whole's)
        return cut

    def put_file(self, path: str, part: pa.Table, whole: bool = False) -> None:
        """Keep one file's rows (``whole``: every column of its table, which any read of some of
        them can be cut from); the least recently used go while the kept rows exceed ``file_bytes``."""
        key = (path, None if whole else tuple(part.column_names))
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
        self.put_file(path, table, whole=True)

    def put(self, key: tuple, result: pa.Table) -> None:
        with self._lock:
            if key in self._kept:
                self._kept_total -= self._kept.pop(key).nbytes
            self._kept[key] = result
            self._kept_total += result.nbytes
            while self._kept and (len(self._kept) > self.entries or self._kept_total > self.file_bytes):
                _, gone = self._kept.popitem(last=False)
                self._kept_total -= gone.nbytes
