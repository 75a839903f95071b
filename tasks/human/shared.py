"""What the human-task stages share: the instructions people read, key-frames of a track, writing a task
file once, withdrawing one when a rerun asks nothing, and a stage's result (completed, or paused
while items wait).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TypeVar

from schemas.dataclass_json import to_json
from schemas.labels import TASK_CLASSES, KeyframeView
from tasks.human.keyframes import evenly_spaced
from tasks.human.labels import asks_nothing, latest_task_of_kind, new_task_id, parse_task, utc_now, write_task
from tasks.stage import StageOutput
from tasks.tracking.clip_tracks import ClipTrack
from warehouse import Warehouse

B = TypeVar("B")


INSTRUCTIONS = {
    "manual_track": "Draw every object that none of the existing tracks covers: its class and a box on each key-frame "
                    "where it is visible. Answer with no object if nothing is missing.",
    "cad_selection": "For every track, choose the CAD candidate whose shape is closest to the object; "
                     "cad_id null if none is similar enough.",
    "correspondences": "For every track, on each key-frame you annotate (two at least: one view gives no depth), click "
                       "4-6 points on the CAD model and the same points in the image; mirror the model if it is the "
                       "mirror image of the object.",
    "verification": "For every track, accept only if the rendered CAD model aligns with the object on every key-frame.",
}


def image_size(wh: Warehouse, clip: str) -> tuple[int, int]:
    frames = wh.read("frames", [clip], columns=["width", "height"])
    if frames.num_rows == 0:
        return (1, 1)
    return int(frames.column("height")[0].as_py()), int(frames.column("width")[0].as_py())


def made_up_cameras(wh: Warehouse, clip: str) -> frozenset[int]:
    """Timestamps (µs) of the clip's frames whose camera SfM interpolated (``frames.camera_interpolated``):
    made-up cameras (held at the clip's ends: frozen while the video moves)."""
    frames = wh.read("frames", [clip], columns=["timestamp_us", "camera_interpolated"]).to_pylist()
    return frozenset(int(f["timestamp_us"]) for f in frames if f["camera_interpolated"])


def on_registered(boxes: Sequence[B], made_up: frozenset[int]) -> tuple[B, ...]:
    """A track's ``boxes`` (each with a ``timestamp_us``) less those on a frame of a made-up camera
    (:func:`made_up_cameras`), where it has others: the clicks of a key-frame solve the pose through
    its camera. The rule of the correspondence task's key-frames (:func:`track_keyframes` with
    ``posed``) and of the boxes its carried clicks must still fall on (:func:`boxes_now`)."""
    registered = tuple(b for b in boxes if b.timestamp_us not in made_up)
    return registered or tuple(boxes)


def track_keyframes(wh: Warehouse, clip: str, tracks: dict[int, ClipTrack], track_ids: list[int],
                    k: int, posed: bool = False) -> dict[int, tuple[KeyframeView, ...]]:
    """Per track of ``track_ids`` (automatic or manual, from ``tracks``: :func:`clip_tracks`),
    ``k`` evenly spaced frames of its boxes with its box there. ``posed``: only frames whose camera
    SfM registered, where the track has any (:func:`on_registered`)."""
    columns = ["timestamp_us", "frame_index", "image_path", "camera_interpolated"]
    frames = {f["frame_index"]: f for f in wh.read("frames", [clip], columns=columns).to_pylist()}
    made_up = frozenset(int(f["timestamp_us"]) for f in frames.values() if f["camera_interpolated"]) if posed else frozenset()
    out = {}
    for t in track_ids:
        boxes = on_registered(tracks[t].boxes if t in tracks else (), made_up)
        views = []
        for i in evenly_spaced(len(boxes), k):
            frame = frames.get(boxes[i].frame_index)
            if frame is not None:
                views.append(KeyframeView(timestamp_us=int(frame["timestamp_us"]), frame_index=int(frame["frame_index"]),
                                          image_path=frame["image_path"], box=tuple(float(v) for v in boxes[i].box)))
        out[t] = tuple(views)
    return out


def boxes_now(tracks: dict[int, ClipTrack], made_up: frozenset[int] = frozenset(),
              fragments: Mapping[int, int] | None = None) -> dict[int, dict[int, list[tuple]]]:
    """Per track of the clip (``tracks``: :func:`tasks.tracking.clip_tracks.clip_tracks`), its boxes by
    frame timestamp (µs): what :mod:`tasks.human.clicks_in_force` and
    :mod:`tasks.human.choices_in_force` compare earlier tasks with (every track, also those not
    asked about: an earlier answer goes to the track that matches it best). ``made_up``: frames of
    made-up cameras, left out as :func:`on_registered` says (for clicks: carried clicks hold only
    where the track has a box now, so those on a frame an SfM run again made interpolated no
    longer hold, and the track is asked again; they went on to the pose solver). ``fragments``:
    tracks said to be another (a drawn object "is track N",
    :func:`tasks.tracking.relations.manual_statements`): their boxes are N's (a drawing tighter
    than N's box took N's earlier answer, and N was asked again)."""
    fragments = fragments or {}
    now: dict[int, dict[int, list[tuple]]] = {}
    for t, track in tracks.items():
        for b in on_registered(track.boxes, made_up):
            now.setdefault(fragments.get(t, t), {}).setdefault(b.timestamp_us, []).append(b.box)
    return now


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
