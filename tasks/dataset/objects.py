"""A clip's share of the dataset, read from the warehouse: its frames and its physical objects.

What the pipeline keeps per track becomes one :class:`DatasetObject` per physical object:

- tracks: :func:`tasks.tracking.clip_tracks.clip_tracks` (automatic, then manual: ``is_track_automatic``
  false); boxes (ymin, xmin, ymax, xmax) normalised to [0, 1] (image frame, origin top-left);
- class: the chosen CAD model's class; without one, the class the track's detector label stands
  for (:func:`tasks.cad.classes.class_of_label`; ``other`` when none);
- model: the answer in force of the CAD-selection task (absent: none chosen or not answered);
- correspondences: the ``correspondences`` rows of the track on the chosen model: 2D normalised
  (x, y), 3D in the model's canonical CAD frame (unmirrored: the official "object space");
- pose: only a pose *accepted* in verification (``verified_poses``): translation (m, world),
  rotation (w, x, y, z) CAD -> world, scale along the CAD axes, mirror flag; object->world is
  mirror => scale => rotation => translation.

World: :func:`clip_dataset` gives frames and poses in the warehouse's aligned world (+Y up);
:meth:`ClipDataset.in_input_world` maps them to the world of the clip's camera file (undoing
``clips.up_rotation``, :mod:`tasks.video.world_up`), as the exports write them.

**What people said first** (:func:`tasks.tracking.relations.relations_in_force`, the statements of
the answers in force). A track said to be no object ("track N is not an object", or a fragment of
such a track) is not exported. A fragment ("same object as track N" in CAD selection or
verification, or a drawn object that "is track N"; chains followed to their root) joins its root's object, as a claimed track does below:
its boxes fill the frames the root has none on, its id is listed in the object's ``merged``, its
own pose and correspondences are dropped; but when the root has no accepted pose and fragments
do, the fragment's of most key-frames (then lowest id) speaks for the object instead (a pose
accepted as "the same object as track N" where N's was rejected), the root joining it. A fragment
whose root has no track stays an object of its own.

**Fragments and duplicates nobody named.** A tracker may cut one object into several tracks, and
several of them may be posed. Each accepted pose, in order of more key-frames, then lower track id,
claims every other track whose boxes the projection of its posed CAD bounding box covers: mean box
IoU >= :data:`SAME_OBJECT_IOU` over the frames where both exist; and every other posed track whose
projection covers its own boxes (between two poses the claim goes both ways). Claimed tracks
(posed or not) join its object the same way (with the tracks already joined to them). Tracks no
pose claims stay objects of their own.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from cadestate.geometry import camera_to_world, project
from cadestate.render import object_to_world
from schemas.tracking import MANUAL_TRACK_BASE
from tasks.cad import classes
from tasks.cad.classes import BY_NAME
from tasks.cad.export import ExportError
from tasks.tracking.relations import TrackRelations, relations_in_force
from tasks.video.world_up import pose_to_input_world, stored_rotation, unalign_extrinsics
from warehouse import Warehouse

SAME_OBJECT_IOU = 0.5
"""Mean IoU of a track's boxes with an accepted pose's projected boxes that makes it part of that object."""

Box = tuple[float, float, float, float]


@dataclass(frozen=True)
class DatasetFrame:
    """One frame: ``timestamp_us``; ``K`` float64[3, 3] pixels; world->camera ``R`` float64[3, 3],
    ``t`` float64[3] (OpenCV axes); ``image_path`` relative to the warehouse root; ``key_frame``:
    a key-frame of the clip's answered manual-track task."""

    timestamp_us: int
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    image_path: str
    key_frame: bool


@dataclass(frozen=True)
class Pose:
    """Object->world of an accepted pose: ``translation`` (m, world), ``rotation`` (w, x, y, z),
    ``scale`` along the CAD axes; the CAD model mirrored (x -> -x) first when ``is_mirrored``."""

    translation: tuple[float, float, float]
    rotation: tuple[float, float, float, float]
    scale: tuple[float, float, float]
    is_mirrored: bool

    def matrix(self) -> np.ndarray:
        """float64[4, 4] object->world, T · R · S · mirror."""
        return object_to_world(self.translation, self.rotation, self.scale, self.is_mirrored)


@dataclass(frozen=True)
class DatasetObject:
    """One physical object. ``track_id``: the track that speaks for it (the posed one);
    ``merged``: the other tracks that joined it; ``boxes`` {timestamp: box}; ``correspondences``
    {timestamp: ((x, y) normalised, (x, y, z) CAD frame) per click}; ``extent`` float[3] the
    model's bounding-box size (m, CAD frame) or None; ``symmetry`` order about +Y (1, 2, 4, 36)."""

    track_id: int
    automatic: bool
    class_name: str
    class_id: str
    boxes: dict[int, Box]
    is_mirrored: bool = False
    cad_id: str | None = None
    pose: Pose | None = None
    correspondences: dict[int, tuple[tuple[tuple[float, float], tuple[float, float, float]], ...]] = field(default_factory=dict)
    merged: tuple[int, ...] = ()
    extent: tuple[float, float, float] | None = None
    symmetry: int = 1
    keyframes: int = 0


@dataclass(frozen=True)
class ClipDataset:
    """A clip's frames (by timestamp order) and objects; ``image_size`` (height, width) px; ``url``
    line 1 of its camera file."""

    clip: str
    url: str
    image_size: tuple[int, int]
    frames: tuple[DatasetFrame, ...]
    objects: tuple[DatasetObject, ...]
    up_rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    """float64[3, 3] Q of ``clips.up_rotation``: X_aligned = Q X_input; identity once in the input world."""

    def require_models(self) -> None:
        """:class:`ExportError` naming the first object whose chosen model is no longer in the
        warehouse's ``cad_models`` (no extent): an export would write it without its model's box."""
        for o in self.objects:
            if o.cad_id and o.extent is None:
                raise ExportError(f"clip {self.clip}, track {o.track_id}: its model {o.cad_id!r} is not in the "
                                  "warehouse's cad_models (its CAD library removed?); ingest the library again, "
                                  "or answer the clip's CAD selection again")

    def in_input_world(self) -> "ClipDataset":
        """The same clip with frames (world->camera ``R Q``, ``t``) and poses (``Q^T T``, ``Q^T R``)
        in the world of its camera file; ``up_rotation`` becomes the identity."""
        Q = self.up_rotation
        if np.array_equal(Q, np.eye(3)):
            return self
        frames = tuple(replace(f, R=unalign_extrinsics(f.R, f.t, Q)[0]) for f in self.frames)
        objects = []
        for o in self.objects:
            if o.pose is not None:
                T, q = pose_to_input_world(o.pose.translation, o.pose.rotation, Q)
                o = replace(o, pose=replace(o.pose, translation=T, rotation=q))
            objects.append(o)
        return replace(self, frames=frames, objects=tuple(objects), up_rotation=np.eye(3))


def class_of_label(label: str) -> tuple[str, str]:
    """(class name, class id) of a detector label (:func:`tasks.cad.classes.class_of_label`;
    ``other`` when it stands for no class)."""
    c = BY_NAME[classes.class_of_label(label) or "other"]
    return c.name, c.id


def _keyframe_stamps(wh: Warehouse, clip: str) -> set[int]:
    """Timestamps of the key-frames of the clip's answered manual-track task (none: empty)."""
    import json

    from tasks.human.answers_in_force import answered_tasks
    from tasks.human.labels import latest_task_of_kind

    task = latest_task_of_kind(wh, clip, "manual_track")
    if task is None or task["task_id"] not in answered_tasks(wh, "manual_track", clip):
        return set()
    return {int(k["timestamp_us"]) for k in json.loads(task["document"])["keyframes"]}


def clip_frames(wh: Warehouse, clip: str) -> tuple[DatasetFrame, ...]:
    keys = _keyframe_stamps(wh, clip)
    rows = wh.read("frames", [clip], columns=["timestamp_us", "K", "world_to_camera_R", "world_to_camera_t",
                                              "image_path"]).sort_by("timestamp_us").to_pylist()
    return tuple(DatasetFrame(int(r["timestamp_us"]), np.asarray(r["K"], np.float64).reshape(3, 3),
                              np.asarray(r["world_to_camera_R"], np.float64).reshape(3, 3),
                              np.asarray(r["world_to_camera_t"], np.float64), r["image_path"],
                              int(r["timestamp_us"]) in keys) for r in rows)


def projected_box(pose: Pose, extent, frame: DatasetFrame, image_size: tuple[int, int]) -> Box | None:
    """The box (ymin, xmin, ymax, xmax), normalised and clipped to the image, of the posed CAD
    bounding box (``extent`` float[3], centred in the CAD frame) on ``frame``; None when a corner
    is behind the camera or the box misses the image."""
    h, w = image_size
    half = np.asarray(extent, np.float64) / 2
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * half
    M = pose.matrix()
    uv, depth = project(frame.K, frame.R, frame.t, corners @ M[:3, :3].T + M[:3, 3])
    if np.any(depth <= 0):
        return None
    x0, y0 = np.clip(uv.min(0), 0, [w, h])
    x1, y1 = np.clip(uv.max(0), 0, [w, h])
    return (y0 / h, x0 / w, y1 / h, x1 / w) if x1 > x0 and y1 > y0 else None


def box_iou(a: Box, b: Box) -> float:
    """IoU of two (ymin, xmin, ymax, xmax) boxes."""
    iy = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    ix = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = iy * ix
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def _covers(claimer: DatasetObject, other: DatasetObject, frames: dict[int, DatasetFrame], image_size) -> bool:
    ious = []
    for ts, box in other.boxes.items():
        projected = projected_box(claimer.pose, claimer.extent, frames[ts], image_size) if ts in frames else None
        if projected is not None:
            ious.append(box_iou(projected, box))
    return bool(ious) and float(np.mean(ious)) >= SAME_OBJECT_IOU


def _same_object(claimer: DatasetObject, other: DatasetObject, frames: dict[int, DatasetFrame], image_size) -> bool:
    """Whether ``claimer``'s accepted pose claims ``other``: its projection covers ``other``'s
    boxes, or ``other`` is posed too and its projection covers ``claimer``'s (between two poses the
    claim goes both ways: a pose on tight boxes (a partial detection) was claimed only when it had
    fewer key-frames, and with more both were exported, one object twice)."""
    return _covers(claimer, other, frames, image_size) or (
        other.pose is not None and other.extent is not None and _covers(other, claimer, frames, image_size))


def join(root: DatasetObject, parts: list[DatasetObject]) -> DatasetObject:
    """``root``'s object with ``parts`` joined: their boxes fill the frames ``root`` has none on
    (in ``parts`` order); their ids, and the tracks joined to them before, go to ``merged``."""
    boxes = dict(root.boxes)
    for x in parts:
        for ts, b in x.boxes.items():
            boxes.setdefault(ts, b)
    merged = set(root.merged) | {x.track_id for x in parts} | {m for x in parts for m in x.merged}
    return replace(root, boxes=dict(sorted(boxes.items())), merged=tuple(sorted(merged)))


def declared_objects(objects: list[DatasetObject], relations: TrackRelations) -> list[DatasetObject]:
    """``objects`` as people said (module docstring): none for the tracks that are no object, each
    fragment joined to its root's object, which a fragment's accepted pose speaks for when the
    root's was not accepted (:meth:`TrackRelations.pose_speakers`); in the speakers' track id order."""
    kept = {o.track_id: o for o in sorted(objects, key=lambda o: o.track_id) if relations.is_object(o.track_id)}
    parts: dict[int, list[DatasetObject]] = {}
    for t, o in kept.items():
        root = relations.root(t)
        if root != t and root in kept:
            parts.setdefault(root, []).append(o)
    joined = {x.track_id for ps in parts.values() for x in ps}
    result = []
    for t, o in kept.items():
        if t in joined:
            continue
        group = [o, *parts.get(t, [])]
        speakers = relations.pose_speakers({x.track_id: x.keyframes for x in group if x.pose is not None})
        speaker = next((x for x in group if x.track_id in speakers), o)
        result.append(join(speaker, [x for x in group if x is not speaker]))
    return sorted(result, key=lambda o: o.track_id)


def merge_objects(objects: list[DatasetObject], frames: tuple[DatasetFrame, ...], image_size: tuple[int, int],
                  relations: TrackRelations | None = None) -> list[DatasetObject]:
    """One object per physical object (the module docstring's rules: ``relations`` first, then
    the accepted poses' claims), in track id order."""
    if relations is not None:
        objects = declared_objects(objects, relations)
    by_ts = {f.timestamp_us: f for f in frames}
    posed = sorted((o for o in objects if o.pose is not None and o.extent is not None),
                   key=lambda o: (-o.keyframes, o.track_id))
    claimed: set[int] = set()
    result: dict[int, DatasetObject] = {}
    for o in posed:
        if o.track_id in claimed:
            continue
        joined = [x for x in objects if x.track_id != o.track_id and x.track_id not in claimed
                  and x.track_id not in result and _same_object(o, x, by_ts, image_size)]
        claimed |= {x.track_id for x in joined}
        result[o.track_id] = join(o, joined)
        claimed.add(o.track_id)
    for o in objects:
        if o.track_id not in claimed:
            result[o.track_id] = o
    return [result[k] for k in sorted(result)]


def clip_dataset(wh: Warehouse, clip: str) -> ClipDataset:
    """The clip's frames and physical objects (module docstring)."""
    from tasks.tracking.clip_tracks import clip_tracks
    from tasks.human.cad_selection import selected_models

    frames = clip_frames(wh, clip)
    info = wh.read("clips", [clip], columns=["url", "width", "height", "up_rotation"]).to_pylist()
    if not info:
        raise ExportError(f"clip {clip!r} is not in the clips table of {wh.root} (cadestate ingest)")
    image_size = (int(info[0]["height"]), int(info[0]["width"]))
    models = {r["cad_id"]: r for r in wh.read("cad_models", columns=["cad_id", "class", "class_id", "extent",
                                                                     "symmetry"]).to_pylist()}
    chosen = selected_models(wh, clip)
    accepted = {int(r["track_id"]): r for r in wh.read("verified_poses", [clip]).to_pylist() if r["accepted"]}
    solved = {int(r["track_id"]): r for r in wh.read("poses", [clip], columns=["track_id", "num_keyframes"]).to_pylist()}
    clicks: dict[int, list[dict]] = {}
    for r in wh.read("correspondences", [clip]).to_pylist():
        clicks.setdefault(int(r["track_id"]), []).append(r)
    objects = []
    for tid, track in clip_tracks(wh, clip).items():
        cad_id = chosen.get(tid)
        v = accepted.get(tid)
        if v is not None:
            cad_id = v["cad_id"]
        model = models.get(cad_id) if cad_id else None
        name, cid = (model["class"], model["class_id"]) if model else class_of_label(track.label)
        rows = sorted((r for r in clicks.get(tid, []) if r["cad_id"] == cad_id),
                      key=lambda r: (r["timestamp_us"], r["point_index"]))
        corr: dict[int, list] = {}
        for r in rows:
            corr.setdefault(int(r["timestamp_us"]), []).append((tuple(r["point_2d"]), tuple(r["point_3d"])))
        pose = Pose(tuple(v["translation"]), tuple(v["rotation"]), tuple(v["scale"]), bool(v["is_mirrored"])) if v else None
        mirrored = pose.is_mirrored if pose else bool(rows and rows[0]["is_mirrored"])
        objects.append(DatasetObject(
            track_id=tid, automatic=tid < MANUAL_TRACK_BASE, class_name=name, class_id=cid,
            boxes={b.timestamp_us: tuple(b.box) for b in track.boxes}, is_mirrored=mirrored, cad_id=cad_id, pose=pose,
            correspondences={ts: tuple(c) for ts, c in corr.items()},
            extent=tuple(model["extent"]) if model else None, symmetry=int(model["symmetry"]) if model else 1,
            keyframes=int(solved.get(tid, {}).get("num_keyframes") or 0)))
    merged = merge_objects(objects, frames, image_size, relations_in_force(wh, clip))
    return ClipDataset(clip, info[0]["url"], image_size, frames, tuple(merged), stored_rotation(info[0]["up_rotation"]))


def camera_centres(frames: tuple[DatasetFrame, ...]) -> np.ndarray:
    """float64[N, 3] camera centres (world) of ``frames``."""
    return np.array([camera_to_world(f.R, f.t)[1] for f in frames]).reshape(-1, 3)
