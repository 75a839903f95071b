"""The tracking stage's pair cues: its hand-binned likelihood ratios against a scikit-learn fit (issue 18).

    python -m bench.cue_compare --warehouse DIR --train BENCH_DIR... --test BENCH_DIR...

Pairs of detector boxes at most ``[tracking] window`` frames apart, both matched to a ground-truth
object (:func:`bench.track_bench.features_of` with ``matched_only``, as ``track_bench fit --source
detector`` takes them), one object or two. Scored on the ``--test`` folders' pairs:

- ``binned``: the edge log-odds of :func:`tasks.tracking.affinity.affinities` with the stored
  calibration (:mod:`tasks.tracking.calibration`; its ``training_seeds`` say what it was fitted on);
- ``binned_refit``: the same tables refitted on the ``--train`` folders (``fit_calibration``);
- ``logistic``: scikit-learn's LogisticRegression on :func:`cue_matrix`, fitted on the ``--train`` folders.

Each as log-loss (of sigmoid(log-odds)) and ROC AUC on the matched pairs, and as tracks: the clips'
detections (all of them) partitioned with each model's edge log-odds (no 3D joining), counted as
:func:`bench.merge_bench.tracking_counts` counts them. Nothing is written.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from bench.benchmark import read_manifest
from bench.track_bench import detector_clip, features_of, open_warehouse
from cadestate.config import TrackingConfig
from tasks.tracking.affinity import PairFeatures, affinities, fit_calibration


def cue_matrix(p: PairFeatures) -> np.ndarray:
    """float[P,8]: cosine, cosine^2, same label, IoU, IoU^2, log gap, IoU x log gap, cosine x IoU."""
    lg = np.log(p.gap.astype(float))
    return np.stack([p.cosine, p.cosine**2, p.same_label.astype(float), p.iou, p.iou**2, lg, p.iou * lg, p.cosine * p.iou], 1)


def partition_counts(wh, bench_dirs: list[Path], edge_log_odds) -> dict:
    """Tracks of every clip partitioned with ``edge_log_odds(PairFeatures) -> float[P]`` (window and
    min_detections of ``[tracking]``), counted against ground truth."""
    from collections import Counter

    from bench.ignore import clip_objects_in_view
    from bench.merge_bench import tracking_counts
    from tasks.tracking.affinity import pair_features
    from tasks.tracking.partition import solve
    from tasks.tracking.tracking import Tracking

    cfg, total = TrackingConfig(), Counter()
    for d in bench_dirs:
        for clip in read_manifest(d).clips:
            cb = detector_clip(wh, d, clip)
            p = pair_features(cb.frame_index, cb.boxes, cb.labels, cb.vectors, cb.cameras, cfg.window)
            w = edge_log_odds(p)
            lab = solve(len(cb.det_id), p.a, p.b, w, groups=cb.frame_index, keys=cb.det_id, refine_result=cfg.refine)
            kept = np.bincount(lab)[lab] >= cfg.min_detections
            track = np.where(kept, np.unique(lab, return_inverse=True)[1], -1)
            total += tracking_counts(Tracking(track, p, w), cb, clip_objects_in_view(d, clip))
    return {**dict(total), "tracks_per_object": round(total["on_objects"] / max(total["objects_found"], 1), 3)}


def folder_pairs(wh, bench_dirs: list[Path]) -> tuple[list[PairFeatures], list[np.ndarray]]:
    feats, truth = [], []
    for d in bench_dirs:
        for clip in read_manifest(d).clips:
            cb = detector_clip(wh, d, clip)
            if cb is None:
                raise ValueError(f"{wh.root}: clip {clip} has no detections or descriptors")
            p, y = features_of(cb, TrackingConfig().window, matched_only=True)
            feats.append(p), truth.append(y)
    return feats, truth


def _scores(y: np.ndarray, log_odds: np.ndarray) -> dict:
    from sklearn.metrics import log_loss, roc_auc_score

    p = 1.0 / (1.0 + np.exp(-np.clip(log_odds, -30, 30)))
    return {"log_loss": round(float(log_loss(y, p, labels=[0, 1])), 4), "roc_auc": round(float(roc_auc_score(y, log_odds)), 4)}


def compare(wh, train: list[Path], test: list[Path]) -> dict:
    """Scores of the three models on the ``test`` folders' pairs (module docstring)."""
    from sklearn.linear_model import LogisticRegression
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    from tasks.tracking.calibration import CALIBRATION

    tr_f, tr_y = folder_pairs(wh, train)
    te_f, te_y = folder_pairs(wh, test)
    y = np.concatenate(te_y)
    cat = lambda fs: PairFeatures(*(np.concatenate([getattr(f, k) for f in fs]) for k in  # noqa: E731
                                    ("a", "b", "gap", "cosine", "same_label", "iou")))
    test_p = cat(te_f)
    lr = make_pipeline(StandardScaler(), LogisticRegression(C=1.0, max_iter=2000))
    lr.fit(cue_matrix(cat(tr_f)), np.concatenate(tr_y))
    refit = fit_calibration(tr_f, tr_y)
    models = {"binned": lambda p: affinities(p, CALIBRATION), "binned_refit": lambda p: affinities(p, refit),
              "logistic": lambda p: lr.decision_function(cue_matrix(p))}
    return {"train_seeds": [read_manifest(d).seed for d in train], "test_seeds": [read_manifest(d).seed for d in test],
            "test_pairs": len(y), "test_one_object": int(y.sum()),
            **{name: {**_scores(y, f(test_p)), "tracks": partition_counts(wh, test, f)} for name, f in models.items()}}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.cue_compare", description=__doc__.splitlines()[0])
    ap.add_argument("--train", nargs="+", type=Path, required=True)
    ap.add_argument("--test", nargs="+", type=Path, required=True)
    ap.add_argument("--warehouse", default=None, help="warehouse of the clips' pipeline tables (default: the configured one)")
    args = ap.parse_args(argv)
    print(json.dumps(compare(open_warehouse(args.warehouse), args.train, args.test), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
