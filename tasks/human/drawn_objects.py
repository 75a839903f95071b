"""The drawn objects of a manual-track label, against each other and the task's tracks (part of
:func:`tasks.human.labels.check_label`): each object drawn once (:func:`check_drawn_once`: an
error), and none drawn over an existing track without saying it is that track
(:func:`drawn_over_tracks`: a warning).

Boxes: (ymin, xmin, ymax, xmax), normalised by the image's height and width.
"""

from __future__ import annotations

import numpy as np

from schemas.labels import Label, Task
from tasks.human.clicks_in_force import SAME_OBJECT_IOU, box_iou
from tasks.human.label_format import field_error, json_path


def _same_drawing(a, b) -> bool:
    """Whether two drawn objects are one: the same class and, on every frame both have a box (at
    least one), boxes overlapping by IoU >= 0.9."""
    mine = {x.timestamp_us: x.box for x in a.boxes}
    shared = [x for x in b.boxes if x.timestamp_us in mine]
    return a.label == b.label and bool(shared) and all(box_iou(mine[x.timestamp_us], x.box) >= 0.9 for x in shared)


def check_drawn_once(label: Label, name: str) -> None:
    """Refuse a manual-track answer naming one object twice (a repeated ``source_id``, two drawings
    of one object, two objects each 'track N'): each would become a manual track of its own. Only
    objects of one class with a box on one frame are compared (every pair was: 8 s for 4,000 objects,
    a tool export of single-box tracks)."""
    sources: dict[str, int] = {}
    tracks: dict[int, int] = {}
    on_frame: dict[tuple[str, int], tuple[list[int], list]] = {}
    for i, a in enumerate(label.answers):
        if a.source_id is not None and (j := sources.setdefault(a.source_id, i)) != i:
            raise field_error(name, ["answers", i, "source_id"], f"{a.source_id!r} is also answers[{j}]'s")
        if a.same_as_track is not None and (j := tracks.setdefault(a.same_as_track, i)) != i:
            raise field_error(name, ["answers", i, "same_as_track"], f"answers[{j}] is track {a.same_as_track} too: "
                                                                     "one drawn object per track")
        near = sorted({j for x in a.boxes for j in _overlapping(on_frame.get((a.label, x.timestamp_us)), x.box)})
        if (j := next((j for j in near if _same_drawing(a, label.answers[j])), None)) is not None:
            raise field_error(name, ["answers", i], f"the same object as answers[{j}] (class {a.label!r}, boxes overlapping "
                                                    "by IoU >= 0.9 on every frame both have)")
        for x in a.boxes:
            ids, boxes = on_frame.setdefault((a.label, x.timestamp_us), ([], []))
            ids.append(i)
            boxes.append(x.box)


def drawn_over_tracks(label: Label, task: Task, name: str) -> list[str]:
    """Warnings of a manual-track label: a drawn object, not said to be a track, whose boxes overlap
    an existing track's of the task by IoU >= :data:`SAME_OBJECT_IOU` on every key-frame both have a
    box (one at least): most likely that track drawn again, which would become a second track of
    the object, asked about and posed twice."""
    tracks = {t.track_id: {b.timestamp_us: b.box for b in t.boxes} for t in task.existing_tracks}
    shown: dict[int, list[tuple[int, tuple]]] = {}  # timestamp -> (track, its box there)
    for t, boxes in tracks.items():
        for ts, box in boxes.items():
            shown.setdefault(ts, []).append((t, box))
    out = []
    for i, a in enumerate(label.answers):
        if a.same_as_track is not None:
            continue
        near = sorted({t for x in a.boxes for t, box in shown.get(x.timestamp_us, ()) if box_iou(box, x.box) >= SAME_OBJECT_IOU})
        for t in near:
            if all(box_iou(tracks[t][x.timestamp_us], x.box) >= SAME_OBJECT_IOU for x in a.boxes if x.timestamp_us in tracks[t]):
                out.append(f"{name}: {json_path(['answers', i])}: its boxes overlap track {t}'s on every key-frame both "
                           f"have (IoU >= {SAME_OBJECT_IOU:g}): if it is that object, say \"same_as_track\": {t} (or leave it "
                           "out: it is tracked), else it becomes a second track of it")
                break
    return out


def _overlapping(drawn: tuple[list[int], list] | None, box) -> list[int]:
    """The objects of ``drawn`` (their indices, and their boxes on one frame) whose box there
    overlaps ``box`` by IoU >= 0.9: those that may be its drawing (all at once, not one by one)."""
    if not drawn:
        return []
    ids, boxes = drawn
    b, q = np.asarray(boxes, np.float64), np.asarray(box, np.float64)
    inter = (np.clip(np.minimum(b[:, 2], q[2]) - np.maximum(b[:, 0], q[0]), 0, None)
             * np.clip(np.minimum(b[:, 3], q[3]) - np.maximum(b[:, 1], q[1]), 0, None))
    union = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1]) + (q[2] - q[0]) * (q[3] - q[1]) - inter
    return [ids[k] for k in np.flatnonzero(inter >= 0.9 * union - 1e-12)]
