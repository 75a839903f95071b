"""Tables of tracks: automatic tracking (stage ``tracking``: ``tracks``, ``track_detections``,
``track_appearance``) and manual tracks (stage ``manual_tracks``: ``manual_tracks``), per clip.

A track is one physical object: a cluster of the clip's detections (at most one per frame).
``track_id`` is the track's rank when tracks are ordered by their first detection id, so it is
the same on every rerun with unchanged inputs (and never depends on the order rows were read).
A manual track (drawn by people on the val/test splits, paper Sec. 3.1) has the id
``MANUAL_TRACK_BASE`` + a digest of the drawn object (tasks.tracking.relations.manual_track_ids): never an automatic id.
"""

from __future__ import annotations

import pyarrow as pa

from schemas.base import CLIP, TableSpec, column, vector

MANUAL_TRACK_BASE = 1_000_000
"""Track ids of manual tracks start here (automatic ids are ranks: far below; int32 above)."""

TRACKS = TableSpec(
    name="tracks",
    mode="replace",
    key=("clip", "track_id"),
    description="One row per automatic track: class by vote, time span, number of detections.",
    schema=pa.schema(
        [
            CLIP,
            column("track_id", pa.int32(), "Track id in the clip: rank of the track ordered by its first det_id."),
            column("label", pa.string(), "Class by vote of its detections (score-weighted; ties: the label first in name order)."),
            column("label_votes", pa.float64(), "Share of the (score-weighted) votes the label got, in (0, 1]."),
            column("first_timestamp_us", pa.int64(), "Timestamp of its first detection.", unit="µs"),
            column("last_timestamp_us", pa.int64(), "Timestamp of its last detection.", unit="µs"),
            column("first_frame_index", pa.int32(), "Frame of its first detection."),
            column("last_frame_index", pa.int32(), "Frame of its last detection."),
            column("num_detections", pa.int32(), "Detections in the track (one per frame at most)."),
            column("mean_score", pa.float32(), "Mean detector score of its detections."),
            column("cohesion", pa.float64(), "Mean edge log-odds between its detections (higher: more certain)."),
        ]
    ),
)

TRACK_DETECTIONS = TableSpec(
    name="track_detections",
    mode="replace",
    key=("clip", "track_id", "det_id"),
    description="Membership: which detections (detections.det_id) form each track.",
    schema=pa.schema(
        [
            CLIP,
            column("track_id", pa.int32(), "tracks.track_id."),
            column("det_id", pa.int64(), "detections.det_id."),
            column("frame_index", pa.int32(), "Frame of the detection."),
            column("timestamp_us", pa.int64(), "Timestamp of the detection.", unit="µs"),
        ]
    ),
)

TRACK_APPEARANCE = TableSpec(
    name="track_appearance",
    mode="replace",
    key=("clip", "track_id"),
    description="Appearance summary of each track for CAD retrieval: mean raw descriptor and medoid detection.",
    schema=pa.schema(
        [
            CLIP,
            column("track_id", pa.int32(), "tracks.track_id."),
            column("vector", pa.list_(pa.field("item", pa.float32(), nullable=False)),
                   "Mean of the track's raw descriptors (embeddings.vector), L2-normalised."),
            column("num_vectors", pa.int32(), "Descriptors averaged."),
            column("medoid_det_id", pa.int64(), "The detection whose descriptor is closest to the mean (a representative crop)."),
            column("model_sha256", pa.string(), "SHA-256 of the embedder of the descriptors."),
        ]
    ),
)

MANUAL_TRACKS = TableSpec(
    name="manual_tracks",
    mode="replace",
    key=("clip", "track_id", "timestamp_us"),
    description="One row per box of a manual track (the objects people drew for the clip's manual-track task), "
                "with the box's appearance descriptor.",
    schema=pa.schema(
        [
            CLIP,
            column("track_id", pa.int32(), "Track id: MANUAL_TRACK_BASE (1,000,000) + a digest of the object (its source_id, else its class and boxes), stable when other objects of the answer change."),
            column("label", pa.string(), "Class the annotator chose (a detector label, as tracks.label)."),
            column("source_id", pa.string(), "The object's id in the annotation tool.", nullable=True),
            column("timestamp_us", pa.int64(), "Frame of the box (a frames row).", unit="µs"),
            column("frame_index", pa.int32(), "frames.frame_index of the box."),
            column("box", vector(4), "(ymin, xmin, ymax, xmax), normalised by image height (y) and width (x).",
                   frame="image, normalised [0,1], origin top-left"),
            column("vector", pa.list_(pa.field("item", pa.float32(), nullable=False)),
                   "Appearance descriptor of the box's crop, unit L2 norm (as embeddings.vector: same embedder, same [embed])."),
            column("model_sha256", pa.string(), "SHA-256 of the ONNX embedder."),
            column("task_id", pa.string(), "The manual_track task the label answered (label_tasks.task_id)."),
        ]
    ),
)
