"""Tables of automatic tracking (stage ``tracking``): ``tracks``, ``track_detections``,
``track_appearance`` per clip.

A track is one physical object: a cluster of the clip's detections (at most one per frame).
``track_id`` is the track's rank when tracks are ordered by their first detection id, so it is
the same on every rerun with unchanged inputs (and never depends on the order rows were read).
"""

from __future__ import annotations

import pyarrow as pa

from schemas.base import CLIP, TableSpec, column

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
