"""Joining track fragments in 3D (issue 18, :mod:`tasks.tracking.merge`): fit its model, measure it.

    python -m bench.merge_bench fit --warehouse DIR BENCH_DIR...    # rewrite tasks/tracking/merge_calibration.py
    python -m bench.merge_bench eval --warehouse DIR BENCH_DIR...   # tracks per object before / after, JSON

Each benchmark folder's clips must have run ``frames``, ``detect`` and ``embed`` in the warehouse
(``cadestate bench run``, or ``cadestate ingest`` of the folder). Detections get their ground-truth
object as the tracking benchmark matches them (:func:`bench.track_bench.detector_clip`: IoU >= 0.5),
a track the object most (more than half) of its detections match.

``fit``: the partition's fragments of every clip (``[tracking]`` defaults, no joining, nothing
dropped); every two fragments with no frame in common that both follow an object are a pair, one
object or two; a logistic regression (scikit-learn, standardised cues :data:`tasks.tracking.merge.CUES`)
is fitted on them and written with the seeds of the folders it saw.

``eval``: per clip, the tracking stage as it was (no joining, no thin rule) and as it is, both
from the same detections; counts tracks, tracks on no object, tracks per object (tracks on an
object in view / objects in view found, :func:`bench.ignore.clip_objects_in_view`), objects split over
two or more tracks, and objects a track followed before that no track follows after (lost to a
wrong join or to the thin rule).
Also the log-loss and ROC AUC of the model on the folders' pairs, against the cue most like the old
rule (appearance alone, as a one-cue logistic fit) for scale.
"""

from __future__ import annotations

import argparse
import json
import pprint
import sys
from collections import Counter
from dataclasses import replace
from pathlib import Path

import numpy as np

from bench.benchmark import read_manifest
from bench.ignore import clip_objects_in_view
from bench.track_bench import ClipBoxes, detector_clip, open_warehouse
from cadestate.config import TrackingConfig
from tasks.tracking.affinity import centred
from tasks.tracking.merge import CUES, MergeModel, compatible, make_fragment, pair_cues
from tasks.tracking.tracking import Geometry, Tracking, read_cameras, read_geometry, track_detections

CALIBRATION_FILE = Path(__file__).resolve().parent.parent / "tasks" / "tracking" / "merge_calibration.py"


def clip_inputs(wh, bench_dir: Path, clip: str) -> tuple[ClipBoxes, Geometry]:
    """The clip's detections with their ground truth, and the geometry the tracking stage sees."""
    cb = detector_clip(wh, bench_dir, clip)
    if cb is None:
        raise ValueError(f"{wh.root}: clip {clip} has no detections or descriptors (run its detect and embed stages)")
    geometry = read_geometry(wh, clip, read_cameras(wh, clip), cb.frame_index, cb.boxes, 6)
    return cb, geometry


def run_tracking(cb: ClipBoxes, geometry: Geometry | None, cfg: TrackingConfig, model: MergeModel | None = None) -> Tracking:
    """The tracking stage's result on the clip (``geometry`` None: as it was before joining in 3D)."""
    return track_detections(cb.det_id, cb.frame_index, cb.boxes, cb.labels, cb.vectors, cb.cameras, cfg,
                            scores=cb.scores, geometry=geometry, merge_model=model)


def track_objects(track: np.ndarray, truth: np.ndarray) -> dict[int, str]:
    """Track id -> its ground-truth object ("" when no object has more than half its detections)."""
    out = {}
    for t in np.unique(track[track >= 0]):
        best, count = Counter(truth[track == t].tolist()).most_common(1)[0]
        out[int(t)] = best if best and 2 * count > int(np.sum(track == t)) else ""
    return out


def fragment_pairs(cb: ClipBoxes, geometry: Geometry) -> tuple[np.ndarray, np.ndarray]:
    """Cues float[P,6] and truth bool[P] of the pairs of the partition's fragments that both follow an object."""
    cfg = replace(TrackingConfig(), merge=False, min_detections=1, thin_detections=1, shadow_iou=1.0, min_track_score=0.0)
    result = run_tracking(cb, geometry, cfg)
    objects = track_objects(result.track, cb.truth)
    looks = centred(cb.vectors)
    frags = {t: make_fragment(np.flatnonzero(result.track == t), cb.frame_index, cb.labels, cb.scores, looks, geometry.rays)
             for t, o in objects.items() if o}
    ids = sorted(frags)
    x, y = [], []
    for i, a in enumerate(ids):
        for b in ids[i + 1:]:
            if compatible(frags[a], frags[b]):
                x.append(pair_cues(frags[a], frags[b]))
                y.append(objects[a] == objects[b])
    return np.asarray(x, float).reshape(-1, len(CUES)), np.asarray(y, bool)


def all_pairs(wh, bench_dirs: list[Path]) -> tuple[np.ndarray, np.ndarray]:
    xs, ys = [], []
    for d in bench_dirs:
        for clip in read_manifest(d).clips:
            x, y = fragment_pairs(*clip_inputs(wh, d, clip))
            xs.append(x), ys.append(y)
    return np.concatenate(xs), np.concatenate(ys)


def fit(wh, bench_dirs: list[Path], write: bool = True) -> dict:
    """Fit the logistic model on the pairs of ``bench_dirs`` (module docstring); rewrite the module."""
    from sklearn.linear_model import LogisticRegression
    from sklearn.preprocessing import StandardScaler

    x, y = all_pairs(wh, bench_dirs)
    scaler = StandardScaler().fit(x)
    lr = LogisticRegression(C=1.0, max_iter=1000).fit(scaler.transform(x), y)
    seeds = [read_manifest(d).seed for d in bench_dirs]
    cal = {"cues": list(CUES), "mean": scaler.mean_.round(6).tolist(), "scale": scaler.scale_.round(6).tolist(),
           "coef": lr.coef_[0].round(6).tolist(), "intercept": round(float(lr.intercept_[0]), 6),
           "pairs": {"one_object": int(y.sum()), "two_objects": int((~y).sum())},
           "training_seeds": seeds,
           "fitted_on": f"fragment pairs of {sum(len(read_manifest(d).clips) for d in bench_dirs)} benchmark clips "
                        f"(seeds {', '.join(map(str, seeds))}), scikit-learn LogisticRegression(C=1) on standardised cues"}
    if write:
        CALIBRATION_FILE.write_text(
            '"""Fitted model of the fragment-joining cues (see tasks/tracking/merge.py). Generated by\n'
            '``python -m bench.merge_bench fit --warehouse DIR BENCH_DIR...`` (the folders\' clips must have run detect and\n'
            'embed in that warehouse); the benchmark seeds it saw are ``training_seeds``. Do not edit by hand."""\n\n'
            f'MERGE_CALIBRATION = {pprint.pformat(cal, width=110, sort_dicts=False)}\n')
    return cal


def tracking_counts(result: Tracking, cb: ClipBoxes, in_view: set[str], before: Tracking | None = None) -> Counter:
    """Counts of one clip's tracks (module docstring); ``objects_lost``: objects in view a track of
    ``before`` followed that no track follows now (joined into another object's track, or dropped)."""
    objects = track_objects(result.track, cb.truth)
    on = Counter(o for o in objects.values() if o in in_view)
    lost = set(track_objects(before.track, cb.truth).values()) & in_view - set(on) if before is not None else set()
    return Counter(tracks=len(objects), no_object=sum(1 for o in objects.values() if not o),
                   on_objects=sum(on.values()), objects_found=len(on), objects_split=sum(1 for c in on.values() if c > 1),
                   joined=result.joined, thin=result.thin, objects_lost=len(lost))


def model_scores(model: MergeModel, x: np.ndarray, y: np.ndarray) -> dict:
    from sklearn.metrics import log_loss, roc_auc_score

    p = model.probability(x) if len(x) else np.zeros(0)
    if len(set(y.tolist())) < 2:
        return {"pairs": len(y)}
    return {"pairs": len(y), "one_object": int(y.sum()), "log_loss": round(float(log_loss(y, p, labels=[0, 1])), 4),
            "roc_auc": round(float(roc_auc_score(y, p)), 4),
            "roc_auc_appearance_alone": round(float(roc_auc_score(y, x[:, CUES.index("appearance")])), 4)}


def evaluate(wh, bench_dirs: list[Path]) -> dict:
    """Before / after counts per folder (module docstring)."""
    from tasks.tracking.tracking import default_merge_model

    model = default_merge_model()
    out = {}
    for d in bench_dirs:
        before, after = Counter(), Counter()
        xs, ys = [], []
        for clip in read_manifest(d).clips:
            cb, geometry = clip_inputs(wh, d, clip)
            in_view = clip_objects_in_view(d, clip)
            old = run_tracking(cb, None, TrackingConfig())
            before += tracking_counts(old, cb, in_view)
            after += tracking_counts(run_tracking(cb, geometry, TrackingConfig(), model), cb, in_view, old)
            x, y = fragment_pairs(cb, geometry)
            xs.append(x), ys.append(y)
        summary = lambda c: {**dict(c), "tracks_per_object": round(c["on_objects"] / c["objects_found"], 3)  # noqa: E731
                             if c["objects_found"] else None}
        out[str(d)] = {"seed": read_manifest(d).seed, "clips": len(read_manifest(d).clips), "before": summary(before),
                       "after": summary(after), "model": model_scores(model, np.concatenate(xs), np.concatenate(ys))}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.merge_bench", description=__doc__.splitlines()[0])
    ap.add_argument("command", choices=("fit", "eval"))
    ap.add_argument("bench_dirs", nargs="+", type=Path)
    ap.add_argument("--warehouse", default=None, help="warehouse of the clips' pipeline tables (default: the configured one)")
    args = ap.parse_args(argv)
    wh = open_warehouse(args.warehouse)
    result = fit(wh, args.bench_dirs) if args.command == "fit" else evaluate(wh, args.bench_dirs)
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
