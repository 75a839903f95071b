"""Parquet storage: one folder per table, one sub-folder per partition (a clip, or a CAD library).

Layout under the warehouse root::

    tables/<table>/clip=<clip>/<time>-<id>.parquet replace-mode tables: one file, swapped whole
                                                   append-mode tables: one file per write
    tables/<table>/library=<library>/...           CAD-library tables, partitioned by library
    tables/<table>/_schema/_schema.parquet         the table's schema, no rows (warehouse.catalog)
    media/<kind>/<partition>/<version>/...         images and other files that rows point to
    inputs/<clip>/...                              the clip's video and camera file
    catalog.duckdb                                 DuckDB views over every table (warehouse.catalog)
    _prefect/                                      Prefect's local state and cached task results
    _locks/<table>/<partition>.lock                locks of partitions (writes, compaction)
    _locks/catalog.lock                            lock of compaction and the snapshot (warehouse.catalog)
    _locks/_units/<clip or library>.lock           held by a run of the unit's stages (tasks.stage_chain.run_unit)
    _cache/inputs/<partition>.json                 input digests that `cadestate status` keeps (tasks.inputs_memo)
    _cache/reads/...                               values kept with their files' state: status's runs, row counts, the annotation app's clip states (warehouse.kept)
    _claims/<item digest>.json                     items the annotation app's pages hold (cadestate.webapp.claims)

File names: ``<time>-<id>.parquet``, ``<time>`` the 20-digit nanoseconds since the epoch at which
the file was published (taken just before it becomes visible), ``<id>`` random. Every write makes a
new name, so a name stands for one content, and names sort in write order: the catalog's snapshot
(:mod:`warehouse.snapshot`) holds the rows of the files named before its watermark and reads only
the newer ones at query time. (Older warehouses named a replace-mode file ``part.parquet``; such a
name sorts after every time, so it is always read as a new file; ``cadestate compact`` renames it.)

Atomicity: every Parquet file is written under a temporary name, flushed to disk and renamed into
place, so a reader or a crash sees the old file or the new one, never half of one. A replace-mode
partition is swapped whole: its new file is written into a fresh folder under ``_staging/``, which
then takes the partition folder's name in one step (:func:`cadestate.atomic.exchange`; a plain
rename for a new partition), under the partition's lock. Media are written to a fresh version folder that no row points to
yet; rows start pointing to it only when their table partition is swapped in, and superseded
versions are removed afterwards (:meth:`Warehouse.publish_media`).

Compaction: an append-mode partition gains a file per write, and readers pay per file, so a write
that leaves more than ``compact_after`` files in one (or ``cadestate compact``) merges them into
one file of the table's current schema (rows in write order; files of an older schema read a newer
column as null). The merged file (named at the time of the merge, so it sorts after every file it
replaces) is written into a fresh folder under ``_staging/`` (outside every table, so no glob sees
it) and flushed; then that folder and the partition folder swap names in one
step (:func:`cadestate.atomic.exchange`), and the old files, now in the staging folder, are
removed. A reader listing the partition sees all the old files or the merged one (under a new
name), never both (rows twice); one that listed the old files and opens one after the swap finds
it gone and fails rather than answer wrong (:meth:`Warehouse.read` lists that partition again; a
DuckDB query reports the missing file, and run again answers). A DuckDB glob (the catalog's views)
whose listing a swap overtakes leaves that partition's rows out without an error instead: it reads
a folder's names, then checks each by its path, which by then leads to the new folder, and drops
the names it does not find there. So `cadestate sql` plans a statement again when a table's folder
changed while it was planned (:meth:`Warehouse.table_times`, :func:`warehouse.query.run_query`);
another DuckDB client of ``catalog.duckdb`` may miss a clip's rows while a batch rewrites it.
Interrupted at any point, a compaction leaves the partition as it was or compacted, plus a staging
folder nothing reads. Writes to a partition and its compaction hold the partition's lock
(:meth:`Warehouse.locked`), so no write lands in a folder being swapped out.
"""

from __future__ import annotations

import contextlib
import difflib
import errno
import fcntl
import functools
import os
import shutil
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from cadestate.atomic import TMP_SUFFIX, atomic_write_bytes, exchange, fsync_dir  # noqa: F401  (atomic_write_bytes: also warehouse's)
from cadestate.lineage import note_read
from cadestate.names import NAME

if TYPE_CHECKING:  # pyarrow is imported where a table is read or written: commands that only query pay nothing for it
    import pyarrow as pa
    import pyarrow.compute as pc

    from schemas import TableSpec
    from schemas.index import TableInfo
    from warehouse.read_cache import ReadCache

LEGACY_FILE = "part.parquet"
"""Name of a replace-mode file in warehouses written before file names held their time."""
STALE_STAGING_S = 86_400.0
"""A ``_staging/`` folder untouched this long is a killed process's: removed (a swap's or a stage's
media; a folder's time changes only when an entry is made in it, so the age is far above any write's)."""
COMPACT_AFTER = 64
"""Default of :attr:`Warehouse.compact_after` (config ``[warehouse] compact_after_files``)."""
READ_RETRIES = 5
"""Times :meth:`Warehouse.read` lists the files again when one vanished (compacted) while it read."""

AFTER_WRITE: list[Callable[[Warehouse], object]] = []
"""Called with the warehouse after each partition write. The package (``warehouse/__init__.py``) adds
the DuckDB catalog's refresh, so this module knows nothing of the catalog, which is built on it."""


def _changes_meaning(given: pa.DataType, wanted: pa.DataType) -> bool:
    """Whether casting a column of type ``given`` to ``wanted`` would reinterpret it rather than
    widen it: a number to a time, text to a number or a time, anything but text to text. Nulls,
    and numbers to numbers, cast as before."""
    import pyarrow as pa

    def text(t: pa.DataType) -> bool:
        return pa.types.is_string(t) or pa.types.is_large_string(t)

    if given == wanted or pa.types.is_null(given) or pa.types.is_dictionary(given):
        return False
    if pa.types.is_timestamp(wanted) or pa.types.is_date(wanted):
        return not (pa.types.is_timestamp(given) or pa.types.is_date(given))
    if pa.types.is_integer(wanted) or pa.types.is_floating(wanted) or pa.types.is_boolean(wanted):
        return text(given)
    if text(wanted):
        return not text(given)
    return False


def warn(message: str) -> None:
    """One line on stderr, ``warning: <message>``: what went wrong after the data was safely in."""
    import sys

    print(f"warning: {message}", file=sys.stderr, flush=True)


def _vanished(e: OSError) -> bool:
    """Whether ``e`` says a file is not there (pyarrow raises some as plain OSError, errno unset)."""
    return isinstance(e, FileNotFoundError) or e.errno == errno.ENOENT or "No such file" in str(e)


def _read_files(files: Sequence[str], schema: pa.Schema, columns: Sequence[str] | None,
                cache: ReadCache | None = None) -> pa.Table:
    """The rows of ``files`` in order, as ``pyarrow.dataset.dataset(files, schema=schema).to_table(columns)``
    gives them (a column a file lacks reads as null, every column cast to ``schema``), without
    importing pyarrow.dataset; through ``cache``, a file whose rows it keeps is not opened."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    target = pa.schema([schema.field(c) for c in columns], metadata=schema.metadata) if columns else schema
    names = tuple(target.names)
    parts = []
    for f in files:
        if cache is not None and (kept := cache.get_file(f, target, names)) is not None:
            parts.append(kept)
            continue
        try:
            pf = pq.ParquetFile(f)
            present = set(pf.schema_arrow.names)
            table = pf.read(columns=[n for n in target.names if n in present])
        except pa.ArrowException as e:  # a truncated or overwritten file (a disk full, a copy cut short)
            why = " ".join(str(e).split())[:200]
            raise WarehouseError(f"{f}: damaged table file ({why}): restore it from a backup; "
                                 "a stage's output is written again by `cadestate run` once its partition "
                                 "folder is removed") from None
        arrays = [table.column(fl.name).cast(fl.type) if fl.name in present else pa.nulls(table.num_rows, fl.type)
                  for fl in target]
        parts.append(pa.Table.from_arrays(arrays, schema=pa.schema(
            [fl.with_nullable(fl.nullable or a.null_count > 0) for fl, a in zip(target, arrays)], metadata=target.metadata)))
        if cache is not None:
            cache.put_file(f, parts[-1], whole=columns is None)
    return _concat(parts)


def _concat(parts: list[pa.Table]) -> pa.Table:
    """``parts`` as one table; a column is nullable where a part's is: a column added to a table
    since a file was written reads as nulls there (even one the schema says is never null), and
    a file merged from those keeps them."""
    import pyarrow as pa

    if len({p.schema for p in parts}) > 1:
        first = parts[0].schema
        schema = pa.schema([fl.with_nullable(any(p.schema.field(i).nullable for p in parts))
                            for i, fl in enumerate(first)], metadata=first.metadata)
        parts = [p.cast(schema) for p in parts]
    return pa.concat_tables(parts)


def _read_listed(files: Sequence[str], schema: pa.Schema, columns: Sequence[str] | None,
                 cache: ReadCache | None = None) -> pa.Table:
    """:func:`_read_files` of ``files`` partition by partition (their folders, in order): a file that
    vanishes (its partition swapped by a write) makes that partition alone listed again, up to
    :data:`READ_RETRIES` times, so that a read of every clip goes through while a batch writes."""
    import pyarrow as pa

    folders: dict[str, list[str]] = {}
    for f in files:
        folders.setdefault(os.path.dirname(f), []).append(f)
    parts = []
    for folder, listed in folders.items():
        for attempt in range(READ_RETRIES):
            try:
                if listed:
                    parts.append(_read_files(listed, schema, columns, cache))
                break
            except OSError as e:
                if not _vanished(e) or attempt == READ_RETRIES - 1:
                    raise
                listed = data_files(folder)
    if not parts:
        target = pa.schema([schema.field(c) for c in columns], metadata=schema.metadata) if columns else schema
        return target.empty_table()
    return _concat(parts)


SMALL_TABLE_BYTES = 64 * 1024
"""Tables smaller than this (in memory) are written uncompressed: a run record, a label file's rows.
Measured on a one-row ``runs`` table (12 columns): zstd costs 1.45 ms a file against 0.73 ms
uncompressed, and encoding in memory and writing the bytes 0.36 ms; a file this small gains
nothing from compression (a compaction's merged file is compressed once it reaches this size)."""


def parquet_bytes(data: pa.Table) -> bytes:
    """``data`` as the bytes of an uncompressed Parquet file."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    sink = pa.BufferOutputStream()
    pq.write_table(data, sink, compression="none")
    return sink.getvalue().to_pybytes()


def data_files(folder: Path | str) -> list[str]:
    """The paths of the ``*.parquet`` files of one partition folder, sorted by name (none when it is
    missing); listed with ``os.listdir`` and joined as strings: ``Path.glob`` and sorting paths cost
    about 10x more, and every read lists its partitions. A listing is taken again when the folder
    was swapped while it was read (a compaction: the folder read may be the old one, its files being
    removed, which would list fewer files or none)."""
    base = os.fspath(folder)
    prefix = os.path.join(base, "")  # joined once: os.path.join per file cost ~1 us each, every read
    while True:
        try:
            before = os.stat(base).st_ino
            names = os.listdir(base)
            if os.stat(base).st_ino == before:
                return [prefix + n for n in sorted(names) if n.endswith(".parquet")]
        except (FileNotFoundError, NotADirectoryError):
            return []
        except OSError as e:  # a folder it may not read: one line naming it, not a traceback
            raise WarehouseError(f"{base}: cannot list its files: {e.strerror or e}") from None


@contextlib.contextmanager
def file_lock(path: Path) -> Iterator[None]:
    """Hold an exclusive ``flock`` on ``path`` (made, with its folder, if missing); a
    :class:`WarehouseError` naming it when it cannot be made or opened."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        f = open(path, "a")
    except OSError as e:
        raise WarehouseError(f"{path}: cannot take its lock: {e.strerror or e}") from None
    with f:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)


def file_name(time_ns: int | None = None) -> str:
    """A data file's name: ``<time>-<id>.parquet`` (see the module), at ``time_ns`` (default now)."""
    return f"{time.time_ns() if time_ns is None else time_ns:020d}-{uuid.uuid4().hex[:8]}.parquet"


@functools.cache
def _published_index() -> dict[str, TableInfo] | None:
    """:func:`schemas.index.read_index`, read once per process (every :class:`Warehouse` asks; the
    schema modules a process imported do not change under it)."""
    from schemas.index import read_index

    return read_index()


class WarehouseError(ValueError):
    """Data that does not fit its table, or an unknown table or partition."""


def _unknown_table(table: str, known) -> str:
    """One line for a table name that is none of ``known``: the nearest name, and where all are listed
    (29 names made a line of 500 characters)."""
    near = difflib.get_close_matches(table, sorted(known), n=1)
    return f"unknown table {table!r}" + (f" (did you mean {near[0]!r}?)" if near else "") + \
        f": `cadestate tables` lists the {len(known)} tables"


def is_name(name: object) -> bool:
    """Whether ``name`` can be a clip, library or model name (:func:`check_name`)."""
    return isinstance(name, str) and bool(NAME.match(name))


def check_name(name: str, what: str = "clip") -> str:
    """Clip, library and model names become folder and file names: letters, digits, '_', '.', '-'
    (at most 200, not starting with '.', not only '-' and '.'; see :data:`NAME`)."""
    if not is_name(name):
        raise WarehouseError(
            f"invalid {what} name {name!r}: use letters, digits, '_', '.' and '-' (at most 200, not starting with '.', "
            "not only '-' and '.')"
        )
    return name


@dataclass(frozen=True)
class Compacted:
    """One partition compacted: ``files`` merged into one file of ``rows`` rows."""

    table: str
    partition: str
    files: int
    rows: int


TABLES_DIR = "tables"
"""The warehouse's folder of tables (``tables/<table>/...``): what tells a warehouse from another folder."""
DIRS_KEPT = 4096
"""How many table and partition folders a :class:`Warehouse` keeps made (:meth:`Warehouse.partition_dir`)."""


class Warehouse:
    """A warehouse rooted at a local directory. A write to an append-mode table that leaves more
    than ``compact_after`` files in its partition compacts the partition."""

    def __init__(self, root: str | os.PathLike, tables: dict[str, TableSpec] | None = None,
                 compact_after: int = COMPACT_AFTER):
        self.root = Path(root).expanduser().resolve()
        if "\\" in self.root.as_posix():  # DuckDB reads it as a folder separator: the views would read no file
            raise WarehouseError(f"{self.root}: a warehouse's path cannot hold a backslash (DuckDB takes it for "
                                 "a folder separator); choose another folder")
        self._tables = tables
        self._default_tables = tables is None  # `tables` fills _tables in: the index stays theirs
        self._info: dict[str, TableInfo] | None = None
        self.compact_after = compact_after
        self._cache: ReadCache | None = None
        self._dirs: dict[tuple[str, str | None], Path] = {}

    @property
    def tables(self) -> dict[str, TableSpec]:
        """The table specs (default: every table of :data:`schemas.TABLES`, imported on first use)."""
        if self._tables is None:
            from schemas import TABLES

            self._tables = TABLES
        return self._tables

    @property
    def info(self) -> dict[str, TableInfo]:
        """What the layout and the catalog need of each table (no pyarrow schema): from the published
        index for the default tables (:mod:`schemas.index`), else from the table specs."""
        if self._info is None:
            from schemas.index import table_info

            index = _published_index() if self._default_tables else None
            self._info = dict(index) if index is not None else {n: table_info(s) for n, s in self.tables.items()}
        return self._info

    def _table(self, table: str) -> TableInfo:
        try:
            return self.info[table]
        except KeyError:
            raise WarehouseError(_unknown_table(table, self.info)) from None

    def __repr__(self) -> str:
        return f"Warehouse({str(self.root)!r})"

    # -- layout ------------------------------------------------------------------------------
    def spec(self, table: str) -> TableSpec:
        try:
            return self.tables[table]
        except KeyError:
            raise WarehouseError(_unknown_table(table, self.tables)) from None

    def table_dir(self, table: str) -> Path:
        return self._folder(table, None)

    def partition_dir(self, table: str, part: str) -> Path:
        return self._folder(table, part)

    def _folder(self, table: str, part: str | None) -> Path:
        """The folder of partition ``part`` of ``table`` (None: the table's folder). Kept once made,
        up to :data:`DIRS_KEPT` of them: every read and write asks for the folders of the tables it
        touches, and a label round's digests alone asked about 2,000 times, 2 ms of path building."""
        key = (table, part)
        if (kept := self._dirs.get(key)) is not None:
            return kept
        info = self._table(table)
        folder = self.root / TABLES_DIR / info.name
        if part is not None:
            folder = folder / f"{info.partition}={check_name(part, info.partition)}"
        if len(self._dirs) >= DIRS_KEPT:
            self._dirs.clear()
        self._dirs[key] = folder
        return folder

    def inputs_dir(self, clip: str) -> Path:
        return self.root / "inputs" / check_name(clip)

    def files(self, table: str, partitions: Sequence[str] | None = None) -> list[Path]:
        """Data files of ``table`` (all partitions, or the named ones), sorted."""
        return [Path(f) for f in self.file_paths(table, partitions)]

    def file_paths(self, table: str, partitions: Sequence[str] | None = None) -> list[str]:
        """:meth:`files` as strings (what readers open; no ``Path`` made per file)."""
        note_read("files", table, *(["*"] if partitions is None else partitions))
        base = self.table_dir(table)
        if partitions is None:
            dirs = sorted(base.glob(f"{self._table(table).partition}=*"))
        else:
            dirs = [self.partition_dir(table, p) for p in partitions]
        return [f for d in dirs for f in data_files(d)]

    def table_times(self) -> tuple[int, ...]:
        """The modification time (ns) of each table's folder, in the order of :attr:`info` (0 for a
        table with none yet). Swapping a partition in (a replace-mode write, a compaction) changes its
        table's, as does making a partition; adding a file to a partition does not. `cadestate sql`
        plans a statement again when they changed while it was planned (:func:`warehouse.query.run_query`).
        Exact where the kernel gives a folder changed after it was looked at a new time (Linux 6.13 on);
        where times keep to the kernel's tick, a swap in the tick of the table's previous change is not seen."""
        times = []
        for name in self.info:
            try:
                times.append(os.stat(self.table_dir(name)).st_mtime_ns)
            except FileNotFoundError:
                times.append(0)
        return tuple(times)

    def has_partition(self, table: str, part: str) -> bool:
        """Whether ``table`` has data in partition ``part`` (one folder looked at, not every partition;
        a name no partition can have has none)."""
        if not is_name(part):
            return False
        return bool(self.file_paths(table, [part]))

    def partitions(self, table: str) -> list[str]:
        """Partitions (clips, or libraries) that have data in ``table``."""
        note_read("partitions", table)
        prefix = f"{self._table(table).partition}="
        return sorted(d.name[len(prefix):] for d in self.table_dir(table).glob(prefix + "*") if data_files(d))

    # -- writing -----------------------------------------------------------------------------
    @contextlib.contextmanager
    def locked(self, table: str, part: str) -> Iterator[None]:
        """Hold the lock of one partition (``_locks/``, an exclusive ``flock``): writes to it and its
        compaction take it, so none happens while another is under way."""
        with file_lock(self.root / "_locks" / self._table(table).name / f"{self.partition_dir(table, part).name}.lock"):
            yield

    def conform(self, table: str, part: str, data: pa.Table) -> pa.Table:
        """Check ``data`` against the table's schema and return it cast to that schema exactly."""
        import pyarrow as pa
        import pyarrow.compute as pc

        spec = self.spec(table)
        names = set(data.column_names)
        missing = [n for n in spec.schema.names if n not in names]
        extra = sorted(names - set(spec.schema.names))
        if missing or extra:
            raise WarehouseError(f"table {table}: missing columns {missing}, unexpected columns {extra}")
        for f in spec.schema:
            if not f.nullable and data.column(f.name).null_count:
                raise WarehouseError(f"table {table}: column {f.name!r} has nulls but is not nullable")
            if _changes_meaning(data.schema.field(f.name).type, f.type):
                raise WarehouseError(f"table {table}: column {f.name!r} is {data.schema.field(f.name).type}, not "
                                     f"{f.type} (a cast would change its meaning: seconds read as a time, text as a number)")
        try:
            data = data.select(spec.schema.names).cast(spec.schema)
        except (pa.ArrowInvalid, pa.ArrowTypeError, pa.ArrowNotImplementedError) as e:
            raise WarehouseError(f"table {table}: data does not fit the schema: {e}") from None
        column = spec.partition
        if data.num_rows and not pc.all(pc.equal(data.column(column), part)).as_py():
            raise WarehouseError(f"table {table}: every row of partition {part!r} must have {column} = {part!r}")
        if data.num_rows > 1:  # append tables too: a write adds no two rows of one key (earlier writes are not read)
            counts = data.group_by(list(spec.key)).aggregate([([], "count_all")])
            dup = counts.filter(pc.greater(counts.column("count_all"), 1))
            if dup.num_rows:
                first = {k: dup.column(k)[0].as_py() for k in spec.key}
                raise WarehouseError(f"table {table}: duplicate key {first} ({dup.num_rows} duplicated keys)")
        return data

    def write(self, table: str, part: str, data: pa.Table) -> int:
        """Write one partition atomically; returns the rows written.

        ``replace`` tables: the partition becomes exactly ``data``, swapped whole (rewriting
        identical data is a no-op in effect: idempotent). ``append`` tables: ``data`` is added as a
        new file, and the partition is compacted when it has more than ``compact_after`` files.
        Both under the partition's lock.
        """
        spec = self.spec(table)
        data = self.conform(table, part, data)
        folder = self.partition_dir(table, part)
        with self.locked(table, part):
            if spec.mode == "replace":
                written = self._swap_in(folder, data)
            else:
                folder.mkdir(parents=True, exist_ok=True)
                written = self._write_file(data, folder)
            if self._cache is not None:  # this process's next read of the file reads nothing
                self._cache.written(str(written), data)
            if spec.mode == "append" and len(data_files(folder)) > self.compact_after:
                try:
                    self._compact_locked(table, part, 2)
                except Exception as e:  # noqa: BLE001  (the rows are in: raising would have them written twice on a retry)
                    warn(f"table {table}, partition {part}: not compacted after a write ({type(e).__name__}: "
                         f"{' '.join(str(e).split())[:300]}); `cadestate compact` merges it")
        for hook in AFTER_WRITE:  # the DuckDB catalog's refresh (warehouse/__init__.py): its views follow the tables
            hook(self)
        return data.num_rows

    @staticmethod
    def _write_file(data: pa.Table, folder: Path) -> Path:
        """Write ``data`` into ``folder`` atomically (a flushed temporary file renamed into place),
        named (:func:`file_name`) once written, just before it shows; returns its path. A table of
        under :data:`SMALL_TABLE_BYTES` is encoded in memory without compression (:func:`parquet_bytes`)."""
        import pyarrow.parquet as pq

        tmp = folder / f".{uuid.uuid4().hex}{TMP_SUFFIX}"
        try:
            if data.nbytes < SMALL_TABLE_BYTES:
                with open(tmp, "wb") as f:
                    f.write(parquet_bytes(data))
                    f.flush()
                    os.fsync(f.fileno())
            else:
                pq.write_table(data, tmp, compression="zstd")
                with open(tmp, "rb+") as f:
                    os.fsync(f.fileno())
            final = folder / file_name()
            os.replace(tmp, final)
        finally:
            tmp.unlink(missing_ok=True)
        fsync_dir(folder)
        return final

    def _swap_in(self, folder: Path, data: pa.Table) -> Path:
        """Make ``data`` the only file of the partition ``folder`` in one step (see the module): a
        replace-mode write, or a compaction's merged file. Returns the file's path."""
        stage = self.root / "_staging" / f"swap-{uuid.uuid4().hex}"
        stage.mkdir(parents=True)
        try:
            name = self._write_file(data, stage).name
            if folder.is_dir():
                exchange(stage, folder)  # the partition now holds the new file, the staging folder the old one
            else:
                folder.parent.mkdir(parents=True, exist_ok=True)
                os.rename(stage, folder)
            fsync_dir(folder.parent)
        finally:
            shutil.rmtree(stage, ignore_errors=True)
        self._sweep_staging()
        return folder / name

    def _sweep_staging(self, now: float | None = None) -> None:
        """Remove the ``_staging/`` folders of processes killed mid-write (untouched for :data:`STALE_STAGING_S`)."""
        now = time.time() if now is None else now
        with contextlib.suppress(OSError):
            for entry in (self.root / "_staging").iterdir():
                with contextlib.suppress(OSError):
                    if now - entry.stat().st_mtime > STALE_STAGING_S:
                        shutil.rmtree(entry, ignore_errors=True)

    def rename_legacy(self) -> dict[str, int]:
        """Give every replace-mode file still named ``part.parquet`` (an older warehouse) a name of
        this layout, from its modification time, under its partition's lock; returns the files
        renamed per table."""
        renamed: dict[str, int] = {}
        for name, info in self.info.items():
            if info.mode != "replace":
                continue
            for old in sorted(self.table_dir(name).glob(f"{info.partition}=*/{LEGACY_FILE}")):
                with self.locked(name, old.parent.name.split("=", 1)[1]):
                    with contextlib.suppress(FileNotFoundError):  # rewritten meanwhile: the write renamed it
                        os.rename(old, old.parent / file_name(old.stat().st_mtime_ns))
                        fsync_dir(old.parent)
                        renamed[name] = renamed.get(name, 0) + 1
        return renamed

    def compact(self, table: str, part: str, min_files: int = 2) -> Compacted | None:
        """Merge the files of one partition of an append-mode table into one (see the module), under
        the partition's lock; None when it has fewer than ``min_files`` files."""
        if self.spec(table).mode != "append":
            raise WarehouseError(f"table {table} is not append-mode (one file per partition): nothing to compact")
        with self.locked(table, part):
            return self._compact_locked(table, part, min_files)

    def drop_rows(self, table: str, part: str, dropped: Callable[[pa.Table], Sequence[bool]]) -> int:
        """Rewrite one partition of an append-mode table without the rows that ``dropped`` marks
        (given the partition's rows, read under its lock; one flag a row): merged into one file and
        swapped in, as a compaction. For debris that no commit record names (a label file's answers
        written by a process killed before its ``label_files`` row). Returns the rows dropped."""
        import pyarrow as pa

        if self.spec(table).mode != "append":
            raise WarehouseError(f"table {table} is not append-mode: its writes replace the partition whole")
        with self.locked(table, part):
            folder = self.partition_dir(table, part)
            files = data_files(folder)
            if not files:
                return 0
            rows = _read_files(files, self.spec(table).schema, None, self._cache)
            keep = [not d for d in dropped(rows)]
            if all(keep):
                return 0
            self._swap_in(folder, rows.filter(pa.array(keep, pa.bool_())))
        for hook in AFTER_WRITE:
            hook(self)
        return keep.count(False)

    def compact_tables(self, tables: Sequence[str] | None = None, min_files: int = 2) -> list[Compacted]:
        """:meth:`compact` every partition of the append-mode ``tables`` (default: all of them)."""
        names = list(tables) if tables is not None else [n for n, i in self.info.items() if i.mode == "append"]
        for name in names:
            if self.spec(name).mode != "append":
                raise WarehouseError(f"table {name} is not append-mode (one file per partition): nothing to compact")
        done = [self.compact(name, part, min_files) for name in names for part in self.partitions(name)]
        return [c for c in done if c is not None]

    def _compact_locked(self, table: str, part: str, min_files: int) -> Compacted | None:
        folder = self.partition_dir(table, part)
        files = data_files(folder)
        if len(files) < max(min_files, 1):
            return None
        merged = _read_files(files, self.spec(table).schema, None, self._cache)  # files this process keeps: not read again
        self._swap_in(folder, merged)  # named now: after every file it merges, under a name no reader has listed
        return Compacted(table, part, len(files), merged.num_rows)

    # -- reading -----------------------------------------------------------------------------
    def cache_reads(self, entries: int = 64, cache: ReadCache | None = None) -> Warehouse:
        """From now on, give the results of :meth:`read` (with no filter or with list filters) again while
        their files are the same files (:class:`warehouse.read_cache.ReadCache`, ``entries`` kept; 0: stop, and
        drop what was kept). ``cache``: keep them there instead (a long-lived process's cache, which
        outlives this object). Returns ``self``."""
        from warehouse.read_cache import ReadCache

        self._cache = cache if cache is not None else ReadCache(entries) if entries > 0 else None
        return self

    @property
    def reads_cached(self) -> bool:
        """Whether :meth:`read` keeps results (:meth:`cache_reads`)."""
        return self._cache is not None

    def read(
        self,
        table: str,
        partitions: Sequence[str] | None = None,
        filters: pc.Expression | list | None = None,
        columns: Sequence[str] | None = None,
    ) -> pa.Table:
        """Read a table (optionally some partitions, a row filter and a column subset).

        ``filters`` is a pyarrow expression or DNF tuples as in ``pyarrow.parquet``
        (``[("timestamp_us", ">=", 10)]``). Files written before a column was added read it as null.
        A file that vanishes while it is read (its partition compacted) makes it list the files again.
        """
        spec, cache = self.spec(table), self._cache
        for attempt in range(READ_RETRIES):
            files = self.file_paths(table, partitions)
            if not files:
                empty = spec.schema.empty_table()
                return empty.select(list(columns)) if columns else empty
            key = cache.key(table, files, columns, filters) if cache is not None else None
            if key is not None and (kept := cache.get(key)) is not None:
                return kept
            try:
                if filters is None:  # file by file: pyarrow.dataset imports pandas (~0.3 s), which `status` never needs
                    result = _read_listed(files, spec.schema, columns, cache)
                    break
                if cache is not None and isinstance(filters, list):  # unchanged files from the cache, filtered here
                    import pyarrow.parquet as pq

                    result = _read_listed(files, spec.schema, None, cache)
                    result = result.filter(pq.filters_to_expression(filters))
                    result = result.select(list(columns)) if columns else result
                    break
                if isinstance(filters, list):
                    import pyarrow.parquet as pq

                    filters = pq.filters_to_expression(filters)
                import pyarrow.dataset as ds  # here, not at the top: it imports pandas

                dataset = ds.dataset(files, schema=spec.schema, format="parquet")
                result = dataset.to_table(columns=list(columns) if columns else None, filter=filters)
                break
            except OSError as e:
                if not _vanished(e) or attempt == READ_RETRIES - 1:
                    raise
        keys = [(k, "ascending") for k in spec.key if not columns or k in columns]
        result = result.sort_by(keys) if keys else result
        if key is not None:
            cache.put(key, result)
        return result

    # -- media -------------------------------------------------------------------------------
    @contextlib.contextmanager
    def staging(self) -> Iterator[Path]:
        """A fresh folder inside the warehouse for files being produced; removed on exit."""
        path = self.root / "_staging" / uuid.uuid4().hex
        path.mkdir(parents=True)
        try:
            yield path
        finally:
            shutil.rmtree(path, ignore_errors=True)

    def publish_media(self, kind: str, part: str, staged: Path, version: str, content: bool = False) -> Path:
        """Move a staged folder to ``media/<kind>/<part>/<version>`` (a new, unreferenced path; with
        ``content``, ``version`` is the digest of the staged files, and a folder of that name holds
        them already: the staged copy is then dropped, and rows written before keep their paths).

        Returns the final folder. Call :meth:`prune_media` after the rows pointing to it are written.
        """
        final = self.root / "media" / kind / check_name(part, "partition") / version
        if final.exists() and content:
            return final
        if final.exists():
            raise WarehouseError(f"media version {final} exists already")
        final.parent.mkdir(parents=True, exist_ok=True)
        os.replace(staged, final)
        fsync_dir(final.parent)
        return final

    def prune_media(self, kind: str, part: str, keep: str) -> None:
        """Remove every media version of (kind, part) but ``keep``."""
        for old in (self.root / "media" / kind / check_name(part, "partition")).glob("*"):
            if old.name != keep:
                shutil.rmtree(old, ignore_errors=True)

    def relative(self, path: Path) -> str:
        """``path`` relative to the warehouse root, with '/' separators (as stored in tables)."""
        return Path(path).resolve().relative_to(self.root).as_posix()
