"""Single source of truth for every warehouse table (and, later, every task and label file)."""

from schemas.base import CLIP, LIBRARY, TableSpec, column, vector
from schemas.cad import CAD_ISSUES, CAD_MODELS, CAD_SAMPLES, CAD_VIEWS
from schemas.core import CLIPS, FRAMES, RUNS

TABLES: dict[str, TableSpec] = {spec.name: spec for spec in (CLIPS, FRAMES, RUNS, CAD_MODELS, CAD_SAMPLES, CAD_VIEWS, CAD_ISSUES)}
"""Every table of the warehouse by name; the DuckDB catalog has one view per entry."""

__all__ = ["TABLES", "TableSpec", "column", "vector", "CLIP", "LIBRARY", "CLIPS", "FRAMES", "RUNS"]
