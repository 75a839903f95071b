"""Parquet storage: one folder per table, one sub-folder per partition (a clip, or a CAD library).

Layout under the warehouse root::

    tables/<table>/clip=<clip>/part.parquet        replace-mode tables (one file, swapped whole)
    tables/<table>/clip=<clip>/<time>-<id>.parquet append-mode tables (one file per write)
    tables/<table>/library=<library>/...           CAD-library tables, partitioned by library
    media/<kind>/<partition>/<version>/...         images and other files that rows point to
    inputs/<clip>/...                              the clip's video and camera file
    catalog.duckdb                                 DuckDB views over every table (warehouse.catalog)
    _prefect/                                      Prefect's local state and cached task results

Atomicity: every Parquet file is written under a temporary name in its final folder, flushed to
disk and renamed into place (``os.replace``), so a reader or a crash sees the old file or the
new one, never half of one. Media are written to a fresh version folder that no row points to
yet; rows start pointing to it only when their table partition is swapped in, and superseded
versions are removed afterwards (:meth:`Warehouse.publish_media`).
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from cadestate.atomic import TMP_SUFFIX, atomic_write_bytes, fsync_dir  # noqa: F401  (atomic_write_bytes: also warehouse's)

if TYPE_CHECKING:  # pyarrow is imported where a table is read or written: commands that only query pay nothing for it
    import pyarrow as pa
    import pyarrow.compute as pc

    from schemas import TableSpec
    from schemas.index import TableInfo

NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,199}$")
REPLACE_FILE = "part.parquet"

AFTER_WRITE: list[Callable[[Warehouse], object]] = []
"""Called with the warehouse after each partition write. The package (``warehouse/__init__.py``) adds
the DuckDB catalog's refresh, so this module knows nothing of the catalog, which is built on it."""


class WarehouseError(ValueError):
    """Data that does not fit its table, or an unknown table or partition."""


def check_name(name: str, what: str = "clip") -> str:
    """Clip, library and model names become folder and file names: letters, digits, '_', '.', '-'
    (at most 200, not starting with '.' or '-')."""
    if not isinstance(name, str) or not NAME.match(name):
        raise WarehouseError(
            f"invalid {what} name {name!r}: use letters, digits, '_', '.' and '-' (at most 200, not starting with '.' or '-')"
        )
    return name


class Warehouse:
    """A warehouse rooted at a local directory."""

    def __init__(self, root: str | os.PathLike, tables: dict[str, TableSpec] | None = None):
        self.root = Path(root).expanduser().resolve()
        self._tables = tables
        self._info: dict[str, TableInfo] | None = None

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
            from schemas.index import read_index, table_info

            index = read_index() if self._tables is None else None
            self._info = index if index is not None else {n: table_info(s) for n, s in self.tables.items()}
        return self._info

    def _table(self, table: str) -> TableInfo:
        try:
            return self.info[table]
        except KeyError:
            raise WarehouseError(f"unknown table {table!r} (known: {', '.join(sorted(self.info))})") from None

    def __repr__(self) -> str:
        return f"Warehouse({str(self.root)!r})"

    # -- layout ------------------------------------------------------------------------------
    def spec(self, table: str) -> TableSpec:
        try:
            return self.tables[table]
        except KeyError:
            raise WarehouseError(f"unknown table {table!r} (known: {', '.join(sorted(self.tables))})") from None

    def table_dir(self, table: str) -> Path:
        return self.root / "tables" / self._table(table).name

    def partition_dir(self, table: str, part: str) -> Path:
        partition = self._table(table).partition
        return self.table_dir(table) / f"{partition}={check_name(part, partition)}"

    def inputs_dir(self, clip: str) -> Path:
        return self.root / "inputs" / check_name(clip)

    def files(self, table: str, partitions: Sequence[str] | None = None) -> list[Path]:
        """Data files of ``table`` (all partitions, or the named ones), sorted."""
        base = self.table_dir(table)
        if partitions is None:
            dirs = sorted(base.glob(f"{self._table(table).partition}=*"))
        else:
            dirs = [self.partition_dir(table, p) for p in partitions]
        return [f for d in dirs for f in sorted(d.glob("*.parquet"))]

    def partitions(self, table: str) -> list[str]:
        """Partitions (clips, or libraries) that have data in ``table``."""
        prefix = f"{self._table(table).partition}="
        return sorted(d.name[len(prefix):] for d in self.table_dir(table).glob(prefix + "*") if any(d.glob("*.parquet")))

    # -- writing -----------------------------------------------------------------------------
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
        try:
            data = data.select(spec.schema.names).cast(spec.schema)
        except (pa.ArrowInvalid, pa.ArrowTypeError, pa.ArrowNotImplementedError) as e:
            raise WarehouseError(f"table {table}: data does not fit the schema: {e}") from None
        column = spec.partition
        if data.num_rows and not pc.all(pc.equal(data.column(column), part)).as_py():
            raise WarehouseError(f"table {table}: every row of partition {part!r} must have {column} = {part!r}")
        if data.num_rows and spec.mode == "replace":
            counts = data.group_by(list(spec.key)).aggregate([([], "count_all")])
            dup = counts.filter(pc.greater(counts.column("count_all"), 1))
            if dup.num_rows:
                first = {k: dup.column(k)[0].as_py() for k in spec.key}
                raise WarehouseError(f"table {table}: duplicate key {first} ({dup.num_rows} duplicated keys)")
        return data

    def write(self, table: str, part: str, data: pa.Table) -> int:
        """Write one partition atomically; returns the rows written.

        ``replace`` tables: the partition becomes exactly ``data`` (rewriting identical data is a
        no-op in effect: idempotent). ``append`` tables: ``data`` is added as a new file.
        """
        spec = self.spec(table)
        data = self.conform(table, part, data)
        folder = self.partition_dir(table, part)
        folder.mkdir(parents=True, exist_ok=True)
        if spec.mode == "replace":
            final = folder / REPLACE_FILE
        else:
            final = folder / f"{time.time_ns():020d}-{uuid.uuid4().hex[:8]}.parquet"
        tmp = folder / f".{final.name}.{uuid.uuid4().hex}{TMP_SUFFIX}"
        import pyarrow.parquet as pq

        try:
            pq.write_table(data, tmp, compression="zstd")
            with open(tmp, "rb+") as f:
                os.fsync(f.fileno())
            os.replace(tmp, final)
        finally:
            tmp.unlink(missing_ok=True)
        fsync_dir(folder)
        for hook in AFTER_WRITE:  # the DuckDB catalog's refresh (warehouse/__init__.py): its views follow the tables
            hook(self)
        return data.num_rows

    # -- reading -----------------------------------------------------------------------------
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
        """
        spec = self.spec(table)
        files = [str(f) for f in self.files(table, partitions)]
        if not files:
            empty = spec.schema.empty_table()
            return empty.select(list(columns)) if columns else empty
        if isinstance(filters, list):
            import pyarrow.parquet as pq

            filters = pq.filters_to_expression(filters)
        import pyarrow.dataset as ds  # here, not at the top: it imports pandas (~1 s), which `sql` never needs

        dataset = ds.dataset(files, schema=spec.schema, format="parquet")
        result = dataset.to_table(columns=list(columns) if columns else None, filter=filters)
        keys = [(k, "ascending") for k in spec.key if not columns or k in columns]
        return result.sort_by(keys) if keys else result

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

    def publish_media(self, kind: str, part: str, staged: Path, version: str) -> Path:
        """Move a staged folder to ``media/<kind>/<part>/<version>`` (a new, unreferenced path).

        Returns the final folder. Call :meth:`prune_media` after the rows pointing to it are written.
        """
        final = self.root / "media" / kind / check_name(part, "partition") / version
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
