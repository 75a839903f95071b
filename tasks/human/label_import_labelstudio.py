"""Manual tracks from a Label Studio video export (JSON): see :mod:`tasks.human.label_import`.

Results of type ``videorectangle`` with ``value.sequence[{frame, enabled, x, y, width, height,
rotation, time}]`` in percent (0-100) and ``value.labels``; ``frame`` is 1-based, every sequence
entry is a key-frame; a rotated box becomes its axis-aligned bounding box (rotation in degrees
about its top-left corner). The newest annotation that was not cancelled is used. With several
tasks in the export, the one whose ``data`` names the clip (as a whole word; among several, the
one whose file is the clip's name); one task that names another video is imported with a warning.
An export with no ``videorectangle`` but other shapes (an image export of the frames) is refused.
Label Studio's ``time`` is not used: it writes frame f (1-based) at f / fps, a frame after the
frame's own time; its frame numbers are time x the labelling config's ``<Video frameRate>`` (24
unless set): a ``framesCount`` other than the frames shown (the clip's; its video's, ``duration_us``
x ``fps``) is warned of (:func:`frame_count_warnings`).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from tasks.human.label_format import LabelError, read_limited
from tasks.human.label_import import (MAX_IMPORT_BYTES, ClipFrames, FrameMapMode, ImportResult, ToolBox, ToolTrack,
                                      _number, _text, _whole, file_time, names_clip, names_clip_exactly, normalised_box,
                                      tracks_to_label, utc_seconds)
from warehouse import Warehouse

MAX_PERCENT = 1000.0
"""Label Studio box coordinates (percent of the frame) beyond +-this are refused: not a box of the frame."""


def _json_number(value: object, where: str) -> float:
    """A finite JSON number (a string that reads as one is not)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise LabelError(f"{where}: must be a number, not {repr(value)[:40]}")
    return _number(value, where)


def _of_type(value: object, kind: type, where: str) -> object:
    """``value`` if it is a ``kind`` (a JSON list or object), else an error naming ``where``."""
    if not isinstance(value, kind):
        raise LabelError(f"{where}: expected {'a list' if kind is list else 'an object'}, not {type(value).__name__}")
    return value


def _ls_annotation(task: dict, where: str) -> tuple[dict, str]:
    """The newest annotation that was not cancelled, and where it is."""
    if "annotations" not in task:
        raise LabelError(f"{where}.annotations: missing: not a Label Studio JSON export (a JSON-MIN or CSV export has "
                         "no annotations list; export the project as JSON)")
    annotations = _of_type(task["annotations"], list, f"{where}.annotations")
    kept = [(a, f"{where}.annotations[{k}]") for k, a in enumerate(annotations)
            if isinstance(a, dict) and not a.get("was_cancelled")]
    if not kept:
        raise LabelError(f"{where}.annotations: no annotation that was not cancelled")
    return max(kept, key=lambda a: (str(a[0].get("updated_at") or a[0].get("created_at") or ""), str(a[0].get("id", ""))))


def _ls_box(item: object, size: tuple[int, int], where: str) -> ToolBox:
    item = _of_type(item, dict, where)
    frame = _whole(_json_number(item.get("frame"), f"{where}.frame"), f"{where}.frame", 1)
    x, y, w, h = (_json_number(item.get(k), f"{where}.{k}") for k in ("x", "y", "width", "height"))
    if max(abs(x), abs(y), abs(w), abs(h)) > MAX_PERCENT:
        raise LabelError(f"{where}: x, y, width and height are percent of the frame, not beyond +-{MAX_PERCENT:g}")
    rotation = _json_number(item.get("rotation") or 0.0, f"{where}.rotation")
    W, H = size
    x, y, w, h = x / 100 * W, y / 100 * H, w / 100 * W, h / 100 * H
    c, s = math.cos(math.radians(rotation)), math.sin(math.radians(rotation))
    xs = [x + dx * c - dy * s for dx, dy in ((0, 0), (w, 0), (w, h), (0, h))]
    ys = [y + dx * s + dy * c for dx, dy in ((0, 0), (w, 0), (w, h), (0, h))]
    return ToolBox(frame - 1, normalised_box(min(xs), min(ys), max(xs), max(ys), W, H))


def _ls_track(result: dict, size: tuple[int, int], where: str, index: int) -> ToolTrack:
    value = _of_type(result.get("value"), dict, f"{where}.value")
    labels = _of_type(value.get("labels"), list, f"{where}.value.labels")
    if not labels:
        raise LabelError(f"{where}.value.labels: no label")
    rid = result.get("id", index)
    if isinstance(rid, bool) or not isinstance(rid, (str, int)):
        raise LabelError(f"{where}.id: must be a string or an integer, not {repr(rid)[:40]}")
    track = ToolTrack(f"labelstudio:{_text(str(rid), f'{where}.id')}", _text(labels[0], f"{where}.value.labels[0]"), where=where)
    sequence = _of_type(value.get("sequence"), list, f"{where}.value.sequence")
    track.boxes = [_ls_box(item, size, f"{where}.value.sequence[{j}]") for j, item in enumerate(sequence)]
    if value.get("framesCount") is not None:
        track.shown_frames = _whole(value["framesCount"], f"{where}.value.framesCount", 0)
        track.shown_where = f"{where}.value.framesCount"
    return track


def _ls_task(data: object, name: str, clip: str | None) -> tuple[dict, str]:
    """The export's one task (with several, the one whose ``data`` names ``clip``) and where it is."""
    tasks = [(t, f"{name}: $[{i}]" if isinstance(data, list) else f"{name}: $")
             for i, t in enumerate(data if isinstance(data, list) else [data]) if isinstance(t, dict)]
    if len(tasks) > 1 and clip is not None:
        tasks = [t for t in tasks if names_clip(json.dumps(t[0].get("data", {})), clip)]
        exact = [t for t in tasks if isinstance(t[0].get("data"), dict) and names_clip_exactly(
            [v for v in t[0]["data"].values() if isinstance(v, str)], clip)]
        tasks = exact if len(exact) == 1 else tasks
    if len(tasks) != 1:
        raise LabelError(f"{name}: $: expected one Label Studio task (for clip {clip!r}), found {len(tasks)}")
    return tasks[0]


LS_SHAPES = ("rectanglelabels", "rectangle", "polygonlabels", "polygon", "ellipselabels", "ellipse", "keypointlabels",
             "brushlabels")
"""Label Studio results that are shapes on one image: an export of them holds no manual tracks."""


def read_labelstudio(path: str | Path, size: tuple[int, int], clip: str | None = None,
                     warnings: list[str] | None = None) -> tuple[list[ToolTrack], str | None]:
    """Tracks of a Label Studio JSON export (``size``: (width, height) of the frames) and when their
    annotation was last saved (None: not said). With several tasks in the export, the one whose
    ``data`` names ``clip`` is used; one task whose ``data`` names a video but not ``clip`` adds a
    line to ``warnings``."""
    name = str(path)
    raw = read_limited(Path(path), MAX_IMPORT_BYTES, "tool exports", "$")
    try:
        data = json.loads(raw.removeprefix(b"\xef\xbb\xbf").decode("utf-8"))
    except UnicodeDecodeError as e:
        raise LabelError(f"{name}: $: not UTF-8 text (byte {e.start})") from None
    except json.JSONDecodeError as e:
        raise LabelError(f"{name}: $: not valid JSON: {e.msg} (line {e.lineno}, column {e.colno})") from None
    except (ValueError, RecursionError) as e:
        raise LabelError(f"{name}: $: not valid JSON: {e or 'nested too deeply'}") from None
    task, where = _ls_task(data, name, clip)
    shown = json.dumps(task.get("data", {}), ensure_ascii=False)
    if clip is not None and warnings is not None and not names_clip(shown, clip):
        warnings.append(f"{where}.data: names no clip {clip!r} ({shown[:80]}): is this the clip's export?")
    annotation, where = _ls_annotation(task, where)
    results = _of_type(annotation.get("result", []), list, f"{where}.result")
    tracks, shapes = [], []
    for i, result in enumerate(results):
        result = _of_type(result, dict, f"{where}.result[{i}]")
        if result.get("type") == "videorectangle":
            tracks.append(_ls_track(result, size, f"{where}.result[{i}]", i))
        elif result.get("type") in LS_SHAPES:
            shapes.append(f"{where}.result[{i}].type")
    if shapes and not tracks:
        raise LabelError(f"{shapes[0]}: {len(shapes)} shape(s) on single images and no videorectangle: manual tracks "
                         "are drawn on the video (a VideoRectangle labelling config)")
    return tracks, utc_seconds(annotation.get("updated_at") or annotation.get("created_at"))


def frame_count_warnings(tracks: list[ToolTrack], frames: ClipFrames, mode: FrameMapMode) -> list[str]:
    """Label Studio numbers a video's frames by time x the labelling config's ``<Video frameRate>``
    (24 unless set), and counts them so (``framesCount``): a count off the frames the tool showed
    (the clip's, or with ``mode`` video its video's: by more than a frame and 1 %) says its frame
    numbers are not theirs, and the boxes would land on other frames."""
    shown = frames.shown(mode)
    if shown is None:
        return []
    have, words = shown
    for t in tracks:
        if t.shown_frames is not None and abs(t.shown_frames - have) > max(1, have / 100):
            rate = f" ({frames.duration_us / 1e6:g} s at {frames.fps:g} fps)" if mode == "video" else ""
            return [f"{t.shown_where}: Label Studio counted {t.shown_frames} frames and {words} {have}{rate}: its frame "
                    "numbers are the clip's only if the labelling config's <Video frameRate> is the rate of the video it showed"]
    return []


def import_labelstudio(wh: Warehouse, path: str | Path, clip: str, task_id: str | None = None, *,
                       frame_map: FrameMapMode = "frames", label_map: dict[str, str] | None = None) -> ImportResult:
    """A ``manual_track`` label document from a Label Studio video JSON export."""
    frames = ClipFrames.of(wh, clip)
    warnings: list[str] = []
    tracks, saved = read_labelstudio(path, (frames.width, frames.height), clip, warnings)
    warnings += frame_count_warnings(tracks, frames, frame_map)
    result = tracks_to_label(wh, tracks, clip, task_id, frame_map, label_map, source=f"labelstudio:{Path(path).name}",
                             name=str(path), created_at=saved or file_time(path), frames=frames)
    result.warnings.extend(warnings)
    return result
