"""Single source of truth for every warehouse table (and, later, every task and label file).

The table specs import pyarrow, so :data:`TABLES` and the names below are resolved on first use
(a module ``__getattr__``): ``import schemas.labels`` (the task and label files) stays light.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from schemas.base import CLIP, LIBRARY, TableSpec, column, vector
    from schemas.core import CLIPS, FRAMES, RUNS

__all__ = ["TABLES", "TableSpec", "column", "vector", "CLIP", "LIBRARY", "CLIPS", "FRAMES", "RUNS"]

_FROM = {"TableSpec": "schemas.base", "column": "schemas.base", "vector": "schemas.base", "CLIP": "schemas.base",
         "LIBRARY": "schemas.base", "CLIPS": "schemas.core", "FRAMES": "schemas.core", "RUNS": "schemas.core"}


def _tables() -> dict[str, Any]:
    """Every table of the warehouse by name; the DuckDB catalog has one view per entry."""
    from schemas.cad import CAD_ISSUES, CAD_MODELS, CAD_SAMPLES, CAD_VIEWS
    from schemas.core import CLIPS, FRAMES, RUNS
    from schemas.detection import CAD_EMBEDDINGS, DETECTIONS, EMBEDDING_WHITENING, EMBEDDINGS
    from schemas.label_tables import LABEL_TABLES
    from schemas.pose import CORRESPONDENCES, POSES, VERIFIED_POSES
    from schemas.retrieval import CAD_CANDIDATES, CAD_MODEL_EMBEDDINGS, LABEL_SIMILARITY
    from schemas.tracking import MANUAL_TRACKS, TRACK_APPEARANCE, TRACK_DETECTIONS, TRACKS

    return {spec.name: spec for spec in (
        CLIPS, FRAMES, RUNS, DETECTIONS, EMBEDDINGS, TRACKS, TRACK_DETECTIONS, TRACK_APPEARANCE, MANUAL_TRACKS,
        CAD_MODELS, CAD_SAMPLES, CAD_VIEWS, CAD_ISSUES, CAD_EMBEDDINGS, EMBEDDING_WHITENING,
        CORRESPONDENCES, POSES, VERIFIED_POSES, CAD_CANDIDATES, LABEL_SIMILARITY, CAD_MODEL_EMBEDDINGS,
        *LABEL_TABLES,
    )}


def __getattr__(name: str) -> Any:
    """``TABLES`` (built once) and the re-exported names of :mod:`schemas.base` and :mod:`schemas.core`."""
    import importlib

    if name == "TABLES":
        value: Any = _tables()
    elif name in _FROM:
        value = getattr(importlib.import_module(_FROM[name]), name)
    else:
        raise AttributeError(f"module 'schemas' has no attribute {name!r}")
    globals()[name] = value
    return value
