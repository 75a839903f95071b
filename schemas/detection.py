"""Tables of detection and appearance embedding: ``detections`` and ``embeddings`` per clip,
``cad_embeddings`` and ``embedding_whitening`` per CAD library.

Boxes follow CAD-Estate: normalised image coordinates (ymin, xmin, ymax, xmax) in [0, 1], origin
at the image's top-left corner, y down. Descriptors are float32, L2-normalised, raw (before the
library's centring/whitening, which :mod:`tasks.retrieval.whitening` applies when comparing).
"""

from __future__ import annotations

import pyarrow as pa

from schemas.base import CLIP, LIBRARY, TableSpec, column, vector

BOX_FRAME = "image, normalised [0,1], origin top-left, y down"

DETECTIONS = TableSpec(
    name="detections",
    mode="replace",
    key=("clip", "det_id"),
    description="One row per detected box: frame, box (ymin, xmin, ymax, xmax normalised), label, score, detector.",
    schema=pa.schema(
        [
            CLIP,
            column("det_id", pa.int64(), "Detection id, unique in the clip: frame_index * 10000 + rank of the box in its frame (by score)."),
            column("timestamp_us", pa.int64(), "Camera timestamp of the frame.", unit="µs"),
            column("frame_index", pa.int32(), "0-based position of the frame in the clip."),
            column("box", vector(4), "(ymin, xmin, ymax, xmax) as in CAD-Estate.", frame=BOX_FRAME),
            column("label", pa.string(), "Class name from the detector's label map."),
            column("label_id", pa.int32(), "Index of the label in the detector's label map."),
            column("score", pa.float32(), "Detector confidence in [0, 1]."),
            column("model_sha256", pa.string(), "SHA-256 of the ONNX detector that produced the box."),
        ]
    ),
)

EMBEDDINGS = TableSpec(
    name="embeddings",
    mode="replace",
    key=("clip", "owner", "owner_id"),
    description="One appearance descriptor per detection crop (L2-normalised, raw: before whitening).",
    schema=pa.schema(
        [
            CLIP,
            column("owner", pa.string(), "What was embedded: 'detection' (owner_id = det_id)."),
            column("owner_id", pa.int64(), "Id of the embedded box within its owner table."),
            column("vector", pa.list_(pa.field("item", pa.float32(), nullable=False)), "Descriptor, unit L2 norm."),
            column("model_sha256", pa.string(), "SHA-256 of the ONNX embedder."),
        ]
    ),
)

CAD_EMBEDDINGS = TableSpec(
    name="cad_embeddings",
    mode="replace",
    key=("library", "cad_id", "view"),
    description="One appearance descriptor per CAD view render (L2-normalised, raw: before whitening).",
    schema=pa.schema(
        [
            LIBRARY,
            column("cad_id", pa.string(), "Model id (cad_models.cad_id)."),
            column("view", pa.int32(), "View index (cad_views.view)."),
            column("vector", pa.list_(pa.field("item", pa.float32(), nullable=False)), "Descriptor, unit L2 norm."),
            column("model_sha256", pa.string(), "SHA-256 of the ONNX embedder."),
        ]
    ),
)

EMBEDDING_WHITENING = TableSpec(
    name="embedding_whitening",
    mode="replace",
    key=("library",),
    description="The transform a library's descriptors go through before they are compared: w = normalise(P (v - mean)).",
    schema=pa.schema(
        [
            LIBRARY,
            column("method", pa.string(), "none | centre | whiten (fitted on the views) | learned (P trained by `make models`)."),
            column("mean", pa.list_(pa.field("item", pa.float32(), nullable=False)), "Mean descriptor [D] (zeros for 'none')."),
            column("projection", pa.list_(pa.field("item", pa.float32(), nullable=False)), "P, [k, D] row-major (identity for 'none' and 'centre')."),
            column("dims", pa.int32(), "k, rows of P."),
            column("views", pa.int64(), "View descriptors it was fitted on."),
        ]
    ),
)
