"""Single source of truth for every warehouse table (and, later, every task and label file)."""

from schemas.base import CLIP, LIBRARY, TableSpec, column, vector
from schemas.cad import CAD_ISSUES, CAD_MODELS, CAD_SAMPLES, CAD_VIEWS
from schemas.core import CLIPS, FRAMES, RUNS
from schemas.detection import CAD_EMBEDDINGS, DETECTIONS, EMBEDDING_WHITENING, EMBEDDINGS
from schemas.labels import LABEL_TABLES
from schemas.pose import CORRESPONDENCES, POSES, VERIFIED_POSES
from schemas.retrieval import CAD_CANDIDATES, CAD_MODEL_EMBEDDINGS, LABEL_SIMILARITY
from schemas.tracking import MANUAL_TRACKS, TRACK_APPEARANCE, TRACK_DETECTIONS, TRACKS

TABLES: dict[str, TableSpec] = {spec.name: spec for spec in (
    CLIPS, FRAMES, RUNS, DETECTIONS, EMBEDDINGS, TRACKS, TRACK_DETECTIONS, TRACK_APPEARANCE, MANUAL_TRACKS,
    CAD_MODELS, CAD_SAMPLES, CAD_VIEWS, CAD_ISSUES, CAD_EMBEDDINGS, EMBEDDING_WHITENING,
    CORRESPONDENCES, POSES, VERIFIED_POSES, CAD_CANDIDATES, LABEL_SIMILARITY, CAD_MODEL_EMBEDDINGS,
    *LABEL_TABLES,
)}
"""Every table of the warehouse by name; the DuckDB catalog has one view per entry."""

__all__ = ["TABLES", "TableSpec", "column", "vector", "CLIP", "LIBRARY", "CLIPS", "FRAMES", "RUNS"]
