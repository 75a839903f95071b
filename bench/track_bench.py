"""Tracking benchmark (issue 6): solver quality and speed, and tracking accuracy on the synthetic benchmark.

    python -m bench.track_bench [--quick] [--warehouse DIR]   # everything; writes bench/results/tracking.json
    python -m bench.track_bench fit [--source detector|gt|mix] [--warehouse DIR] --bench-dir DIR...
                                           # refit the cue calibration, rewrite tasks/tracking/calibration.py

``--warehouse``: the warehouse holding the pipeline's tables of the benchmark clips (default: the
configured one, ``load_config().warehouse.root``, as for the ``cadestate`` CLI).

Parts:
- ``objective``: heuristic objective / exact MILP optimum on random tracking-like instances and
  on real instances (windows of the benchmark clips' graphs built from ground-truth boxes);
- ``timing``: heuristic solve time against the number of detections, 100..5,000 (real graphs: the
  benchmark clips' graphs, concatenated in time to reach the size; and random tracking-like ones);
- ``scale``: time and peak memory of the whole tracking computation (cues, weights, solver) on
  synthetic clips of 5k, 20k and 35k detections, each in its own process (``bench.track_scale``);
- ``bound``: the heuristic's objective on every benchmark clip's whole graph (and on a synthetic
  clip's and a random instance's) against an upper bound on the optimum, the cycle LP relaxation (``bench.track_bound_bench``):
  objective / bound is at most objective / optimum, shown where the exact MILP cannot go;
- ``tracking``: HOTA/MOTA/IDF1/ID switches (``bench.eval_tracking``, ignore rule of
  ``bench.ignore``) on the default benchmark from ground-truth boxes (appearance from the embedder
  on those boxes, labels = ground-truth classes) and, when the clips' ``detect`` and ``embed``
  stages have run in the warehouse, from detector boxes (tracked again here with the current
  calibration), and of the ``tracks`` the pipeline's ``tracking`` stage wrote there
  (:func:`tracking_accuracy`, also in ``cadestate bench report``).

Calibration (``fit``): the cue tables are fitted on true / false pairs of boxes. ``detector``
(default when every clip has detections and descriptors): the detector's boxes, each matched to
a ground-truth box of its frame (Hungarian, IoU >= 0.5) for its identity; pairs with an unmatched
box (false positives, duplicates) are left out of the fit. ``gt``: the ground-truth boxes (labels
never disagree within an object there, so the label cue is capped at ``LABEL_CLIP_GT``). ``mix``
(the stored calibration): both sets of pairs pooled, except the label cue, fitted on the detector
pairs alone (the tracker always sees a detector's labels in the pipeline).

Descriptors of the ground-truth boxes are cached under ``data/bench/track_cache/``.
"""

from __future__ import annotations

import json
import pprint
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from bench.benchmark import ignore_rule, read_manifest
from bench.eval_tracking import TrackBox, boxes_from_objects, evaluate_tracking_clips
from cadestate.config import EmbedConfig, TrackingConfig
from schemas.official import read_objects
from tasks.tracking.affinity import LABEL_CLIP_GT, Cameras, PairFeatures, affinities, fit_calibration, pair_features
from tasks.tracking.partition import ExactSolverError, objective, solve, solve_exact
from tasks.tracking.tracking import track_detections
from tasks.video.camera_file import parse_camera_file

BENCH_DIR = Path("data/bench/default")
CACHE = Path("data/bench/track_cache")
RESULTS = Path("bench/results")
CALIBRATION_FILE = Path(__file__).resolve().parent.parent / "tasks" / "tracking" / "calibration.py"


@dataclass
class ClipBoxes:
    """One clip's boxes as the tracker sees them, with the ground-truth identity of each."""

    clip: str
    det_id: np.ndarray
    frame_index: np.ndarray
    timestamp_us: np.ndarray
    boxes: np.ndarray
    labels: np.ndarray
    scores: np.ndarray
    truth: np.ndarray  # ground-truth track id (str), "" when unmatched (detector false positive)
    vectors: np.ndarray | None
    cameras: Cameras


def clip_cameras(bench_dir: Path, clip: str) -> tuple[np.ndarray, Cameras]:
    """(camera timestamps, Cameras) from the clip's RealEstate10K file (640x360 video)."""
    from schemas.official import read_frames

    track = parse_camera_file(bench_dir / f"{clip}.txt")
    H, W = read_frames(bench_dir / clip / "frames.json").image_size
    intr = track.intrinsics
    K = np.zeros((len(intr), 3, 3))
    K[:, 0, 0], K[:, 1, 1] = intr[:, 0] * W, intr[:, 1] * H
    K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = intr[:, 2] * W, intr[:, 3] * H, 1.0
    return track.timestamps_us, Cameras(K, track.world_to_camera[:, :, :3].copy(), int(W), int(H))


def gt_clip(bench_dir: Path, clip: str, embed: bool = True) -> ClipBoxes:
    """The clip's ground-truth boxes as detections (ids: frame * 10000 + rank by area in the frame)."""
    ts, cams = clip_cameras(bench_dir, clip)
    frame_of = {int(t): k for k, t in enumerate(ts)}
    objects = read_objects(bench_dir / clip / "objects.json")
    rows = [(frame_of[e.timestamp], e.timestamp, e.box, o.cls, o.track_id) for o in objects.objects for e in o.track]
    rows.sort(key=lambda r: (r[0], -(r[2][2] - r[2][0]) * (r[2][3] - r[2][1]), r[4]))
    frame = np.array([r[0] for r in rows], dtype=np.int64)
    rank = np.zeros(len(rows), dtype=np.int64)
    for k in range(1, len(rows)):
        rank[k] = rank[k - 1] + 1 if frame[k] == frame[k - 1] else 0
    boxes = np.array([r[2] for r in rows], dtype=np.float64).reshape(-1, 4)
    cb = ClipBoxes(clip, frame * 10000 + rank, frame, np.array([r[1] for r in rows], dtype=np.int64), boxes,
                   np.array([r[3] for r in rows], dtype=object), np.ones(len(rows)), np.array([r[4] for r in rows], dtype=object),
                   None, cams)
    if embed:
        cb.vectors = gt_vectors(bench_dir, cb)
    return cb


def gt_vectors(bench_dir: Path, cb: ClipBoxes) -> np.ndarray:
    """Embedder descriptors of the ground-truth boxes (cached per clip and embed config)."""
    from cadestate.lineage import digest
    from tasks.detection.models.embedder import load_embedder
    from tasks.video.decode import decode_at

    cfg = EmbedConfig()
    key = digest(cb.clip, json.dumps(cfg.__dict__, sort_keys=True), str(cb.boxes.tobytes().hex()[:64]), str(len(cb.boxes)))
    path = CACHE / f"{cb.clip}-{key}.npy"
    if path.is_file():
        return np.load(path)
    embedder = load_embedder(cfg)
    out = np.zeros((len(cb.boxes), 768), np.float32)
    frames = np.unique(cb.frame_index)
    ts = np.array([cb.timestamp_us[cb.frame_index == f][0] for f in frames])
    W, H = cb.cameras.width, cb.cameras.height
    for f, decoded in zip(frames, decode_at(bench_dir / f"{cb.clip}.mp4", ts)):
        k = np.flatnonzero(cb.frame_index == f)
        px = cb.boxes[k][:, [1, 0, 3, 2]] * [W, H, W, H]
        out[k] = embedder.embed(decoded.rgb, px)
    CACHE.mkdir(parents=True, exist_ok=True)
    np.save(path, out)
    return out


def open_warehouse(root: str | Path | None = None):
    """The warehouse at ``root``, default the configured one (``load_config().warehouse.root``)."""
    from cadestate.config import load_config
    from warehouse import Warehouse

    return Warehouse(root if root is not None else load_config().warehouse.root)


def match_truth(frame: np.ndarray, boxes: np.ndarray, gt: ClipBoxes) -> np.ndarray:
    """The ground-truth identity object[N] of each box float[N, 4] (ymin, xmin, ymax, xmax,
    normalised) on frame int[N]: matched to ``gt``'s boxes of its frame (Hungarian on IoU, kept
    when >= 0.5); "" when unmatched."""
    from bench.ignore import box_iou, match_pairs

    truth = np.full(len(frame), "", dtype=object)
    for f in np.unique(frame):
        p, g = np.flatnonzero(frame == f), np.flatnonzero(gt.frame_index == f)
        if len(g) == 0:
            continue
        r, c = match_pairs(box_iou(boxes[p], gt.boxes[g]), 0.5)
        truth[p[r]] = gt.truth[g[c]]
    return truth


def detector_clip(wh, bench_dir: Path, clip: str) -> ClipBoxes | None:
    """The clip's detector boxes from the warehouse ``wh``, each matched to a ground-truth box
    of its frame (:func:`match_truth`) for its true identity; None when not detected yet."""
    if clip not in wh.partitions("detections") or clip not in wh.partitions("embeddings"):
        return None
    d = wh.read("detections", partitions=[clip], columns=["det_id", "timestamp_us", "frame_index", "box", "label", "score"]).to_pydict()
    e = wh.read("embeddings", partitions=[clip], columns=["owner", "owner_id", "vector"]).to_pydict()
    vec = {i: v for o, i, v in zip(e["owner"], e["owner_id"], e["vector"]) if o == "detection"}
    if any(i not in vec for i in d["det_id"]):
        return None
    order = np.argsort(d["det_id"])
    get = lambda k: [d[k][i] for i in order]  # noqa: E731
    _, cams = clip_cameras(bench_dir, clip)
    det_id = np.array(get("det_id"), dtype=np.int64)
    frame = np.array(get("frame_index"), dtype=np.int64)
    boxes = np.array(get("box"), dtype=np.float64).reshape(-1, 4)
    truth = match_truth(frame, boxes, gt_clip(bench_dir, clip, embed=False))
    return ClipBoxes(clip, det_id, frame, np.array(get("timestamp_us"), dtype=np.int64), boxes,
                     np.array(get("label"), dtype=object), np.array(get("score"), dtype=np.float64), truth,
                     np.array([vec[i] for i in det_id], dtype=np.float32), cams)


def detector_clips(wh, bench_dir: Path, clips) -> list[ClipBoxes] | None:
    """:func:`detector_clip` of every clip, or None unless all of them have detections and descriptors."""
    if wh is None:
        return None
    det = [detector_clip(wh, bench_dir, c) for c in clips]
    return det if det and all(x is not None for x in det) else None


def features_of(cb: ClipBoxes, window: int, matched_only: bool = False) -> tuple[PairFeatures, np.ndarray]:
    """Pair cues of a clip and whether each pair is one object (unmatched detections: never one;
    ``matched_only``: pairs with an unmatched detection are left out)."""
    p = pair_features(cb.frame_index, cb.boxes, cb.labels, cb.vectors, cb.cameras, window)
    ta, tb = cb.truth[p.a], cb.truth[p.b]
    if matched_only:
        keep = (ta != "") & (tb != "")
        p = PairFeatures(p.a[keep], p.b[keep], p.gap[keep], None if p.cosine is None else p.cosine[keep],
                         p.same_label[keep], p.iou[keep])
        ta, tb = ta[keep], tb[keep]
    return p, (ta == tb) & (ta != "")


FIT_SOURCES = ("detector", "gt", "mix")


def _shown(path: Path) -> str:
    """``path`` relative to the working directory when inside it (for messages and generated files)."""
    try:
        return str(Path(path).resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def fit(bench_dirs: list[Path], write: bool = True, wh=None, source: str | None = None) -> dict:
    """Fit the calibration on the true/false pairs of the benchmark folders ``bench_dirs`` and rewrite
    tasks/tracking/calibration.py, with the folders' seeds (``training_seeds``).

    ``source`` (module docstring): ``detector`` (matched detector boxes; the default when every
    clip has detections and descriptors in ``wh``, default the configured warehouse), ``gt``
    (ground-truth boxes) or ``mix`` (both pooled)."""
    bench_dirs = [Path(d) for d in bench_dirs]
    clips = [(d, c) for d in bench_dirs for c in read_manifest(d).clips]
    window = max(TrackingConfig().window, 16)
    wh = open_warehouse() if wh is None else wh
    det = [detector_clip(wh, d, c) for d, c in clips]
    det = det if det and all(x is not None for x in det) else None
    source = source or ("detector" if det else "gt")
    if source not in FIT_SOURCES:
        raise ValueError(f"source must be one of {FIT_SOURCES}, not {source!r}")
    if source in ("detector", "mix") and det is None:
        raise ValueError(f"{wh.root}: not every benchmark clip has detections and descriptors (run detect and embed)")
    feats, truth = [], []
    if source in ("detector", "mix"):
        for cb in det:
            p, y = features_of(cb, window, matched_only=True)
            feats.append(p), truth.append(y)
    if source in ("gt", "mix"):
        for d, c in clips:
            p, y = features_of(gt_clip(d, c), window)
            feats.append(p), truth.append(y)
    cal = fit_calibration(feats, truth, label_clip=LABEL_CLIP_GT if source == "gt" else None)
    if source == "mix":  # labels: the detector's only (ground-truth labels never disagree within an object)
        cal["label"] = fit_calibration(feats[:len(det)], truth[:len(det)])["label"]
    described = {"detector": "detector boxes matched to ground truth (IoU >= 0.5; pairs with an unmatched box left out)",
                 "gt": "ground-truth boxes",
                 "mix": "ground-truth boxes and detector boxes matched to ground truth (IoU >= 0.5; pairs with an "
                        "unmatched box left out), pooled (label cue: detector boxes only)"}[source]
    seeds = [read_manifest(d).seed for d in bench_dirs]
    cal["training_seeds"] = seeds
    cal["fitted_on"] = (f"{described} of {len(clips)} benchmark clips (seeds {', '.join(map(str, seeds))}; detections "
                        f"and descriptors from {_shown(wh.root)}), pairs up to {window} frames apart")
    if write:
        text = (f'"""Fitted calibration of the tracking cues (see tasks/tracking/affinity.py). Generated by\n'
                f'``python -m bench.track_bench fit --source {source} --bench-dir DIR...`` (the benchmark clips\' detect and\n'
                f'embed stages must have run in the configured warehouse, or pass ``--warehouse DIR``); the benchmark seeds it\n'
                f'saw are ``training_seeds``. Do not edit by hand."""\n\n'
                f'CALIBRATION = {pprint.pformat(cal, width=110, sort_dicts=False)}\n')
        CALIBRATION_FILE.write_text(text)
    return cal


# ------------------------------------------------------------------------------------- instances

def random_instance(n: int, rng: np.random.Generator, per_frame: int = 8, window: int = 8, noise: float = 1.0):
    """A tracking-like random graph: objects living over frame intervals, per_frame detections a
    frame, edges up to ``window`` frames apart with weight +-2 for same/different object plus
    Gaussian noise of std ``2 * noise``. Returns (n, i, j, w, groups)."""
    F = max(1, n // per_frame)
    frames = np.sort(rng.integers(0, F, n))
    life = max(2, F // 3)
    n_obj = max(per_frame * 3, 2)
    start = rng.integers(-life, F, n_obj)
    obj = np.empty(n, dtype=np.int64)
    for k, f in enumerate(frames):
        alive = np.flatnonzero((start <= f) & (f < start + life))
        obj[k] = rng.choice(alive) if len(alive) else rng.integers(n_obj)
    a, b = _window_pairs(frames, window)
    w = np.where(obj[a] == obj[b], 2.0, -2.0) + rng.normal(0, 2 * noise, len(a))
    return n, a, b, w, frames


def _window_pairs(frames: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    from tasks.tracking.affinity import candidate_pairs

    return candidate_pairs(frames, window)


def real_graph(cb: ClipBoxes, cfg: TrackingConfig = TrackingConfig()):
    """The graph the tracker solves for a clip: (n, i, j, w, groups). ``cb``: a :class:`ClipBoxes`, or
    anything with its detection fields (``bench.track_scale.SyntheticClip``)."""
    from tasks.tracking.tracking import default_calibration

    p = pair_features(cb.frame_index, cb.boxes, cb.labels, cb.vectors, cb.cameras, cfg.window)
    w = affinities(p, default_calibration(), appearance_weight=cfg.appearance_weight, label_weight=cfg.label_weight,
                   motion_weight=cfg.motion_weight, bias=cfg.bias)
    return len(cb.det_id), p.a, p.b, w, cb.frame_index


def subgraph(g, nodes: np.ndarray):
    n, i, j, w, groups = g
    local = np.full(n, -1, dtype=np.int64)
    local[nodes] = np.arange(len(nodes))
    keep = (local[i] >= 0) & (local[j] >= 0)
    return len(nodes), local[i[keep]], local[j[keep]], w[keep], groups[nodes]


def objective_bench(clips: list[ClipBoxes], seed: int = 0, random_sizes=(20, 30, 40, 60), per_size: int = 5,
                    real_frames: int = 12, time_limit: float = 60.0) -> dict:
    """Heuristic / exact objective on random and real instances (windows of ``real_frames`` frames)."""
    rng = np.random.default_rng(seed)
    out: dict = {"random": [], "real": []}

    def compare(kind: str, g, name: str) -> None:
        n, i, j, w, groups = g
        t0 = time.perf_counter()
        h = solve(n, i, j, w, groups=groups)
        th = time.perf_counter() - t0
        t0 = time.perf_counter()
        try:
            e = solve_exact(n, i, j, w, groups=groups, time_limit=time_limit, max_nodes=200)
        except ExactSolverError as err:
            out[kind].append({"instance": name, "n": n, "exact": None, "error": str(err)})
            return
        te = time.perf_counter() - t0
        oh, oe = objective(h, i, j, w), objective(e, i, j, w)
        out[kind].append({"instance": name, "n": n, "edges": len(w), "heuristic": round(oh, 4), "exact": round(oe, 4),
                          "ratio": round(oh / oe, 6) if oe > 0 else 1.0, "heuristic_s": round(th, 4), "exact_s": round(te, 3)})

    for n in random_sizes:
        for k in range(per_size):
            compare("random", random_instance(n, rng, per_frame=6, window=6, noise=0.6), f"random n={n} #{k}")
    for cb in clips:
        g = real_graph(cb)
        frames = np.unique(cb.frame_index)
        for s in range(0, len(frames), real_frames * 4):  # every 4th window of real_frames frames
            nodes = np.flatnonzero(np.isin(cb.frame_index, frames[s:s + real_frames]))
            compare("real", subgraph(g, nodes), f"{cb.clip} frames {frames[s]}-{frames[min(s + real_frames, len(frames)) - 1]}")
        compare("real", g, f"{cb.clip} whole clip")
    for kind in ("random", "real"):
        ratios = [r["ratio"] for r in out[kind] if r.get("exact") is not None]
        out[f"{kind}_summary"] = {"instances": len(out[kind]), "solved_exactly": len(ratios),
                                  "mean_ratio": round(float(np.mean(ratios)), 6) if ratios else None,
                                  "min_ratio": round(float(np.min(ratios)), 6) if ratios else None,
                                  "largest_exact_n": max((r["n"] for r in out[kind] if r.get("exact") is not None), default=0),
                                  "objective_sum_ratio": round(sum(r["heuristic"] for r in out[kind] if r.get("exact") is not None)
                                                               / max(sum(r["exact"] for r in out[kind] if r.get("exact") is not None), 1e-12), 6)}
    return out


def concatenated(clips: list[ClipBoxes], n: int):
    """A real graph of exactly ``n`` detections: clips' graphs laid end to end in time (cut at n)."""
    parts, offset, total = [], 0, 0
    k = 0
    while total < n:
        cb = clips[k % len(clips)]
        parts.append((cb, offset))
        offset += int(cb.frame_index.max()) + 1 + 100  # no edges across clips
        total += len(cb.det_id)
        k += 1
    ns, I, J, W, G = 0, [], [], [], []
    for cb, off in parts:
        m, i, j, w, g = real_graph(cb)
        I.append(i + ns), J.append(j + ns), W.append(w), G.append(g + off)
        ns += m
    g = (ns, np.concatenate(I), np.concatenate(J), np.concatenate(W), np.concatenate(G))
    return subgraph(g, np.arange(n))


def timing_bench(clips: list[ClipBoxes], sizes=(100, 200, 500, 1000, 2000, 5000), repeats: int = 3, seed: int = 0) -> dict:
    """Heuristic solve time (best of ``repeats``) against the number of detections."""
    rng = np.random.default_rng(seed)
    out = {"real": [], "random": []}
    for n in sizes:
        for kind, g in (("real", concatenated(clips, n) if clips else None),
                        ("random", random_instance(n, rng, per_frame=8, window=8, noise=0.6))):
            if g is None:
                continue
            best = np.inf
            for _ in range(repeats):
                t0 = time.perf_counter()
                solve(g[0], g[1], g[2], g[3], groups=g[4])
                best = min(best, time.perf_counter() - t0)
            out[kind].append({"n": n, "edges": len(g[3]), "seconds": round(best, 4)})
    return out


def track_boxes(cb: ClipBoxes, track: np.ndarray) -> list[TrackBox]:
    return [TrackBox(int(cb.timestamp_us[k]), str(track[k]), tuple(cb.boxes[k])) for k in np.flatnonzero(track >= 0)]


def tracking_bench(bench_dir: Path, clips: list[ClipBoxes], cfg: TrackingConfig = TrackingConfig()) -> dict:
    """Tracking metrics on the benchmark: the tracker's output on ``clips`` against ground truth."""
    pairs = []
    seconds = 0.0
    for cb in clips:
        t0 = time.perf_counter()
        res = track_detections(cb.det_id, cb.frame_index, cb.boxes, cb.labels, cb.vectors, cb.cameras, cfg, scores=cb.scores)
        seconds += time.perf_counter() - t0
        gt = boxes_from_objects(read_objects(bench_dir / cb.clip / "objects.json"), ignore_rule(bench_dir, cb.clip))
        pairs.append((gt, track_boxes(cb, res.track)))
    rep = evaluate_tracking_clips(pairs).as_dict()
    rep = {k: (round(v, 4) if isinstance(v, float) else v) for k, v in rep.items()}
    rep["tracker_seconds_total"] = round(seconds, 3)
    rep["detections"] = int(sum(len(cb.det_id) for cb in clips))
    return rep


def warehouse_tracks(bench_dir: Path, wh, clip: str) -> tuple[list[TrackBox], list[TrackBox]]:
    """(ground-truth boxes with the ignore flag, boxes of the pipeline's ``tracks``) of one clip: the
    ``track_detections`` of the clip joined to its ``detections`` for the boxes, keyed by timestamp."""
    gt = boxes_from_objects(read_objects(Path(bench_dir) / clip / "objects.json"), ignore_rule(bench_dir, clip))
    members = wh.read("track_detections", partitions=[clip], columns=["track_id", "det_id"]).to_pydict()
    dets = wh.read("detections", partitions=[clip], columns=["det_id", "timestamp_us", "box"]).to_pydict()
    by_id = {d: (ts, box) for d, ts, box in zip(dets["det_id"], dets["timestamp_us"], dets["box"])}
    missing = [d for d in members["det_id"] if d not in by_id]
    if missing:
        raise ValueError(f"clip {clip}: track_detections names det_id {missing[0]} that detections lacks (rerun tracking)")
    pred = [TrackBox(int(by_id[d][0]), str(t), tuple(float(x) for x in by_id[d][1]))
            for t, d in zip(members["track_id"], members["det_id"])]
    return gt, pred


def tracking_accuracy(bench_dir: Path, wh) -> dict | None:
    """HOTA/MOTA/IDF1/ID switches of the pipeline's ``tracks`` against the ground-truth tracks, over
    the benchmark clips whose ``tracking`` stage has run in ``wh`` (ignore rule of ``bench.ignore``,
    class-agnostic, IoU >= 0.5); None when none has."""
    parts = set(wh.partitions("track_detections")) & set(wh.partitions("detections"))
    clips = [c for c in read_manifest(bench_dir).clips if c in parts]
    if not clips:
        return None
    rep = evaluate_tracking_clips([warehouse_tracks(bench_dir, wh, c) for c in clips]).as_dict()
    rep = {k: (round(v, 4) if isinstance(v, float) else v) for k, v in rep.items()}
    n_tracks = sum(wh.read("tracks", partitions=[c], columns=["track_id"]).num_rows
                   for c in clips if c in wh.partitions("tracks"))
    return {"clips": len(clips), "tracks": n_tracks, **rep}


def tracking_markdown(tracking: dict | None) -> list[str]:
    """Lines of the report's tracking section (empty before the tracking stage ran)."""
    if not tracking:
        return []
    keys = [("HOTA", "hota"), ("DetA", "deta"), ("AssA", "assa"), ("MOTA", "mota"), ("IDF1", "idf1"),
            ("ID switches", "id_switches"), ("precision", "precision"), ("recall", "recall")]
    return [f"## Tracking (the `tracks` of {tracking['clips']} clips, IoU >= 0.5, class-agnostic, ignore regions excluded)", "",
            f"{tracking['tracks']} tracks; {tracking['num_gt_boxes']} ground-truth boxes, {tracking['num_pred_boxes']} "
            f"tracked boxes kept ({tracking['dropped_pred_boxes']} on ignore regions dropped).", "",
            "| " + " | ".join(k for k, _ in keys) + " |", "|" + "---:|" * len(keys),
            "| " + " | ".join(str(tracking[v]) for _, v in keys) + " |", ""]


def run(bench_dir: Path = BENCH_DIR, quick: bool = False, wh=None) -> dict:
    """All parts (see module docstring); ``wh``: the warehouse with the pipeline's tables (default:
    the configured one). Without a benchmark in ``bench_dir`` the parts on its clips are left out
    (said so in ``benchmark``) and the others run on synthetic and random instances alone."""
    from bench import track_bound_bench, track_scale

    out: dict = {"config": TrackingConfig().__dict__}
    clips: list[ClipBoxes] = []
    if not (Path(bench_dir) / "manifest.json").is_file():
        out["benchmark"] = f"not measured: no benchmark in {_shown(Path(bench_dir))}"
    else:
        wh = open_warehouse() if wh is None else wh
        names = read_manifest(bench_dir).clips
        clips = [gt_clip(bench_dir, c) for c in names]
        out["warehouse"] = _shown(wh.root)
        out["tracking_from_gt_boxes"] = tracking_bench(bench_dir, clips)
        out["tracking_from_gt_boxes_no_appearance"] = tracking_bench(bench_dir, clips, replace(TrackingConfig(), appearance_weight=0.0))
        det = detector_clips(wh, bench_dir, names)
        if det:
            out["tracking_from_detector_boxes"] = tracking_bench(bench_dir, det)
            out["tracking_from_detector_boxes_no_appearance"] = tracking_bench(bench_dir, det, replace(TrackingConfig(), appearance_weight=0.0))
        else:
            out["tracking_from_detector_boxes"] = f"not measured: the benchmark clips have no detect/embed output in {_shown(wh.root)}"
        out["pipeline_tracks"] = tracking_accuracy(bench_dir, wh) or f"not measured: no tracking output in {_shown(wh.root)}"
    out["scale"] = track_scale.run()
    out["timing"] = timing_bench(clips, sizes=(100, 500, 1000, 5000) if quick else (100, 200, 500, 1000, 2000, 5000))
    out["objective"] = objective_bench(clips[:4] if quick else clips, per_size=2 if quick else 5)
    out["bound"] = track_bound_bench.run(  # every benchmark clip; a synthetic clip (easy) and a random graph (hard)
        [(f"{cb.clip} whole clip", real_graph(cb)) for cb in clips]
        + [("synthetic clip n=5000", real_graph(track_scale.synthetic_clip(5000))),
           ("random n=200", random_instance(200, np.random.default_rng(0), per_frame=8, window=8, noise=0.6))])
    return out


def main(argv: list[str]) -> None:
    import argparse

    parser = argparse.ArgumentParser(prog="python -m bench.track_bench", description=__doc__.split("\n\n")[0])
    parser.add_argument("command", nargs="?", choices=("run", "fit"), default="run")
    parser.add_argument("--quick", action="store_true", help="fewer sizes and instances (run)")
    parser.add_argument("--warehouse", type=Path, default=None,
                        help="warehouse with the pipeline's tables (default: the configured one)")
    parser.add_argument("--source", choices=FIT_SOURCES, default=None,
                        help="boxes to fit on (fit; default: detector when every clip has detections)")
    parser.add_argument("--bench-dir", type=Path, action="append", default=None,
                        help="benchmark folder (repeat for several; fit: the folders to fit on, never the ones reported; "
                             f"run: the first; default {BENCH_DIR})")
    args = parser.parse_args(argv)
    wh = open_warehouse(args.warehouse)
    if args.command == "fit":
        cal = fit(args.bench_dir or [BENCH_DIR], wh=wh, source=args.source)
        print(json.dumps(cal, indent=1))
        print(f"wrote {CALIBRATION_FILE}")
        return
    result = run((args.bench_dir or [BENCH_DIR])[0], quick=args.quick, wh=wh)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "tracking.json").write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k not in ("objective", "bound")}, indent=1))
    print(json.dumps({k: v for k, v in result["objective"].items() if k.endswith("summary")}, indent=1))
    print(json.dumps(result["bound"], indent=1))
    print(f"saved {RESULTS / 'tracking.json'}")


if __name__ == "__main__":
    main(sys.argv[1:])
