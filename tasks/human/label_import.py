"""Manual tracks from the annotation tools teams already use: CVAT video XML and Label Studio video JSON.

Both become a ``manual_track`` label file (:mod:`schemas.labels`) for a task of the clip, checked
like any label file before it is written; ``cadestate labels ingest`` then ingests it. The label
file keeps the "track N is not an object" statements of the task's answer in force, and the "this is
track N" said of a tool track imported before (an import answers the task whole, and a statement
made in the app would otherwise be lost by the next import) where the track of that tool id is
still that drawing: CVAT numbers the tracks of each export from 0, so an id names another object
once a track was deleted (kept: the same class, boxes overlapping by IoU >= :data:`SAME_DRAWING_IOU`
on every frame both have, one at least). It is dated by the export, so the same export makes the same file.

- CVAT for video 1.1: :mod:`tasks.human.label_import_cvat`.
- Label Studio video (JSON export): :mod:`tasks.human.label_import_labelstudio`.

Files are read whole (at most :data:`MAX_IMPORT_BYTES`) and checked as they are read: every
number an element or field needs must be there and be a finite number (frames: whole numbers),
every label a non-empty string; a problem is a :class:`tasks.human.label_format.LabelError` of one line naming
the file and the element or attribute (``/annotations/track[2]/box[0]/@xtl``) or the field
(``$[0].annotations[1].result[3].value``).
A file with tracks of which none has a box left on a frame of the clip is refused too: an empty
label would say that nothing is missing.

Frame numbers map to camera timestamps in one of two ways (``frame_map``):
``frames`` (default): the tool showed the clip's extracted frames as an image sequence, so tool
frame n is ``frames.frame_index`` n (refused when the tool says it showed more frames than the
clip has: CVAT's ``stop_frame``, Label Studio's ``framesCount``); ``video``: the tool showed the video, so tool frame n (0-based) is at n / fps seconds and maps to the camera frame whose decoded
video frame is nearest, within half a video frame (boxes between camera frames are dropped).
"""

from __future__ import annotations

import bisect
import datetime as dt
import difflib
import json
import math
import re
import shlex
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from schemas.labels import Task
from tasks.human.answers_in_force import current_answers
from tasks.human.clicks_in_force import box_iou
from tasks.human.label_format import LabelError, parse_label
from tasks.human.labels import ClipFacts, check_label, label_document, latest_task_of_kind, withdrawn_why
from tasks.tracking.relations import manual_answer_statements
from warehouse import Warehouse, atomic_write_bytes

FrameMapMode = Literal["frames", "video"]

MAX_IMPORT_BYTES = 200_000_000
"""Largest tool export read (200 MB): a CVAT file with every interpolated box of a long video stays
well below; bigger files are refused before they are parsed."""

MAX_FRAME = 10**9
"""Frame numbers at or above this are refused (no clip has a billion frames)."""


@dataclass(frozen=True)
class ToolBox:
    """A box from a tool: its frame (``index``: 0-based frame number) and (ymin, xmin, ymax, xmax) normalised."""

    index: int
    box: tuple[float, float, float, float]


@dataclass
class ToolTrack:
    """A track from a tool: its id there, its label, its boxes, and where it is in the file;
    ``shown_frames``: how many frames the tool says it showed, numbered from 0 (None: it does not
    say), stated at ``shown_where``."""

    source_id: str
    label: str
    boxes: list[ToolBox] = field(default_factory=list)
    where: str = ""
    shown_frames: int | None = None
    shown_where: str = ""


@dataclass
class ImportResult:
    """The label document made, what was left out, and warnings (in words)."""

    document: dict
    dropped: list[str]
    warnings: list[str] = field(default_factory=list)


def names_clip(text: str, clip: str) -> bool:
    """Whether ``text`` holds ``clip`` as a whole word (``c1`` is not in ``c10.mp4`` nor ``c1_b.mp4``;
    ``room`` is in ``room-2.mp4``: see :func:`names_clip_exactly`)."""
    return re.search(rf"(?<![A-Za-z0-9_]){re.escape(clip)}(?![A-Za-z0-9_])", text) is not None


def names_clip_exactly(texts: tuple[str, ...] | list[str], clip: str) -> bool:
    """Whether one of ``texts`` (names, file paths) is ``clip`` itself or a file of that name
    (Label Studio's upload prefix ``<8 hex>-`` aside): ``room.mp4`` is, ``room-2.mp4`` is not."""
    for text in texts:
        stem = Path(str(text)).stem if text else ""
        if clip in (text, stem, re.sub(r"^[0-9a-f]{8}-", "", stem)):
            return True
    return False


def file_time(path: str | Path) -> str:
    """When ``path`` was last written, in UTC seconds (ISO 8601): the date of a label made from an
    export that states none."""
    return dt.datetime.fromtimestamp(Path(path).stat().st_mtime, dt.timezone.utc).isoformat(timespec="seconds")


# ------------------------------------------------------------------------------ frames

@dataclass(frozen=True)
class ClipFrames:
    """A clip's frames as the importers map tool frames to them; ``duration_us``: its video's
    (None: not known)."""

    by_index: dict[int, int]
    video_times: list[int]
    timestamps: list[int]
    fps: float
    width: int
    height: int
    duration_us: int | None = None

    @staticmethod
    def of(wh: Warehouse, clip: str) -> ClipFrames:
        rows = wh.read("frames", [clip], columns=["timestamp_us", "frame_index", "video_time_us", "width", "height"]).to_pylist()
        if not rows:
            raise LabelError(f"clip {clip!r}: no frames in the warehouse")
        clips = wh.read("clips", [clip], columns=["fps", "duration_us"]).to_pylist()
        fps = clips[0]["fps"] if clips else None
        rows.sort(key=lambda r: r["video_time_us"])
        return ClipFrames({r["frame_index"]: r["timestamp_us"] for r in rows}, [r["video_time_us"] for r in rows],
                          [r["timestamp_us"] for r in rows], float(fps) if fps else 30.0,
                          rows[0]["width"], rows[0]["height"], clips[0]["duration_us"] if clips else None)

    def shown(self, mode: FrameMapMode) -> tuple[int, str] | None:
        """How many frames a tool showing the clip (``mode``) shows, in words; None: not known."""
        if mode == "frames":
            return len(self.timestamps), "the clip has"
        if not self.duration_us:
            return None
        return round(self.duration_us / 1e6 * self.fps), "the clip's video has"

    def timestamp(self, b: ToolBox, mode: FrameMapMode) -> int | None:
        """The camera timestamp of a tool box's frame, or None when no camera frame matches."""
        if mode == "frames":
            return self.by_index.get(b.index)
        t = b.index / self.fps * 1e6
        i = bisect.bisect_left(self.video_times, t)
        best = min((j for j in (i - 1, i) if 0 <= j < len(self.video_times)), key=lambda j: abs(self.video_times[j] - t))
        return self.timestamps[best] if abs(self.video_times[best] - t) <= 0.5e6 / self.fps else None


def _clip01(v: float) -> float:
    return min(max(v, 0.0), 1.0)


def normalised_box(x0: float, y0: float, x1: float, y1: float, width: float, height: float) -> tuple[float, float, float, float]:
    """(ymin, xmin, ymax, xmax) in [0, 1] from pixel corners."""
    return (_clip01(min(y0, y1) / height), _clip01(min(x0, x1) / width), _clip01(max(y0, y1) / height), _clip01(max(x0, x1) / width))


# ------------------------------------------------------------------------------ checked values

def _number(value: object, where: str) -> float:
    """A finite number from a JSON number or an XML string; ``where``: the file and the element,
    attribute (``.../box[0]/@xtl``) or field."""
    try:
        if isinstance(value, bool) or not isinstance(value, (int, float, str)):
            raise TypeError
        number = float(value)
    except (TypeError, ValueError, OverflowError):
        raise LabelError(f"{where}: must be a number, not {repr(value)[:40]}") from None
    if not math.isfinite(number):
        raise LabelError(f"{where}: must be a finite number, not {repr(value)[:40]}")
    return number


def _whole(value: object, where: str, low: int, high: int = MAX_FRAME) -> int:
    """A whole number in [low, high) (frames, sizes)."""
    number = _number(value, where)
    if number != int(number) or not low <= number < high:
        raise LabelError(f"{where}: must be a whole number from {low} to {high - 1}, not {repr(value)[:40]}")
    return int(number)


def _text(value: object, where: str) -> str:
    """A non-empty string that is valid Unicode (a label, an id)."""
    if not isinstance(value, str) or not value:
        raise LabelError(f"{where}: must be a non-empty string, not {repr(value)[:40]}")
    try:
        value.encode("utf-8")
    except UnicodeEncodeError:
        raise LabelError(f"{where}: not valid Unicode (a lone surrogate such as \\ud800)") from None
    return value


def utc_seconds(text: object) -> str | None:
    """An ISO 8601 time with its zone (``Z`` too; CVAT's ``2026-03-01 10:00:00.123456+00:00``) in
    UTC seconds; None when it is not one (no zone, not a time)."""
    try:
        when = dt.datetime.fromisoformat(str(text).strip().replace("Z", "+00:00"))
    except ValueError:
        return None
    return when.astimezone(dt.timezone.utc).isoformat(timespec="seconds") if when.tzinfo else None


# ------------------------------------------------------------------------------ label files

def _listed(numbers: list[int], most: int = 10) -> str:
    """``1, 3, 5`` (at most ``most`` of them, then ``... last``)."""
    shown = ", ".join(map(str, numbers[:most]))
    return shown if len(numbers) <= most else f"{shown}, ... {numbers[-1]}"


def _map_hint(tool_label: str, classes: tuple[str, ...]) -> str:
    """How ``--map`` renames ``tool_label``: to the class it names in other letter case or
    spelling ('Chair', 'chairs': chair), when there is one."""
    folded = {c.casefold(): c for c in classes}
    near = next(iter(difflib.get_close_matches(tool_label.casefold(), folded, 1, 0.8)), None)
    return f"is it {folded[near]!r}? --map {shlex.quote(f'{tool_label}={folded[near]}')}" if near else "--map renames a tool label"


def _answered_task(wh: Warehouse, clip: str, task_id: str | None) -> Task:
    """The manual_track task an import answers: ``task_id``, else the clip's newest."""
    if task_id is None:
        row = latest_task_of_kind(wh, clip, "manual_track")
        if row is None:
            raise LabelError(f"clip {clip!r}: no manual_track task to answer: a clip gets one when its split is one of "
                             "[manual_tracks] splits (`cadestate ingest --split val`) and its manual_tracks stage has run")
        if (why := withdrawn_why(row)) is not None:
            raise LabelError(f"clip {clip!r}: its manual_track task was withdrawn: {why}")
        task_id = row["task_id"]
    task = ClipFacts(wh).task(clip, task_id)
    if task is None or task.kind != "manual_track":
        raise LabelError(f"clip {clip!r}: no manual_track task {task_id!r}")
    return task


def tracks_to_label(wh: Warehouse, tracks: list[ToolTrack], clip: str, task_id: str | None = None,
                    frame_map: FrameMapMode = "frames", label_map: dict[str, str] | None = None,
                    source: str = "", name: str = "tool tracks", created_at: str | None = None,
                    frames: ClipFrames | None = None) -> ImportResult:
    """A validated ``manual_track`` label document from tool tracks (answering ``task_id``, else the
    clip's newest manual-track task), dated ``created_at`` (default: now), keeping the "track N is
    not an object" statements of the task's answer in force, and its "this is track N" of each tool
    track it drew before (by ``source_id``); ``name``: the file, for errors;
    ``frames``: the clip's, when the caller read them already."""
    task = _answered_task(wh, clip, task_id)
    frames = frames or ClipFrames.of(wh, clip)
    if frame_map == "frames":
        for t in tracks:
            if t.shown_frames is not None and t.shown_frames > len(frames.timestamps):
                raise LabelError(f"{t.shown_where}: the tool showed {t.shown_frames} frames and clip {clip!r} has "
                                 f"{len(frames.timestamps)}: was the task made on the video? (--frame-map video)")
    not_objects, drawn_as = _statements_in_force(wh, clip, task.task_id)
    answers, dropped, unlinked = [], [], []
    for t in tracks:
        label = (label_map or {}).get(t.label, t.label)
        if task.classes and label not in task.classes:
            raise LabelError(f"{t.where or name}: class {label!r} is not one of the task's: {', '.join(task.classes)} "
                             f"({_map_hint(t.label, task.classes)})")
        boxes: dict[int, tuple] = {}
        off: list[int] = []  # the tool's numbers of the frames that are no camera frame
        for b in t.boxes:
            ts = frames.timestamp(b, frame_map)
            if ts is None:
                off.append(b.index + (1 if t.source_id.startswith("labelstudio") else 0))
            elif ts in boxes:
                dropped.append(f"{t.source_id}: a second box on frame {ts} µs, left out")
            elif b.box[0] < b.box[2] and b.box[1] < b.box[3]:
                boxes[ts] = b.box
            else:
                dropped.append(f"{t.source_id}: empty box on frame {ts} µs")
        if off:
            dropped.append(f"{t.source_id}: {len(off)} box(es) on frames that are no camera frame of the clip: "
                           f"frames {_listed(off)}")
        if not boxes:
            dropped.append(f"{t.source_id}: no box left, track left out")
            continue
        link = drawn_as.get(t.source_id)
        if link is not None and not _same_drawing(link, label, boxes):
            unlinked.append(f"{t.source_id} (was track {link.track})")
            link = None
        answers.append({"label": label, "boxes": [{"timestamp_us": ts, "box": list(boxes[ts])} for ts in sorted(boxes)],
                        "source_id": t.source_id, **({"same_as_track": link.track} if link is not None else {})})
    if tracks and not answers:
        raise LabelError(f"{name}: none of its {len(tracks)} track(s) has a box on a frame of clip {clip!r} "
                         f"(--frame-map {'video' if frame_map == 'frames' else 'frames'}?)")
    created = created_at or dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")
    doc = label_document("manual_track", clip, task.task_id, answers, annotator=f"import:{source}" if source else None,
                         created_at=created, **({"not_objects": not_objects} if not_objects else {}))
    try:
        check_label(parse_label(json.dumps(doc).encode(), name)[0], ClipFacts(wh), name)
    except LabelError as e:  # its paths are the label's, which is in no file: named as the export's tracks
        where = {t.source_id: t.where.removeprefix(f"{name}: ") for t in tracks if t.where}
        named = [f"{where[a['source_id']]} ({a['source_id']})" if a["source_id"] in where else a["source_id"] for a in answers]
        raise LabelError(re.sub(r"\$\.answers\[(\d+)\]|answers\[(\d+)\]",
                                lambda m: named[int(m.group(1) or m.group(2))], str(e))) from None
    kept = [f"{name}: keeps the answer in force's 'track N is not an object' for track(s) "
            f"{', '.join(map(str, not_objects))} (put them in the label file to change them)"] if not_objects else []
    if linked := [f"{a['source_id']} is track {a['same_as_track']}" for a in answers if "same_as_track" in a]:
        kept.append(f"{name}: keeps the answer in force's 'this is track N': {'; '.join(linked)} "
                    "(put them in the label file to change them)")
    if unlinked:
        kept.append(f"{name}: leaves out the answer in force's 'this is track N' of {', '.join(unlinked)}: that id "
                    "is another drawing in this export (another class, or boxes elsewhere; CVAT numbers tracks anew "
                    "in each export)")
    return ImportResult(doc, dropped, kept)


SAME_DRAWING_IOU = 0.5
"""Least IoU, on every frame both have, of a tool track's boxes with those of the object of the same
tool id in the answer in force for the "this is track N" said of it to be kept."""


@dataclass(frozen=True)
class DrawnAs:
    """An object of the answer in force said to be an existing ``track``: its class and boxes
    ({timestamp_us: (ymin, xmin, ymax, xmax) normalised})."""

    track: int
    label: str
    boxes: dict[int, tuple]


def _same_drawing(link: DrawnAs, label: str, boxes: dict[int, tuple]) -> bool:
    """Whether a tool track (``label``, ``boxes`` by timestamp) is still the object ``link``."""
    shared = [ts for ts in boxes if ts in link.boxes]
    return label == link.label and bool(shared) and \
        all(box_iou(tuple(boxes[ts]), tuple(link.boxes[ts])) >= SAME_DRAWING_IOU for ts in shared)


def _statements_in_force(wh: Warehouse, clip: str, task_id: str) -> tuple[list[int], dict[str, DrawnAs]]:
    """(tracks said to be no object, {tool id of a drawn object said to be an existing track: that
    object}) of the manual-track task's answer in force."""
    not_objects, same_as = manual_answer_statements(wh, clip, task_id)
    if not same_as:
        return sorted(not_objects), {}
    objects: dict[int, list[dict]] = {}
    for r in current_answers(wh, "manual_track", [clip], task_id).to_pylist():
        if r["task_id"] == task_id and r["source_id"] and r["object_index"] in same_as:
            objects.setdefault(r["object_index"], []).append(r)
    return sorted(not_objects), {rs[0]["source_id"]: DrawnAs(same_as[i], rs[0]["label"], {r["timestamp_us"]: tuple(r["box"]) for r in rs})
                                 for i, rs in objects.items()}


def write_label(doc: dict, out_dir: str | Path, stem: str) -> Path:
    """Write a label document as ``<out_dir>/<stem>.json`` (atomically); returns the path."""
    path = Path(out_dir) / f"{stem}.json"
    atomic_write_bytes(path, (json.dumps(doc, indent=1, ensure_ascii=False, allow_nan=False) + "\n").encode())
    return path
