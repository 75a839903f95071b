"""The official CAD-Estate annotation files (``frames.json``, ``objects.json``): dataclasses, reader, writer.

Conventions (google-research/cad-estate, ``input_file_structures.py``, ``frames.py``, ``objects.py``):

- ``frames.json``: ``clip_name``; ``image_size`` = (height, width) or null; ``frames``: one entry per
  frame with ``timestamp`` (int µs), ``key_frame`` (bool), ``intrinsics`` (fx, fy, cx, cy),
  ``extrinsics`` {``translation``: (x, y, z), ``rotation``: (w, x, y, z)}: the camera matrix is
  ``translate(t) · R(q)``, **world->view**. Our cameras are OpenCV (x right, y down, z forward).
  Intrinsics are in **pixels** (unlike RealEstate10K's normalised ones): the official loader passes
  them with ``image_size`` to ``gl_projection_matrix_from_intrinsics(w, h, fx, fy, cx, cy)``, which
  divides fx, cx by the width and fy, cy by the height. A file whose principal point lies within
  one pixel of the top-left corner (normalised values) is refused by :func:`frames_from_json`.
- ``objects.json``: ``clip_name``; ``objects``: one entry per object with ``track_id`` (str),
  ``is_track_automatic``, ``class`` (class id: ShapeNet synset or cadestate-<name>), optional
  ``cad_id``, optional pose ``translation``, ``rotation`` (w, x, y, z), ``scale`` (absent when the
  pose failed verification), ``is_mirrored``, and ``track``: per-frame entries with ``timestamp``,
  ``box`` (ymin, xmin, ymax, xmax) normalised to [0, 1] and ``correspondences`` (list of
  ``{"2d": (x, y) normalised, "3d": (x, y, z) object space}``: the CAD model's own canonical frame,
  before the mirror, so a mirrored object's points are those clicked on the unmirrored model) or null.
- Object-to-world: mirror => scale => rotation => translation (``cadestate.render.object_to_world``).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cadestate.atomic import atomic_write_bytes


class OfficialFormatError(ValueError):
    """A malformed frames.json / objects.json; the message names the file and the field."""


@dataclass(frozen=True)
class Frame:
    """One frame: ``timestamp`` µs; ``intrinsics`` (fx, fy, cx, cy) in pixels; world->camera
    ``translation`` (x, y, z) and ``rotation`` (w, x, y, z) quaternion (OpenCV camera axes)."""

    timestamp: int
    key_frame: bool
    intrinsics: tuple[float, float, float, float]
    translation: tuple[float, float, float]
    rotation: tuple[float, float, float, float]


@dataclass(frozen=True)
class FramesFile:
    """A clip's frames; ``image_size`` (height, width) in pixels, the size the intrinsics refer to."""

    clip_name: str
    image_size: tuple[int, int] | None  # (height, width)
    frames: tuple[Frame, ...]


@dataclass(frozen=True)
class Correspondence:
    """A 2D point (x, y) normalised to [0, 1] and its 3D point (x, y, z) in the object's CAD frame."""

    xy: tuple[float, float]
    xyz: tuple[float, float, float]


@dataclass(frozen=True)
class TrackEntry:
    """The object's box on one frame: (ymin, xmin, ymax, xmax) normalised to [0, 1]."""

    timestamp: int
    box: tuple[float, float, float, float]
    correspondences: tuple[Correspondence, ...] | None = None


@dataclass(frozen=True)
class ObjectAnnotation:
    """One object. The pose (translation, rotation (w, x, y, z), scale) is None when absent."""

    track_id: str
    cls: str
    is_track_automatic: bool
    is_mirrored: bool
    track: tuple[TrackEntry, ...]
    cad_id: str | None = None
    translation: tuple[float, float, float] | None = None
    rotation: tuple[float, float, float, float] | None = None
    scale: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class ObjectsFile:
    clip_name: str
    objects: tuple[ObjectAnnotation, ...] = field(default_factory=tuple)


def _tuple(where: str, value: Any, n: int, kind: type = float) -> tuple:
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise OfficialFormatError(f"{where}: expected a list of {n} numbers, got {value!r}")
    if kind is int:
        return tuple(_int(f"{where}[{i}]", v) for i, v in enumerate(value))
    try:
        return tuple(kind(v) for v in value)
    except (TypeError, ValueError):
        raise OfficialFormatError(f"{where}: expected numbers, got {value!r}") from None


def _field(where: str, entry: Any, key: str, default: Any = ...) -> Any:
    """``entry[key]`` of a JSON object; ``where`` names the entry (``file: objects[3]``)."""
    if not isinstance(entry, dict):
        raise OfficialFormatError(f"{where}: expected an object, got {entry!r:.60}")
    if key in entry:
        return entry[key]
    if default is ...:
        raise OfficialFormatError(f"{where}: missing field {key!r}")
    return default


def _list(where: str, value: Any) -> list:
    if not isinstance(value, list):
        raise OfficialFormatError(f"{where}: expected a list, got {value!r:.60}")
    return value


def _int(where: str, value: Any) -> int:
    """A whole number (a timestamp in µs): an int, or a float with no fraction."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value != value or float(value) != int(value):
        raise OfficialFormatError(f"{where}: expected a whole number, got {value!r:.60}")
    return int(value)


def _bool(where: str, value: Any) -> bool:
    if not isinstance(value, bool):
        raise OfficialFormatError(f"{where}: expected true or false, got {value!r:.60}")
    return value


def frames_to_json(f: FramesFile) -> dict:
    return {
        "clip_name": f.clip_name,
        "image_size": list(f.image_size) if f.image_size else None,
        "frames": [{"timestamp": fr.timestamp, "key_frame": fr.key_frame, "intrinsics": list(fr.intrinsics),
                    "extrinsics": {"translation": list(fr.translation), "rotation": list(fr.rotation)}}
                   for fr in f.frames],
    }


def frames_from_json(data: Any, source: str = "frames.json") -> FramesFile:
    """Parse a ``frames.json`` document; a malformed one raises :class:`OfficialFormatError` naming
    ``source`` and the field (``frames[3].extrinsics.rotation``)."""
    frames = []
    for i, fr in enumerate(_list(f"{source}: frames", _field(source, data, "frames"))):
        where = f"{source}: frames[{i}]"
        extrinsics = _field(where, fr, "extrinsics")
        frames.append(Frame(_int(f"{where}.timestamp", _field(where, fr, "timestamp")),
                            _bool(f"{where}.key_frame", _field(where, fr, "key_frame")),
                            _tuple(f"{where}.intrinsics", _field(where, fr, "intrinsics"), 4),
                            _tuple(f"{where}.extrinsics.translation", _field(f"{where}.extrinsics", extrinsics, "translation"), 3),
                            _tuple(f"{where}.extrinsics.rotation", _field(f"{where}.extrinsics", extrinsics, "rotation"), 4)))
    _check_pixel_intrinsics(tuple(frames), source)
    size = _field(source, data, "image_size", None)
    return FramesFile(str(_field(source, data, "clip_name")), _tuple(f"{source}: image_size", size, 2, int) if size else None,
                      tuple(frames))


def _check_pixel_intrinsics(frames: tuple[Frame, ...], source: str) -> None:
    """Refuse normalised intrinsics (an old file): a principal point within one pixel of the
    top-left corner is what (fx, fy, cx, cy) divided by the image size look like."""
    for i, fr in enumerate(frames):
        if fr.intrinsics[2] <= 1.0 and fr.intrinsics[3] <= 1.0:
            raise OfficialFormatError(f"{source}: frames[{i}].intrinsics: {list(fr.intrinsics)} look normalised; the "
                                      "official format stores (fx, fy, cx, cy) in pixels (regenerate the file)")


def objects_to_json(f: ObjectsFile) -> dict:
    objects = []
    for o in f.objects:
        entry: dict[str, Any] = {"track_id": o.track_id, "is_track_automatic": o.is_track_automatic, "class": o.cls}
        if o.cad_id is not None:
            entry["cad_id"] = o.cad_id
        if o.translation is not None:
            entry.update(translation=list(o.translation), rotation=list(o.rotation), scale=list(o.scale))
        entry["is_mirrored"] = o.is_mirrored
        entry["track"] = [{"timestamp": t.timestamp, "box": list(t.box),
                           "correspondences": None if t.correspondences is None else
                           [{"2d": list(c.xy), "3d": list(c.xyz)} for c in t.correspondences]}
                          for t in o.track]
        objects.append(entry)
    return {"clip_name": f.clip_name, "objects": objects}


def _track_entry(where: str, entry: Any) -> TrackEntry:
    pairs = _field(where, entry, "correspondences", None)
    return TrackEntry(_int(f"{where}.timestamp", _field(where, entry, "timestamp")), _tuple(f"{where}.box", _field(where, entry, "box"), 4),
                      None if pairs is None else tuple(
                          Correspondence(_tuple(f"{where}.correspondences[{k}].2d", _field(f"{where}.correspondences[{k}]", c, "2d"), 2),
                                         _tuple(f"{where}.correspondences[{k}].3d", _field(f"{where}.correspondences[{k}]", c, "3d"), 3))
                          for k, c in enumerate(_list(f"{where}.correspondences", pairs))))


def objects_from_json(data: Any, source: str = "objects.json") -> ObjectsFile:
    """Parse an ``objects.json`` document; a malformed one raises :class:`OfficialFormatError`
    naming ``source`` and the field (``objects[2].track[5].box``)."""
    objects = []
    for i, o in enumerate(_list(f"{source}: objects", _field(source, data, "objects"))):
        where = f"{source}: objects[{i}]"
        track = tuple(_track_entry(f"{where}.track[{j}]", t) for j, t in enumerate(_list(f"{where}.track", _field(where, o, "track"))))
        posed = "translation" in o
        cad_id = _field(where, o, "cad_id", None)
        objects.append(ObjectAnnotation(
            track_id=str(_field(where, o, "track_id")), cls=str(_field(where, o, "class")),
            is_track_automatic=_bool(f"{where}.is_track_automatic", _field(where, o, "is_track_automatic")),
            is_mirrored=_bool(f"{where}.is_mirrored", _field(where, o, "is_mirrored", False)), track=track,
            cad_id=None if cad_id is None else str(cad_id),
            translation=_tuple(f"{where}.translation", o["translation"], 3) if posed else None,
            rotation=_tuple(f"{where}.rotation", _field(where, o, "rotation"), 4) if posed else None,
            scale=_tuple(f"{where}.scale", _field(where, o, "scale"), 3) if posed else None))
    return ObjectsFile(str(_field(source, data, "clip_name")), tuple(objects))


def write_json(path: str | os.PathLike, data: dict) -> None:
    """Write JSON atomically."""
    atomic_write_bytes(Path(path), json.dumps(data, indent=1).encode())


def read_frames(path: str | os.PathLike) -> FramesFile:
    return frames_from_json(_load(path), str(path))


def read_objects(path: str | os.PathLike) -> ObjectsFile:
    return objects_from_json(_load(path), str(path))


def _load(path: str | os.PathLike) -> dict:
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise OfficialFormatError(f"{path}: not valid JSON: {e}") from None
