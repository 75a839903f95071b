"""The DuckDB catalog: ``<root>/catalog.duckdb`` holds one view per warehouse table.

Any DuckDB client can open it (``duckdb data/warehouse/catalog.duckdb``) and query every table.
A view reads its table's Parquet files through a glob, so new partitions show up without a
refresh; the catalog is rebuilt (atomically) after each write so new tables and new columns do
too. A table with no data yet is a view over an empty Parquet file holding just its schema
(``_schemas/<table>.parquet``), so every table is always queryable. Paths in the views are
absolute: after moving a warehouse, run ``cadestate catalog`` to rebuild them.
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path
from typing import TYPE_CHECKING

import duckdb
import pyarrow.parquet as pq

if TYPE_CHECKING:
    from warehouse.store import Warehouse

CATALOG_FILE = "catalog.duckdb"


def _sql_str(value: str) -> str:
    return "'" + value.replace("'", "''") + "'"


def _schema_file(wh: Warehouse, table: str) -> Path:
    """An empty Parquet file with the table's schema (rewritten when the schema changes)."""
    path = wh.root / "_schemas" / f"{table}.parquet"
    schema = wh.spec(table).schema
    if not path.exists() or not pq.read_schema(path).equals(schema, check_metadata=True):
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
        pq.write_table(schema.empty_table(), tmp)
        os.replace(tmp, path)
    return path


def view_sql(wh: Warehouse, table: str) -> str:
    """The CREATE VIEW statement of one table."""
    if wh.files(table):
        source = (wh.table_dir(table) / "*" / "*.parquet").as_posix()
    else:
        source = _schema_file(wh, table).as_posix()
    return f"CREATE OR REPLACE VIEW {table} AS SELECT * FROM read_parquet({_sql_str(source)}, union_by_name = true)"


def refresh_catalog(wh: Warehouse) -> Path:
    """(Re)build the catalog file with a view per table; atomic (built aside, then renamed)."""
    wh.root.mkdir(parents=True, exist_ok=True)
    final = wh.root / CATALOG_FILE
    tmp = wh.root / f".{CATALOG_FILE}.{uuid.uuid4().hex}.tmp"
    try:
        con = duckdb.connect(str(tmp))
        try:
            for name, spec in sorted(wh.tables.items()):
                con.execute(view_sql(wh, name))
                con.execute(f"COMMENT ON VIEW {name} IS {_sql_str(spec.description)}")
            con.execute("CHECKPOINT")
        finally:
            con.close()
        os.replace(tmp, final)
    finally:
        tmp.unlink(missing_ok=True)
        Path(f"{tmp}.wal").unlink(missing_ok=True)
    return final


def connect(wh: Warehouse, read_only: bool = True) -> duckdb.DuckDBPyConnection:
    """Open the catalog (built first if missing). Read-only by default."""
    path = wh.root / CATALOG_FILE
    if not path.exists():
        refresh_catalog(wh)
    return duckdb.connect(str(path), read_only=read_only)
