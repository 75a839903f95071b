"""The DuckDB catalog: ``<root>/catalog.duckdb`` holds one view per warehouse table.

Any DuckDB client can open it (``duckdb data/warehouse/catalog.duckdb``) and query every table.
A view reads its table's Parquet files through a glob, so new partitions show up without a
refresh; the catalog is rebuilt (atomically) after each write so new tables and new columns do
too. A table with no data yet is a view over an empty Parquet file holding just its schema
(``_schemas/<table>.parquet``), so every table is always queryable.

Paths in the views are absolute, so the catalog also records the root it was built for (the macro
``warehouse_root()``). :func:`connect` rebuilds a catalog built for another root (a moved or
copied warehouse), one that is not a readable DuckDB database, or one from before that macro;
``cadestate catalog`` rebuilds it by hand. The catalog is derived data: rebuilding loses nothing.
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path

import duckdb

from warehouse.store import Warehouse, WarehouseError

CATALOG_FILE = "catalog.duckdb"
ROOT_MACRO = "warehouse_root"
SCHEMA_DIGEST = b"cadestate.schema_sha256"


class CatalogError(WarehouseError):
    """The catalog file can be neither read nor rebuilt."""


def _sql_str(value: str) -> str:
    return "'" + value.replace("'", "''") + "'"


def _schema_digest(con: duckdb.DuckDBPyConnection, path: Path) -> str | None:
    """The schema digest stored in the schema file ``path`` (None: missing or unreadable), read by
    DuckDB (the file's key-value metadata), so that a current file costs no pyarrow."""
    try:
        rows = con.execute("SELECT decode(value) FROM parquet_kv_metadata(?) WHERE decode(key) = ?",
                           [str(path), SCHEMA_DIGEST.decode()]).fetchall()
    except (duckdb.Error, UnicodeDecodeError):
        return None
    return rows[0][0] if rows else None


def _schema_file(wh: Warehouse, table: str, con: duckdb.DuckDBPyConnection) -> Path:
    """An empty Parquet file with the table's schema, rewritten only when the schema changes (a
    Parquet round trip renames list items, so the file records the digest of the schema it holds)."""
    path = wh.root / "_schemas" / f"{table}.parquet"
    digest = wh.info[table].schema_sha256  # the schema's (schemas.index.schema_sha256)
    if _schema_digest(con, path) != digest:
        import pyarrow.parquet as pq

        schema = wh.spec(table).schema
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
        meta = {**(schema.metadata or {}), SCHEMA_DIGEST: digest.encode()}
        pq.write_table(schema.with_metadata(meta).empty_table(), tmp)
        os.replace(tmp, path)
    return path


def view_sql(wh: Warehouse, table: str, con: duckdb.DuckDBPyConnection | None = None) -> str:
    """The CREATE VIEW statement of one table (``con`` reads the digests of the schema files)."""
    if wh.files(table):
        source = (wh.table_dir(table) / "*" / "*.parquet").as_posix()
    else:
        source = _schema_file(wh, table, con or duckdb.connect()).as_posix()
    return f"CREATE OR REPLACE VIEW {table} AS SELECT * FROM read_parquet({_sql_str(source)}, union_by_name = true)"


def row_counts(wh: Warehouse) -> dict[str, int]:
    """Rows of each table, from its Parquet files' footers (read by DuckDB)."""
    files = {name: [str(f) for f in wh.files(name)] for name in wh.info}
    every = [f for paths in files.values() for f in paths]
    con = duckdb.connect()
    try:
        rows = dict(con.execute("SELECT file_name, num_rows FROM parquet_file_metadata(?)", [every]).fetchall()) if every else {}
    except duckdb.Error as e:
        raise WarehouseError(f"cannot read the tables of {wh.root}: {one_line(str(e))}") from None
    finally:
        con.close()
    return {name: sum(rows[f] for f in paths) for name, paths in files.items()}


def create_views(con: duckdb.DuckDBPyConnection, wh: Warehouse) -> None:
    """Create in ``con`` a view per table of ``wh`` (commented with its description) and the macro
    ``warehouse_root()`` naming the root the views read."""
    for name, info in sorted(wh.info.items()):
        con.execute(view_sql(wh, name, con))
        con.execute(f"COMMENT ON VIEW {name} IS {_sql_str(info.description)}")
    con.execute(f"CREATE OR REPLACE MACRO {ROOT_MACRO}() AS {_sql_str(str(wh.root))}")


def refresh_catalog(wh: Warehouse) -> Path:
    """(Re)build the catalog file with a view per table; atomic (built aside, then renamed)."""
    wh.root.mkdir(parents=True, exist_ok=True)
    final = wh.root / CATALOG_FILE
    tmp = wh.root / f".{CATALOG_FILE}.{uuid.uuid4().hex}.tmp"
    try:
        con = duckdb.connect(str(tmp))
        try:
            create_views(con, wh)
            con.execute("CHECKPOINT")
        finally:
            con.close()
        os.replace(tmp, final)
    finally:
        tmp.unlink(missing_ok=True)
        Path(f"{tmp}.wal").unlink(missing_ok=True)
    return final


def rebuild_catalog(wh: Warehouse) -> Path:
    """:func:`refresh_catalog`, with a catalog that cannot be written reported as a
    :class:`CatalogError` naming it."""
    try:
        return refresh_catalog(wh)
    except (OSError, duckdb.Error) as e:
        raise CatalogError(f"cannot rebuild the catalog {wh.root / CATALOG_FILE}: {one_line(str(e))}") from None


def built_for(path: Path) -> str | None:
    """The warehouse root the catalog file ``path`` was built for; None when it is missing, not a
    readable DuckDB database, or older than the ``warehouse_root()`` macro."""
    if not path.is_file():
        return None
    try:
        con = duckdb.connect(str(path), read_only=True)
    except duckdb.Error:
        return None
    try:
        return con.execute(f"SELECT {ROOT_MACRO}()").fetchone()[0]
    except duckdb.Error:
        return None
    finally:
        con.close()


def connect(wh: Warehouse, read_only: bool = True) -> duckdb.DuckDBPyConnection:
    """Open the catalog, (re)built first when it is missing, unreadable or built for another root
    (a moved or copied warehouse). Read-only by default."""
    path = wh.root / CATALOG_FILE
    if built_for(path) != str(wh.root):
        rebuild_catalog(wh)
    try:
        return duckdb.connect(str(path), read_only=read_only)
    except duckdb.Error as e:
        raise CatalogError(f"cannot open the catalog {path}: {one_line(str(e))}") from None


def one_line(message: str, limit: int = 500) -> str:
    """``message`` as one line (whitespace runs, line breaks included, become one space), cut to
    about ``limit`` characters."""
    text = " ".join(message.split())
    return text if len(text) <= limit else text[:limit] + f"... ({len(text) - limit} more characters)"
