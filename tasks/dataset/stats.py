"""``cadestate stats``: the dataset's figures (the paper's Table 2 and section 4) and its cost, for
any warehouse.

The dataset is what ``cadestate export official`` writes: per clip its frames and its physical
objects (:func:`tasks.dataset.objects.clip_dataset`); an object is *posed* when its pose was
accepted in verification. Clips are chosen with a SQL condition on the ``clips`` table
(``--where``), and, as the export chooses them, only those whose verification completed (a clip
still waiting for verdicts would count every object of it as not posed); tables come from DuckDB
(the warehouse catalog) into pandas.

Figures: the yield first (posed objects of all physical objects, posed or not: what the pipeline
made of what it found), scenes (clips), frames, frames per scene, objects, posed objects, classes
of posed objects and those with > 100 and > 1,000, posed objects per scene, posed objects visible
per frame (with a box on it), distinct CAD models; per frame with >= 2 posed objects visible, the
ratio of the nearest to the farthest object distance (camera centre to object translation, world
metres); per visible posed object and frame, the truncation: the share of its projected CAD
bounding box (the box of the 8 posed corners, pixels) outside the image (1 when a corner is behind
the camera: the box reaches beyond the image). Cost: compute seconds per stage (``runs``) and of
the CAD libraries (shared by every clip), human items answered per task kind (a manual_track label
is one item, any other one item per track answered), and annotation seconds: the ``seconds`` label
files give per item (``label_effort``), summed over every ingested label file (a superseded answer
cost time too), per kind (None when no item of the kind gave any) and per posed object (None
unless every item gave its seconds: a partial sum would flatter), with the count of items that
gave no ``seconds`` (their time is missing from the sums).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from cadestate.geometry import camera_to_world, project
from tasks.dataset.objects import ClipDataset, clip_dataset
from warehouse import Warehouse

if TYPE_CHECKING:
    from tasks.cad.export import ExportClips


@dataclass(frozen=True)
class DatasetTables:
    """pandas DataFrames. ``objects``: clip, track_id, class, cad_id, posed, automatic (one row per
    physical object); ``visible``: clip, timestamp_us, track_id, class, distance_m, truncated (one
    row per posed object and frame it has a box on; both NaN when its model has no extent);
    ``frames``: clip, timestamp_us; ``runs``: stage, duration_s (the clips'); ``library_s``: the
    seconds of the CAD libraries' runs;
    ``labels`` (one row per ingested label file): kind, num_answers, items (answered items: 1 for
    manual_track, else num_answers), timed_items (items with ``seconds``), seconds (their sum)."""

    clips: list[str]
    objects: object
    visible: object
    frames: object
    runs: object
    labels: object
    library_s: float = 0.0


def select_clips(wh: Warehouse, where: str = "true") -> ExportClips:
    """The clips of the ``clips`` table matching the SQL condition ``where`` (sorted), as ``export
    official`` chooses them: ``chosen`` those whose verification completed, ``unfinished`` the others
    (:func:`tasks.cad.export.verification_completed`). :class:`warehouse.query.QueryError` when
    ``where`` is not one condition (:func:`warehouse.query.sql_condition`) or fails; a
    :class:`warehouse.WarehouseError` naming a file of the tables that cannot be read."""
    from tasks.cad.export import ExportClips, verification_completed
    from warehouse.query import run_query, sql_condition

    sql = f"SELECT clip FROM clips WHERE (\n{sql_condition(where)}\n) ORDER BY clip"  # a trailing -- comment ends at the newline
    with run_query(wh, sql) as result:  # read-only: the user's SQL
        matching = [row[0] for batch in result.batches for row in batch]
    done = verification_completed(wh, matching) if matching else set()
    return ExportClips([c for c in matching if c in done], [c for c in matching if c not in done])


def _truncation_and_distance(ds: ClipDataset, o, frame) -> tuple[float, float]:
    """(distance_m, truncated share) of posed object ``o`` on ``frame`` (share 1 when a corner of its
    box is behind the camera: the box's projection reaches beyond the image)."""
    h, w = ds.image_size
    half = np.asarray(o.extent, np.float64) / 2
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * half
    M = o.pose.matrix()
    uv, depth = project(frame.K, frame.R, frame.t, corners @ M[:3, :3].T + M[:3, 3])
    distance = float(np.linalg.norm(np.asarray(o.pose.translation) - camera_to_world(frame.R, frame.t)[1]))
    if np.any(depth <= 0):
        return distance, 1.0
    (x0, y0), (x1, y1) = uv.min(0), uv.max(0)
    area = (x1 - x0) * (y1 - y0)
    inside = max(0.0, min(x1, w) - max(x0, 0)) * max(0.0, min(y1, h) - max(y0, 0))
    return distance, float(1 - inside / area) if area > 0 else float("nan")


def dataset_tables(wh: Warehouse, clips: list[str],
                   each: Callable[[ClipDataset], None] | None = None) -> DatasetTables:
    """The tables :func:`statistics` reads, for ``clips``; ``each`` (the HTML report's clip pages)
    is called with every clip's dataset as it is read: one clip's dataset is in memory at a time,
    and read once (~0.4 s a clip)."""
    import duckdb
    import pandas as pd

    from warehouse import WarehouseError, connect
    from warehouse.catalog import one_line

    objects, visible = [], []
    for clip in clips:
        ds = clip_dataset(wh, clip)
        if each is not None:
            each(ds)
        frames = {f.timestamp_us: f for f in ds.frames}
        for o in ds.objects:
            objects.append({"clip": clip, "track_id": o.track_id, "class": o.class_name, "cad_id": o.cad_id,
                            "posed": o.pose is not None, "automatic": o.automatic})
            if o.pose is None:
                continue
            for ts in o.boxes:
                if ts in frames:
                    d, tr = _truncation_and_distance(ds, o, frames[ts]) if o.extent else (float("nan"),) * 2
                    visible.append({"clip": clip, "timestamp_us": ts, "track_id": o.track_id, "class": o.class_name,
                                    "distance_m": d, "truncated": tr})
    con = connect(wh)
    try:
        params = [clips]
        frames_df = con.execute("SELECT clip, timestamp_us FROM frames WHERE list_contains(?, clip)", params).df()
        runs_df = con.execute("SELECT stage, duration_s FROM runs WHERE list_contains(?, clip)", params).df()
        library_s = con.execute("SELECT coalesce(sum(duration_s), 0.0) FROM runs WHERE clip IN "
                                "(SELECT DISTINCT library FROM cad_models)").fetchone()[0] if clips else 0.0
        labels_df = con.execute(
            "SELECT f.kind, any_value(f.num_answers) AS num_answers, "
            "CASE WHEN f.kind = 'manual_track' THEN 1 ELSE any_value(f.num_answers) END AS items, "
            "count(e.seconds) AS timed_items, coalesce(sum(e.seconds), 0.0) AS seconds FROM label_files f "
            "LEFT JOIN label_effort e USING (clip, label_sha256, ingested_at) WHERE list_contains(?, f.clip) "
            "GROUP BY f.clip, f.label_sha256, f.ingested_at, f.kind", params).df()
    except duckdb.Error as e:  # a damaged file: one line naming it, not a traceback
        raise WarehouseError(f"cannot read the warehouse {wh.root}: {one_line(str(e))}") from None
    finally:
        con.close()
    columns = {"objects": ["clip", "track_id", "class", "cad_id", "posed", "automatic"],
               "visible": ["clip", "timestamp_us", "track_id", "class", "distance_m", "truncated"]}
    return DatasetTables(clips, pd.DataFrame(objects, columns=columns["objects"]),
                         pd.DataFrame(visible, columns=columns["visible"]), frames_df, runs_df, labels_df, float(library_s))


def statistics(t: DatasetTables) -> dict:
    """The figures of the module docstring as a dict of plain numbers (means 0 for no clip/frame)."""
    posed = t.objects[t.objects["posed"].astype(bool)]  # bool even when empty (an empty column is of object dtype)
    per_class = posed["class"].value_counts()
    n_clips, n_frames = len(t.clips), len(t.frames)
    per_frame = t.visible.dropna(subset=["distance_m"]).groupby(["clip", "timestamp_us"])["distance_m"]
    ratios = (per_frame.min() / per_frame.max())[per_frame.count() >= 2]
    truncated = t.visible["truncated"].dropna()
    seconds = float(t.labels["seconds"].sum())
    missing = int(t.labels["items"].sum()) - int(t.labels["timed_items"].sum())
    by_kind = t.labels.groupby("kind")
    return {
        "yield": len(posed) / len(t.objects) if len(t.objects) else None,
        "scenes": n_clips, "frames": n_frames, "frames_per_scene": n_frames / n_clips if n_clips else 0.0,
        "objects": len(t.objects), "posed_objects": len(posed), "classes": int(per_class.size),
        "classes_over_100": int((per_class > 100).sum()), "classes_over_1000": int((per_class > 1000).sum()),
        "objects_per_scene": len(posed) / n_clips if n_clips else 0.0,
        "objects_per_frame": len(t.visible) / n_frames if n_frames else 0.0,
        "cad_models": int(posed["cad_id"].nunique()),
        "near_far_ratio_mean": float(ratios.mean()) if len(ratios) else None,
        "near_far_ratio_median": float(ratios.median()) if len(ratios) else None,
        "frames_with_two_posed": int(len(ratios)),
        "truncated_share": float((truncated > 0).mean()) if len(truncated) else None,
        "truncated_mean": float(truncated.mean()) if len(truncated) else None,
        "per_class": {k: int(v) for k, v in per_class.sort_index().items()},
        "compute_s_per_stage": {k: round(float(v), 2) for k, v in t.runs.groupby("stage")["duration_s"].sum().items()},
        "compute_s_cad_libraries": round(t.library_s, 2),
        "human_items": {k: int(v) for k, v in by_kind["items"].sum().items()},
        "annotation_s": round(seconds, 3),
        "annotation_s_per_kind": {k: round(float(s), 3) if timed else None
                                  for (k, s), timed in zip(by_kind["seconds"].sum().items(), by_kind["timed_items"].sum())},
        "items_without_seconds": missing,
        "annotation_s_per_posed_object": seconds / len(posed) if len(posed) and len(t.labels) and not missing else None,
    }


TABLE_ROWS = (("scenes", "#Scenes (clips)"), ("posed_objects", "#Posed objects"),
              ("objects", "#Objects (physical, posed or not)"),
              ("classes", "#Classes"), ("classes_over_1000", "#Classes >1000"), ("classes_over_100", "#Classes >100"),
              ("objects_per_scene", "#Posed objects per scene"), ("objects_per_frame", "#Posed objects per frame (visible)"),
              ("cad_models", "#CAD models"), ("frames", "#Frames"), ("frames_per_scene", "#Frames per scene"),
              ("near_far_ratio_median", "Nearest / farthest object distance (median per frame)"),
              ("truncated_share", "Share of visible posed objects truncated by the image border"))


def statistics_lines(stats: dict) -> list[tuple[str, str]]:
    """(label, value) rows: the yield, then Table 2 and section 4, values formatted."""
    fmt = lambda v: "-" if v is None else f"{v:.2f}" if isinstance(v, float) else str(v)  # noqa: E731
    share = "-" if stats["yield"] is None else f"{100 * stats['yield']:.1f} %"
    return [("Yield (posed of all objects found)", f"{stats['posed_objects']} of {stats['objects']} ({share})"),
            *((label, fmt(stats[key])) for key, label in TABLE_ROWS)]


def cost_lines(stats: dict) -> list[tuple[str, str]]:
    """(label, value) rows of the dataset's cost: compute seconds per stage and of the CAD libraries,
    human items answered per kind, then :func:`annotation_cost_lines`."""
    from tasks.registry import stages_of

    order = {st.name: i for i, st in enumerate(stages_of("clip"))}  # the pipeline's order; others after, by name
    per_stage = sorted(stats["compute_s_per_stage"].items(), key=lambda kv: (order.get(kv[0], len(order)), kv[0]))
    rows = [(f"compute s: {k}", f"{v:.2f}") for k, v in per_stage]
    rows.append(("compute s: CAD libraries (shared by every clip)", f"{stats['compute_s_cad_libraries']:.2f}"))
    rows += [(f"human items answered: {k}", str(v)) for k, v in stats["human_items"].items()]
    return rows + annotation_cost_lines(stats)


def annotation_cost_lines(stats: dict) -> list[tuple[str, str]]:
    """(label, value) rows of the annotation time the label files record (``label_effort``)."""
    per_object = stats["annotation_s_per_posed_object"]
    rows = [(f"annotation s: {k}", "-" if v is None else f"{v:.1f}") for k, v in stats["annotation_s_per_kind"].items()]
    rows.append(("annotation s per posed object" + (" (shown when every item is timed)" if stats["items_without_seconds"] else ""),
                 "-" if per_object is None else f"{per_object:.1f}"))
    rows.append(("answered items with no seconds recorded (missing from the sums)", str(stats["items_without_seconds"])))
    return rows
