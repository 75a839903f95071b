"""Stage ``tracking``: associate a clip's detections into tracks, one per physical object (paper, Sec. 3.1).

Reads: the clip's ``detections``, ``embeddings`` (owner 'detection') and ``frames`` (cameras).
Writes: its ``tracks``, ``track_detections`` and ``track_appearance`` partitions.

Every two detections at most ``window`` frames apart get an edge whose weight is the log-odds
that they show one object (:mod:`tasks.tracking.affinity`: appearance, label agreement, box
continuity after compensating the camera rotation, calibrated on the synthetic benchmark);
detections of one frame can never share a track (cannot-links). The graph is partitioned into
cliques maximising the summed log-odds inside them (:func:`tasks.tracking.partition.solve`). The
cliques that are fragments of one object are then joined in 3D (:mod:`tasks.tracking.merge`, with
``merge``); tracks with fewer than ``min_detections`` detections are dropped, and so are the tracks
too thin to annotate (fewer than ``thin_detections``, none on a ``[manual_tracks]`` key-frame),
the shadow tracks, which follow an object a stronger track follows (:mod:`tasks.tracking.shadow`),
and the weak tracks, whose detections score less than ``min_track_score`` on average (boxes the
detector barely kept: mostly on no object, or on part of one).
Track ids are ranks by first detection id, so a rerun with unchanged inputs gives the same ids.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from cadestate.config import TrackingConfig
from cadestate.lineage import digest, table_digest
from tasks.human.keyframes import regular_keyframes
from tasks.stage import StageContext, StageDef, StageOutput
from tasks.tracking.affinity import Cameras, PairFeatures, affinities, centred, pair_features
from tasks.tracking.merge import MergeModel, merge_step
from tasks.tracking.partition import solve
from tasks.tracking.track3d import Rays, box_rays
from tasks.tracking.shadow import shadow_groups
from warehouse import Warehouse


class TrackingError(ValueError):
    """Inputs the tracker cannot use (no calibration, descriptors missing for some detections)."""


def default_calibration() -> dict:
    from tasks.tracking.calibration import CALIBRATION

    if CALIBRATION is None:
        raise TrackingError("tasks/tracking/calibration.py holds no calibration: run `python -m bench.track_bench fit`")
    return CALIBRATION


def default_merge_model() -> MergeModel:
    from tasks.tracking.merge_calibration import MERGE_CALIBRATION

    if MERGE_CALIBRATION is None:
        raise TrackingError("tasks/tracking/merge_calibration.py holds no model: run `python -m bench.merge_bench fit`")
    return MergeModel.from_dict(MERGE_CALIBRATION)


@dataclass(frozen=True)
class Geometry:
    """What joining fragments in 3D needs of a clip of N detections: ``rays`` through the box
    centres (aligned world) and the manual-track ``keyframes`` (frame indices int[K])."""

    rays: Rays
    keyframes: np.ndarray


@dataclass(frozen=True)
class Tracking:
    """Result on N detections: ``track`` int64[N] (track id, -1 = left out), the graph it solved,
    the fragments ``joined`` in 3D, and the ``thin``, ``shadows`` and ``weak`` tracks dropped."""

    track: np.ndarray
    pairs: PairFeatures
    weights: np.ndarray
    joined: int = 0
    thin: int = 0
    shadows: int = 0
    weak: int = 0


def track_detections(det_id: np.ndarray, frame_index: np.ndarray, boxes: np.ndarray, labels: np.ndarray,
                     vectors: np.ndarray | None, cameras: Cameras | None, cfg: TrackingConfig,
                     scores: np.ndarray | None = None, calibration: dict | None = None,
                     geometry: Geometry | None = None, merge_model: MergeModel | None = None) -> Tracking:
    """Tracks of one clip's detections (arrays of length N; ``det_id`` unique).

    Returns track ids 0..T-1 ordered by each track's smallest det_id, -1 for detections left
    out (score below ``min_score``, in a track shorter than ``min_detections``, too thin, a
    shadow, or weak). With ``geometry`` the partition's fragments are joined in 3D (``cfg.merge``;
    ``merge_model``: default the stored one), then thin tracks, shadow tracks
    (:mod:`tasks.tracking.shadow`) and weak tracks (mean score below ``cfg.min_track_score``) are
    dropped; without it none of these happens."""
    det_id = np.asarray(det_id, dtype=np.int64)
    n = len(det_id)
    if len(np.unique(det_id)) != n:
        raise TrackingError("det_id must be unique")
    calibration = calibration or default_calibration()
    keep = np.ones(n, dtype=bool) if scores is None else np.asarray(scores) >= cfg.min_score
    idx = np.flatnonzero(keep)
    f = np.asarray(frame_index, dtype=np.int64)[idx]
    kept_boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)[idx]
    vec = None if (vectors is None or cfg.appearance_weight == 0) else np.asarray(vectors)[idx]
    feats = pair_features(f, kept_boxes, np.asarray(labels)[idx], vec, cameras if cfg.use_cameras else None, cfg.window)
    w = affinities(feats, calibration, appearance_weight=cfg.appearance_weight, label_weight=cfg.label_weight,
                   motion_weight=cfg.motion_weight, bias=cfg.bias)
    lab = solve(len(idx), feats.a, feats.b, w, groups=f, keys=det_id[idx], refine_result=cfg.refine)
    groups = [g for g in np.split(np.argsort(lab, kind="stable"), np.cumsum(np.bincount(lab))[:-1]) if len(g)]
    joined = thin = shadows = weak = 0
    if geometry is None:
        groups = [g for g in groups if len(g) >= cfg.min_detections]
    else:
        model = (merge_model or default_merge_model()) if cfg.merge else None
        sc = np.ones(len(idx)) if scores is None else np.asarray(scores, np.float64)[idx]
        merged = merge_step(groups, f, np.asarray(labels)[idx], sc, None if vec is None else centred(vec),
                            geometry.rays.subset(idx), geometry.keyframes, model, cfg.merge_min_probability,
                            cfg.min_detections, cfg.thin_detections)
        groups, joined, thin = merged.groups, merged.joins, merged.thin
        drop = shadow_groups(groups, f, kept_boxes, sc, cfg.shadow_iou, cfg.shadow_share)
        groups, shadows = [g for g, s in zip(groups, drop) if not s], int(drop.sum())
        strong = [g for g in groups if sc[g].mean() >= cfg.min_track_score]
        groups, weak = strong, len(groups) - len(strong)
    # track ids: kept groups ranked by their smallest det_id
    groups.sort(key=lambda g: det_id[idx[g]].min())
    track = np.full(n, -1, dtype=np.int64)
    for t, g in enumerate(groups):
        track[idx[g]] = t
    pairs = PairFeatures(idx[feats.a], idx[feats.b], feats.gap, feats.cosine, feats.same_label, feats.iou)
    return Tracking(track, pairs, w, joined, thin, shadows, weak)


def vote(labels: list[str], weights: list[float]) -> tuple[str, float]:
    """Label with the largest summed weight (ties: first in name order) and its share of the votes."""
    tot: dict[str, float] = {}
    for lab, x in zip(labels, weights):
        tot[lab] = tot.get(lab, 0.0) + max(float(x), 1e-6)
    best = min(tot, key=lambda k: (-tot[k], k))
    return best, tot[best] / sum(tot.values())


def read_cameras(wh: Warehouse, clip: str) -> Cameras:
    """The clip's cameras from ``frames``, indexed by frame_index."""
    t = wh.read("frames", partitions=[clip], columns=["frame_index", "K", "world_to_camera_R", "width", "height"]).to_pydict()
    order = np.argsort(t["frame_index"])
    fi = np.asarray(t["frame_index"])[order]
    if not np.array_equal(fi, np.arange(len(fi))):
        raise TrackingError(f"clip {clip}: frame_index is not 0..{len(fi) - 1}")
    K = np.asarray(t["K"], dtype=np.float64)[order].reshape(-1, 3, 3)
    R = np.asarray(t["world_to_camera_R"], dtype=np.float64)[order].reshape(-1, 3, 3)
    return Cameras(K, R, int(t["width"][0]), int(t["height"][0]))


def detection_vectors(emb: pa.Table, det_id: np.ndarray, clip: str) -> tuple[np.ndarray, str]:
    """(descriptors float32[N,D] of the detections ``det_id`` int64[N], in that order; the model
    sha256 of the first) from the clip's ``embeddings`` rows (owner 'detection'), read as Arrow
    buffers: no Python object per value (a 35k-detection clip holds 27M of them)."""
    import pyarrow.compute as pc

    emb = emb.filter(pc.equal(emb["owner"], "detection"))
    ids = emb["owner_id"].to_numpy()
    order = np.argsort(ids, kind="stable")
    pos = np.searchsorted(ids, det_id, sorter=order)
    found = pos < len(ids)
    found[found] = ids[order[pos[found]]] == det_id[found]
    if not found.all():
        missing = det_id[~found]
        raise TrackingError(f"clip {clip}: {len(missing)} detections have no descriptor (e.g. det_id {missing[0]}): "
                            "rerun its embed stage")
    rows = order[pos]
    col = emb["vector"].combine_chunks()
    lengths = pc.list_value_length(col).to_numpy(zero_copy_only=False)
    if len(lengths) and (lengths != lengths[0]).any():
        raise TrackingError(f"clip {clip}: descriptors of different lengths ({lengths.min()} to {lengths.max()})")
    if len(lengths) and lengths[0] == 0:
        raise TrackingError(f"clip {clip}: descriptors of length 0: rerun its embed stage")
    flat = col.flatten().to_numpy(zero_copy_only=False).astype(np.float32, copy=False)
    vectors = flat.reshape(len(ids), int(lengths[0]) if len(lengths) else 0)[rows]
    bad = ~np.isfinite(vectors).all(axis=1)
    if bad.any():  # one NaN would spread through the clip's mean descriptor into every cosine
        raise TrackingError(f"clip {clip}: {int(bad.sum())} descriptors hold a value that is not a finite number "
                            f"(e.g. det_id {int(det_id[bad][0])}): rerun its embed stage")
    return vectors, str(emb["model_sha256"][int(rows[0])])


def read_geometry(wh: Warehouse, clip: str, cameras: Cameras, frame_index: np.ndarray, boxes: np.ndarray,
                  keyframes: int) -> Geometry:
    """Rays through the centres of ``boxes`` float[N,4] seen on frames ``frame_index`` int[N], and the
    clip's ``keyframes`` manual-track key-frames (:func:`tasks.human.keyframes.regular_keyframes`)."""
    t = wh.read("frames", partitions=[clip], columns=["frame_index", "timestamp_us", "world_to_camera_t"]).to_pydict()
    order = np.argsort(t["frame_index"])
    trans = np.asarray(t["world_to_camera_t"], dtype=np.float64)[order].reshape(-1, 3)
    stamps = np.asarray(t["timestamp_us"], dtype=np.int64)[order].tolist()
    f = np.asarray(frame_index, dtype=np.int64)
    rays = box_rays(boxes, cameras.K[f], cameras.R[f], trans[f], cameras.width, cameras.height)
    return Geometry(rays, np.asarray(regular_keyframes(stamps, keyframes), dtype=np.int64))


def track_tables(clip: str, dets: dict, vectors: np.ndarray | None, model_sha: str, result: Tracking
                 ) -> tuple[pa.Table, pa.Table, pa.Table]:
    """Rows of ``tracks``, ``track_detections`` and ``track_appearance`` (``dets``: column arrays)."""
    track = result.track
    ids = np.asarray(dets["det_id"], dtype=np.int64)
    frames = np.asarray(dets["frame_index"], dtype=np.int64)
    ts = np.asarray(dets["timestamp_us"], dtype=np.int64)
    scores = np.asarray(dets["score"], dtype=np.float64)
    labels = list(dets["label"])
    pa_, pb = result.pairs.a, result.pairs.b
    inside = (track[pa_] == track[pb]) & (track[pa_] >= 0)
    n_tracks = int(track.max()) + 1 if len(track) and track.max() >= 0 else 0
    coh_sum = np.bincount(track[pa_][inside], weights=result.weights[inside], minlength=n_tracks)
    coh_cnt = np.bincount(track[pa_][inside], minlength=n_tracks)
    rows, members, looks = [], [], []
    for t in range(n_tracks):
        m = np.flatnonzero(track == t)
        m = m[np.lexsort((ids[m], frames[m]))]
        label, share = vote([labels[k] for k in m], scores[m].tolist())
        rows.append({"clip": clip, "track_id": t, "label": label, "label_votes": share,
                     "first_timestamp_us": int(ts[m[0]]), "last_timestamp_us": int(ts[m[-1]]),
                     "first_frame_index": int(frames[m[0]]), "last_frame_index": int(frames[m[-1]]),
                     "num_detections": len(m), "mean_score": float(scores[m].mean()),
                     "cohesion": float(coh_sum[t] / coh_cnt[t]) if coh_cnt[t] else 0.0})
        members += [{"clip": clip, "track_id": t, "det_id": int(ids[k]), "frame_index": int(frames[k]),
                     "timestamp_us": int(ts[k])} for k in m]
        if vectors is not None:
            v = np.asarray(vectors[m], dtype=np.float64)
            mean = v.mean(0)
            mean /= max(np.linalg.norm(mean), 1e-12)
            sims = v @ mean
            medoid = m[np.lexsort((ids[m], -sims))[0]]
            looks.append({"clip": clip, "track_id": t, "vector": mean.astype(np.float32).tolist(),
                          "num_vectors": len(m), "medoid_det_id": int(ids[medoid]), "model_sha256": model_sha})
    from schemas.tracking import TRACK_APPEARANCE, TRACK_DETECTIONS, TRACKS

    return (pa.Table.from_pylist(rows, schema=TRACKS.schema), pa.Table.from_pylist(members, schema=TRACK_DETECTIONS.schema),
            pa.Table.from_pylist(looks, schema=TRACK_APPEARANCE.schema))


def track_clip(wh: Warehouse, cfg: TrackingConfig, clip: str, run_id: str, keyframes: int = 6) -> StageOutput:
    """Track the clip's detections and write its three tracking partitions (see module docstring)."""

    dets = wh.read("detections", partitions=[clip],
                   columns=["det_id", "timestamp_us", "frame_index", "box", "label", "score"]).to_pydict()
    order = np.argsort(np.asarray(dets["det_id"], dtype=np.int64), kind="stable")
    dets = {k: [v[i] for i in order.tolist()] for k, v in dets.items()}
    emb = wh.read("embeddings", partitions=[clip], columns=["owner", "owner_id", "vector", "model_sha256"])
    vectors, model_sha = (detection_vectors(emb, np.asarray(dets["det_id"], dtype=np.int64), clip)
                          if dets["det_id"] else (None, ""))
    cameras = read_cameras(wh, clip)
    boxes = np.asarray(dets["box"], dtype=np.float64).reshape(-1, 4)
    geometry = read_geometry(wh, clip, cameras, np.asarray(dets["frame_index"]), boxes, keyframes)
    result = track_detections(np.asarray(dets["det_id"]), np.asarray(dets["frame_index"]), boxes,
                              np.asarray(dets["label"], dtype=object), vectors, cameras, cfg, scores=np.asarray(dets["score"]),
                              geometry=geometry)
    tracks, members, looks = track_tables(clip, dets, vectors, model_sha, result)
    written = wh.write("tracks", clip, tracks) + wh.write("track_detections", clip, members) + wh.write("track_appearance", clip, looks)
    out = digest(table_digest(tracks), table_digest(members), table_digest(looks))
    return StageOutput(written, out, f"{tracks.num_rows} tracks from {len(dets['det_id'])} detections "
                                     f"({result.joined} fragments joined in 3D, {result.thin} thin tracks dropped, "
                                     f"{result.shadows} shadow tracks dropped, {result.weak} weak tracks dropped)")


def _run(ctx: StageContext) -> StageOutput:
    return track_clip(ctx.wh, ctx.cfg, ctx.unit, ctx.run_id, ctx.config.section("manual_tracks").keyframes)


STAGE = StageDef(
    name="tracking", section="tracking", scope="clip", upstream=("frames", "detect", "embed"),
    tables=("tracks", "track_detections", "track_appearance"),
    description="associate detections into tracks by clique partitioning, join fragments in 3D",
    extra_sections=("manual_tracks.keyframes",), run=_run,
)
