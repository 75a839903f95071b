"""Single source of truth for every warehouse table (and, later, every task and label file)."""

from schemas.base import GLOBAL_PARTITION, PARTITION_COLUMN, TableSpec, column, vector
from schemas.core import CLIPS, FRAMES, RUNS

TABLES: dict[str, TableSpec] = {spec.name: spec for spec in (CLIPS, FRAMES, RUNS)}
"""Every table of the warehouse by name; the DuckDB catalog has one view per entry."""

__all__ = ["TABLES", "TableSpec", "column", "vector", "PARTITION_COLUMN", "GLOBAL_PARTITION", "CLIPS", "FRAMES", "RUNS"]
