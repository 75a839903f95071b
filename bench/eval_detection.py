"""Per-class detection recall and precision at IoU 0.5 on the synthetic benchmark.

Detector labels are the furniture detector's class names or COCO names; ground-truth classes are
the CAD vocabulary (:mod:`tasks.cad.classes`); :func:`tasks.cad.classes.class_of_label` says which
label stands for which class. Per frame:

1. predictions on ignore regions are dropped (:func:`bench.ignore.predictions_to_drop`, the one
   ignore rule, its matching within each class);
2. per class, predictions whose label maps to it are matched one-to-one (Hungarian on IoU,
   IoU >= 0.5) to the non-ignored ground-truth boxes of that class: true positives;
3. unmatched non-ignored ground truth is a miss of its class; an unmatched kept prediction is a
   false positive of the class its label maps to (or of ``"(other label)"`` when it maps to none).

``class-agnostic`` recall matches any label to any class (the detector found *something* there),
which separates localisation from naming.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from bench.ignore import IGNORE_IOU, box_iou, match_pairs, predictions_to_drop
from tasks.cad.classes import class_of_label

OTHER = "(other label)"


@dataclass(frozen=True)
class FrameBoxes:
    """One frame: ground truth boxes float[N,4], classes [N], ignore bool[N]; predictions float[M,4]
    and labels [M] (detector names). Boxes (ymin, xmin, ymax, xmax) normalised."""

    gt_boxes: np.ndarray
    gt_classes: Sequence[str]
    gt_ignore: np.ndarray
    pred_boxes: np.ndarray
    pred_labels: Sequence[str]


def _match(iou: np.ndarray) -> int:
    """Size of the largest one-to-one matching with IoU >= IGNORE_IOU (:func:`bench.ignore.match_pairs`)."""
    return len(match_pairs(iou, IGNORE_IOU)[0])


def evaluate_detections(frames: Iterable[FrameBoxes]) -> dict:
    """Counts and rates per class, overall, and class-agnostic (see module docstring)."""
    tp, gt_n, pred_n = Counter(), Counter(), Counter()
    agnostic_tp = 0
    for f in frames:
        named = np.array([class_of_label(label) or OTHER for label in f.pred_labels], dtype=object)
        keep = ~predictions_to_drop(f.pred_boxes, f.gt_boxes, f.gt_ignore, pred_classes=named, gt_classes=f.gt_classes)
        pred_boxes = np.asarray(f.pred_boxes, np.float64).reshape(-1, 4)[keep]
        pred_cls = named[keep]
        valid = ~np.asarray(f.gt_ignore, bool)
        gt_boxes = np.asarray(f.gt_boxes, np.float64).reshape(-1, 4)[valid]
        gt_cls = np.array(list(f.gt_classes), dtype=object)[valid]
        gt_n.update(gt_cls.tolist())
        pred_n.update(pred_cls.tolist())
        agnostic_tp += _match(box_iou(gt_boxes, pred_boxes))
        for c in set(gt_cls.tolist()):
            tp[c] += _match(box_iou(gt_boxes[gt_cls == c], pred_boxes[pred_cls == c]))
    classes = sorted(set(gt_n) | set(pred_n))
    per_class = {c: {"ground_truth": gt_n[c], "predictions": pred_n[c], "true_positives": tp[c],
                     "recall": round(tp[c] / gt_n[c], 4) if gt_n[c] else None,
                     "precision": round(tp[c] / pred_n[c], 4) if pred_n[c] else None} for c in classes}
    total_gt, total_pred, total_tp = sum(gt_n.values()), sum(pred_n.values()), sum(tp.values())
    return {
        "iou": IGNORE_IOU,
        "recall": round(total_tp / total_gt, 4) if total_gt else None,
        "precision": round(total_tp / total_pred, 4) if total_pred else None,
        "class_agnostic_recall": round(agnostic_tp / total_gt, 4) if total_gt else None,
        "ground_truth": total_gt, "predictions": total_pred, "per_class": per_class,
    }
