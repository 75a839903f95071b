"""Tracking and detection metrics: HOTA, MOTA, IDF1, ID switches, detection precision/recall.

The metrics themselves come from TrackEval (``trackeval==1.3.0``, the MOTChallenge / HOTA
authors' reference code; NumPy 2 clean, no patch needed): ``trackeval.metrics.HOTA``,
``CLEAR`` (MOTA, MOTP, IDSW, CLR_Pr / CLR_Re) and ``Identity`` (IDF1, IDP, IDR) are fed
directly with per-frame IoU matrices (no dataset files). CLEAR and Identity match at
IoU >= ``iou_threshold`` (0.5); HOTA averages over its own IoU thresholds 0.05..0.95.

The ignore rule (``bench.ignore``) is applied first: ignore ground-truth boxes are removed and
the predictions that lie on them (and match no real object) are dropped.

Boxes are (ymin, xmin, ymax, xmax), normalised (as in ``objects.json``) or pixels, consistently.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from bench.ignore import IGNORE_IOU, box_iou, predictions_to_drop
from schemas.official import ObjectsFile


@dataclass(frozen=True)
class TrackBox:
    """One box of one track on one frame (``frame``: any int key, e.g. the timestamp in µs).
    ``ignore`` is only meaningful for ground truth (see ``bench.ignore.is_ignored``)."""

    frame: int
    track_id: str
    box: tuple[float, float, float, float]
    ignore: bool = False


def boxes_from_objects(objects: ObjectsFile, ignore=None) -> list[TrackBox]:
    """The track boxes of an official ``objects.json``, keyed by timestamp. ``ignore``: optional
    function (ObjectAnnotation, TrackEntry) -> bool that flags ground-truth ignore boxes."""
    return [TrackBox(t.timestamp, o.track_id, t.box, bool(ignore(o, t)) if ignore else False)
            for o in objects.objects for t in o.track]


@dataclass(frozen=True)
class TrackingReport:
    """Scores in [0, 1] (MOTA can be negative); counts after the ignore rule."""

    hota: float
    deta: float
    assa: float
    loca: float
    mota: float
    motp: float
    idf1: float
    idp: float
    idr: float
    id_switches: int
    precision: float
    recall: float
    true_positives: int
    false_positives: int
    misses: int
    num_gt_boxes: int
    num_pred_boxes: int
    ignored_gt_boxes: int
    dropped_pred_boxes: int

    def as_dict(self) -> dict:
        return asdict(self)


def apply_ignore(gt: Sequence[TrackBox], pred: Sequence[TrackBox], iou_threshold: float = IGNORE_IOU
                 ) -> tuple[list[TrackBox], list[TrackBox], int, int]:
    """Remove ignore ground-truth boxes and the predictions on them, frame by frame.
    Returns (kept gt, kept predictions, number of ignored gt boxes, number of dropped predictions)."""
    gt_by_frame: dict[int, list[TrackBox]] = defaultdict(list)
    for b in gt:
        gt_by_frame[b.frame].append(b)
    pred_by_frame: dict[int, list[TrackBox]] = defaultdict(list)
    for b in pred:
        pred_by_frame[b.frame].append(b)
    kept_pred: list[TrackBox] = []
    for frame, boxes in pred_by_frame.items():
        g = gt_by_frame.get(frame, [])
        drop = predictions_to_drop(np.array([b.box for b in boxes]), np.array([b.box for b in g]).reshape(-1, 4),
                                   np.array([b.ignore for b in g], dtype=bool), iou_threshold)
        kept_pred += [b for b, d in zip(boxes, drop) if not d]
    kept_gt = [b for b in gt if not b.ignore]
    return kept_gt, kept_pred, len(gt) - len(kept_gt), len(pred) - len(kept_pred)


def _check_unique(boxes: Sequence[TrackBox], what: str) -> None:
    seen = set()
    for b in boxes:
        if (b.frame, b.track_id) in seen:
            raise ValueError(f"{what}: track {b.track_id!r} has two boxes on frame {b.frame}")
        seen.add((b.frame, b.track_id))


def trackeval_data(gt: Sequence[TrackBox], pred: Sequence[TrackBox]) -> dict:
    """The per-sequence ``data`` dict that TrackEval's metrics read: contiguous 0-based ids, one
    entry per frame (sorted union of frames), similarity = IoU float[n_gt_t, n_pred_t]."""
    frames = sorted({b.frame for b in gt} | {b.frame for b in pred})
    gt_ids = {tid: i for i, tid in enumerate(sorted({b.track_id for b in gt}))}
    pred_ids = {tid: i for i, tid in enumerate(sorted({b.track_id for b in pred}))}
    g_f: dict[int, list[TrackBox]] = defaultdict(list)
    p_f: dict[int, list[TrackBox]] = defaultdict(list)
    for b in gt:
        g_f[b.frame].append(b)
    for b in pred:
        p_f[b.frame].append(b)
    data = {"num_timesteps": len(frames), "num_gt_ids": len(gt_ids), "num_tracker_ids": len(pred_ids),
            "num_gt_dets": len(gt), "num_tracker_dets": len(pred), "gt_ids": [], "tracker_ids": [],
            "similarity_scores": []}
    for f in frames:
        g, p = g_f.get(f, []), p_f.get(f, [])
        data["gt_ids"].append(np.array([gt_ids[b.track_id] for b in g], dtype=int))
        data["tracker_ids"].append(np.array([pred_ids[b.track_id] for b in p], dtype=int))
        data["similarity_scores"].append(box_iou(np.array([b.box for b in g]).reshape(-1, 4),
                                                 np.array([b.box for b in p]).reshape(-1, 4)))
    return data


def _metrics(iou_threshold: float):
    from trackeval.metrics import CLEAR, HOTA, Identity  # imported lazily: heavy (matplotlib, cv2)

    config = {"THRESHOLD": iou_threshold, "PRINT_CONFIG": False}
    return HOTA(), CLEAR(dict(config)), Identity(dict(config))


def evaluate_tracking_clips(clips: Iterable[tuple[Sequence[TrackBox], Sequence[TrackBox]]],
                            iou_threshold: float = IGNORE_IOU) -> TrackingReport:
    """Tracking metrics over several clips ((ground truth, predictions) per clip); per-clip
    results are combined by TrackEval's ``combine_sequences`` (counts summed, then scores)."""
    hota, clear, ident = _metrics(iou_threshold)
    res: dict[str, dict[str, dict]] = {"hota": {}, "clear": {}, "identity": {}}
    ignored = dropped = n_gt = n_pred = 0
    for i, (gt, pred) in enumerate(clips):
        _check_unique(gt, "ground truth")
        _check_unique(pred, "predictions")
        g, p, ig, dr = apply_ignore(gt, pred, iou_threshold)
        ignored, dropped, n_gt, n_pred = ignored + ig, dropped + dr, n_gt + len(g), n_pred + len(p)
        data = trackeval_data(g, p)
        for name, metric in (("hota", hota), ("clear", clear), ("identity", ident)):
            res[name][str(i)] = metric.eval_sequence(data)
    if not res["hota"]:
        raise ValueError("no clips to evaluate")
    h = hota.combine_sequences(res["hota"])
    c = clear.combine_sequences(res["clear"])
    d = ident.combine_sequences(res["identity"])
    return TrackingReport(
        hota=float(np.mean(h["HOTA"])), deta=float(np.mean(h["DetA"])), assa=float(np.mean(h["AssA"])),
        loca=float(np.mean(h["LocA"])), mota=float(c["MOTA"]), motp=float(c["MOTP"]), idf1=float(d["IDF1"]),
        idp=float(d["IDP"]), idr=float(d["IDR"]), id_switches=int(c["IDSW"]), precision=float(c["CLR_Pr"]),
        recall=float(c["CLR_Re"]), true_positives=int(c["CLR_TP"]), false_positives=int(c["CLR_FP"]),
        misses=int(c["CLR_FN"]), num_gt_boxes=n_gt, num_pred_boxes=n_pred, ignored_gt_boxes=ignored,
        dropped_pred_boxes=dropped)


def evaluate_tracking(gt: Sequence[TrackBox], pred: Sequence[TrackBox], iou_threshold: float = IGNORE_IOU
                      ) -> TrackingReport:
    """Tracking metrics of one clip (see ``evaluate_tracking_clips``)."""
    return evaluate_tracking_clips([(gt, pred)], iou_threshold)
