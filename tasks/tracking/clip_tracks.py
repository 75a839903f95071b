"""A clip's tracks as every stage after tracking sees them: the automatic tracks (``tracks``,
``track_detections``, ``detections``, ``embeddings``) and the manual tracks people drew
(``manual_tracks``, ids from :data:`schemas.tracking.MANUAL_TRACK_BASE`), in one list.

Retrieval, the human tasks and the benchmark read tracks through :func:`clip_tracks` only, so a
manual track goes through CAD selection, correspondences, pose and verification like any other.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np

from warehouse import Warehouse


class MissingDescriptor(LookupError):
    """A box of a track has no appearance descriptor (its embed or manual_tracks stage must rerun)."""


@dataclass(frozen=True)
class TrackBox:
    """One box of a track on one frame (a ``frames`` row: ``frame_index``, ``timestamp_us``).

    ``box``: (ymin, xmin, ymax, xmax) normalised by image height (y) and width (x), origin top-left.
    ``label``: the detector's label of this detection, or the class drawn. ``det_id``:
    ``detections.det_id``, None for a drawn box. ``vector``: the raw unit appearance descriptor
    float32[D] (``embeddings.vector`` / ``manual_tracks.vector``) when asked for, else None."""

    frame_index: int
    timestamp_us: int
    box: tuple[float, float, float, float]
    label: str
    det_id: int | None = None
    vector: np.ndarray | None = None


@dataclass(frozen=True)
class ClipTrack:
    """One track: ``track_id`` (``tracks.track_id``, or ``manual_tracks.track_id`` when ``manual``),
    its class ``label`` (``tracks.label`` by vote; the drawn class of a manual track) and its
    ``boxes`` ordered by (frame_index, det_id)."""

    track_id: int
    label: str
    manual: bool
    boxes: tuple[TrackBox, ...]


def _automatic(wh: Warehouse, clip: str, vectors: bool) -> list[ClipTrack]:
    members = wh.read("track_detections", [clip], columns=["track_id", "det_id"]).to_pylist()
    dets = {d["det_id"]: d for d in wh.read("detections", [clip], columns=["det_id", "frame_index", "timestamp_us", "box",
                                                                          "label"]).to_pylist()}
    voted = {r["track_id"]: r["label"] for r in wh.read("tracks", [clip], columns=["track_id", "label"]).to_pylist()}
    looks = {}
    if vectors:
        looks = {e["owner_id"]: e["vector"] for e in wh.read("embeddings", [clip], filters=[("owner", "==", "detection")],
                                                             columns=["owner_id", "vector"]).to_pylist()}
    boxes: dict[int, list[TrackBox]] = {}
    for m in sorted(members, key=lambda m: (m["track_id"], m["det_id"])):
        d = dets.get(m["det_id"])
        if d is None:
            raise MissingDescriptor(f"clip {clip}: track {m['track_id']} lists detection {m['det_id']}, which `detections` "
                                    "does not have: rerun its tracking stage")
        if vectors and m["det_id"] not in looks:
            raise MissingDescriptor(f"clip {clip}: detection {m['det_id']} has no descriptor: rerun its embed stage")
        vector = np.asarray(looks[m["det_id"]], np.float32) if vectors else None
        boxes.setdefault(m["track_id"], []).append(
            TrackBox(int(d["frame_index"]), int(d["timestamp_us"]), tuple(d["box"]), d["label"], int(d["det_id"]), vector))
    out = []
    for t, bs in boxes.items():
        bs.sort(key=lambda b: (b.frame_index, b.det_id))
        label = voted.get(t) or Counter(b.label for b in bs).most_common(1)[0][0]
        out.append(ClipTrack(int(t), label, False, tuple(bs)))
    return out


def _manual(wh: Warehouse, clip: str, vectors: bool) -> list[ClipTrack]:
    columns = ["track_id", "label", "frame_index", "timestamp_us", "box"] + (["vector"] if vectors else [])
    boxes: dict[int, list[TrackBox]] = {}
    labels: dict[int, str] = {}
    for r in wh.read("manual_tracks", [clip], columns=columns).to_pylist():
        vector = np.asarray(r["vector"], np.float32) if vectors else None
        boxes.setdefault(r["track_id"], []).append(
            TrackBox(int(r["frame_index"]), int(r["timestamp_us"]), tuple(r["box"]), r["label"], None, vector))
        labels[r["track_id"]] = r["label"]
    return [ClipTrack(int(t), labels[t], True, tuple(sorted(bs, key=lambda b: b.frame_index))) for t, bs in boxes.items()]


def clip_tracks(wh: Warehouse, clip: str, vectors: bool = False) -> dict[int, ClipTrack]:
    """Every track of ``clip`` (automatic, then manual) by track id, ascending. ``vectors``: fill
    each box's descriptor (raises :class:`MissingDescriptor` when one is missing)."""
    tracks = _automatic(wh, clip, vectors) + _manual(wh, clip, vectors)
    return {t.track_id: t for t in sorted(tracks, key=lambda t: t.track_id)}

