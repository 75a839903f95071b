"""The DuckDB catalog: ``<root>/catalog.duckdb`` holds one view per warehouse table.

Any DuckDB client can open it (``duckdb data/warehouse/catalog.duckdb``) and query every table.
Views are created once; a write never touches the catalog. Each view reads, at query time,
``read_parquet([<schema file>, 'tables/<table>/*/*.parquet'])``: the schema file
(``tables/<table>/_schema/_schema.parquet``, no rows, the table's current schema) comes first, so
DuckDB takes the columns from it, and lies inside the glob (one folder down, as every partition's
files: a shallow glob lists faster than ``**``), so the glob always matches something: an empty
table is queryable, its first rows and every new partition or file show up with no refresh. Having
no rows, the schema file adds none, though the list names it twice. ``cadestate compact`` also
keeps a snapshot of most tables' rows in the catalog (:mod:`warehouse.snapshot`); such a table's
view reads its snapshot and only the files written since.

Schema changes: without ``union_by_name`` DuckDB reads only the first file's schema when it binds
(cheap), but then every file must have its columns. So the catalog records, per table, the schema
digest its view was made for and whether every data file then had that schema (``uniform``). A
table with files of an older schema (a column added since they were written) is read with
``union_by_name = true`` (those files read the new column as null), which reads every file's footer
per query, until the catalog is rebuilt after its files were rewritten (``cadestate compact``
rewrites append-mode partitions; ``cadestate catalog`` checks again).

The catalog is rebuilt (atomically: built aside, then renamed) only when it is missing, unreadable,
of an older layout, built for another root (paths in the views are absolute: a moved or copied
warehouse), or when a table was added or removed or its schema or description changed:
:func:`ensure_catalog`, which :func:`connect` calls, and the store calls after a process's first
write. Files are checked (footers read) only for the tables whose schema changed. The catalog is
derived data: rebuilding loses nothing.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
import uuid
from collections.abc import Collection, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import duckdb

from warehouse import snapshot
from warehouse.store import READ_RETRIES, Compacted, Warehouse, WarehouseError, atomic_write_bytes, file_lock, warn

if TYPE_CHECKING:
    import pyarrow as pa

CATALOG_FILE = "catalog.duckdb"
SCHEMA_FILE = "_schema.parquet"
ROOT_MACRO = "warehouse_root"
VIEWS_MACRO = "catalog_views"
SNAPSHOT_RETRIES = 5
"""Tries of a catalog build that takes snapshots: a write that swaps a partition while the snapshot
reads it removes a file it listed (the build reads again from the start)."""
LAYOUT = 3
"""Version of how views are made; a catalog of another layout is rebuilt."""
SCHEMA_DIGEST = b"cadestate.schema_sha256"
STALE_S = 3600.0
"""A pin or half-built catalog beside the catalog untouched this long is a killed rebuild's: removed."""

_ENSURED: set[Path] = set()
"""Roots whose catalog this process has made sure of (after a write, checked once per process)."""


class CatalogError(WarehouseError):
    """The catalog file can be neither read nor rebuilt."""


def _sql_str(value: str) -> str:
    return "'" + value.replace("'", "''") + "'"


def schema_path(wh: Warehouse, table: str) -> Path:
    """The table's schema file: empty, inside its view's glob."""
    return wh.table_dir(table) / "_schema" / SCHEMA_FILE


def _schema_digest(con: duckdb.DuckDBPyConnection, path: Path) -> str | None:
    """The schema digest stored in the schema file ``path`` (None: missing or unreadable), read by
    DuckDB (the file's key-value metadata), so that a current file costs no pyarrow."""
    try:
        rows = con.execute("SELECT decode(value) FROM parquet_kv_metadata(?) WHERE decode(key) = ?",
                           [snapshot.literal(path), SCHEMA_DIGEST.decode()]).fetchall()  # a pattern: g[1]'s, not g1's
    except (duckdb.Error, UnicodeDecodeError):
        return None
    return rows[0][0] if rows else None


def _schema_file(wh: Warehouse, table: str, con: duckdb.DuckDBPyConnection) -> Path:
    """Write the table's schema file unless it holds the current schema already (a Parquet round
    trip renames list items, so the file records the digest of the schema it holds)."""
    path = schema_path(wh, table)
    digest = wh.info[table].schema_sha256  # the schema's (schemas.index.schema_sha256)
    if _schema_digest(con, path) != digest:
        import pyarrow as pa
        import pyarrow.parquet as pq

        schema = wh.spec(table).schema
        path.parent.mkdir(parents=True, exist_ok=True)
        meta = {**(schema.metadata or {}), SCHEMA_DIGEST: digest.encode()}
        sink = pa.BufferOutputStream()
        pq.write_table(schema.with_metadata(meta).empty_table(), sink)
        # synced before the rename: an empty file after a power cut failed every query of the table
        atomic_write_bytes(path, sink.getvalue().to_pybytes())
        (wh.table_dir(table) / SCHEMA_FILE).unlink(missing_ok=True)  # where an older layout kept it
    return path


def uniform(wh: Warehouse, table: str) -> bool:
    """Whether every data file of ``table`` has its current schema (every footer is read); a
    :class:`WarehouseError` naming a file whose footer cannot be read (damaged)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    expected = pq.read_schema(_schema_file(wh, table, duckdb.connect()))
    for f in wh.files(table):
        try:
            if not _same_columns(pq.read_schema(f), expected):
                return False
        except FileNotFoundError:  # compacted or replaced meanwhile: its successor has the current schema
            continue
        except (OSError, pa.ArrowException) as e:  # "Parquet magic bytes not found in footer": a traceback
            raise WarehouseError(f"table {table}: cannot read its files: {f}: {one_line(str(e))}") from None
    return True


def _same_columns(found: pa.Schema, expected: pa.Schema) -> bool:
    """Whether a file's schema has ``expected``'s columns, in its order and of its types: whether a
    column may hold nulls does not count (DuckDB reads them alike), and a file merged from files
    written before a never-null column was added holds it as nullable (their rows are null there):
    with it counted, a table never had its fast view back after `cadestate compact`."""
    return found.names == expected.names and all(a.type.equals(b.type) for a, b in zip(found, expected))


def view_sql(wh: Warehouse, table: str, uniform: bool = True, mark: str | None = None) -> str:
    """The CREATE VIEW statement of one table (``union_by_name`` unless its files are ``uniform``;
    over its snapshot taken at ``mark`` and the newer files, when it has one)."""
    return snapshot.view_sql(wh, table, schema_path(wh, table), uniform, mark)


def expected_views(wh: Warehouse) -> dict:
    """What a current catalog of ``wh`` records, less each table's ``uniform``."""
    return {"layout": LAYOUT, "root": str(wh.root),
            "tables": {name: {"schema": info.schema_sha256, "description": info.description}
                       for name, info in sorted(wh.info.items())}}


def _plain(record: dict) -> dict:
    """``record`` less what a rebuild works out (each table's ``uniform`` and ``snapshot``)."""
    return {**record, "tables": {n: {k: v for k, v in t.items() if k not in ("uniform", "snapshot")}
                                 for n, t in record["tables"].items()}}


def recorded_views(path: Path) -> dict | None:
    """What the catalog file ``path`` records of its views; None when it is missing, not a readable
    DuckDB database, or of an older layout."""
    if not path.is_file():
        return None
    try:
        con = duckdb.connect(str(path), read_only=True)
    except duckdb.Error as e:
        if not _held_for_writing(e):
            return None
        with _copied(path) as copy:
            return recorded_views(copy) if copy != path else None
    try:
        record = json.loads(con.execute(f"SELECT {VIEWS_MACRO}()").fetchone()[0])
        return record if isinstance(record, dict) and record.get("layout") == LAYOUT else None
    except (duckdb.Error, ValueError, TypeError):
        return None
    finally:
        con.close()


def plan_views(wh: Warehouse, previous: dict | None = None, recheck: Collection[str] = ()) -> dict:
    """The record of the views to make: :func:`expected_views` with each table's ``uniform``, kept
    from ``previous`` (a recorded catalog, of any root) where the table's schema is the same and it
    is not in ``recheck``, else checked (:func:`uniform`)."""
    plan = expected_views(wh)
    before = (previous or {}).get("tables", {})
    for name, table in plan["tables"].items():
        old = before.get(name, {})
        same = old.get("schema") == table["schema"] and isinstance(old.get("uniform"), bool) and name not in recheck
        table["uniform"] = old["uniform"] if same else uniform(wh, name)
    return plan


def row_counts(wh: Warehouse) -> dict[str, int]:
    """Rows of each table, from its Parquet files' footers (read by DuckDB). The files are listed
    just before they are read (DuckDB connected first: connecting takes 4x the reading), and a file
    that vanished meanwhile (its partition rewritten or compacted) makes it list them again."""
    con = duckdb.connect()
    tries = 0
    try:
        while True:
            tries += 1
            files = {name: wh.file_paths(name) for name in wh.info}
            every = [f for paths in files.values() for f in paths]
            try:
                rows = dict(con.execute("SELECT file_name, num_rows FROM parquet_file_metadata(?)",
                                        [[snapshot.literal(Path(f)) for f in every]]).fetchall()) if every else {}
                return {name: sum(rows[f] for f in paths) for name, paths in files.items()}
            except duckdb.Error as e:
                if all(map(os.path.exists, every)) or tries == READ_RETRIES:
                    raise WarehouseError(f"cannot read the tables of {wh.root}: {one_line(str(e))}") from None
    finally:
        con.close()


def create_views(con: duckdb.DuckDBPyConnection, wh: Warehouse, plan: dict | None = None) -> dict:
    """Create in ``con`` a view per table of ``wh`` (commented with its description), the macro
    ``warehouse_root()`` naming the root the views read and ``catalog_views()`` recording ``plan``
    (default: :func:`plan_views` from the catalog file when it is current: no snapshot, which
    ``con`` would lack). A table whose plan names a ``snapshot`` reads it from ``con``. Returns the plan."""
    if plan is None:
        plan = plan_views(wh, recorded_views(wh.root / CATALOG_FILE))
    for name, table in plan["tables"].items():
        _schema_file(wh, name, con)
        con.execute(view_sql(wh, name, table["uniform"], table.get("snapshot")))
        con.execute(f"COMMENT ON VIEW {name} IS {_sql_str(table['description'])}")
    con.execute(f"CREATE OR REPLACE MACRO {ROOT_MACRO}() AS {_sql_str(str(wh.root))}")
    con.execute(f"CREATE OR REPLACE MACRO {VIEWS_MACRO}() AS {_sql_str(json.dumps(plan, sort_keys=True))}")
    return plan


def attach_views(con: duckdb.DuckDBPyConnection, wh: Warehouse) -> None:
    """Give ``con`` (a fresh in-memory session) the views of ``wh``: the catalog file's, attached
    read-only as ``warehouse`` and made the default, when it is current for ``wh`` (it records
    :func:`expected_views` and every schema file is there; a few milliseconds). A catalog that is
    not (moved, damaged, of older schemas) is rebuilt first, as any command that opens the catalog
    does; where that fails (another client holds it open, a read-only warehouse), the views are
    made in ``con`` (:func:`create_views`: every schema file checked, every view created)."""
    if _attach_current(con, wh):
        return
    with contextlib.suppress(CatalogError):
        rebuild_catalog(wh)
        if _attach_current(con, wh):
            return
    create_views(con, wh)


def _attach_current(con: duckdb.DuckDBPyConnection, wh: Warehouse) -> bool:
    """Attach the catalog file to ``con`` as ``warehouse`` and use it, if it is current for ``wh``;
    else leave ``con`` as it was and say False."""
    path = wh.root / CATALOG_FILE
    if not path.is_file():
        return False
    try:
        con.execute(f"ATTACH {_sql_str(str(path))} AS warehouse (READ_ONLY)")
        con.execute("USE warehouse")
        record = json.loads(con.execute(f"SELECT {VIEWS_MACRO}()").fetchone()[0])
        if _plain(record) == expected_views(wh) and all(schema_path(wh, name).is_file() for name in wh.info):
            return True
    except (duckdb.Error, ValueError, TypeError, KeyError, AttributeError):
        pass
    con.execute("USE memory")
    con.execute("DETACH DATABASE IF EXISTS warehouse")
    return False


def refresh_catalog(wh: Warehouse, recheck: bool | Collection[str] = False,
                    snapshots: Collection[str] = (), whole: Collection[str] = ()) -> Path:
    """(Re)build the catalog file; atomic (built aside, then renamed). Whether each table's files
    all have its schema is kept from the current catalog where the schema did not change, unless
    ``recheck`` (True: every table; else the tables named). The tables in ``snapshots`` get a new
    snapshot (:func:`warehouse.snapshot.carry`; read whole for those in ``whole``), the others keep
    theirs where their schema did not change."""
    wh.root.mkdir(parents=True, exist_ok=True)
    final = wh.root / CATALOG_FILE
    tmp = wh.root / f".{CATALOG_FILE}.{uuid.uuid4().hex}.tmp"
    with _pinned(final) as current:
        recorded = recorded_views(current)
        plan = plan_views(wh, None if recheck is True else recorded, () if recheck is False else recheck)
        for attempt in range(SNAPSHOT_RETRIES):
            try:
                con = duckdb.connect(str(tmp))
                try:
                    schema_files = {name: _schema_file(wh, name, con) for name in plan["tables"]}
                    snapshot.carry(con, wh, plan, recorded, current, schema_files, snapshots, whole)
                    create_views(con, wh, plan)
                    con.execute("CHECKPOINT")
                finally:
                    con.close()
                os.replace(tmp, final)
                break
            except duckdb.IOException as e:  # a file a write swapped away while the snapshot read it: read again
                if not snapshots or attempt == SNAPSHOT_RETRIES - 1 or "No such file" not in str(e) and "Cannot open" not in str(e):
                    raise
            finally:
                tmp.unlink(missing_ok=True)
                Path(f"{tmp}.wal").unlink(missing_ok=True)
    _ENSURED.add(wh.root)
    return final


@contextlib.contextmanager
def _pinned(path: Path) -> Iterator[Path]:
    """``path`` as it is now, for the length of the block: a hard link to it beside it (removed
    after), so that the watermarks a rebuild reads and the snapshots it copies come from one
    catalog even when another process replaces the file meanwhile (a snapshot and a rebuild at
    once). ``path`` itself where it is missing or the file system has no hard links. The pins and
    half-built catalogs (``.tmp``, ``.tmp.wal``) of killed rebuilds are removed :data:`STALE_S` on."""
    for stale in path.parent.glob(f".{path.name}.*"):  # a killed rebuild's, an hour on
        with contextlib.suppress(OSError):
            if stale.name.endswith((".pin", ".tmp", ".tmp.wal")) and _age_s(stale) > STALE_S:
                stale.unlink()
    if _opened_for_writing(path):
        with _copied(path) as copy:
            yield copy
        return
    pin = _pin_name(path)
    try:
        os.link(path, pin)
    except OSError:
        yield path
        return
    try:
        yield pin
    finally:
        pin.unlink(missing_ok=True)


def _pin_name(path: Path) -> Path:
    """A new pin's name beside ``path``: the time made, a random id (see :func:`_age_s`)."""
    return path.with_name(f".{path.name}.{time.time_ns()}-{uuid.uuid4().hex}.pin")


def _held_for_writing(e: duckdb.Error) -> bool:
    """Whether ``e``, from opening a database, says another process holds it open read-write."""
    return "Could not set lock" in str(e) or "Conflicting lock" in str(e)


def _opened_for_writing(path: Path) -> bool:
    """Whether another process holds the catalog ``path`` open read-write: a DuckDB client opened
    on it (``duckdb data/warehouse/catalog.duckdb``, as the module says any client can)."""
    try:
        duckdb.connect(str(path), read_only=True).close()
    except duckdb.Error as e:
        return _held_for_writing(e)
    return False


@contextlib.contextmanager
def _copied(path: Path) -> Iterator[Path]:
    """A copy of the catalog ``path`` (a pin's name, removed after) to read its record and snapshots
    from while another process holds it open read-write: DuckDB refuses to open it even read-only
    then, and a write or `sql` took it for unreadable and rebuilt the catalog without its record:
    every table's footers read again, every snapshot lost. (Its changes not yet checkpointed, in its
    ``.wal``, are not the catalog's.) ``path`` itself where no copy can be made (gone meanwhile, a
    full disk): what opens it then fails as it did."""
    import shutil

    copy = _pin_name(path)
    try:
        try:
            shutil.copyfile(path, copy)
        except OSError:
            yield path
            return
        yield copy
    finally:
        copy.unlink(missing_ok=True)


def _age_s(left: Path) -> float:
    """Seconds since a pin was made, from the time in its name (a hard link has the catalog's own
    modification time: a live pin of a catalog built an hour before looked stale, and another
    rebuild removed it under a compaction), or since a half-built catalog was last written."""
    made, dash, _ = left.name.removesuffix(".pin").rpartition(".")[2].partition("-")
    if left.name.endswith(".pin") and dash and made.isdigit():
        return time.time() - int(made) / 1e9
    return time.time() - left.stat().st_mtime


def rebuild_catalog(wh: Warehouse, recheck: bool | Collection[str] = False,
                    snapshots: Collection[str] = (), whole: Collection[str] = ()) -> Path:
    """:func:`refresh_catalog`, with a catalog that cannot be written reported as a
    :class:`CatalogError` naming it."""
    if "?" in str(wh.root):  # DuckDB reads what follows a '?' in a database path as options
        raise CatalogError(f"cannot build the catalog {wh.root / CATALOG_FILE}: DuckDB cannot keep one in a folder "
                           "whose path holds '?' (rename the folder)")
    try:
        return refresh_catalog(wh, recheck, snapshots, whole)
    except (OSError, duckdb.Error) as e:
        raise CatalogError(f"cannot rebuild the catalog {wh.root / CATALOG_FILE}: {one_line(str(e))}") from None


def ensure_catalog(wh: Warehouse) -> Path:
    """The catalog file, rebuilt first unless it is current (see the module) and every schema file
    is there."""
    path = wh.root / CATALOG_FILE
    record = recorded_views(path)
    current = record is not None and _plain(record) == expected_views(wh)
    if not current or not all(schema_path(wh, name).is_file() for name in wh.info):
        rebuild_catalog(wh)
    _ENSURED.add(wh.root)
    return path


@contextlib.contextmanager
def snapshot_lock(wh: Warehouse) -> Iterator[None]:
    """Hold the warehouse's snapshot lock (``_locks/catalog.lock``): one compaction and snapshot at a time."""
    with file_lock(wh.root / "_locks" / "catalog.lock"):
        yield


def take_snapshots(wh: Warehouse, compacted: Collection[str] = (), renamed: Collection[str] | bool = ()) -> list[str]:
    """Rebuild the catalog with a new snapshot of every table that keeps one
    (:func:`warehouse.snapshot.kept`), read whole for the tables whose files were ``renamed``
    (:meth:`Warehouse.rename_legacy`; True: every table), and with the files of the ``compacted`` tables that it reads
    by name (files of an older schema) checked again, so that a table whose files now all have its
    schema gets its fast view back. Call it under :func:`snapshot_lock`. Returns the tables
    snapshotted."""
    recorded = (recorded_views(wh.root / CATALOG_FILE) or {"tables": {}})["tables"]  # none: the rebuild checks every table
    mixed = [t for t in compacted if not recorded.get(t, {}).get("uniform", True)]
    tables = [name for name in wh.info if snapshot.kept(wh.spec(name))]
    rebuild_catalog(wh, recheck=mixed, snapshots=tables, whole=tables if renamed is True else renamed)
    return tables


@dataclass(frozen=True)
class Compaction:
    """What :func:`compact_warehouse` did: files renamed per table, partitions merged, tables snapshotted."""

    renamed: dict[str, int]
    compacted: list[Compacted]
    snapshotted: list[str]


def compact_warehouse(wh: Warehouse, tables: Collection[str] | None = None, min_files: int = 2,
                      whole: bool = False) -> Compaction:
    """What ``cadestate compact`` does, under :func:`snapshot_lock`: files of an older layout renamed
    (:meth:`Warehouse.rename_legacy`), the partitions of the append-mode ``tables`` (default: all)
    with at least ``min_files`` files merged, then a new snapshot (:func:`take_snapshots`; from the
    files alone, not from the last snapshot, when ``whole``)."""
    with snapshot_lock(wh):
        renamed = wh.rename_legacy()
        done = wh.compact_tables(None if tables is None else list(tables), min_files)
        kept = take_snapshots(wh, sorted({c.table for c in done}), True if whole else sorted(renamed))
    return Compaction(renamed, done, kept)


def after_write(wh: Warehouse) -> None:
    """The store's after-write hook: :func:`ensure_catalog`, once per process and root (so a
    warehouse has a catalog from its first write, and new code's schemas reach it). A catalog that
    cannot be built is a warning, not a failed write: the data is in, and readers rebuild it or
    read the tables without it (:func:`connect`). So is a damaged file of any table (it raised
    after the write was in: a retried append wrote its rows twice)."""
    if wh.root not in _ENSURED:
        try:
            ensure_catalog(wh)
        except WarehouseError as e:  # CatalogError included
            _ENSURED.add(wh.root)  # said once per process
            warn(f"{e} (the write itself is done)")


def connect(wh: Warehouse, read_only: bool = True) -> duckdb.DuckDBPyConnection:
    """Open the catalog (:func:`ensure_catalog` first). Read-only by default; to read, a catalog
    that is out of date and cannot be rebuilt (a read-only copy of a warehouse) gives way to the
    views made in memory, as `cadestate sql` makes them (:func:`attach_views`)."""
    try:
        path = ensure_catalog(wh)
    except CatalogError:
        if not read_only:
            raise
        con = duckdb.connect(":memory:")
        create_views(con, wh)
        return con
    try:
        return duckdb.connect(str(path), read_only=read_only)
    except duckdb.Error as e:
        if read_only and _held_for_writing(e):  # a client holds it open read-write: a copy built aside replaces it
            with contextlib.suppress(CatalogError, duckdb.Error):
                return duckdb.connect(str(rebuild_catalog(wh)), read_only=True)
        raise CatalogError(f"cannot open the catalog {path}: {one_line(str(e))}") from None


def one_line(message: str, limit: int = 500) -> str:
    """``message`` as one line (whitespace runs, line breaks included, become one space), cut to
    about ``limit`` characters."""
    text = " ".join(message.split())
    return text if len(text) <= limit else text[:limit] + f"... ({len(text) - limit} more characters)"
