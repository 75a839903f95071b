"""Manual tracks from a CVAT for video 1.1 export (``annotations.xml`` of a task, a job or a project).

``<track id label source task_id>`` holds ``<box frame xtl ytl xbr ybr outside occluded keyframe
rotation>`` in pixels, normalised by the ``original_size`` of the export's meta (``meta/task``,
``meta/original_size`` of a job export, the chosen task's in a project export), else the clip's frame
size; a box rotated about its centre becomes its axis-aligned bounding box. Boxes with
``outside="1"`` are dropped; by default only ``keyframe="1"`` boxes (the ones drawn, not
interpolated) are kept. A "CVAT for images" export (shapes on single frames, no tracks) is refused.

Frame numbers (CVAT's ``bindings.py``): a task or job export numbers a frame by its place in the
data uploaded (``relative * step + start_frame``), so with the clip's frames uploaded as an image
sequence it is the clip's ``frame_index`` whatever the task's start frame or step. A project export
adds to each task's frames those of the tasks before it in its subset (tasks in ``(subset, id)``
order, each ``start_frame + step * size`` frames): that offset is taken off. The tool's frames run
to ``stop_frame`` (else ``start_frame + step * (size - 1)``): beyond the clip's frames, the task was
made on the video (``--frame-map video``).

Track ids: ``cvat:<track id>``, ``cvat:job<job id>:<track id>`` for a job export (CVAT numbers the
tracks of every export from 0: two jobs' exports of one task name different objects alike).
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

from tasks.human.label_format import LabelError, read_limited
from tasks.human.label_import import (MAX_IMPORT_BYTES, ClipFrames, FrameMapMode, ImportResult, ToolBox, ToolTrack,
                                      _number, _text, _whole, file_time, names_clip, names_clip_exactly, normalised_box,
                                      tracks_to_label, utc_seconds)
from warehouse import Warehouse

SHAPES = ("box", "polygon", "polyline", "points", "ellipse", "mask", "cuboid", "skeleton", "tag")
"""What a "CVAT for images" ``<image>`` holds (any of them: the export is of the wrong kind)."""


@dataclass(frozen=True)
class CvatSource:
    """What of one CVAT export the tracks come from: the task whose tracks are kept (``task_id``
    None: every track), the frame offset a project export added to its frames, the tool's last
    frame number + 1 (``span``; None: not said) stated at ``span_where``, the frame size (None: not
    said), the prefix of its track ids, the name and file of its video ('' when made on images),
    and when it was dumped."""

    task_id: str | None
    offset: int
    span: int | None
    span_where: str
    size: tuple[int, int] | None
    id_prefix: str
    names: str
    dumped: str | None


def _parse_xml(path: str | Path) -> ET.Element:
    name = str(path)
    data = read_limited(Path(path), MAX_IMPORT_BYTES, "tool exports", "/")
    try:
        return ET.fromstring(data)
    except ET.ParseError as e:
        raise LabelError(f"{name}: not well-formed XML: {e}") from None
    except (LookupError, ValueError) as e:  # an encoding Python does not know, or that cannot hold the bytes
        raise LabelError(f"{name}: not a readable XML file: {e}") from None


def _step(meta: ET.Element, where: str) -> int:
    """The frame step of a task (``frame_filter`` ``step=N``; 1 when none)."""
    found = re.search(r"step\s*=\s*(\S+)", meta.findtext("frame_filter") or "")
    return _whole(found.group(1), f"{where}/frame_filter", 1) if found else 1


def _frames_of(meta: ET.Element, where: str) -> tuple[int, int | None]:
    """(start_frame + step * size: the frames a project export gives the task, the tool's last
    frame number + 1 or None) of a task or job meta element."""
    start = _whole(meta.findtext("start_frame") or "0", f"{where}/start_frame", 0)
    size = _whole(meta.findtext("size"), f"{where}/size", 0) if meta.find("size") is not None else None
    step = _step(meta, where)
    if meta.find("stop_frame") is not None:
        span = _whole(meta.findtext("stop_frame"), f"{where}/stop_frame", 0) + 1
    else:
        span = start + step * (size - 1) + 1 if size else None
    return start + step * (size or 0), span


def _size(meta: ET.Element | None, where: str) -> tuple[int, int] | None:
    original = meta.find("original_size") if meta is not None else None
    if original is None:
        return None
    return tuple(_whole(original.findtext(k), f"{where}/original_size/{k}", 1) for k in ("width", "height"))


def _project_task(tasks: list[ET.Element], name: str, clip: str) -> int:
    """The index of the task of a project export whose name or video names ``clip`` (as a whole
    word; among several, the one named exactly ``clip``)."""
    texts = [(t.findtext("name") or "", t.findtext("source") or "") for t in tasks]
    chosen = [i for i, texts_i in enumerate(texts) if names_clip(" ".join(texts_i), clip)]
    if len(chosen) > 1:
        chosen = [i for i in chosen if names_clip_exactly(texts[i], clip)] or chosen
    if len(chosen) != 1:
        listed = ", ".join(repr(n) for n, _ in texts[:8])
        raise LabelError(f"{name}: /annotations/meta/project/tasks: a project export of {len(tasks)} tasks ({listed}), "
                         f"{'none' if not chosen else len(chosen)} of which names clip {clip!r}; export the clip's task alone")
    return chosen[0]


def _video_names(meta: ET.Element) -> str:
    """The name and video file of a task made on a video ('' for one made on images: its name is free)."""
    return f"{meta.findtext('name') or ''} {meta.findtext('source')}" if meta.findtext("source") else ""


def cvat_source(root: ET.Element, name: str, clip: str | None) -> CvatSource:
    """Which tracks of an export to keep and how to read their frames (see the module)."""
    dumped = root.findtext("meta/dumped")
    tasks = root.findall("meta/project/tasks/task")
    if tasks and clip is not None:
        i = _project_task(tasks, name, clip) if len(tasks) > 1 else 0
        offset, subset = 0, None
        for j, task in enumerate(tasks[:i + 1]):
            where = f"{name}: /annotations/meta/project/tasks/task[{j}]"
            if task.findtext("subset") != subset:
                offset, subset = 0, task.findtext("subset")
            frames, span = _frames_of(task, where)
            if j < i:
                offset += frames
        field = "stop_frame" if tasks[i].find("stop_frame") is not None else "size"  # what the span came from
        return CvatSource(tasks[i].findtext("id") if len(tasks) > 1 else None, offset, span, f"{where}/{field}",
                          _size(tasks[i], where), "", _video_names(tasks[i]), dumped)
    for owner in ("task", "job"):
        if (meta := root.find(f"meta/{owner}")) is not None:
            where = f"{name}: /annotations/meta/{owner}"
            _, span = _frames_of(meta, where)
            size = _size(meta, where) or _size(root.find("meta"), f"{name}: /annotations/meta")
            prefix = f"job{_text(meta.findtext('id'), f'{where}/id')}:" if owner == "job" else ""
            return CvatSource(None, 0, span, f"{where}/{'stop_frame' if meta.find('stop_frame') is not None else 'size'}",
                              size, prefix, _video_names(meta), dumped)
    return CvatSource(None, 0, None, "", _size(root.find("meta"), f"{name}: /annotations/meta"), "", "", dumped)


def _cvat_box(box: ET.Element, at: str, width: int, height: int) -> tuple[float, float, float, float]:
    """The normalised axis-aligned box of a CVAT ``<box>`` (its ``rotation``, degrees about its centre, applied)."""
    x0, y0, x1, y1 = (_number(box.get(a), f"{at}/@{a}") for a in ("xtl", "ytl", "xbr", "ybr"))
    rotation = _number(box.get("rotation", "0"), f"{at}/@rotation")
    if rotation:
        c, s = abs(math.cos(math.radians(rotation))), abs(math.sin(math.radians(rotation)))
        cx, cy, hw, hh = (x0 + x1) / 2, (y0 + y1) / 2, abs(x1 - x0) / 2, abs(y1 - y0) / 2
        x0, x1 = cx - (hw * c + hh * s), cx + (hw * c + hh * s)
        y0, y1 = cy - (hw * s + hh * c), cy + (hw * s + hh * c)
    return normalised_box(x0, y0, x1, y1, width, height)


def read_cvat(path: str | Path, size: tuple[int, int] | None = None, keyframes_only: bool = True,
              skip_sources: tuple[str, ...] = (), clip: str | None = None) -> tuple[list[ToolTrack], CvatSource]:
    """Tracks of a CVAT video XML 1.1 file, their frames the task's own (``size``: (width, height)
    when the file has none; ``clip``: the clip, to pick its task from a project export), and where
    they come from."""
    name = str(path)
    root = _parse_xml(path)
    if root.tag != "annotations":
        raise LabelError(f"{name}: /{root.tag}: not a CVAT annotations file (root element must be <annotations>)")
    if not root.findall("track"):
        for i, image in enumerate(root.findall("image")):
            if (shape := next((s for s in image if s.tag in SHAPES), None)) is not None:
                raise LabelError(f"{name}: /annotations/image[{i}]/{shape.tag}[0]: a 'CVAT for images' export holds shapes "
                                 "on single frames, not tracks; export the task as 'CVAT for video 1.1'")
    source = cvat_source(root, name, clip)
    width, height = source.size or size or (0, 0)
    if min(width, height) <= 0:
        raise LabelError(f"{name}: /annotations/meta: no original_size and no frame size given")
    tracks, skipped = [], 0
    for i, el in enumerate(root.findall("track")):
        where = f"{name}: /annotations/track[{i}]"
        if source.task_id is not None and el.get("task_id", source.task_id) != source.task_id:
            continue
        if el.get("source", "manual") in skip_sources:
            skipped += 1
            continue
        track = ToolTrack(f"cvat:{source.id_prefix}{el.get('id', i)}", _text(el.get("label"), f"{where}/@label"), where=where,
                          shown_frames=source.span, shown_where=source.span_where)
        for j, box in enumerate(el.findall("box")):
            if box.get("outside", "0") == "1" or (keyframes_only and box.get("keyframe", "1") != "1"):
                continue
            at = f"{where}/box[{j}]"
            frame = _whole(box.get("frame"), f"{at}/@frame", 0)
            if frame < source.offset:
                raise LabelError(f"{at}/@frame: {frame} is before the frames of the clip's task in this project "
                                 f"export (from {source.offset})")
            track.boxes.append(ToolBox(frame - source.offset, _cvat_box(box, at, width, height)))
        tracks.append(track)
    if skipped and not tracks:
        raise LabelError(f"{name}: /annotations: each of its {skipped} track(s) has a --skip-source source "
                         f"({', '.join(skip_sources)}): the label would say that nothing is missing")
    return tracks, source


def import_cvat(wh: Warehouse, path: str | Path, clip: str, task_id: str | None = None, *, frame_map: FrameMapMode = "frames",
                keyframes_only: bool = True, skip_sources: tuple[str, ...] = (), label_map: dict[str, str] | None = None) -> ImportResult:
    """A ``manual_track`` label document from a CVAT video XML 1.1 file, dated when CVAT dumped it
    (else when the file was written): the same export makes the same label file."""
    frames = ClipFrames.of(wh, clip)
    tracks, source = read_cvat(path, (frames.width, frames.height), keyframes_only, skip_sources, clip)
    result = tracks_to_label(wh, tracks, clip, task_id, frame_map, label_map, source=f"cvat:{Path(path).name}",
                             name=str(path), created_at=utc_seconds(source.dumped) or file_time(path), frames=frames)
    if source.names and not names_clip(source.names, clip):
        result.warnings.append(f"{path}: /annotations/meta: its task ({source.names.strip()[:80]}) names no clip "
                               f"{clip!r}: is this the clip's export?")
    return result
