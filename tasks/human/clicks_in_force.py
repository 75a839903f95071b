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
there is at least one such key-frame. An earlier answer speaks of one object: where it holds for
several tracks now (a track and its shadow, or two objects whose boxes overlap on the one clicked
key-frame), the best matched takes it (:func:`taken_answers`). Of the answers a track takes, the
newest given on the model chosen now holds. Going back to an earlier state (a detector A, then B,
then A again) finds A's task id and A's answers in force again.

Boxes: (ymin, xmin, ymax, xmax), normalised by the image's height and width (``detections.box``).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Mapping, Sequence
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


Earlier = tuple[object, int, tuple[list[dict], dict]]
"""An answer to an earlier task: (ingested_at, track id it was given on, (its rows, the item its
task version showed when it was given))."""


def earlier_answers(answers: pa.Table, tasks: pa.Table, kind: str, task_id: str) -> list[Earlier]:
    """The answers of ``kind`` given on other tasks than ``task_id``, newest first, each with the
    item it was given on (:func:`seen_then`); an answer is the rows of one (task, track) in
    ``answers`` (the clip's answers in force: one row, or a row per click). ``tasks``: the clip's
    ``label_tasks`` rows; answers to a task not on record say nothing of what they saw: left out."""
    rows: dict[tuple[str, int], list[dict]] = {}
    for r in answers.to_pylist():
        rows.setdefault((r["task_id"], int(r["track_id"])), []).append(r)
    shown = item_versions(tasks, kind)
    return [(at, key[1], (rows[key], seen_then(shown[key], at)))
            for at, key in sorted(((rs[0]["ingested_at"], key) for key, rs in rows.items() if key[0] != task_id and key in shown),
                                  key=lambda x: x[0], reverse=True)]


Match = tuple[int, float]
"""How well a track now matches an earlier item: the key-frames compared, their mean IoU (more is better)."""


def match(frames: Iterable[int], then: Mapping[int, Box], now: Mapping[int, list[Box]]) -> Match | None:
    """How well the track whose boxes are ``now`` (timestamp -> its boxes there) is the object an
    earlier item showed with the boxes ``then``, compared on ``frames`` (timestamps, each with a box
    then): None unless on every one of them one of its boxes overlaps the box then (IoU >=
    :data:`SAME_OBJECT_IOU`), else how many frames and the mean of the best IoUs."""
    ious = [max((box_iou(then[ts], b) for b in now.get(ts, ())), default=0.0) for ts in frames]
    return None if any(iou < SAME_OBJECT_IOU for iou in ious) else (len(ious), sum(ious) / len(ious) if ious else 0.0)


def holds(clicked: set[int], then: Mapping[int, Box], now: Mapping[int, list[Box]]) -> Match | None:
    """Whether clicks on the key-frames ``clicked`` (timestamps), given while the task showed the
    boxes ``then``, speak of the track whose boxes are ``now``: :func:`match` on the clicked
    key-frames shown with a box (a track without a box there now does not match)."""
    return match(sorted(ts for ts in clicked if ts in then), then, now)


def taken_answers(earlier: Sequence[tuple[object, int, T]], tracks: Iterable[int],
                  match_of: Callable[[int, T], Match | None]) -> dict[int, list[T]]:
    """Which earlier answers speak for each track now. ``earlier``: (ingested_at, track id it was
    given on, answer); ``match_of(track, answer)``: how well the answer's item matches the track now
    (None: not at all). An answer speaks of one object, so where it matches several tracks (a track
    and its shadow, or an object and another that overlaps it on one key-frame), the best matched
    takes it (then the track of the same id, then the smaller id). Per track, the answers it takes,
    newest first; of equally new ones (one label file answers many tracks), the one given on a track
    of the same id, then the best matched. Tracks that take none are absent. An answer whose object
    has no track now still goes to a track it matches (the boxes overlap on every key-frame they
    share, which may be one)."""
    tracks = sorted(set(tracks))
    taken: dict[int, list[tuple[object, bool, Match, int, T]]] = {}
    for order, (at, then_id, answer) in enumerate(earlier):
        scored = [(m, t == then_id, -t) for t in tracks if (m := match_of(t, answer)) is not None]
        if scored:
            m, same, neg_t = max(scored)
            taken.setdefault(-neg_t, []).append((at, same, m, -order, answer))
    return {t: [o[4] for o in sorted(options, key=lambda o: o[:4], reverse=True)] for t, options in taken.items()}


def held_clicks(task_id: str, chosen: Mapping[int, str], now: Mapping[int, Mapping[int, list[Box]]], answers: pa.Table,
                tasks: pa.Table) -> dict[int, CorrespondenceAnswer]:
    """Per track of ``chosen`` (track -> chosen cad_id), the clicks that answer its item of task
    ``task_id`` (see the module): its answer under that id, else, of the answers to other tasks that
    speak of its object (:func:`taken_answers`: matched by :func:`holds` on a clicked key-frame at
    least), the newest given on the model chosen now. ``now``: the boxes by timestamp of the clip's
    tracks, all of them (an answer goes to the track that matches it best, chosen or not);
    ``answers``: the clip's correspondence answers in force over all tasks; ``tasks``: its
    ``label_tasks`` rows. Tracks without are absent."""
    under_id: dict[int, list[dict]] = {}
    for r in answers.to_pylist():
        if r["task_id"] == task_id:
            under_id.setdefault(int(r["track_id"]), []).append(r)

    def clicks_match(t: int, e: tuple[list[dict], dict]) -> Match | None:
        m = holds({int(r["timestamp_us"]) for r in e[0]}, item_boxes(e[1]), now.get(t, {}))
        return m if m is not None and m[0] > 0 else None

    taken = taken_answers(earlier_answers(answers, tasks, "correspondences", task_id), set(now) | set(chosen), clicks_match)
    out = {}
    for t, cad in chosen.items():
        if t in under_id:
            out[t] = to_answer(t, under_id[t])
        elif found := next((e for e in taken.get(t, ()) if e[0][0]["cad_id"] == cad), None):
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
