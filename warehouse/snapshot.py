"""The catalog's snapshot: a table's rows as of a watermark, kept in the catalog file, so that a
query opens only the files written since.

A table is one Parquet file per partition (a clip) and more, and DuckDB opens every file a query
reads: at 10,000 clips, a query over one table took 2-4 s, nearly all of it opening files. So
``cadestate compact`` copies each table's rows into ``snapshot.<table>`` in ``catalog.duckdb``,
each row with the file it came from (``_file``, relative to the table's folder), up to a
watermark ``W`` (a time, 20 digits of nanoseconds, one minute before the snapshot starts). The
table's view then reads:

- the snapshot's rows whose file is still there (a listing of the table's folder: no file opened;
  a file replaced or merged away since takes its rows with it);
- plus the files named after ``W`` (file names are their publication time,
  :func:`warehouse.store.file_name`; DuckDB prunes the others by name before opening any).

Every file is named after ``W`` or was there when the snapshot listed the table (a write publishes
its file within moments of taking its name, and the snapshot waits out a minute of margin), so a
file is read exactly once: from the snapshot or from itself. This assumes the clocks of the
machines that write a shared warehouse (Dask workers) agree within that minute, as NTP keeps them:
a file named more than a minute in the past when it appears (or a backup copied back into a
partition, which keeps its old names) is missed until the next snapshot. That one starts from the
last: it keeps the rows whose files are still there and reads the files named between the two
watermarks, and those named before that it lacks (a listing of the table's folder against the
files the snapshot holds: none opened).

Tables whose rows carry descriptors or point sets (a variable-length list of float32 or of lists:
``embeddings``, ``cad_samples``, ...) are not copied: a copy would double the warehouse's largest
files, and SQL over them is rare. Their views read the files, as before.
"""

from __future__ import annotations

import time
from collections.abc import Collection, Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import duckdb

if TYPE_CHECKING:
    from schemas import TableSpec
    from warehouse.store import Warehouse

SCHEMA = "snapshot"
"""The catalog's schema that holds the snapshot tables (one per table, named as it)."""
MARGIN_NS = 60 * 10**9
"""How long before the snapshot's start its watermark lies: a file named before that (its write
took its name) has been published by then."""
DATA_GLOB = "*/*.parquet"
"""A table's files, relative to its folder: every partition's, and the schema file (no rows)."""


def kept(spec: TableSpec) -> bool:
    """Whether the snapshot copies ``spec``'s rows: not when a column is a variable-length list of
    float32 (a descriptor) or of lists (a point set)."""
    import pyarrow as pa

    def bulky(t: pa.DataType) -> bool:
        return pa.types.is_list(t) and (pa.types.is_float32(t.value_type) or pa.types.is_list(t.value_type)
                                        or pa.types.is_fixed_size_list(t.value_type))

    return not any(bulky(f.type) for f in spec.schema)


def watermark(now_ns: int | None = None) -> str:
    """The watermark of a snapshot taken now: a file name prefix (see the module)."""
    return f"{(time.time_ns() if now_ns is None else now_ns) - MARGIN_NS:020d}"


def _str(value: str) -> str:
    return "'" + value.replace("'", "''") + "'"


def literal(path: Path) -> str:
    """``path`` as a DuckDB file pattern matching itself alone: a ``[``, ``*`` or ``?`` in the
    warehouse's folder names (``runs[2]``) made the views read nothing, or another folder's files."""
    return "".join(f"[{c}]" if c in "[*?" else c for c in path.as_posix())


def _glob(wh: Warehouse, table: str) -> str:
    return _str(f"{literal(wh.table_dir(table))}/{DATA_GLOB}")


def _relative(wh: Warehouse, table: str, column: str) -> str:
    """SQL of the path in ``column`` relative to the table's folder."""
    return f"substr({column}, {len(wh.table_dir(table).as_posix()) + 2})"


def _files(wh: Warehouse, table: str, schema_file: Path, uniform: bool) -> str:
    union = "" if uniform else ", union_by_name = true"
    return f"read_parquet([{_str(literal(schema_file))}, {_glob(wh, table)}], filename = true{union})"


def _present(wh: Warehouse, table: str, source: str) -> str:
    """Rows of ``source`` (a snapshot table) whose file is in the table's folder now."""
    return f"SELECT * FROM {source} WHERE _file IN (SELECT {_relative(wh, table, 'file')} FROM glob({_glob(wh, table)}))"


def view_sql(wh: Warehouse, table: str, schema_file: Path, uniform: bool, mark: str | None) -> str:
    """The CREATE VIEW statement of ``table``: its files (``mark`` None), or its snapshot taken at
    ``mark`` and the files named after it."""
    head = f'CREATE OR REPLACE VIEW "{table}" AS '
    if mark is None:
        union = "" if uniform else ", union_by_name = true"
        return head + f"SELECT * FROM read_parquet([{_str(literal(schema_file))}, {_glob(wh, table)}]{union})"
    return (head + f'SELECT * EXCLUDE (_file) FROM ({_present(wh, table, f"{SCHEMA}.{table}")}) '
            f"UNION ALL BY NAME SELECT * EXCLUDE (filename) FROM {_files(wh, table, schema_file, uniform)} "
            f"WHERE parse_filename(filename) > {_str(mark)}")


def take(con: duckdb.DuckDBPyConnection, wh: Warehouse, table: str, schema_file: Path, uniform: bool, mark: str,
         previous: str | None = None, previous_mark: str | None = None) -> None:
    """Create ``snapshot.<table>`` in ``con``: the rows of the files named up to ``mark``; from
    ``previous`` (the last snapshot of this table, another database's, taken at ``previous_mark``)
    those whose file is still there, and only the files named after ``previous_mark`` read."""
    new = (f"SELECT * EXCLUDE (filename), {_relative(wh, table, 'filename')} AS _file FROM "
           f"{_files(wh, table, schema_file, uniform)} WHERE parse_filename(filename) <= {_str(mark)}")
    if previous is not None and previous_mark is not None:
        since = f"parse_filename(filename) > {_str(previous_mark)}"
        if lacking := _named_before_but_lacking(con, wh, table, previous, previous_mark):
            since = f"({since} OR filename IN ({', '.join(_str(f) for f in lacking)}))"
        new = f"{_present(wh, table, previous)} UNION ALL BY NAME {new} AND {since}"
    con.execute(f'CREATE TABLE {SCHEMA}."{table}" AS {new}')


def _named_before_but_lacking(con: duckdb.DuckDBPyConnection, wh: Warehouse, table: str, previous: str,
                              previous_mark: str) -> list[str]:
    """The table's files (absolute paths) named up to ``previous_mark`` that the snapshot
    ``previous`` does not hold: copied back into a partition by hand (a backup restored keeps its
    old names), or written by a machine whose clock was behind. Listed, not opened."""
    base = wh.table_dir(table)
    held = {row[0] for row in con.execute(f"SELECT DISTINCT _file FROM {previous}").fetchall()}
    return [f.as_posix() for f in sorted(base.glob(DATA_GLOB))
            if f.name <= previous_mark and f.relative_to(base).as_posix() not in held]


def carry(con: duckdb.DuckDBPyConnection, wh: Warehouse, plan: dict, recorded: dict | None, catalog: Path,
          schema_files: Mapping[str, Path], fresh: Collection[str] = (), whole: Collection[str] = ()) -> None:
    """Give the catalog being built in ``con`` its snapshots and note each table's watermark in
    ``plan`` (``snapshot``: a watermark or None): a table in ``fresh`` gets a new snapshot (from its
    recorded one where that is of the same schema and the table is not in ``whole``, else from its
    files alone); any other keeps its recorded snapshot (copied from ``catalog``, the current
    catalog file) where the schema is the same, else has none. ``schema_files``: each table's
    schema file (there already)."""
    before = (recorded or {}).get("tables", {})
    usable = {name: before[name]["snapshot"] for name, table in plan["tables"].items()
              if before.get(name, {}).get("snapshot") and before[name].get("schema") == table["schema"]}
    if usable:
        con.execute(f"ATTACH {_str(str(catalog))} AS previous (READ_ONLY)")
    con.execute(f"CREATE SCHEMA IF NOT EXISTS {SCHEMA}")
    mark = watermark()
    for name, table in plan["tables"].items():
        old = f'previous.{SCHEMA}."{name}"' if name in usable else None
        if name in fresh:
            since = None if name in whole else old
            # from the last snapshot, the watermark never goes back (a clock set back): its files are in it
            at = mark if since is None else max(mark, usable[name])
            take(con, wh, name, schema_files[name], table["uniform"], at, since, usable.get(name))
            table["snapshot"] = at
        elif old is not None:
            con.execute(f'CREATE TABLE {SCHEMA}."{name}" AS SELECT * FROM {old}')
            table["snapshot"] = usable[name]
        else:
            table["snapshot"] = None
    if usable:
        con.execute("DETACH previous")
