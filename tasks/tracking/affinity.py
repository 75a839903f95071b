"""Pairwise affinities of detections for ``tracking``: signed log-odds that two detections are one object.

Candidate pairs: every two detections at most ``[tracking] window`` frames apart (same-frame pairs
are never one object: the solver gets them as cannot-links, see :mod:`tasks.tracking.partition`).
Cues of a pair (a earlier, b later), each turned into a log-likelihood ratio
``log p(cue | same object) / p(cue | different objects)`` by a binned table fitted on the
synthetic benchmark's true and false pairs (:mod:`tasks.tracking.calibration`, refit with
``python -m bench.track_bench fit``):

- appearance: cosine of the two descriptors after centring them on the clip's mean descriptor
  (raw descriptors of one backbone all point roughly the same way; centring on the clip makes
  the cosine discriminative without depending on any other stage's output);
- label: whether the two labels agree;
- motion: IoU of box b with box a carried into frame b by the camera rotation between the two
  frames (infinite homography ``K_b R_b R_a^T K_a^-1``: what a static object's box does when the
  camera turns; the remaining translation parallax is small over a few frames), per frame-gap
  bucket (the same IoU means less after 8 frames than after 1);
- prior: the log-odds of a pair at that gap being one object, before looking at it.

Edge weight = prior(gap) + appearance_weight * L_app + label_weight * L_label
+ motion_weight * L_motion + bias. Boxes are normalised (ymin, xmin, ymax, xmax).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

LLR_CLIP = 10.0
"""Largest |log-likelihood ratio| of one bin (empty bins of a small fitting set stay finite)."""

SMOOTHING = 2.0
"""Pseudo-pairs (of the smaller class) added when fitting, spread like the pooled histogram."""

PAIR_CHUNK = 8192
"""Candidate pairs whose cues are computed at once: bounds the memory of the appearance cue to two
gathered float32[PAIR_CHUNK, D] buffers (2 x 8192 x 768 x 4 B = 50 MB) whatever the clip's length."""

LABEL_CLIP_GT = 3.0
"""|log-likelihood ratio| cap of the label cue when fitted on ground-truth boxes: their labels never
disagree within an object, a detector's do (chair / couch flips), so the fit alone would forbid it."""


@dataclass(frozen=True)
class Cameras:
    """Per frame (indexed by ``frame_index``): pixel intrinsics K float[F,3,3], world->camera
    rotation R float[F,3,3], and the image size in pixels."""

    K: np.ndarray
    R: np.ndarray
    width: int
    height: int


@dataclass(frozen=True)
class PairFeatures:
    """Cue values of the candidate pairs (indices ``a`` < ``b`` in time) of one clip."""

    a: np.ndarray  # int64[P] detection index (earlier frame)
    b: np.ndarray  # int64[P] detection index (later frame)
    gap: np.ndarray  # int64[P] frame difference >= 1
    cosine: np.ndarray | None  # float64[P], None without descriptors
    same_label: np.ndarray  # bool[P]
    iou: np.ndarray  # float64[P] IoU after camera-rotation compensation (plain IoU without cameras)


def candidate_pairs(frame_index: np.ndarray, window: int, min_gap: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """All (a, b) with min_gap <= frame[b] - frame[a] <= window, ordered by (a, b) in the frame-sorted
    order (``min_gap`` 0: two detections of one frame once each, a before b in that order)."""
    f = np.asarray(frame_index, dtype=np.int64)
    order = np.argsort(f, kind="stable")
    fs = f[order]
    start = np.maximum(np.searchsorted(fs, fs + min_gap, side="left"), np.arange(len(fs)) + 1)
    end = np.searchsorted(fs, fs + window, side="right")
    cnt = end - start
    a_sorted = np.repeat(np.arange(len(fs)), cnt)
    offs = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    b_sorted = np.repeat(start, cnt) + offs
    return order[a_sorted], order[b_sorted]


def box_iou_pairs(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Row-wise IoU of boxes float[P,4] and float[P,4] (ymin, xmin, ymax, xmax)."""
    y0 = np.maximum(p[:, 0], q[:, 0])
    x0 = np.maximum(p[:, 1], q[:, 1])
    y1 = np.minimum(p[:, 2], q[:, 2])
    x1 = np.minimum(p[:, 3], q[:, 3])
    inter = np.clip(y1 - y0, 0, None) * np.clip(x1 - x0, 0, None)
    area = lambda r: np.clip(r[:, 2] - r[:, 0], 0, None) * np.clip(r[:, 3] - r[:, 1], 0, None)  # noqa: E731
    union = area(p) + area(q) - inter
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(union > 0, inter / union, 0.0)


def homographies(fa: np.ndarray, fb: np.ndarray, cams: Cameras) -> np.ndarray:
    """Infinite homographies float[P,3,3] ``K_b R_b R_a^T K_a^-1`` of the frame pairs (fa[p], fb[p]),
    computed once per distinct frame pair (a clip's pairs share a few per frame) and gathered:
    each matrix is the same product of the same stacked operations, so the same values to the bit."""
    key = np.stack([np.asarray(fa, np.int64), np.asarray(fb, np.int64)], axis=1)
    uniq, inv = np.unique(key, axis=0, return_inverse=True)
    ua, ub = uniq[:, 0], uniq[:, 1]
    Hm = cams.K[ub] @ cams.R[ub] @ np.swapaxes(cams.R[ua], 1, 2) @ np.linalg.inv(cams.K[ua])
    return Hm[inv.ravel()]


def rotation_warp(boxes: np.ndarray, fa: np.ndarray, fb: np.ndarray, cams: Cameras) -> np.ndarray:
    """Boxes float[P,4] of frames ``fa`` carried into frames ``fb`` by the camera rotation alone
    (bounding box of the four warped corners). Corners that land behind camera b keep the box as is."""
    W, H = cams.width, cams.height
    Hm = homographies(fa, fb, cams)  # [P,3,3]
    ys = boxes[:, [0, 0, 2, 2]] * H
    xs = boxes[:, [1, 3, 1, 3]] * W
    pts = np.stack([xs, ys, np.ones_like(xs)], axis=2)  # [P,4,3]
    q = np.einsum("pij,pkj->pki", Hm, pts)
    ok = np.all(q[:, :, 2] > 1e-9, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = q[:, :, 0] / q[:, :, 2] / W
        v = q[:, :, 1] / q[:, :, 2] / H
    warped = np.stack([v.min(1), u.min(1), v.max(1), u.max(1)], axis=1)
    return np.where(ok[:, None], warped, boxes)


def centred(vectors: np.ndarray) -> np.ndarray:
    """Descriptors centred on their mean and renormalised (float32[N,D]; N may be 0)."""
    v = np.asarray(vectors, np.float64)
    if len(v):  # no descriptor has no mean (numpy would warn of an empty slice)
        v = v - v.mean(0, keepdims=True)
    n = np.linalg.norm(v, axis=1, keepdims=True)
    return (v / np.where(n > 0, n, 1)).astype(np.float32)


def pair_cosines(v: np.ndarray, a: np.ndarray, b: np.ndarray, chunk: int = PAIR_CHUNK) -> np.ndarray:
    """Dot products float64[P] of rows ``a`` and ``b`` (int[P]) of ``v`` float32[N,D] (centred, unit
    descriptors: the cosines), ``chunk`` pairs at a time gathered into two reused float32[chunk,D]
    buffers: memory O(chunk x D), not O(P x D). Each value is the einsum of the one pair's rows,
    as on whole arrays, so the result is the same to the bit whatever ``chunk``."""
    out = np.empty(len(a), dtype=np.float64)
    m = min(chunk, len(a))
    va, vb = np.empty((m, v.shape[1]), v.dtype), np.empty((m, v.shape[1]), v.dtype)
    for s in range(0, len(a), chunk):
        k = min(chunk, len(a) - s)
        np.take(v, a[s:s + k], axis=0, out=va[:k], mode="clip")  # indices are valid: "clip" skips take's buffering
        np.take(v, b[s:s + k], axis=0, out=vb[:k], mode="clip")
        out[s:s + k] = np.einsum("pd,pd->p", va[:k], vb[:k])
    return out


def pair_ious(boxes: np.ndarray, f: np.ndarray, a: np.ndarray, b: np.ndarray, cameras: Cameras | None,
              chunk: int = PAIR_CHUNK) -> np.ndarray:
    """IoU float64[P] of box b with box a of each pair (a, b: int[P] into ``boxes`` float[N,4] and
    frames ``f`` int[N]), box a carried into b's frame by the camera rotation when ``cameras``;
    ``chunk`` pairs at a time (the warp's per-pair temporaries are ~1 KB a pair)."""
    out = np.empty(len(a), dtype=np.float64)
    for s in range(0, len(a), chunk):
        ca, cb = a[s:s + chunk], b[s:s + chunk]
        ba = boxes[ca]
        if cameras is not None:
            ba = rotation_warp(ba, f[ca], f[cb], cameras)
        out[s:s + len(ca)] = box_iou_pairs(ba, boxes[cb])
    return out


def pair_features(frame_index: np.ndarray, boxes: np.ndarray, labels: np.ndarray, vectors: np.ndarray | None,
                  cameras: Cameras | None, window: int) -> PairFeatures:
    """Cues of every candidate pair of one clip's detections (see module docstring), computed
    ``PAIR_CHUNK`` pairs at a time: memory O(P) for the cues, not O(P x D).

    ``vectors``: descriptors float[N,D] (raw; centred here on the clip), or None."""
    f = np.asarray(frame_index, dtype=np.int64)
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    _, label_code = np.unique(np.asarray(labels), return_inverse=True)
    label_code = label_code.ravel()
    a, b = candidate_pairs(f, window)
    iou = pair_ious(boxes, f, a, b, cameras)
    cos = None
    if vectors is not None:
        cos = pair_cosines(centred(vectors), a, b)
    return PairFeatures(a, b, f[b] - f[a], cos, label_code[a] == label_code[b], iou)


# ------------------------------------------------------------------------------------- calibration

def _llr(hist_true: np.ndarray, hist_false: np.ndarray) -> np.ndarray:
    """Smoothed, clipped log-likelihood ratio per bin (last axis = bins).

    Each class gets pseudo-counts in proportion to its size (``SMOOTHING`` pairs for the smaller
    class), spread like the pooled histogram: a bin seldom seen in either class tends to 0."""
    nt = hist_true.sum(-1, keepdims=True)
    nf = hist_false.sum(-1, keepdims=True)
    pooled = hist_true + hist_false + 1e-3
    pooled = pooled / pooled.sum(-1, keepdims=True)
    beta = SMOOTHING / np.maximum(np.minimum(nt, nf), 1.0)
    t = (hist_true + beta * nt * pooled) / np.maximum(nt * (1 + beta), 1e-12)
    f = (hist_false + beta * nf * pooled) / np.maximum(nf * (1 + beta), 1e-12)
    return np.clip(np.log(np.maximum(t, 1e-300)) - np.log(np.maximum(f, 1e-300)), -LLR_CLIP, LLR_CLIP)


def _fill_empty(values: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """``values`` (last axis = bins) with each bin that no pair fell in (``seen`` False, broadcast
    to ``values``) given the value of the nearest bin one did (the lower of two as near). Such a
    bin's ratio is 0, "no evidence", which read as neutral what lies past the fitted range: cosines
    under -0.8 (two objects of opposite look, the clip's two main ones once centred) weighed 0
    where -0.8 to -0.3 weighed -10, and gaps past the fitting window took no prior at all."""
    out = np.array(values, np.float64)
    seen = np.broadcast_to(np.asarray(seen, bool), out.shape)
    for row, row_seen in zip(out.reshape(-1, out.shape[-1]), seen.reshape(-1, out.shape[-1])):
        have = np.flatnonzero(row_seen)
        if len(have) == 0:
            continue
        bins = np.arange(len(row))
        nearest = have[np.argmin(np.abs(bins[:, None] - have[None, :]), axis=1)]
        row[:] = row[nearest]
    return out


def gap_bucket(gap: np.ndarray, edges) -> np.ndarray:
    """Index of each gap's bucket: bucket k holds gaps in [edges[k], edges[k+1]) (last one open)."""
    return np.clip(np.searchsorted(np.asarray(edges), gap, side="right") - 1, 0, len(edges) - 1)


def _bin(x: np.ndarray, edges) -> np.ndarray:
    """The bin of each cue value among ``edges`` (the ends' bins take what lies beyond them)."""
    if np.isnan(x).any():  # searchsorted puts NaN past every edge: the strongest attraction there is
        raise ValueError(f"{int(np.isnan(x).sum())} pair cue(s) are NaN (a NaN box or descriptor): no weight can be given")
    return np.clip(np.searchsorted(np.asarray(edges), x, side="right") - 1, 0, len(edges) - 2)


DEFAULT_GAP_EDGES = (1, 2, 3, 5, 9, 17)
DEFAULT_IOU_EDGES = (0.0, 1e-6, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0 + 1e-9)
DEFAULT_COS_EDGES = tuple(np.round(np.linspace(-1.0, 1.0, 21), 6).tolist()[:-1] + [1.0 + 1e-9])


def fit_calibration(features: list[PairFeatures], truth: list[np.ndarray], *, gap_edges=DEFAULT_GAP_EDGES,
                    iou_edges=DEFAULT_IOU_EDGES, cos_edges=DEFAULT_COS_EDGES, label_clip: float | None = None) -> dict:
    """Binned log-likelihood tables and per-gap prior log-odds from pairs with known truth
    (``truth[k]``: bool per pair of ``features[k]``, True = one object). Returns the dict that
    :mod:`tasks.tracking.calibration` stores."""
    gap = np.concatenate([p.gap for p in features])
    y = np.concatenate(truth).astype(bool)
    iou = np.concatenate([p.iou for p in features])
    same = np.concatenate([p.same_label for p in features])
    gb = gap_bucket(gap, gap_edges)
    ng, ni = len(gap_edges), len(iou_edges) - 1
    ib = _bin(iou, iou_edges)
    ht = np.zeros((ng, ni))
    hf = np.zeros((ng, ni))
    np.add.at(ht, (gb[y], ib[y]), 1)
    np.add.at(hf, (gb[~y], ib[~y]), 1)
    seen_gap = (ht + hf).sum(1) > 0  # a bucket past the fitting window: the last fitted one's values
    prior = _fill_empty(np.log((ht.sum(1) + 1.0) / (hf.sum(1) + 1.0)), seen_gap)
    motion = _fill_empty(_fill_empty(_llr(ht, hf), ht + hf > 0).T, seen_gap).T
    lab = _llr(np.array([np.sum(y & ~same), np.sum(y & same)], float),
               np.array([np.sum(~y & ~same), np.sum(~y & same)], float))
    if label_clip is not None:
        lab = np.clip(lab, -label_clip, label_clip)
    out = {
        "gap_edges": list(gap_edges), "prior": prior.round(4).tolist(),
        "iou_edges": list(iou_edges), "motion": motion.round(4).tolist(),
        "label": {"different": round(float(lab[0]), 4), "same": round(float(lab[1]), 4)},
        "cos_edges": list(cos_edges), "appearance": None,
        "pairs": {"true": int(y.sum()), "false": int((~y).sum())},
    }
    if all(p.cosine is not None for p in features):
        cos = np.concatenate([p.cosine for p in features])
        cb = _bin(cos, cos_edges)
        nc = len(cos_edges) - 1
        ct, cf = np.bincount(cb[y], minlength=nc).astype(float), np.bincount(cb[~y], minlength=nc).astype(float)
        out["appearance"] = _fill_empty(_llr(ct, cf), ct + cf > 0).round(4).tolist()
    return out


def affinities(p: PairFeatures, calibration: dict, *, appearance_weight: float = 1.0, label_weight: float = 1.0,
               motion_weight: float = 1.0, bias: float = 0.0) -> np.ndarray:
    """Edge weight (signed log-odds) per pair, from the cues and a calibration (see module docstring)."""
    gb = gap_bucket(p.gap, calibration["gap_edges"])
    w = np.asarray(calibration["prior"])[gb] + bias
    w = w + motion_weight * np.asarray(calibration["motion"])[gb, _bin(p.iou, calibration["iou_edges"])]
    lab = calibration["label"]
    w = w + label_weight * np.where(p.same_label, lab["same"], lab["different"])
    if p.cosine is not None and calibration.get("appearance") is not None:
        w = w + appearance_weight * np.asarray(calibration["appearance"])[_bin(p.cosine, calibration["cos_edges"])]
    return w
