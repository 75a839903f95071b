"""Tables of CAD retrieval (paper, Sec. 3.2): ``label_similarity`` and ``cad_model_embeddings``
per CAD library, ``cad_candidates`` per clip.

A track's score for a CAD model is the mean, over every (detection of the track, view of the model)
pair, of ``class_similarity(detection label, model class) ** x * appearance(detection, view)``, with
``class_similarity`` the cosine of the two label names in a sentence encoder's space (clipped at
0), ``x`` = ``[retrieval] class_exponent`` (``drawn_class_exponent`` for a manual track's drawn
boxes; 1 is the paper's product) and ``appearance = (1 + cosine) / 2`` of the whitened descriptors
(:mod:`tasks.retrieval.whitening`). The ``score`` column's description, written before the exponent,
stays as it is: the column descriptions of ``cad_candidates`` are part of the digest that names a
clip's CAD-selection task (:func:`cadestate.lineage.table_digest`), so editing one would leave
every answer given unmatched.
"""

from __future__ import annotations

import pyarrow as pa

from schemas.base import CLIP, LIBRARY, TableSpec, column

FLOATS = pa.list_(pa.field("item", pa.float32(), nullable=False))

LABEL_SIMILARITY = TableSpec(
    name="label_similarity",
    mode="replace",
    key=("library", "detector_label", "cad_class"),
    description="Cosine similarity of every detector label and every CAD class of a library (sentence encoder).",
    schema=pa.schema(
        [
            LIBRARY,
            column("detector_label", pa.string(), "A label of the detector's label map ([detect] labels)."),
            column("cad_class", pa.string(), "A class of the library (cad_models.class)."),
            column("similarity", pa.float32(), "Cosine of the two names' sentence embeddings, in [-1, 1]."),
            column("encoder", pa.string(), "The sentence encoder (package==version)."),
        ]
    ),
)

CAD_MODEL_EMBEDDINGS = TableSpec(
    name="cad_model_embeddings",
    mode="replace",
    key=("library", "cad_id"),
    description="Per CAD model, the mean of its views' whitened unit descriptors (what retrieval compares tracks with).",
    schema=pa.schema(
        [
            LIBRARY,
            column("cad_id", pa.string(), "cad_models.cad_id."),
            column("class", pa.string(), "cad_models.class."),
            column("vector", FLOATS, "Mean over views of whiten(view descriptor), [k] (not renormalised)."),
            column("views", pa.int32(), "Views averaged."),
        ]
    ),
)

CAD_CANDIDATES = TableSpec(
    name="cad_candidates",
    mode="replace",
    key=("clip", "track_id", "rank"),
    description="The top CAD models of every track: appearance x class-label similarity over all detection x view pairs.",
    schema=pa.schema(
        [
            CLIP,
            column("track_id", pa.int32(), "tracks.track_id."),
            column("rank", pa.int32(), "1 = shown first: by score, with at most [retrieval] max_per_class of one class while other classes have models."),
            column("library", pa.string(), "CAD library of the model."),
            column("cad_id", pa.string(), "cad_models.cad_id."),
            column("cad_class", pa.string(), "cad_models.class."),
            column("score", pa.float32(), "Mean of class_similarity x appearance over detection x view pairs, in [0, 1]."),
            column("appearance", pa.float32(), "Mean appearance (1 + cosine) / 2 alone, in [0, 1]."),
            column("class_similarity", pa.float32(), "Mean clipped class-label similarity over the track's detections, in [0, 1]."),
        ]
    ),
)
