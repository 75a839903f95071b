"""What the human-task stages share: the instructions people read, key-frames of a track, writing a task
file once, withdrawing one when a rerun asks nothing, and a stage's result (completed, or paused
while items wait).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from schemas.dataclass_json import to_json
from schemas.labels import TASK_CLASSES, KeyframeView
from tasks.human.keyframes import evenly_spaced
from tasks.human.labels import asks_nothing, latest_task_of_kind, new_task_id, parse_task, utc_now, write_task
from tasks.stage import StageOutput
from tasks.tracking.clip_tracks import ClipTrack, clip_tracks
from warehouse import Warehouse


INSTRUCTIONS = {
    "manual_track": "Draw every object that none of the existing tracks covers: its class and a box on each key-frame "
                    "where it is visible. Answer with no object if nothing is missing.",
    "cad_selection": "For every track, choose the CAD candidate whose shape is closest to the object; "
                     "cad_id null if none is similar enough.",
    "correspondences": "For every track, on each key-frame you annotate, click 4-6 points on the CAD model and the "
                       "same points in the image; mirror the model if it is the mirror image of the object.",
    "verification": "For every track, accept only if the rendered CAD model aligns with the object on every key-frame.",
}


def image_size(wh: Warehouse, clip: str) -> tuple[int, int]:
    frames = wh.read("frames", [clip], columns=["width", "height"])
    if frames.num_rows == 0:
        return (1, 1)
    return int(frames.column("height")[0].as_py()), int(frames.column("width")[0].as_py())


def track_keyframes(wh: Warehouse, clip: str, tracks: dict[int, ClipTrack], track_ids: list[int],
                    k: int, posed: bool = False) -> dict[int, tuple[KeyframeView, ...]]:
    """Per track of ``track_ids`` (automatic or manual, from ``tracks``: :func:`clip_tracks`),
    ``k`` evenly spaced frames of its boxes with its box there. ``posed``: only frames whose camera
    SfM registered (``frames.camera_interpolated`` not true), where the track has any: the clicks of
    a key-frame solve the pose through its camera, and an interpolated one (held at the clip's ends:
    frozen while the video moves) is a made-up camera."""
    columns = ["timestamp_us", "frame_index", "image_path", "camera_interpolated"]
    frames = {f["frame_index"]: f for f in wh.read("frames", [clip], columns=columns).to_pylist()}
    out = {}
    for t in track_ids:
        boxes = tracks[t].boxes if t in tracks else ()
        if posed:
            registered = tuple(b for b in boxes if not (frames.get(b.frame_index) or {}).get("camera_interpolated"))
            boxes = registered or boxes
        views = []
        for i in evenly_spaced(len(boxes), k):
            frame = frames.get(boxes[i].frame_index)
            if frame is not None:
                views.append(KeyframeView(timestamp_us=int(frame["timestamp_us"]), frame_index=int(frame["frame_index"]),
                                          image_path=frame["image_path"], box=tuple(float(v) for v in boxes[i].box)))
        out[t] = tuple(views)
    return out


def boxes_now(tracks: dict[int, ClipTrack]) -> dict[int, dict[int, list[tuple]]]:
    """Per track of the clip (``tracks``: :func:`tasks.tracking.clip_tracks.clip_tracks`), its boxes by
    frame timestamp (µs): what :mod:`tasks.human.clicks_in_force` and
    :mod:`tasks.human.choices_in_force` compare earlier tasks with (every track, also those not
    asked about: an earlier answer goes to the track that matches it best)."""
    now: dict[int, dict[int, list[tuple]]] = {}
    for t, track in tracks.items():
        for b in track.boxes:
            now.setdefault(t, {}).setdefault(b.timestamp_us, []).append(b.box)
    return now


def on_registered_cameras(wh: Warehouse, clip: str, boxes: dict[int, dict[int, list[tuple]]]) -> dict[int, dict[int, list[tuple]]]:
    """``boxes`` (:func:`boxes_now`) less those on frames whose camera SfM interpolated, for each
    track with a box on a registered frame (as :func:`track_keyframes` with ``posed`` asks): clicks
    carried from an earlier task hold only where the track has a box now, so clicks on a frame
    that an SfM run again made interpolated (a made-up camera) no longer hold, and the track is
    asked again; they went on to the pose solver."""
    frames = wh.read("frames", [clip], columns=["timestamp_us", "camera_interpolated"]).to_pylist()
    made_up = {int(f["timestamp_us"]) for f in frames if f["camera_interpolated"]}
    if not made_up:
        return boxes
    out = {}
    for t, by_ts in boxes.items():
        registered = {ts: b for ts, b in by_ts.items() if ts not in made_up}
        out[t] = registered or by_ts
    return out


def write_task_once(wh: Warehouse, task) -> Path:
    """Write ``task``; if the newest version of the same task id says the same (but for
    ``created_at``) and is still the clip's newest task of its kind, keep that version (no new
    file or ``label_tasks`` row). A task that comes back after another took its place (upstream
    went A, then B, then A again) is written anew: the newest task of a kind is the one in force
    (:func:`tasks.human.labels.latest_tasks`)."""
    row = latest_task_of_kind(wh, task.clip, task.kind)  # when it is this task, also its newest version
    if row is not None and row["task_id"] == task.task_id:
        old = parse_task(row["document"], f"task {task.task_id}")
        same = dataclasses.replace(task, created_at=old.created_at)
        if to_json(same) == json.loads(row["document"]):
            return write_task(wh, same)
    return write_task(wh, task)


def withdraw_task(wh: Warehouse, clip: str, kind: str, why: str) -> str:
    """When a rerun asks nothing of ``kind`` (``why``: e.g. "no track has a chosen CAD model"), make
    the clip's newest task of the kind one with nothing to answer
    (:func:`tasks.human.labels.asks_nothing`), so that its earlier task, no longer in force, stops
    waiting in the app and in ``cadestate status``; nothing is written when there is no earlier
    task or it asks nothing already. Returns what to add to the stage's message ("" if nothing)."""
    row = latest_task_of_kind(wh, clip, kind)
    if row is None or asks_nothing(json.loads(row["document"])):
        return ""
    empty = {"keyframes": (), "existing_tracks": (), "classes": ()} if kind == "manual_track" else {"items": ()}
    write_task(wh, TASK_CLASSES[kind](task_id=new_task_id(kind, clip, "withdrawn"), clip=clip, created_at=utc_now().isoformat(),
                                      image_size=image_size(wh, clip), instructions=f"Nothing to answer: {why}.", **empty))
    return f"; task {row['task_id']} withdrawn"


def task_output(rows: int, output_hash: str, summary: str, kind: str, path: str, waiting: int, total: int,
                what: str = "tracks") -> StageOutput:
    """A human-task stage's result: completed, or paused while ``waiting`` of ``total`` items of
    its ``kind`` task at ``path`` are unanswered (the message names the task file)."""
    if not waiting:
        return StageOutput(rows, output_hash, summary)
    return StageOutput(rows, output_hash, f"waits for labels: {waiting} of {total} {what} unanswered in {kind} task {path}; "
                                          f"{summary}", paused=True)
