"""Manual tracks from the annotation tools teams already use: CVAT video XML and Label Studio video JSON.

Both become a ``manual_track`` label file (:mod:`schemas.labels`) for a task of the clip, checked
like any label file before it is written; ``cadestate labels ingest`` then ingests it.

- CVAT for video 1.1 (``annotations.xml``): ``<track id label source>`` holding
  ``<box frame xtl ytl xbr ybr outside occluded keyframe>`` in pixels (normalised by
  ``meta/*/original_size``, else the clip's frame size). Boxes with ``outside="1"`` are dropped;
  by default only ``keyframe="1"`` boxes (the ones drawn, not interpolated) are kept. ``frame``
  is 0-based.
- Label Studio video (JSON export): results of type ``videorectangle`` with
  ``value.sequence[{frame, enabled, x, y, width, height, rotation, time}]`` in percent (0-100) and
  ``value.labels``; ``frame`` is 1-based, every sequence entry is a key-frame; a rotated box
  becomes its axis-aligned bounding box (rotation in degrees about its top-left corner). The
  newest annotation that was not cancelled is used.

Frame numbers map to camera timestamps in one of two ways (``frame_map``):
``frames`` (default): the tool showed the clip's extracted frames as an image sequence, so tool
frame n is ``frames.frame_index`` n; ``video``: the tool showed the video, so tool frame n is at
n / fps seconds (Label Studio: its ``time``) and maps to the camera frame whose decoded video
frame is nearest, within half a video frame (boxes between camera frames are dropped).
"""

from __future__ import annotations

import bisect
import datetime as dt
import json
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from tasks.labels import ClipFacts, LabelError, check_label, label_document, latest_task_of_kind, parse_label
from warehouse import Warehouse, atomic_write_bytes

FrameMapMode = Literal["frames", "video"]


@dataclass(frozen=True)
class ToolBox:
    """A box from a tool: its frame (``index``: 0-based frame number, ``time_s`` when the tool gives it)
    and (ymin, xmin, ymax, xmax) normalised."""

    index: int
    time_s: float | None
    box: tuple[float, float, float, float]


@dataclass
class ToolTrack:
    source_id: str
    label: str
    boxes: list[ToolBox] = field(default_factory=list)


@dataclass
class ImportResult:
    """The label document made, and what was left out (in words)."""

    document: dict
    dropped: list[str]


# ------------------------------------------------------------------------------ frames

@dataclass(frozen=True)
class ClipFrames:
    by_index: dict[int, int]
    video_times: list[int]
    timestamps: list[int]
    fps: float
    width: int
    height: int

    @staticmethod
    def of(wh: Warehouse, clip: str) -> ClipFrames:
        rows = wh.read("frames", [clip], columns=["timestamp_us", "frame_index", "video_time_us", "width", "height"]).to_pylist()
        if not rows:
            raise LabelError(f"clip {clip!r}: no frames in the warehouse")
        clips = wh.read("clips", [clip], columns=["fps"]).column("fps").to_pylist()
        rows.sort(key=lambda r: r["video_time_us"])
        return ClipFrames({r["frame_index"]: r["timestamp_us"] for r in rows}, [r["video_time_us"] for r in rows],
                          [r["timestamp_us"] for r in rows], float(clips[0]) if clips and clips[0] else 30.0,
                          rows[0]["width"], rows[0]["height"])

    def timestamp(self, b: ToolBox, mode: FrameMapMode) -> int | None:
        """The camera timestamp of a tool box's frame, or None when no camera frame matches."""
        if mode == "frames":
            return self.by_index.get(b.index)
        t = (b.time_s if b.time_s is not None else b.index / self.fps) * 1e6
        i = bisect.bisect_left(self.video_times, t)
        best = min((j for j in (i - 1, i) if 0 <= j < len(self.video_times)), key=lambda j: abs(self.video_times[j] - t))
        return self.timestamps[best] if abs(self.video_times[best] - t) <= 0.5e6 / self.fps else None


def _clip01(v: float) -> float:
    return min(max(v, 0.0), 1.0)


def normalised_box(x0: float, y0: float, x1: float, y1: float, width: float, height: float) -> tuple[float, float, float, float]:
    """(ymin, xmin, ymax, xmax) in [0, 1] from pixel corners."""
    return (_clip01(min(y0, y1) / height), _clip01(min(x0, x1) / width), _clip01(max(y0, y1) / height), _clip01(max(x0, x1) / width))


# ------------------------------------------------------------------------------ CVAT

def _xml_number(el: ET.Element, attr: str, where: str) -> float:
    value = el.get(attr)
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise LabelError(f"{where}: attribute {attr!r} must be a number, not {value!r}") from None
    if not math.isfinite(number):
        raise LabelError(f"{where}: attribute {attr!r} is not finite")
    return number


def read_cvat(path: str | Path, size: tuple[int, int] | None = None, keyframes_only: bool = True,
              skip_sources: tuple[str, ...] = ()) -> list[ToolTrack]:
    """Tracks of a CVAT video XML 1.1 file (``size``: (width, height) when the file has none)."""
    name = str(path)
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as e:
        raise LabelError(f"{name}: not a readable XML file: {e}") from None
    if root.tag != "annotations":
        raise LabelError(f"{name}: /{root.tag}: not a CVAT annotations file (root element must be <annotations>)")
    original = root.find("meta/task/original_size")
    original = original if original is not None else root.find("meta/job/original_size")
    if original is not None:
        size = (int(float(original.findtext("width", "0"))), int(float(original.findtext("height", "0"))))
    if not size or min(size) <= 0:
        raise LabelError(f"{name}: /annotations/meta: no original_size and no frame size given")
    tracks = []
    for i, el in enumerate(root.findall("track")):
        track = ToolTrack(f"cvat:{el.get('id', i)}", el.get("label") or "")
        if el.get("source", "manual") in skip_sources:
            continue
        for j, box in enumerate(el.findall("box")):
            where = f"{name}: /annotations/track[{i}]/box[{j}]"
            if box.get("outside", "0") == "1" or (keyframes_only and box.get("keyframe", "1") != "1"):
                continue
            frame = _xml_number(box, "frame", where)
            corners = [_xml_number(box, a, where) for a in ("xtl", "ytl", "xbr", "ybr")]
            track.boxes.append(ToolBox(int(frame), None, normalised_box(*corners, *size)))
        tracks.append(track)
    return tracks


# ------------------------------------------------------------------------------ Label Studio

def _ls_annotation(task: dict, name: str) -> dict | None:
    annotations = [a for a in task.get("annotations") or [] if isinstance(a, dict) and not a.get("was_cancelled")]
    if not annotations:
        return None
    return max(annotations, key=lambda a: (str(a.get("updated_at") or a.get("created_at") or ""), str(a.get("id", ""))))


def _ls_box(item: dict, size: tuple[int, int], where: str) -> ToolBox:
    try:
        frame, x, y, w, h = (float(item[k]) for k in ("frame", "x", "y", "width", "height"))
        rotation = float(item.get("rotation") or 0.0)
        time_s = None if item.get("time") is None else float(item["time"])
    except (KeyError, TypeError, ValueError) as e:
        raise LabelError(f"{where}: needs numbers frame, x, y, width, height ({e})") from None
    if not all(map(math.isfinite, (frame, x, y, w, h, rotation))) or frame < 1:
        raise LabelError(f"{where}: not a finite box on a frame >= 1")
    W, H = size
    x, y, w, h = x / 100 * W, y / 100 * H, w / 100 * W, h / 100 * H
    c, s = math.cos(math.radians(rotation)), math.sin(math.radians(rotation))
    xs = [x + dx * c - dy * s for dx, dy in ((0, 0), (w, 0), (w, h), (0, h))]
    ys = [y + dx * s + dy * c for dx, dy in ((0, 0), (w, 0), (w, h), (0, h))]
    return ToolBox(int(frame) - 1, time_s, normalised_box(min(xs), min(ys), max(xs), max(ys), W, H))


def read_labelstudio(path: str | Path, size: tuple[int, int], clip: str | None = None) -> list[ToolTrack]:
    """Tracks of a Label Studio JSON export (``size``: (width, height) of the frames). With several
    tasks in the export, the one whose ``data`` mentions ``clip`` is used."""
    name = str(path)
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise LabelError(f"{name}: not a readable JSON file: {e}") from None
    tasks = [t for t in (data if isinstance(data, list) else [data]) if isinstance(t, dict)]
    if len(tasks) > 1 and clip is not None:
        tasks = [t for t in tasks if clip in json.dumps(t.get("data", {}))]
    if len(tasks) != 1:
        raise LabelError(f"{name}: $: expected one Label Studio task (for clip {clip!r}), found {len(tasks)}")
    annotation = _ls_annotation(tasks[0], name)
    tracks = []
    for i, result in enumerate((annotation or {}).get("result") or []):
        if not isinstance(result, dict) or result.get("type") != "videorectangle":
            continue
        where = f"{name}: $.annotations[*].result[{i}]"
        value = result.get("value") or {}
        labels = value.get("labels") or []
        if not isinstance(value.get("sequence"), list):
            raise LabelError(f"{where}.value.sequence: missing")
        track = ToolTrack(f"labelstudio:{result.get('id', i)}", str(labels[0]) if labels else "")
        track.boxes = [_ls_box(item, size, f"{where}.value.sequence[{j}]") for j, item in enumerate(value["sequence"])
                       if isinstance(item, dict)]
        tracks.append(track)
    return tracks


# ------------------------------------------------------------------------------ label files

def tracks_to_label(wh: Warehouse, tracks: list[ToolTrack], clip: str, task_id: str | None = None,
                    frame_map: FrameMapMode = "frames", label_map: dict[str, str] | None = None,
                    source: str = "") -> ImportResult:
    """A validated ``manual_track`` label document from tool tracks (answering ``task_id``, else the
    clip's newest manual-track task)."""
    if task_id is None:
        row = latest_task_of_kind(wh, clip, "manual_track")
        if row is None:
            raise LabelError(f"clip {clip!r}: no manual_track task to answer (give the task id)")
        task_id = row["task_id"]
    frames = ClipFrames.of(wh, clip)
    answers, dropped = [], []
    for t in tracks:
        boxes: dict[int, tuple] = {}
        for b in t.boxes:
            ts = frames.timestamp(b, frame_map)
            if ts is None:
                dropped.append(f"{t.source_id}: frame {b.index + (1 if t.source_id.startswith('labelstudio') else 0)} "
                               f"is not a camera frame of the clip")
            elif b.box[0] < b.box[2] and b.box[1] < b.box[3]:
                boxes.setdefault(ts, b.box)
            else:
                dropped.append(f"{t.source_id}: empty box on frame {ts} µs")
        if not boxes:
            dropped.append(f"{t.source_id}: no box left, track left out")
            continue
        label = (label_map or {}).get(t.label, t.label)
        answers.append({"label": label, "boxes": [{"timestamp_us": ts, "box": list(boxes[ts])} for ts in sorted(boxes)],
                        "source_id": t.source_id})
    created = dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")
    doc = label_document("manual_track", clip, task_id, answers, annotator=f"import:{source}" if source else None,
                         created_at=created)
    name = f"import of {source or 'tool tracks'}"
    check_label(parse_label(json.dumps(doc).encode(), name)[0], ClipFacts(wh), name)
    return ImportResult(doc, dropped)


def import_cvat(wh: Warehouse, path: str | Path, clip: str, task_id: str | None = None, *, frame_map: FrameMapMode = "frames",
                keyframes_only: bool = True, skip_sources: tuple[str, ...] = (), label_map: dict[str, str] | None = None) -> ImportResult:
    """A ``manual_track`` label document from a CVAT video XML 1.1 file."""
    frames = ClipFrames.of(wh, clip)
    tracks = read_cvat(path, (frames.width, frames.height), keyframes_only, skip_sources)
    return tracks_to_label(wh, tracks, clip, task_id, frame_map, label_map, source=f"cvat:{Path(path).name}")


def import_labelstudio(wh: Warehouse, path: str | Path, clip: str, task_id: str | None = None, *,
                       frame_map: FrameMapMode = "frames", label_map: dict[str, str] | None = None) -> ImportResult:
    """A ``manual_track`` label document from a Label Studio video JSON export."""
    frames = ClipFrames.of(wh, clip)
    tracks = read_labelstudio(path, (frames.width, frames.height), clip)
    return tracks_to_label(wh, tracks, clip, task_id, frame_map, label_map, source=f"labelstudio:{Path(path).name}")


def write_label(doc: dict, out_dir: str | Path, stem: str) -> Path:
    """Write a label document as ``<out_dir>/<stem>.json`` (atomically); returns the path."""
    path = Path(out_dir) / f"{stem}.json"
    atomic_write_bytes(path, (json.dumps(doc, indent=1, ensure_ascii=False, allow_nan=False) + "\n").encode())
    return path
