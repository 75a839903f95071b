"""What the ``pose`` stage reads besides ``frames``, and their digests (its inputs in lineage).

Kept apart from the solver (:mod:`tasks.pose.pose`) so that ``cadestate status`` can tell whether the
stage is stale without importing PyTorch.
"""

from __future__ import annotations

import pyarrow as pa

from cadestate.lineage import digest, table_digest
from warehouse import Warehouse


def input_digests(wh: Warehouse, clip: str) -> list[str]:
    """The stage's inputs besides ``frames``, from one read: the digest of the clip's
    :func:`answered_correspondences` (new clicks, or a changed choice of model, re-solve the clip)
    and :func:`cad_models_digest` of the models they use."""
    corr = answered_correspondences(wh, clip)
    return [table_digest(corr), cad_models_digest(wh, corr)]


MODEL_FACTS = ("cad_id", "class", "symmetry", "extent")
"""The ``cad_models`` columns the stage reads."""


def cad_models_digest(wh: Warehouse, corr: pa.Table) -> str:
    """Digest of the ``cad_models`` facts (:data:`MODEL_FACTS`) of the models that the
    correspondences ``corr`` reference (a re-ingested library that changes a model's class,
    symmetry or bounding box re-solves the clips that use it, and only those). A referenced model
    missing from ``cad_models`` leaves a row with nulls (it turns into ``unknown_cad``)."""
    needed = sorted(set(corr.column("cad_id").to_pylist()))
    if not needed:
        return digest("no models")
    facts = {r["cad_id"]: r for r in wh.read("cad_models", columns=list(MODEL_FACTS)).to_pylist() if r["cad_id"] in needed}
    rows = [facts.get(c, {"cad_id": c, "class": None, "symmetry": None, "extent": None}) for c in needed]
    return digest(*(f"{r['cad_id']}\t{r['class']}\t{r['symmetry']}\t{r['extent']}" for r in rows))


def answered_correspondences(wh: Warehouse, clip: str) -> pa.Table:
    """The clip's ``correspondences``: when they came from label files, the clicks that answer its
    newest correspondences task (:mod:`tasks.human.clicks_in_force`), kept only for the tracks
    whose clicks use the model chosen for them now (:func:`tasks.human.cad_selection.selected_models`):
    while the task is behind (nothing chosen any more, a choice changed, a manual track taken
    back), no track is posed from stale clicks. Rows no label file wrote are all kept."""
    corr = wh.read("correspondences", [clip])
    if not wh.has_partition("correspondence_labels", clip):
        return corr
    from tasks.human.cad_selection import selected_models

    chosen = {str(t): c for t, c in selected_models(wh, clip).items() if c is not None}
    keep = [chosen.get(t) == c for t, c in zip(corr.column("track_id").to_pylist(), corr.column("cad_id").to_pylist())]
    return corr.filter(pa.array(keep, pa.bool_()))
