"""Whether clicks given on a correspondences task still speak of the track that has their id now.

Tracks are made anew when detection or tracking reruns (another detector, another config), and a
remade track may carry an id that meant another object before: four identical dining chairs get the
same CAD model, so the clicks of one chair must not pose another. A task showed each track on its
key-frames with the track's box there (:class:`schemas.labels.KeyframeView`); the clicks on a
key-frame hold for the track of that id now when the track has a box on that frame overlapping the
box shown (IoU >= :data:`SAME_OBJECT_IOU`): the same object, though its boxes moved a little. A
track with one clicked key-frame that fails is asked again, all of it; one that no longer exists
is not posed from its old clicks.

Boxes: (ymin, xmin, ymax, xmax), normalised by the image's height and width (``detections.box``).
"""

from __future__ import annotations

import json

import pyarrow as pa

from tasks.tracking.clip_tracks import clip_tracks
from warehouse import Warehouse

SAME_OBJECT_IOU = 0.5
"""A clicked key-frame's box shown then and the track's box there now overlap at least this much."""

Box = tuple[float, float, float, float]


def box_iou(a: Box, b: Box) -> float:
    """Intersection over union of two (ymin, xmin, ymax, xmax) boxes (0 when either is empty)."""
    h = min(a[2], b[2]) - max(a[0], b[0])
    w = min(a[3], b[3]) - max(a[1], b[1])
    inter = max(h, 0.0) * max(w, 0.0)
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def shown_boxes(wh: Warehouse, clip: str) -> dict[tuple[str, int], list[tuple[object, dict[int, Box]]]]:
    """Per (correspondences task id, track id): each version of the task (its ``created_at``) with
    the boxes it showed the track with, by key-frame timestamp (µs); versions oldest first."""
    if not wh.has_partition("label_tasks", clip):
        return {}
    tasks = wh.read("label_tasks", [clip], columns=["task_id", "kind", "created_at", "document"])
    shown: dict[tuple[str, int], list[tuple[object, dict[int, Box]]]] = {}
    for row in tasks.filter(pa.compute.equal(tasks.column("kind"), "correspondences")).to_pylist():
        for item in json.loads(row["document"])["items"]:
            boxes = {int(k["timestamp_us"]): tuple(k["box"]) for k in item["keyframes"] if k.get("box") is not None}
            shown.setdefault((row["task_id"], int(item["track_id"])), []).append((row["created_at"], boxes))
    return {k: sorted(v, key=lambda x: x[0]) for k, v in shown.items()}


def seen_then(versions: list[tuple[object, dict[int, Box]]], ingested_at) -> dict[int, Box]:
    """The boxes of the task version the answer saw: the newest written before it was ingested
    (the oldest when none was)."""
    before = [boxes for at, boxes in versions if at <= ingested_at]
    return before[-1] if before else versions[0][1]


def holding_tracks(wh: Warehouse, clip: str) -> set[int]:
    """The tracks whose newest correspondence answer (over all tasks, as ``correspondences`` holds
    it: :func:`tasks.human.label_ingest.correspondence_table`) still holds for the track of that
    id now (see the module): on every clicked key-frame where the task showed a box, the track has a
    box now that overlaps it. An answer whose task is not on record holds."""
    from tasks.human.label_ingest import current_answers

    answers = current_answers(wh, "correspondences", [clip])
    if answers.num_rows == 0:
        return set()
    newest: dict[int, tuple] = {}
    stamps: dict[tuple, set[int]] = {}
    for r in answers.select(["task_id", "track_id", "timestamp_us", "ingested_at"]).to_pylist():
        t, key = int(r["track_id"]), (r["task_id"], r["ingested_at"])
        stamps.setdefault((t, *key), set()).add(int(r["timestamp_us"]))
        if t not in newest or r["ingested_at"] > newest[t][1]:
            newest[t] = key
    shown = shown_boxes(wh, clip)
    now = {t: {b.timestamp_us: b.box for b in track.boxes} for t, track in clip_tracks(wh, clip).items()}
    holding = set()
    for t, (task_id, at) in newest.items():
        versions = shown.get((task_id, t))
        then = seen_then(versions, at) if versions else {}
        current = now.get(t)
        if current is not None and all(ts in current and box_iou(then[ts], current[ts]) >= SAME_OBJECT_IOU
               for ts in stamps[(t, task_id, at)] if ts in then):
            holding.add(t)
    return holding
