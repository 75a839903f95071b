"""Task files out, label files in: writing tasks and validating labels (see :mod:`schemas.labels`).

A stage that needs people calls :func:`write_task` (the task file goes to
``<warehouse>/label_tasks/<clip>/<task_id>.json`` and its document to the ``label_tasks`` table)
and pauses; :func:`validate_label` checks a label file in two steps:

1. the document (:mod:`tasks.human.label_format`): size, UTF-8 JSON, finite numbers, valid Unicode,
   the kind's JSON Schema, ``created_at``, different 3D points per key-frame;
2. the warehouse: the clip exists, the task exists and is of that kind, track ids are the task's,
   a chosen ``cad_id`` is one of the track's candidates (or the task's model), timestamps are
   frames of the clip, clicks are on the item's key-frames (or those of its ``previous`` clicks)
   and their 3D points within the model's bounding box, boxes have positive size, no track or
   key-frame is answered twice, no object is drawn twice in one manual-track answer, and the
   tracks named by ``same_as_track`` / ``not_objects`` are the task's (another track than the one
   answered; a CAD-selection fragment's ``cad_id`` is null).

So everything that could make a row fail to be written is refused here, before ingest writes
anything. Every failure is a :class:`LabelError` whose message is one line naming the file and
the field as a JSON path, e.g. ``labels/c1.json: $.answers[0].track_id: unknown track 7``.
Values that are legal but suspicious become warnings (:attr:`LabelFile.warnings`: two clicks at one
image point, a drawn object over an existing track: :mod:`tasks.human.drawn_objects`). Ingest (into
the answer tables) is :mod:`tasks.human.label_ingest`.
"""

from __future__ import annotations

import datetime as dt
import functools
import hashlib
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import pyarrow as pa

from cadestate.lineage import digest
from schemas.dataclass_json import to_json
from schemas.labels import LABEL_FORMAT, Label, Task
from tasks.human.drawn_objects import check_drawn_once, drawn_over_tracks
from tasks.human.label_format import (MAX_LABEL_BYTES, LabelError, check_clicks, check_size, check_time, field_error, parse_label,
                                parse_task, read_limited)
from warehouse import Warehouse, atomic_write_bytes, check_name

TASK_DIR = "label_tasks"
"""Folder of the task files under the warehouse root."""


@dataclass(frozen=True)
class LabelFile:
    """A validated label file: where it came from, its bytes' SHA-256, its text, its content, its
    ``created_at`` in UTC (None: not given) and warnings on legal but suspicious values."""

    path: Path
    sha256: str
    document: str
    label: Label
    created_at: dt.datetime | None = None
    warnings: tuple[str, ...] = ()

    @property
    def kind(self) -> str:
        return self.label.kind

    @property
    def clip(self) -> str:
        return self.label.clip

    @property
    def task_id(self) -> str:
        return self.label.task_id


# ------------------------------------------------------------------------------ task files

def new_task_id(kind: str, clip: str, *parts: str) -> str:
    """A task id that is the same whenever the task's inputs are (``parts``: digests of what the
    task shows), so a rerun with unchanged upstream work finds the labels of the earlier run."""
    return f"{check_name(clip)}.{kind}.{digest(kind, clip, *parts)[:12]}"


def utc_now() -> dt.datetime:
    return dt.datetime.now(dt.timezone.utc)


def write_task(wh: Warehouse, task: Task) -> Path:
    """Write the task file (atomically) and register it in ``label_tasks``; returns its path.

    Checks the task against its own schema first (a stage bug must not reach people). Writing the
    same task again (same id and bytes) leaves everything as it is. A new row is dated after every
    task of its kind the clip has (:func:`_dated_after_its_kind`)."""
    text, created_at = _task_text(task)
    data = text.encode()
    path = wh.root / TASK_DIR / check_name(task.clip) / f"{check_name(task.task_id, 'task id')}.json"
    sha = hashlib.sha256(data).hexdigest()
    known = wh.read("label_tasks", [task.clip], filters=[("task_id", "=", task.task_id)], columns=["task_sha256"])
    if path.is_file() and path.read_bytes() == data and sha in known.column("task_sha256").to_pylist():
        return path
    if (later := _dated_after_its_kind(wh, task, created_at)) is not task:
        task = later
        text, created_at = _task_text(task)
        data = text.encode()
        sha = hashlib.sha256(data).hexdigest()
    atomic_write_bytes(path, data)
    items = getattr(task, "items", None)
    row = {"clip": task.clip, "task_id": task.task_id, "kind": task.kind, "path": wh.relative(path),
           "task_sha256": sha, "num_items": len(items if items is not None else task.keyframes),
           "created_at": created_at, "document": text}
    wh.write("label_tasks", task.clip, pa.Table.from_pylist([row]))
    return path


def _task_text(task: Task) -> tuple[str, dt.datetime]:
    """The task file's text, checked against its own schema, and its ``created_at`` (UTC)."""
    text = json.dumps(to_json(task), indent=1, ensure_ascii=False, allow_nan=False) + "\n"
    parse_task(text, f"task {task.task_id}")
    return text, check_time(task.created_at, "created_at", f"task {task.task_id}")


def _dated_after_its_kind(wh: Warehouse, task: Task, created_at: dt.datetime) -> Task:
    """``task``, dated a microsecond after the newest task of its kind of its clip where it is not
    after it already: the newest by date is the one in force, and a stage run on a clock behind
    (another machine's, a clock set back) wrote a task people were told to answer while the one
    before stayed in force (their answers never reached the data, and each run wrote it again)."""
    if not wh.has_partition("label_tasks", task.clip):
        return task
    rows = wh.read("label_tasks", [task.clip], filters=[("kind", "=", task.kind)], columns=["created_at"])
    newest = max(rows.column("created_at").to_pylist(), default=None)
    if newest is None or created_at > newest:
        return task
    return replace(task, created_at=(newest + dt.timedelta(microseconds=1)).isoformat())


def latest_task(wh: Warehouse, clip: str, task_id: str) -> dict | None:
    """The newest ``label_tasks`` row of a task (its document is what labels are checked against;
    the first of equal times). Only that row becomes a Python object: a task rewritten after each
    answer has a row, with its whole document, per version."""
    if not wh.has_partition("label_tasks", clip):
        return None
    table = wh.read("label_tasks", [clip])
    newest = _newest_rows(table, "task_id").get(task_id)
    return None if newest is None else table.slice(newest, 1).to_pylist()[0]


def latest_task_of_kind(wh: Warehouse, clip: str, kind: str) -> dict | None:
    """The newest ``label_tasks`` row of ``kind`` for ``clip`` (e.g. the task an import answers)."""
    return latest_tasks(wh, clip).get(kind)


def latest_tasks(wh: Warehouse, clip: str, columns: Sequence[str] | None = None) -> dict[str, dict]:
    """The newest ``label_tasks`` row of each kind for ``clip`` (kind -> row; the first of equal
    times), from one read: only those rows become Python objects (a task's document can be large);
    ``columns``: only these (with kind and created_at; e.g. no document read at all)."""
    if not wh.has_partition("label_tasks", clip):
        return {}
    table = wh.read("label_tasks", [clip], columns=columns)
    return {kind: table.slice(i, 1).to_pylist()[0] for kind, i in _newest_rows(table, "kind").items()}


def asks_nothing(document: Mapping[str, Any]) -> bool:
    """Whether a task document (parsed JSON) has nothing to answer: the stage withdrew its earlier
    task of the kind (:func:`tasks.human.shared.withdraw_task`); such a task is in force, as the
    newest of its kind, only to say so."""
    return not document.get("keyframes" if document.get("kind") == "manual_track" else "items")


def withdrawn_why(row: Mapping[str, Any] | None) -> str | None:
    """Why the task of a ``label_tasks`` row (with its document; a kind's newest) was withdrawn: its
    instructions when it asks nothing (:func:`asks_nothing`); None when it asks something, or no row."""
    if row is None:
        return None
    document = json.loads(row["document"])
    return document["instructions"] if asks_nothing(document) else None


def _newest_rows(table: pa.Table, column: str) -> dict[str, int]:
    """Index of the newest ``label_tasks`` row (the first of equal times) of each value of ``column``."""
    values, created = table.column(column).to_pylist(), table.column("created_at").to_pylist()
    newest: dict[str, int] = {}
    for i, (value, at) in enumerate(zip(values, created)):
        if value not in newest or at > created[newest[value]]:
            newest[value] = i
    return newest


# ------------------------------------------------------------------------------ warehouse checks

class ClipFacts:
    """What label checks need from the warehouse, read once per clip (ingest reuses one instance)."""

    def __init__(self, wh: Warehouse):
        self.wh = wh
        self._clips: dict[str, bool] = {}

    def has_clip(self, clip: str) -> bool:
        """Whether ``clip`` is registered (its folder looked at once, not every clip's)."""
        if clip not in self._clips:
            self._clips[clip] = self.wh.has_partition("clips", clip)
        return self._clips[clip]

    @functools.cache
    def timestamps(self, clip: str) -> frozenset[int]:
        return frozenset(self.wh.read("frames", [clip], columns=["timestamp_us"]).column("timestamp_us").to_pylist())

    @functools.cached_property
    def extents(self) -> dict[str, tuple[float, float, float]]:
        """cad_id -> the canonical bounding box's size (m, along the CAD axes) of every model."""
        rows = self.wh.read("cad_models", columns=["cad_id", "extent"]).to_pylist()
        return {r["cad_id"]: tuple(r["extent"]) for r in rows if r["extent"] is not None}

    @functools.cache
    def same_as(self, clip: str, kind: str, task_id: str) -> dict[int, int]:
        """{track: the track it is the same object as} of the answers in force of a cad_selection or
        verification task ({} for other kinds)."""
        if kind not in ("cad_selection", "verification"):
            return {}
        from tasks.tracking.relations import same_as_statements  # it reads answers in force, which read label files

        return same_as_statements(self.wh, clip, kind, task_id)

    def take(self, label: Label) -> None:
        """Count ``label``'s 'same object as' answers as in force for the labels checked after it (a
        file accepted earlier in the same ingest, not written yet)."""
        links = self.same_as(label.clip, label.kind, label.task_id)
        for a in label.answers if label.kind in ("cad_selection", "verification") else ():
            if a.same_as_track is None:
                links.pop(a.track_id, None)
            else:
                links[a.track_id] = a.same_as_track

    @functools.cache
    def task(self, clip: str, task_id: str) -> Task | None:
        row = latest_task(self.wh, clip, task_id)
        return None if row is None else parse_task(row["document"], f"task {task_id}")


def _check_boxes(boxes, stamps: frozenset[int], name: str, path: list) -> None:
    seen = set()
    for j, b in enumerate(boxes):
        if b.timestamp_us not in stamps:
            raise field_error(name, [*path, j, "timestamp_us"], f"{b.timestamp_us} is not a frame of the clip")
        if b.timestamp_us in seen:
            raise field_error(name, [*path, j, "timestamp_us"], f"a second box on frame {b.timestamp_us}")
        seen.add(b.timestamp_us)
        ymin, xmin, ymax, xmax = b.box
        if not (ymin < ymax and xmin < xmax):
            raise field_error(name, [*path, j, "box"], f"empty box {list(b.box)}: need ymin < ymax and xmin < xmax")


BOX_SLACK = (0.05, 0.01)
"""A clicked 3D point lies within its model's canonical box grown by 5 % and 1 cm per axis (the
mesh's surface is inside the box; the slack absorbs rounding): a point beyond is a unit error
(centimetres for metres) or a point of another model."""


def _check_xyz(points, extent: tuple[float, float, float] | None, name: str, path: list) -> None:
    if extent is None:
        return
    limit = [e / 2 * (1 + BOX_SLACK[0]) + BOX_SLACK[1] for e in extent]
    for k, q in enumerate(points):
        if any(abs(v) > lim for v, lim in zip(q.xyz, limit)):
            raise field_error(name, [*path, k, "xyz"], f"{list(q.xyz)} is outside the model's bounding box "
                              f"(extent {[round(e, 3) for e in extent]} m, centred on 0): metres expected")


def _items(task: Task, name: str, label: Label) -> dict[int, Any]:
    """The task's items by track id, and a check that each answered track is one of them, once."""
    items = {it.track_id: it for it in task.items}
    seen = set()
    for i, a in enumerate(label.answers):
        if a.track_id not in items:
            raise field_error(name, ["answers", i, "track_id"],
                              f"unknown track {a.track_id} (task {task.task_id} has tracks {', '.join(map(str, sorted(items)))})")
        if a.track_id in seen:
            raise field_error(name, ["answers", i, "track_id"], f"track {a.track_id} is answered twice")
        seen.add(a.track_id)
    return items


def check_label(label: Label, facts: ClipFacts, name: str) -> list[str]:
    """The warehouse checks of a parsed label (see the module docstring); returns its warnings
    that need the warehouse (:mod:`tasks.human.drawn_objects`)."""
    if not facts.has_clip(label.clip):
        raise field_error(name, ["clip"], f"unknown clip {label.clip!r}")
    task = facts.task(label.clip, label.task_id)
    if task is None:
        raise field_error(name, ["task_id"], f"unknown task {label.task_id!r} for clip {label.clip!r}")
    if task.kind != label.kind:
        raise field_error(name, ["kind"], f"task {label.task_id} is a {task.kind} task, not {label.kind}")
    if not (task.keyframes if task.kind == "manual_track" else task.items):  # asks_nothing: withdrawn by a rerun
        raise field_error(name, ["task_id"], f"task {label.task_id} asks nothing (a rerun withdrew the kind's task: "
                                             f"{task.instructions})")
    stamps = facts.timestamps(label.clip)
    if label.kind == "manual_track":
        existing = {t.track_id for t in task.existing_tracks}
        for i, a in enumerate(label.answers):
            if task.classes and a.label not in task.classes:
                raise field_error(name, ["answers", i, "label"], f"class {a.label!r} is not one of the task's: {', '.join(task.classes)}")
            _check_boxes(a.boxes, stamps, name, ["answers", i, "boxes"])
            if a.same_as_track is not None and a.same_as_track not in existing:
                raise field_error(name, ["answers", i, "same_as_track"], f"track {a.same_as_track} is not an existing track of task {task.task_id}")
            if a.same_as_track is not None and a.same_as_track in label.not_objects:
                raise field_error(name, ["answers", i, "same_as_track"], f"track {a.same_as_track} is also said to be no object "
                                                                         "(not_objects): one of the two is wrong")
        for i, t in enumerate(label.not_objects):
            if t not in existing:
                raise field_error(name, ["not_objects", i], f"track {t} is not an existing track of task {task.task_id}")
            if t in label.not_objects[:i]:
                raise field_error(name, ["not_objects", i], f"track {t} is listed twice")
        check_drawn_once(label, name)
        return drawn_over_tracks(label, task, name)
    items = _items(task, name, label)
    for i, a in enumerate(label.answers):
        item = items[a.track_id]
        if label.kind == "cad_selection" and a.cad_id is not None and a.cad_id not in {c.cad_id for c in item.candidates}:
            raise field_error(name, ["answers", i, "cad_id"], f"{a.cad_id!r} is not a candidate of track {a.track_id}")
        if label.kind in ("cad_selection", "verification") and a.same_as_track is not None:
            if a.same_as_track not in items or a.same_as_track == a.track_id:
                raise field_error(name, ["answers", i, "same_as_track"],
                                  f"track {a.same_as_track} is not another track of task {task.task_id}")
            if label.kind == "cad_selection" and a.cad_id is not None:
                raise field_error(name, ["answers", i, "cad_id"], f"must be null when same_as_track is given (track {a.track_id} "
                                                                  f"is a fragment of track {a.same_as_track})")
        if label.kind == "correspondences":
            if a.cad_id != item.cad_id:
                raise field_error(name, ["answers", i, "cad_id"], f"{a.cad_id!r} is not the task's model {item.cad_id!r} for track {a.track_id}")
            shown = {k.timestamp_us for k in item.keyframes}
            shown |= {k.timestamp_us for k in item.previous.keyframes} if item.previous is not None else set()
            seen = set()
            for j, kf in enumerate(a.keyframes):
                where = ["answers", i, "keyframes", j, "timestamp_us"]
                if kf.timestamp_us not in stamps:
                    raise field_error(name, where, f"{kf.timestamp_us} is not a frame of the clip")
                if kf.timestamp_us not in shown:
                    raise field_error(name, where, f"{kf.timestamp_us} is not a key-frame of track {a.track_id} in task "
                                                   f"{task.task_id} (its key-frames: {', '.join(map(str, sorted(shown)))})")
                if kf.timestamp_us in seen:
                    raise field_error(name, where, f"key-frame {kf.timestamp_us} is answered twice")
                seen.add(kf.timestamp_us)
                _check_xyz(kf.points, facts.extents.get(a.cad_id), name, ["answers", i, "keyframes", j, "points"])
    _check_same_as_cycles(label, name, facts.same_as(label.clip, label.kind, label.task_id))  # each names another track
    return []


def _check_same_as_cycles(label, name: str, in_force: Mapping[int, int] | None = None) -> None:
    """Refuse answers whose ``same_as_track`` links go round (track 0 the same object as 1, and 1 as
    0), within the label or with the links of the task's answers in force (``in_force``: track ->
    the track it is the same object as; the label's answers replace those of their tracks): none
    of them would be the object, and the object would leave the dataset."""
    answered = {a.track_id for a in label.answers}
    same: dict[int, tuple[int | None, int]] = {t: (None, o) for t, o in (in_force or {}).items() if t not in answered}
    same |= {a.track_id: (i, a.same_as_track) for i, a in enumerate(label.answers)
             if getattr(a, "same_as_track", None) is not None}
    for start in [t for t in same if same[t][0] is not None]:
        seen, track = [start], same[start][1]
        while track in same and track not in seen:
            seen.append(track)
            track = same[track][1]
        if track == start:
            before = [t for t in seen if same[t][0] is None]
            said = f" ({', '.join(f'{t} -> {same[t][1]}' for t in before)} answered before)" if before else ""
            ring = " -> ".join(str(t) for t in [*seen, start])
            raise field_error(name, ["answers", same[start][0], "same_as_track"],
                              f"tracks {ring} each name the next as the same object{said}: one of them must be the object "
                              "(its own answer)")


def validate_label(path: str | Path, wh: Warehouse | None = None, facts: ClipFacts | None = None,
                   data: bytes | None = None, max_bytes: int = MAX_LABEL_BYTES) -> LabelFile:
    """Validate one label file (``data``: its bytes, when read already): its format, and against
    the warehouse when ``wh`` (or ``facts``) is given. Raises :class:`LabelError` naming the file
    and the field."""
    path = Path(path)
    name = str(path)
    if data is None:
        data = read_limited(path, max_bytes)
    check_size(data, name, max_bytes)
    label, created_at = parse_label(data, name)
    warnings = check_clicks(label, name)
    if facts is None and wh is not None:
        facts = ClipFacts(wh)
    if facts is not None:
        warnings += check_label(label, facts, name)
    text = data.decode("utf-8").removeprefix("\ufeff")  # a byte-order mark is no part of the JSON document kept
    return LabelFile(path, hashlib.sha256(data).hexdigest(), text, label, created_at, tuple(warnings))


def label_document(kind: str, clip: str, task_id: str, answers: list[dict], **header: Any) -> dict:
    """A label document (plain JSON data) for ``kind``: what importers and simulated annotators write."""
    return {"format": LABEL_FORMAT, "kind": kind, "task_id": task_id, "clip": clip, **header, "answers": answers}
