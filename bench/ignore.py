"""The "ignore region" rule of the synthetic benchmark: the ONE place it is defined.

Used by detection and tracking evaluation (``bench.eval_tracking``). A ground-truth box is
*ignored* (neither a miss when no prediction covers it, nor a target whose prediction counts as a
false positive) when

- the object is mostly hidden: visible fraction < ``MIN_VISIBLE_FRACTION`` (0.3), or
- it is cut off by the image border: truncated fraction > ``MAX_TRUNCATED_FRACTION`` (0.5), or
- its class is not one the detectors are asked to find (``DETECTABLE_CLASSES``: the furniture
  detector's classes, every class the benchmark's rooms hold; the COCO detector is measured on the
  same ground truth, so a cabinet it cannot name is a miss).

Predictions on ignore regions are *dropped* (not counted as false positives). Decision, per frame:
predictions are first matched one-to-one (Hungarian, IoU >= ``IGNORE_IOU``) to the non-ignored
ground-truth boxes (when classes are given, within each class first, then the rest whatever
their class); only the predictions left unmatched are then dropped when they overlap any
ignore box with IoU >= ``IGNORE_IOU`` (an ignore box can absorb several predictions, like COCO's
crowd regions). So a prediction that covers a real object is never thrown away because an ignored
one lies nearby.

Boxes are (ymin, xmin, ymax, xmax), normalised to [0, 1] as in the official ``objects.json``
(IoU does not change when x and y are scaled independently, so pixels work just as well).

The "in view" rule of the dataset's yield (``bench report``), also defined here only: a box is
*in view* when it passes the visibility and truncation tests above (:func:`box_in_view`; the class
is not looked at: a manual track can add an object no detector finds), and a ground-truth object
is *in view* when at least ``MIN_FRAMES_IN_VIEW`` of its boxes are (:func:`objects_in_view`,
:func:`clip_objects_in_view`). Only objects in view are expected in the dataset.
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

from tasks.detection.models.furniture_files import FURNITURE_CLASSES

MIN_VISIBLE_FRACTION = 0.3
"""A ground-truth box whose object is less visible than this (occlusion) is ignored."""

MAX_TRUNCATED_FRACTION = 0.5
"""A ground-truth box whose object has more than this share outside the image is ignored."""

MIN_FRAMES_IN_VIEW = 3
"""Frames with an in-view box an object needs to count as in view (expected in the dataset). Why 3:
the automatic tracker drops tracks of fewer detections (``TrackingConfig.min_detections`` = 3),
and an object seen on one or two frames gives its annotators no choice of key-frames and the pose
solver almost no parallax; such an object is not one the pipeline can be asked to pose."""

IGNORE_IOU = 0.5
"""IoU at which a prediction counts as lying on a (ground-truth or ignore) box."""

DETECTABLE_CLASSES = frozenset(FURNITURE_CLASSES)
"""Class names (tasks/cad/classes.py vocabulary) that the detectors are asked to find."""


def match_pairs(iou: np.ndarray, threshold: float = IGNORE_IOU) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of a one-to-one matching of ``iou`` float[R, C]'s pairs at ``threshold`` or more:
    as many pairs as can be, and of those matchings the one of the largest IoU sum (a pair under the
    threshold never takes the place of two that pass it)."""
    iou = np.asarray(iou, dtype=np.float64)
    if iou.size == 0:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    ok = iou >= threshold
    weight = np.where(ok, 1.0 + iou / (min(iou.shape) + 1), 0.0)  # a pair more outweighs any IoU sum
    rows, cols = linear_sum_assignment(-weight)
    keep = ok[rows, cols]
    return rows[keep], cols[keep]


def is_ignored(class_name: str, visible_fraction: float = 1.0, truncated_fraction: float = 0.0, *,
               detectable: frozenset[str] | set[str] = DETECTABLE_CLASSES,
               min_visible: float = MIN_VISIBLE_FRACTION, max_truncated: float = MAX_TRUNCATED_FRACTION) -> bool:
    """Whether one ground-truth box is an ignore region.

    ``class_name``: the human-readable class ("chair"), not the ShapeNet synset;
    ``visible_fraction``: share of the object's projection not hidden by other objects, in [0, 1];
    ``truncated_fraction``: share of the object's projection outside the image, in [0, 1].
    """
    return (not box_in_view(visible_fraction, truncated_fraction, min_visible=min_visible, max_truncated=max_truncated)
            or class_name not in detectable)


def box_in_view(visible_fraction: float, truncated_fraction: float, *, min_visible: float = MIN_VISIBLE_FRACTION,
                max_truncated: float = MAX_TRUNCATED_FRACTION) -> bool:
    """Whether one ground-truth box shows its object well enough to annotate: visible fraction
    at least ``min_visible`` and truncated fraction at most ``max_truncated`` (fractions in [0, 1])."""
    return visible_fraction >= min_visible and truncated_fraction <= max_truncated


def objects_in_view(boxes: Iterable[tuple[str, float, float]], min_frames: int = MIN_FRAMES_IN_VIEW) -> set[str]:
    """The objects in view among ``boxes``: (object id, visible fraction, truncated fraction), one
    per frame the object has a ground-truth box on; an object is in view with at least
    ``min_frames`` boxes in view (:func:`box_in_view`)."""
    frames: Counter[str] = Counter(obj for obj, visible, truncated in boxes if box_in_view(visible, truncated))
    return {obj for obj, n in frames.items() if n >= min_frames}


def box_fractions(bench_dir: Path, clip: str) -> dict[tuple[int, str], tuple[float, float]]:
    """(camera timestamp, ground-truth track id) -> (visible fraction, truncated fraction) of every
    box of the benchmark clip, from its ``visibility.json``. A box missing there is neither visible
    nor in the image: look it up with ``.get(key, (0.0, 1.0))``."""
    visibility = json.loads((Path(bench_dir) / clip / "visibility.json").read_text())
    return {(f["timestamp"], o["track_id"]): (o["visible_fraction"], o["truncated_fraction"])
            for f in visibility["frames"] for o in f["objects"]}


def clip_objects_in_view(bench_dir: Path, clip: str, min_frames: int = MIN_FRAMES_IN_VIEW) -> set[str]:
    """Ground-truth track ids of the benchmark clip's objects in view, from its ``objects.json``
    (the boxes) and ``visibility.json`` (their fractions, :func:`box_fractions`)."""
    from schemas.official import read_objects

    fractions = box_fractions(bench_dir, clip)
    boxes = [(obj.track_id, *fractions.get((e.timestamp, obj.track_id), (0.0, 1.0)))
             for obj in read_objects(Path(bench_dir) / clip / "objects.json").objects for e in obj.track]
    return objects_in_view(boxes, min_frames)


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of boxes float[N, 4] x float[M, 4] (ymin, xmin, ymax, xmax) -> float[N, M] (0 for empty boxes)."""
    a = np.asarray(a, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 4)
    y0 = np.maximum(a[:, None, 0], b[None, :, 0])
    x0 = np.maximum(a[:, None, 1], b[None, :, 1])
    y1 = np.minimum(a[:, None, 2], b[None, :, 2])
    x1 = np.minimum(a[:, None, 3], b[None, :, 3])
    inter = np.clip(y1 - y0, 0, None) * np.clip(x1 - x0, 0, None)
    area_a = np.clip(a[:, 2] - a[:, 0], 0, None) * np.clip(a[:, 3] - a[:, 1], 0, None)
    area_b = np.clip(b[:, 2] - b[:, 0], 0, None) * np.clip(b[:, 3] - b[:, 1], 0, None)
    union = area_a[:, None] + area_b[None, :] - inter
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(union > 0, inter / union, 0.0)


def predictions_to_drop(pred_boxes: np.ndarray, gt_boxes: np.ndarray, gt_ignore: np.ndarray,
                        iou_threshold: float = IGNORE_IOU, pred_classes: Sequence[str] | None = None,
                        gt_classes: Sequence[str] | None = None) -> np.ndarray:
    """Which predictions of ONE frame lie on ignore regions and must be dropped.

    ``pred_boxes`` float[M, 4]; ``gt_boxes`` float[N, 4]; ``gt_ignore`` bool[N]; ``pred_classes``
    and ``gt_classes`` (M and N names, both or neither): predictions are matched to the boxes in
    view of their own class first, then the others to the boxes in view left, whatever their
    class (class-agnostic alone, a chair box on a hidden chair under a table took the table's
    match from the table box, which was dropped: a miss and a false positive; class-aware alone, a
    sofa box on a table in view beside a hidden chair was dropped, no false positive).
    Returns bool[M]: True for a prediction that is matched (Hungarian, IoU >= threshold) to no
    non-ignored ground-truth box and overlaps some ignore box with IoU >= threshold.
    """
    pred_boxes = np.asarray(pred_boxes, dtype=np.float64).reshape(-1, 4)
    gt_boxes = np.asarray(gt_boxes, dtype=np.float64).reshape(-1, 4)
    gt_ignore = np.asarray(gt_ignore, dtype=bool).reshape(-1)
    drop = np.zeros(len(pred_boxes), dtype=bool)
    if len(pred_boxes) == 0 or not gt_ignore.any():
        return drop
    matched = np.zeros(len(pred_boxes), dtype=bool)
    valid = gt_boxes[~gt_ignore]
    taken = np.zeros(len(valid), dtype=bool)
    if pred_classes is not None and gt_classes is not None:
        pred_cls = np.asarray(list(pred_classes), object)
        valid_cls = np.asarray(list(gt_classes), object)[~gt_ignore]
        for c in set(valid_cls.tolist()):
            preds, gts = np.flatnonzero(pred_cls == c), np.flatnonzero(valid_cls == c)
            rows, cols = match_pairs(box_iou(valid[gts], pred_boxes[preds]), iou_threshold)
            matched[preds[cols]], taken[gts[rows]] = True, True
    preds, gts = np.flatnonzero(~matched), np.flatnonzero(~taken)
    _, cols = match_pairs(box_iou(valid[gts], pred_boxes[preds]), iou_threshold)
    matched[preds[cols]] = True
    on_ignore = (box_iou(gt_boxes[gt_ignore], pred_boxes) >= iou_threshold).any(axis=0)
    return on_ignore & ~matched
