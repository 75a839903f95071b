"""Which verdict answers each item of a clip's verification task, when the task changed under it: a
verdict given on an earlier task still holds while the overlay it was given on has not visibly moved.

The verification task id is a digest of every pose of the clip, so one pose solved anew (a track
clicked later, a rerun after another detector) makes a new task; and every floor-standing pose of
the clip shares the floor height (:mod:`tasks.pose.support`), so the others move with it, most by
millimetres. An item (a track, its pose, its key-frames) is answered by

1. the answer in force under the task's own id (:func:`tasks.human.answers_in_force.current_answers`),
   else
2. its ``previous``: the newest verdict given on an earlier verification task of the clip on the
   pose the item shows, whatever id its track had then (tracks are remade and renumbered when
   detection or tracking reruns). "On the pose the item shows": the earlier task showed the same
   model with the same mirroring, and the overlay moved by at most ``[verification] carry_max_px``:
   the corners of the posed model's bounding box, projected into every key-frame either pose is
   shown on, lie at most that many pixels from where they were (:func:`overlay_shift_px`), so the
   person would be shown what they judged (0 carries a verdict only to the identical pose). A
   verdict speaks of one overlay: where it holds for several poses (a pose and its duplicate), the
   one it matches best takes it (:func:`tasks.human.clicks_in_force.taken_answers`: the smallest
   shift). The newest verdict a pose takes decides (of equally new ones, from one label file, the
   one given on a track of the same id), and the stage carries it (:func:`held_verdicts`) when

   - it accepted or rejected (an answer "same object as track N" is asked again: the other track
     may have changed), and
   - the item is not flagged "may be the same object as track N", unless the verdict was given on
     an item flagged too (the person saw a flag and judged; a new partner's item is asked, and
     "same object as track N" is said there).

The stages, the web app's queue and the simulated annotators count both alike
(:func:`tasks.human.answers_in_force.answered_items`). Frames: poses map the CAD model's canonical
box (bbox-centred, metres) into the world (+Y up, :func:`cadestate.render.object_to_world`);
cameras are world->camera (OpenCV) with pixel intrinsics, as in the ``frames`` table.
"""

from __future__ import annotations

from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from cadestate.geometry import project
from tasks.human.clicks_in_force import Match, earlier_answers, taken_answers
from tasks.pose.duplicates import posed_box

CORNERS = np.array([[i, j, k] for i in (-0.5, 0.5) for j in (-0.5, 0.5) for k in (-0.5, 0.5)])
"""float64[8, 3]: the corners of a box of unit size about its centre."""

NEAR_M = 0.01
"""The near plane (m) of the verification overlays (:func:`tasks.human.verification.render_overlays`)."""


@dataclass(frozen=True)
class FrameCamera:
    """One frame's camera: ``K`` float64[3, 3] pixel intrinsics; ``R`` float64[3, 3], ``t``
    float64[3] world -> camera (X_cam = R X_world + t; OpenCV axes)."""

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray

    @staticmethod
    def of(row: Mapping) -> FrameCamera:
        """From a ``frames`` row (``K``, ``world_to_camera_R``, ``world_to_camera_t``, row-major)."""
        matrix = lambda key: np.asarray(row[key], np.float64).reshape(3, 3)  # noqa: E731
        return FrameCamera(matrix("K"), matrix("world_to_camera_R"), np.asarray(row["world_to_camera_t"], np.float64))


def box_corners(extent: Sequence[float], pose: Mapping) -> np.ndarray:
    """float64[8, 3] world corners of a model of size ``extent`` (m, CAD axes) under ``pose``
    (``translation``, ``rotation`` (w, x, y, z), ``scale``, ``is_mirrored``), in :data:`CORNERS`' order."""
    box = posed_box(extent, pose["translation"], pose["rotation"], pose["scale"], bool(pose["is_mirrored"]))
    return box.centre + (CORNERS * box.extent) @ box.axes.T


def overlay_shift_px(extent: Sequence[float], then: Mapping, now: Mapping, cameras: Iterable[FrameCamera]) -> float:
    """How far (px) the overlay of a model of size ``extent`` moves from pose ``then`` to pose
    ``now`` (keys of :func:`box_corners`): the largest distance between a corner of its posed box
    projected under each pose, over ``cameras``, 0 without cameras. A corner nearer than the
    overlays' near plane (:data:`NEAR_M`; a large object seen from close up) under both poses is
    not drawn there and is left out; one that crosses it between the poses makes the shift
    infinite (the overlay there is not a shifted copy)."""
    a, b = box_corners(extent, then), box_corners(extent, now)
    shift = 0.0
    for cam in cameras:
        ua, za = project(cam.K, cam.R, cam.t, a)
        ub, zb = project(cam.K, cam.R, cam.t, b)
        front = za > NEAR_M
        if (front != (zb > NEAR_M)).any():
            return float("inf")
        if front.any():
            shift = max(shift, float(np.max(np.linalg.norm(ua[front] - ub[front], axis=1))))
    return shift


def held_verdicts(task_id: str, poses: list[dict], answers: pa.Table, tasks: pa.Table, extents: Mapping[str, Sequence[float]],
                  cameras: Mapping[int, FrameCamera], max_px: float, flagged: Collection[int] = ()) -> dict[int, dict]:
    """Per track of ``poses`` (``poses`` rows: ``track_id``, ``cad_id``, the pose,
    ``keyframe_timestamps_us``; all the clip's poses: a verdict goes to the pose it matches best)
    without an answer under ``task_id``, the verdict that still holds (see the module), as its
    ``verification_labels`` row. ``answers``: the clip's verification answers in force over all
    tasks; ``tasks``: its ``label_tasks`` rows; ``extents``: cad_id -> the model's box size;
    ``cameras``: the clip's cameras by timestamp (µs); ``max_px``: ``[verification]
    carry_max_px``; ``flagged``: the tracks flagged "may be the same object as track N" now, which
    take a verdict only if it was given on a flagged item. Tracks without are absent."""
    under_id = {int(r["track_id"]) for r in answers.to_pylist() if r["task_id"] == task_id}
    now = {int(p["track_id"]): p for p in poses}
    taken = taken_answers(earlier_answers(answers, tasks, "verification", task_id), now,
                          lambda t, e: _overlay_match(e[1], now[t], extents, cameras, max_px))
    out = {}
    for t, verdicts in taken.items():
        (newest, *_), item = verdicts[0]  # the newest answer's row decides
        if t not in under_id and newest.get("same_as_track") is None and (t not in flagged or item.get("maybe_same_as")):
            out[t] = newest
    return out


def _same_pose(a: Mapping[str, Sequence[float]], b: Mapping[str, Sequence[float]]) -> bool:
    """Whether two poses (translation, rotation as a (w, x, y, z) quaternion, scale) are the same:
    q and -q are one rotation (a half turn, w = 0, may come out with either sign)."""
    close = lambda u, v: np.allclose(u, v, rtol=0, atol=1e-9)  # noqa: E731
    return (close(a["translation"], b["translation"]) and close(a["scale"], b["scale"])
            and (close(a["rotation"], b["rotation"]) or close(a["rotation"], np.negative(b["rotation"]))))


def _overlay_match(item: dict, pose: dict, extents: Mapping[str, Sequence[float]], cameras: Mapping[int, FrameCamera],
                   max_px: float) -> Match | None:
    """Whether (and how well: 1 and minus the shift in px, as a :data:`Match`) a verification item
    (its document) shows, within ``max_px``, the overlays ``pose`` (a ``poses`` row) would be shown
    with now: the same model and mirroring; the identical pose when ``max_px`` is 0 or the model's
    size is unknown, else the overlay moved by at most ``max_px`` on the item's key-frames and the
    pose's own (:func:`overlay_shift_px`)."""
    then = item["pose"]
    if item["cad_id"] != pose["cad_id"] or bool(then["is_mirrored"]) != bool(pose["is_mirrored"]):
        return None
    if _same_pose(then, pose):
        return 1, 0.0
    extent = extents.get(pose["cad_id"])
    stamps = {int(k["timestamp_us"]) for k in item["keyframes"]} | {int(s) for s in pose["keyframe_timestamps_us"] or ()}
    views = [cameras[s] for s in sorted(stamps) if s in cameras]
    if max_px <= 0 or extent is None or not views:
        return None
    shift = overlay_shift_px(extent, then, pose, views)
    return (1, -shift) if shift <= max_px else None
