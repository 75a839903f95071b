"""The pattern every warehouse table follows.

A table is a :class:`TableSpec`: a pyarrow schema whose fields carry their meaning in metadata
(``description``, ``unit``, ``frame``), the key columns that identify a row, a partition column
and a write mode. Per-clip tables are partitioned by ``clip`` (``clip=<name>`` folders), CAD
library tables by ``library``, so a stage rewrites exactly the partitions it owns and nothing else.
The partition column is the schema's first field.

Write modes:
- ``replace``: one Parquet file per partition, swapped atomically as a whole. Stage outputs.
- ``append``: one Parquet file per write, never rewritten. Histories (``runs``, label files).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import pyarrow as pa

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


CLIP = column("clip", pa.string(), "Clip name; the partition key of every per-clip table.")
LIBRARY = column("library", pa.string(), "CAD library name; the partition key of every CAD-library table.")


@dataclass(frozen=True)
class TableSpec:
    """One warehouse table.

    Attributes:
        name: table (and DuckDB view) name.
        schema: pyarrow schema; its first field is the partition column.
        key: columns that identify a row within the table (the partition column included).
        mode: ``replace`` (a partition is rewritten as a whole) or ``append`` (a history).
        description: one line for ``cadestate tables`` and the catalog's comments.
    """

    name: str
    schema: pa.Schema
    key: tuple[str, ...]
    mode: Literal["replace", "append"]
    description: str

    @property
    def partition(self) -> str:
        """The partition column (``clip`` or ``library``)."""
        return self.schema.names[0]

    def __post_init__(self) -> None:
        if self.partition not in ("clip", "library") or self.key[0] != self.partition:
            raise ValueError(f"table {self.name}: the first column and first key must be 'clip' or 'library'")
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
