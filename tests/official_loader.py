"""A small reader of the official CAD-Estate dataset, written from the format description
(../shared/reference/formats.md), not from our writer: tests read what we export with it.

It does what the official loader does, in numpy:

- ``frames.json``: pixel intrinsics and ``image_size`` (height, width) -> an OpenGL projection
  (view -> clip space: ``x_ndc = 2 fx / W · x / z + 2 cx / W - 1``, the same for y with fy, cy, H;
  view space is OpenCV's, z forward); extrinsics -> the world->view matrix ``translate(t) · R(q)``.
- ``objects.json``: ``class`` looked up among the CAD root's ``shapenet_classes.json`` ids (a class
  name fails), object->world ``T · R · S · diag(-1, 1, 1)`` (the last factor when mirrored), the
  model's triangles from ``<cad root>/<class>/<cad_id>.npz`` and its symmetry from
  ``symmetry_dict.json``; boxes (ymin, xmin, ymax, xmax) in [0, 1].
- images: ``<frames root>/<video_id>/<video_id>_<timestamp>.jpg``, the video id being the clip
  name without its ``_<start timestamp>`` suffix.

Pixels: origin at the top-left image corner, x right, y down; ``(x_ndc + 1) / 2 · W``.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np


class LoaderError(ValueError):
    """What the official loader would fail on."""


def translate(t) -> np.ndarray:
    """float64[4, 4] translation by float[3]."""
    M = np.eye(4)
    M[:3, 3] = t
    return M


def rotate(q) -> np.ndarray:
    """float64[4, 4] rotation of the quaternion float[4] (w, x, y, z), normalised."""
    w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
    M = np.eye(4)
    M[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                 [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                 [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]
    return M


def scale(s) -> np.ndarray:
    """float64[4, 4] scale by float[3]."""
    return np.diag([*np.asarray(s, np.float64), 1.0])


def gl_projection(width: float, height: float, fx: float, fy: float, cx: float, cy: float,
                  near: float = 0.1, far: float = 200.0) -> np.ndarray:
    """float64[4, 4] view -> clip space from pixel intrinsics (the official convention)."""
    return np.array([[2 * fx / width, 0, 2 * cx / width - 1, 0],
                     [0, 2 * fy / height, 2 * cy / height - 1, 0],
                     [0, 0, (far + near) / (far - near), -2 * near * far / (far - near)],
                     [0, 0, 1, 0]])


@dataclass(frozen=True)
class LoadedFrames:
    """``timestamps`` int64[N] µs; ``projection`` float64[N, 4, 4] view->clip; ``world_to_view``
    float64[N, 4, 4]; ``key_frames`` bool[N]; ``image_size`` (height, width)."""

    clip_name: str
    image_size: tuple[int, int]
    timestamps: np.ndarray
    projection: np.ndarray
    world_to_view: np.ndarray
    key_frames: np.ndarray


@dataclass(frozen=True)
class LoadedObject:
    """One object: ``label`` its index in shapenet_classes.json; ``object_to_world`` float64[4, 4]
    (identity when unposed); ``triangles`` float64[T, 3, 3] in world space (empty when unposed);
    ``boxes`` {timestamp: (ymin, xmin, ymax, xmax)}; ``correspondences`` {timestamp: [(2d, 3d)]}."""

    track_id: str
    label: int
    class_id: str
    automatic: bool
    cad_id: str | None
    symmetry: int
    object_to_world: np.ndarray
    triangles: np.ndarray
    boxes: dict[int, tuple[float, float, float, float]]
    correspondences: dict[int, list[tuple[tuple[float, float], tuple[float, float, float]]]]


def load_frames(path: Path) -> LoadedFrames:
    data = json.loads(Path(path).read_text())
    h, w = data["image_size"]
    frames = data["frames"]
    projection = np.stack([gl_projection(w, h, *f["intrinsics"]) for f in frames])
    world_to_view = np.stack([translate(f["extrinsics"]["translation"]) @ rotate(f["extrinsics"]["rotation"])
                              for f in frames])
    return LoadedFrames(data["clip_name"], (int(h), int(w)), np.array([f["timestamp"] for f in frames], np.int64),
                        projection, world_to_view, np.array([f["key_frame"] for f in frames], bool))


def load_objects(path: Path, cad_root: Path) -> list[LoadedObject]:
    data = json.loads(Path(path).read_text())
    classes = [c["id"] for c in json.loads((Path(cad_root) / "shapenet_classes.json").read_text())]
    symmetry = json.loads((Path(cad_root) / "symmetry_dict.json").read_text())
    out = []
    for o in data["objects"]:
        if o["class"] not in classes:
            raise LoaderError(f"class {o['class']!r} is not a class id of shapenet_classes.json")
        M, triangles, sym = np.eye(4), np.zeros((0, 3, 3)), 1
        if "translation" in o:
            M = translate(o["translation"]) @ rotate(o["rotation"]) @ scale(o["scale"])
            if o["is_mirrored"]:
                M = M @ scale([-1, 1, 1])
            soup = np.load(Path(cad_root) / o["class"] / f"{o['cad_id']}.npz")["vertices"].astype(np.float64)
            triangles = soup @ M[:3, :3].T + M[:3, 3]
            sym = int(symmetry[f"{o['class']}_{o['cad_id']}"])
        corr = {e["timestamp"]: [(tuple(c["2d"]), tuple(c["3d"])) for c in e["correspondences"]]
                for e in o["track"] if e["correspondences"] is not None}
        out.append(LoadedObject(o["track_id"], classes.index(o["class"]), o["class"], o["is_track_automatic"],
                                o.get("cad_id"), sym, M, triangles, {e["timestamp"]: tuple(e["box"]) for e in o["track"]},
                                corr))
    return out


def video_id(clip_name: str) -> str:
    match = re.match(r"^(.+)_\d+$", clip_name)
    if match is None:
        raise LoaderError(f"clip name {clip_name!r} is not <video_id>_<start timestamp>")
    return match.group(1)


def image_path(frames_root: Path, clip_name: str, timestamp: int) -> Path:
    vid = video_id(clip_name)
    return Path(frames_root) / vid / f"{vid}_{timestamp}.jpg"


def to_pixels(frames: LoadedFrames, index: int, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points float[N, 3] -> pixels float[N, 2] on frame ``index`` and their view-space depth float[N]."""
    h, w = frames.image_size
    X = np.concatenate([points, np.ones((len(points), 1))], 1)
    view = X @ frames.world_to_view[index].T
    clip = view @ frames.projection[index].T
    ndc = clip[:, :2] / clip[:, 3:4]
    return np.stack([(ndc[:, 0] + 1) / 2 * w, (ndc[:, 1] + 1) / 2 * h], 1), view[:, 2]


def silhouette(triangles_px: np.ndarray, height: int, width: int) -> np.ndarray:
    """bool[H, W]: pixel centres covered by any of the triangles float[T, 3, 2] (pixels)."""
    mask = np.zeros((height, width), bool)
    for tri in triangles_px:
        x0, y0 = np.floor(tri.min(0) - 0.5).astype(int)
        x1, y1 = np.ceil(tri.max(0) - 0.5).astype(int)
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, width - 1), min(y1, height - 1)
        if x1 < x0 or y1 < y0:
            continue
        px, py = np.meshgrid(np.arange(x0, x1 + 1) + 0.5, np.arange(y0, y1 + 1) + 0.5)
        (ax, ay), (bx, by), (cx, cy) = tri
        e0 = (bx - ax) * (py - ay) - (by - ay) * (px - ax)
        e1 = (cx - bx) * (py - by) - (cy - by) * (px - bx)
        e2 = (ax - cx) * (py - cy) - (ay - cy) * (px - cx)
        inside = ((e0 >= 0) & (e1 >= 0) & (e2 >= 0)) | ((e0 <= 0) & (e1 <= 0) & (e2 <= 0))
        mask[y0:y1 + 1, x0:x1 + 1] |= inside
    return mask
