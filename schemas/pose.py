"""Tables of 9-DoF pose solving (paper section 3.4): ``correspondences`` (human clicks) and ``poses``.

Frames: 2D points are normalised image coordinates (x by the width, y by the height; origin at
the top-left corner, x right, y down); 3D points are in the canonical CAD frame of the model
(metres, +Y up, front +Z, bbox-centred), *unmirrored*. Poses map that frame to the world with the
official CAD-Estate order mirror => scale => rotation => translation, i.e.
``X_world = T + R · diag(S) · diag(-1, 1, 1)[mirrored] · X_cad`` (see :mod:`cadestate.render`).
"""

from __future__ import annotations

import pyarrow as pa

from schemas.base import CLIP, TableSpec, column, vector

CAD_FRAME = "canonical CAD (+Y up, front +Z, unmirrored)"


def _maybe(size: int) -> pa.DataType:
    """A fixed-size float64 list for a nullable column (a null row's child slots are null too,
    which a non-nullable item field cannot hold)."""
    return pa.list_(pa.field("item", pa.float64()), size)

CORRESPONDENCES = TableSpec(
    name="correspondences",
    mode="replace",
    key=("clip", "track_id", "timestamp_us", "point_index"),
    description="3D<->2D point correspondences of the human task (one row per click): the input of pose solving.",
    schema=pa.schema([
        CLIP,
        column("track_id", pa.string(), "Track (object) the click belongs to: tracks.track_id written as text (cast "
                                         "to INTEGER to compare or sort as a number)."),
        column("timestamp_us", pa.int64(), "Key-frame: camera timestamp of the frame clicked on (a `frames` row).", unit="µs"),
        column("point_index", pa.int32(), "0-based index of the click within its key-frame."),
        column("cad_id", pa.string(), "CAD model the 3D points lie on (a `cad_models` row)."),
        column("point_2d", vector(2), "Clicked image point (x, y), normalised by width and height.",
               frame="image, normalised [0,1], origin top-left, x right, y down"),
        column("point_3d", vector(3), "Matching point on the CAD model.", unit="m", frame=CAD_FRAME),
        column("is_mirrored", pa.bool_(), "The annotator mirrored the CAD model (x -> -x) for this track; same on every row of a track."),
    ]),
)

POSES = TableSpec(
    name="poses",
    mode="replace",
    key=("clip", "track_id"),
    description="One 9-DoF pose per annotated track, solved from its correspondences; use only status = 'ok'.",
    schema=pa.schema([
        CLIP,
        column("track_id", pa.string(), "Track (object): tracks.track_id written as text (cast to INTEGER to compare "
                                         "or sort as a number)."),
        column("cad_id", pa.string(), "CAD model posed."),
        column("class", pa.string(), "Class of the CAD model."),
        column("status", pa.string(), "ok | invalid_input | too_few_points | single_keyframe | collinear_points | "
                                      "behind_camera | high_residual | low_parallax | unknown_cad | missing_camera (tasks/pose/checks.py)."),
        column("message", pa.string(), "Why the status is what it is, in words."),
        column("translation", _maybe(3), "T of the object-to-world T·R·S·mirror (null: not solved).", unit="m",
               frame="world (+Y up)", nullable=True),
        column("rotation", _maybe(4), "R as a unit quaternion (w, x, y, z) (null: not solved).", frame="CAD -> world", nullable=True),
        column("scale", _maybe(3), "S (sx, sy, sz) along the CAD axes (null: not solved).", frame=CAD_FRAME, nullable=True),
        column("is_mirrored", pa.bool_(), "Mirror x -> -x before scaling (from the correspondences)."),
        column("symmetry", pa.int32(), "Symmetry order about +Y of the CAD model used by the solver (1, 2, 4, 36)."),
        column("upright", pa.bool_(), "The up-axis term applied (class in [pose] upright_classes)."),
        column("coplanar_axis", pa.int32(), "CAD axis (0 x, 1 y, 2 z) perpendicular to co-planar 3D points, whose scale "
                                            "was tied to the mean of the other two; -1 none."),
        column("num_keyframes", pa.int32(), "Key-frames with correspondences."),
        column("num_points", pa.int32(), "Correspondences used."),
        column("loss_total", pa.float64(), "Final L_repr + alpha L_up + beta L_front + L_prop + L_axes + L_floor (tasks/pose/solver.py; null: not solved).", nullable=True),
        column("loss_reprojection", pa.float64(), "Final L_repr per point: the robust loss of [pose] huber_px summed over "
                                                  "du and dv (|du| + |dv| when huber_px = 0; with the default 5 px, smaller "
                                                  "than the pixel error: read keyframe_error_px for errors in pixels).",
               unit="px", nullable=True),
        column("loss_up", pa.float64(), "Final L_up: |R e_y - e_y|_1 (0 when not upright).", nullable=True),
        column("loss_front", pa.float64(), "Final L_front: mean depth below [pose] min_depth.", unit="m", nullable=True),
        column("keyframe_timestamps_us", pa.list_(pa.int64()), "Key-frames, in the order of keyframe_error_px.", unit="µs"),
        column("keyframe_error_px", pa.list_(pa.float64()), "Mean Euclidean reprojection error per key-frame (empty: not solved).", unit="px"),
        column("parallax_deg", pa.float64(), "Largest angle between the rays from the object to its key-frame cameras.",
               unit="deg", nullable=True),
        column("iterations", pa.int32(), "Optimiser iterations run (0: not solved)."),
        column("start", pa.int32(), "Which start won (turn by start·360/starts deg about up; -1: not solved)."),
        column("loss_floor", pa.float64(), "Final L_floor, the support term: [pose] floor_prior · |bottom - support_height| / "
                                           "object height (0 unless floor_prior is 'used' or 'host'; null: not solved).",
               unit="px", nullable=True),
        column("floor_prior", pa.string(), "The support prior (tasks/pose/support.py): none (off, a class that does not rest "
                                           "on a support, no bounding box or no pose) | no_floor (the clip has no floor "
                                           "estimate) | off_floor (no support within [pose] floor_max_gap heights of its "
                                           "bottom: own pose kept) | rejected (the reprojection loss grew more than [pose] "
                                           "floor_max_growth: own pose kept) | used (solved resting on the floor) | host "
                                           "(solved resting on the top of support_track)."),
        column("floor_height", pa.float64(), "The clip's floor height estimate (lowest bounding-box points of its solved "
                                             "floor objects, inverse-variance weighted mean of those within [pose] "
                                             "floor_max_gap heights of their weighted median; null: none).", unit="m",
               frame="world (+Y up), height along +Y", nullable=True),
        column("support_track", pa.string(), "The track whose top the object was solved resting on (floor_prior 'host') or "
                                             "tried to (a rejected host); null: the floor or none.", nullable=True),
        column("support_height", pa.float64(), "Height of the support the object was solved resting on (or tried to: "
                                               "rejected); null: none.", unit="m",
               frame="world (+Y up), height along +Y", nullable=True),
        column("config_hash", pa.string(), "Digest of the [pose] config section that produced the row."),
    ]),
)

VERIFIED_POSES = TableSpec(
    name="verified_poses",
    mode="replace",
    key=("clip", "track_id"),
    description="The verdict of people on each solved pose (verification task, paper 3.5): accepted poses are the "
                "dataset's; tracks not answered yet are absent.",
    schema=pa.schema([
        CLIP,
        column("track_id", pa.string(), "Track (object), as poses.track_id."),
        column("cad_id", pa.string(), "CAD model posed."),
        column("class", pa.string(), "Class of the CAD model."),
        column("accepted", pa.bool_(), "True: the rendered CAD aligns on every key-frame."),
        column("translation", _maybe(3), "T of the object-to-world T·R·S·mirror.", unit="m", frame="world (+Y up)", nullable=True),
        column("rotation", _maybe(4), "R as a unit quaternion (w, x, y, z).", frame="CAD -> world", nullable=True),
        column("scale", _maybe(3), "S (sx, sy, sz) along the CAD axes.", frame=CAD_FRAME, nullable=True),
        column("is_mirrored", pa.bool_(), "Mirror x -> -x before scaling."),
        column("task_id", pa.string(), "The verification task answered (label_tasks.task_id)."),
        column("comment", pa.string(), "The verifier's comment.", nullable=True),
    ]),
)
