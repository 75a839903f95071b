"""Evaluators of the synthetic benchmark: one entry point over the evaluation modules.

- ``bench.ignore``: the ignore-region rule (occluded / truncated / non-COCO ground truth);
- ``bench.eval_pose``: Scan2CAD 9-DoF pose accuracy (instance and class mean);
- ``bench.eval_tracking``: HOTA, MOTA, IDF1, ID switches, detection precision/recall (TrackEval);
- ``bench.eval_retrieval``: CAD model / class recall@1 and @10;
- ``bench.stats``: dataset statistics as in the paper's Table 2.

``evaluate_clips`` scores a set of predicted ``objects.json`` against the ground truth's.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from bench.eval_pose import (PosedObject, PoseReport, is_correct, match_and_score, posed_objects,
                             rotation_error_deg, scale_error_pct, symmetry_order, translation_error)
from bench.eval_retrieval import RetrievalReport, retrieval_recall
from bench.eval_tracking import (TrackBox, TrackingReport, apply_ignore, boxes_from_objects, evaluate_tracking,
                                 evaluate_tracking_clips)
from bench.ignore import DETECTABLE_CLASSES, box_iou, is_ignored, predictions_to_drop
from bench.stats import dataset_statistics, statistics_markdown
from schemas.official import ObjectAnnotation, ObjectsFile, TrackEntry

__all__ = [
    "DETECTABLE_CLASSES", "PoseReport", "PosedObject", "RetrievalReport", "TrackBox", "TrackingReport", "apply_ignore",
    "box_iou", "boxes_from_objects", "dataset_statistics", "evaluate_clips", "evaluate_tracking",
    "evaluate_tracking_clips", "is_correct", "is_ignored", "match_and_score", "posed_objects",
    "predictions_to_drop", "retrieval_recall", "rotation_error_deg", "scale_error_pct", "statistics_markdown",
    "symmetry_order", "translation_error",
]


def evaluate_clips(pairs: Sequence[tuple[ObjectsFile, ObjectsFile]], symmetries=None,
                   gt_ignore: Callable[[ObjectAnnotation, TrackEntry], bool] | None = None,
                   match: str = "track", tracking: bool = True) -> dict:
    """Pose accuracy and (optionally) tracking metrics for (ground truth, prediction) objects.json
    pairs of the same clips. ``symmetries``: cad_id -> order (see ``match_and_score``);
    ``gt_ignore(object, track_entry)``: flags ignore boxes (build it with ``is_ignored``)."""
    for gt, pred in pairs:
        if gt.clip_name != pred.clip_name:
            raise ValueError(f"ground truth of {gt.clip_name!r} paired with predictions of {pred.clip_name!r}")
    gts = [o for gt, _ in pairs for o in posed_objects(gt)]
    preds = [o for _, pred in pairs for o in posed_objects(pred)]
    result = {"pose": match_and_score(preds, gts, symmetries, match).as_dict()}
    if tracking:
        clips = [(boxes_from_objects(gt, gt_ignore), boxes_from_objects(pred)) for gt, pred in pairs]
        result["tracking"] = evaluate_tracking_clips(clips).as_dict()
    return result
