"""Which clicks answer each item of a clip's correspondences task: one rule for the stage that
writes the task, the ``correspondences`` table that pose reads, the web app's queue and the
simulated annotators.

An item (a track, its chosen CAD model, its key-frames with the track's box there) is answered by

1. the answer in force under the task's own id (:func:`tasks.human.answers_in_force.current_answers`),
   else
2. its ``previous``: clicks given on an earlier correspondences task of the clip that still hold,
   which the stage finds when it writes the task (:func:`held_clicks`) and carries in the item.

The task id names every item's track, model, key-frames and boxes
(:func:`item_key`), so an answer under it was given on what the task shows now. Clicks of an
earlier task hold when they use the item's model and speak of the same object, whatever id its
track had then: tracks are made anew when detection or tracking reruns, and a remade track may
carry an id that meant another object, or another id (four identical dining chairs get the same
model, so one chair's clicks must not pose another). On every clicked key-frame where the earlier
task showed a box, the track now has a box overlapping it (IoU >= :data:`SAME_OBJECT_IOU`), and
there is at least one such key-frame. Going back to an earlier state (a detector A, then B, then A
again) finds A's task id and A's answers in force again.

Boxes: (ymin, xmin, ymax, xmax), normalised by the image's height and width (``detections.box``).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping, Sequence
from typing import TypeVar

import pyarrow as pa

from schemas.labels import CorrespondenceAnswer, CorrespondenceKeyframe, CorrespondencePoint, KeyframeView

SAME_OBJECT_IOU = 0.5
"""A clicked key-frame's box shown then and the track's box there now overlap at least this much."""

Box = tuple[float, float, float, float]
T = TypeVar("T")


def box_iou(a: Box, b: Box) -> float:
    """Intersection over union of two (ymin, xmin, ymax, xmax) boxes (0 when either is empty)."""
    h = min(a[2], b[2]) - max(a[0], b[0])
    w = min(a[3], b[3]) - max(a[1], b[1])
    inter = max(h, 0.0) * max(w, 0.0)
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def item_key(track_id: int, cad_id: str, keyframes: Sequence[KeyframeView]) -> str:
    """What an item shows, as a part of the task id: track, model, and each key-frame's timestamp
    (µs) and box (4 decimals; "-": none)."""
    views = ";".join(f"{k.timestamp_us}@" + ("-" if k.box is None else ",".join(f"{v:.4f}" for v in k.box))
                     for k in keyframes)
    return f"{track_id}:{cad_id}:{views}"


def item_versions(tasks: pa.Table, kind: str) -> dict[tuple[str, int], list[tuple[object, dict]]]:
    """Per (task id, track id) of the tasks of ``kind`` among ``tasks`` (``label_tasks`` rows with
    ``task_id``, ``kind``, ``created_at``, ``document``): each version of the task (its
    ``created_at``) with the item it showed for the track (its document); oldest first."""
    shown: dict[tuple[str, int], list[tuple[object, dict]]] = {}
    for row in tasks.to_pylist():
        if row["kind"] == kind:
            for item in json.loads(row["document"])["items"]:
                shown.setdefault((row["task_id"], int(item["track_id"])), []).append((row["created_at"], item))
    return {k: sorted(v, key=lambda x: x[0]) for k, v in shown.items()}


def item_boxes(item: dict) -> dict[int, Box]:
    """The boxes an item (its document) showed the track with, by key-frame timestamp."""
    return {int(k["timestamp_us"]): tuple(k["box"]) for k in item["keyframes"] if k.get("box") is not None}


def seen_then(versions: list[tuple[object, T]], ingested_at) -> T:
    """What the task version an answer saw showed (``versions``: :func:`item_versions`'): the newest
    written before the answer was ingested (the oldest when none was)."""
    before = [shown for at, shown in versions if at <= ingested_at]
    return before[-1] if before else versions[0][1]


def newest_holding(earlier: Sequence[tuple[object, int, T]], track: int, test: Callable[[T], bool]) -> T | None:
    """The answer an item of ``track`` takes from ``earlier`` ((ingested_at, track id, answer),
    newest first): the newest for which ``test`` holds; among equally new ones (one label file
    answers many tracks), the one given on a track of the same id. None when none holds."""
    best: tuple[object, int, T] | None = None
    for entry in earlier:
        if best is not None and entry[0] != best[0]:
            break
        if (best is None or entry[1] == track) and test(entry[2]):
            best = entry
    return None if best is None else best[2]


def holds(clicked: set[int], then: Mapping[int, Box], now: Mapping[int, list[Box]]) -> bool:
    """Whether clicks on the key-frames ``clicked`` (timestamps), given while the task showed the
    boxes ``then``, speak of the track whose boxes are ``now`` (timestamp -> its boxes there)."""
    return all(any(box_iou(then[ts], b) >= SAME_OBJECT_IOU for b in now.get(ts, ())) for ts in clicked if ts in then)


def held_clicks(task_id: str, chosen: Mapping[int, str], now: Mapping[int, Mapping[int, list[Box]]], answers: pa.Table,
                tasks: pa.Table) -> dict[int, CorrespondenceAnswer]:
    """Per track of ``chosen`` (track -> chosen cad_id), the clicks that answer its item of task
    ``task_id`` (see the module): its answer under that id, else the newest answer of another task,
    on a track of any id, that holds. ``now``: each track's boxes by timestamp; ``answers``: the
    clip's correspondence answers in force over all tasks; ``tasks``: its ``label_tasks`` rows.
    Tracks without are absent."""
    rows: dict[tuple[str, int], list[dict]] = {}
    for r in answers.to_pylist():
        rows.setdefault((r["task_id"], int(r["track_id"])), []).append(r)
    shown = item_versions(tasks, "correspondences")
    earlier = [(at, key[1], (rows[key], {int(r["timestamp_us"]) for r in rows[key]}, item_boxes(seen_then(shown[key], at))))
               for at, key in sorted(((rs[0]["ingested_at"], key) for key, rs in rows.items()
                                      if key[0] != task_id and key in shown), reverse=True)]
    out = {}
    for t, cad in chosen.items():
        if (task_id, t) in rows:
            out[t] = to_answer(t, rows[(task_id, t)])
            continue
        found = newest_holding(earlier, t, lambda e: e[0][0]["cad_id"] == cad and bool(e[1] & e[2].keys())
                               and holds(e[1], e[2], now.get(t, {})))
        if found is not None:
            out[t] = to_answer(t, found[0])
    return out


def to_answer(track_id: int, rows: list[dict]) -> CorrespondenceAnswer:
    """One track's answer rows (``correspondence_labels``) as the answer they came from."""
    by_frame: dict[int, list[dict]] = {}
    for r in sorted(rows, key=lambda r: (r["timestamp_us"], r["point_index"])):
        by_frame.setdefault(int(r["timestamp_us"]), []).append(r)
    keyframes = tuple(CorrespondenceKeyframe(timestamp_us=ts, points=tuple(
        CorrespondencePoint(x=r["point_2d"][0], y=r["point_2d"][1], xyz=tuple(r["point_3d"])) for r in rs))
        for ts, rs in by_frame.items())
    return CorrespondenceAnswer(track_id=track_id, cad_id=rows[0]["cad_id"], is_mirrored=bool(rows[0]["is_mirrored"]),
                                keyframes=keyframes)


def in_force_rows(clip: str, doc: dict, answers: pa.Table) -> list[dict]:
    """``correspondences`` rows of the task ``doc`` (a correspondences task document): per item,
    the answer in force under its id (``answers``: that task's, from ``correspondence_labels``),
    else the item's ``previous``."""
    under_id: dict[int, list[dict]] = {}
    for r in answers.to_pylist():
        under_id.setdefault(int(r["track_id"]), []).append(r)
    out = []
    for item in doc["items"]:
        t = int(item["track_id"])
        if t in under_id:
            clicks = [(r["timestamp_us"], r["point_index"], r["cad_id"], r["point_2d"], r["point_3d"], r["is_mirrored"])
                      for r in under_id[t]]
        elif (prev := item.get("previous")) is not None:
            clicks = [(kf["timestamp_us"], k, prev["cad_id"], [p["x"], p["y"]], list(p["xyz"]), prev["is_mirrored"])
                      for kf in prev["keyframes"] for k, p in enumerate(kf["points"])]
        else:
            continue
        out += [{"clip": clip, "track_id": str(t), "timestamp_us": ts, "point_index": k, "cad_id": cad, "point_2d": p2,
                 "point_3d": p3, "is_mirrored": mirrored} for ts, k, cad, p2, p3, mirrored in clicks]
    return out
