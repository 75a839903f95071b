"""The pattern every warehouse table follows.

A table is a :class:`TableSpec`: a pyarrow schema whose fields carry their meaning in metadata
(``description``, ``unit``, ``frame``), the key columns that identify a row, and a write mode.
Every table is partitioned by clip (``clips=<name>`` folders), or is a single ``_global``
partition for library-wide tables (the CAD library later), so a stage rewrites exactly the
partitions it owns and nothing else.

Write modes:
- ``replace``: one Parquet file per partition, swapped atomically as a whole. Stage outputs.
- ``append``: one Parquet file per write, never rewritten. Histories (``runs``, label files).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import pyarrow as pa

PARTITION_COLUMN = "clip"
GLOBAL_PARTITION = "_global"
"""Partition name of tables that do not belong to one clip."""


def column(
    name: str,
    type_: pa.DataType,
    description: str,
    *,
    unit: str | None = None,
    frame: str | None = None,
    nullable: bool = False,
) -> pa.Field:
    """A schema field whose metadata states its meaning, unit and coordinate frame."""
    meta = {"description": description}
    if unit:
        meta["unit"] = unit
    if frame:
        meta["frame"] = frame
    return pa.field(name, type_, nullable=nullable, metadata=meta)


def vector(size: int, dtype: pa.DataType = pa.float64()) -> pa.DataType:
    """A fixed-size list (DuckDB reads it as an ARRAY, e.g. DOUBLE[9])."""
    return pa.list_(pa.field("item", dtype, nullable=False), size)


CLIP = column(PARTITION_COLUMN, pa.string(), "Clip name; the partition key of every per-clip table.")


@dataclass(frozen=True)
class TableSpec:
    """One warehouse table.

    Attributes:
        name: table (and DuckDB view) name.
        schema: pyarrow schema; the first field is always ``clip``.
        key: columns that identify a row within the table (``clip`` included).
        mode: ``replace`` (a partition is rewritten as a whole) or ``append`` (a history).
        description: one line for ``cadestate tables`` and the catalog's comments.
    """

    name: str
    schema: pa.Schema
    key: tuple[str, ...]
    mode: Literal["replace", "append"]
    description: str

    def __post_init__(self) -> None:
        if self.schema.names[0] != PARTITION_COLUMN:
            raise ValueError(f"table {self.name}: the first column must be {PARTITION_COLUMN!r}")
        missing = [k for k in self.key if k not in self.schema.names]
        if missing:
            raise ValueError(f"table {self.name}: key columns {missing} are not in the schema")

    def describe(self) -> list[tuple[str, str, str, str, str]]:
        """Rows (column, type, unit, frame, description) for documentation and ``--help``."""
        rows = []
        for f in self.schema:
            m = {k.decode(): v.decode() for k, v in (f.metadata or {}).items()}
            rows.append((f.name, str(f.type), m.get("unit", ""), m.get("frame", ""), m.get("description", "")))
        return rows
