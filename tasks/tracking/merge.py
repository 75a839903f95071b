"""Fragments of one object joined in 3D, after the clique partition of ``tracking`` (issue 18).

The partition links detections at most ``[tracking] window`` frames apart, so an object that leaves
the view and comes back, or whose detections pause, is split over several tracks. The cameras are
known, so each fragment has a 3D position (:mod:`tasks.tracking.track3d`). Two fragments are joined
when they never hold two boxes in one frame and a logistic model of their cues says they are one
object with probability >= ``[tracking] merge_min_probability``. Cues of a pair (:data:`CUES`):

- ``ray_misfit``: log(1 + sqrt of the chi-square) the rays of both gain when one point must explain them
  all (the 3D distance of the two fragments in units of their uncertainty: two fragments seen from
  a narrow baseline are far apart only along the rays, which costs little);
- ``appearance``: cosine of the fragments' mean descriptors, centred on the clip's mean (as the
  tracking cue, :func:`tasks.tracking.affinity.centred`);
- ``same_label``: whether their score-weighted labels agree;
- ``log_gap``: log(1 + frames between their nearest detections);
- ``size_ratio``: |log| of the ratio of their objects' sizes (box diagonal x depth to the joint point);
- ``log_min_count``: log of the smaller fragment's detections (a short fragment's cues say less).

The model (:mod:`tasks.tracking.merge_calibration`, fitted on the benchmark by ``python -m
bench.merge_bench fit``) is applied greedily: the most probable pair is joined, its cues to the
others recomputed, until no pair reaches the threshold.

Thin tracks (part 2): after joining, a track with fewer than ``[tracking] thin_detections``
detections and no box on a manual-track key-frame (:func:`tasks.human.keyframes.regular_keyframes`,
``[manual_tracks] keyframes``) is too thin for people to annotate: it is dropped.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np

from tasks.tracking.track3d import Point3D, Rays, object_size, triangulate

CUES = ("ray_misfit", "appearance", "same_label", "log_gap", "size_ratio", "log_min_count")


@dataclass(frozen=True)
class Fragment:
    """One track before joining: ``members`` int64[M] indices of its detections (into the clip's
    arrays), ``frames`` int64[M] their frames (distinct), ``label`` its score-weighted label,
    ``look`` float64[D] sum of its centred descriptors (or empty), ``rays`` its box-centre rays,
    ``point`` their intersection."""

    members: np.ndarray
    frames: np.ndarray
    label: str
    look: np.ndarray
    rays: Rays
    point: Point3D


@dataclass(frozen=True)
class MergeModel:
    """Logistic model of the pair cues: p = sigmoid(coef . (x - mean) / scale + intercept), x float[6] in :data:`CUES` order."""

    mean: np.ndarray
    scale: np.ndarray
    coef: np.ndarray
    intercept: float

    @classmethod
    def from_dict(cls, d: dict) -> MergeModel:
        if tuple(d["cues"]) != CUES:
            raise ValueError(f"merge calibration has cues {d['cues']}, this code computes {CUES}: refit it")
        return cls(np.asarray(d["mean"], float), np.asarray(d["scale"], float), np.asarray(d["coef"], float),
                   float(d["intercept"]))

    def probability(self, x: np.ndarray) -> np.ndarray:
        """Probability float[P] that each pair of cues x float[P,6] is one object."""
        z = ((np.atleast_2d(x) - self.mean) / self.scale) @ self.coef + self.intercept
        return 1.0 / (1.0 + np.exp(-z))

    def bound(self, x: np.ndarray) -> float:
        """The most a pair with cues x float[6] can score whatever its 3D cues (``ray_misfit`` and
        ``size_ratio``, NaN in x): both are >= 0, so a negative coefficient does best at 0; 1 when
        one is positive (no bound)."""
        unknown = np.isnan(x)
        if (self.coef[unknown] > 0).any():
            return 1.0
        return float(self.probability(np.where(unknown, 0.0, x))[0])


@dataclass(frozen=True)
class MergeResult:
    """``groups``: the joined tracks, each the sorted detection indices int64[M], thin ones left out;
    ``joins``: fragments joined into another; ``thin``: tracks dropped as too thin."""

    groups: list[np.ndarray]
    joins: int
    thin: int


def vote_label(labels: np.ndarray, scores: np.ndarray) -> str:
    """The label with the largest summed score (ties: first in name order)."""
    tot: dict[str, float] = {}
    for lab, s in zip(labels.tolist(), scores.tolist()):
        tot[lab] = tot.get(lab, 0.0) + max(float(s), 1e-6)
    return min(tot, key=lambda k: (-tot[k], k))


def make_fragment(members: np.ndarray, frames: np.ndarray, labels: np.ndarray, scores: np.ndarray,
                  looks: np.ndarray | None, rays: Rays) -> Fragment:
    """The fragment of detections ``members`` (arrays of the clip; ``looks``: centred descriptors or None)."""
    m = np.sort(np.asarray(members, np.int64))
    sub = rays.subset(m)
    look = looks[m].sum(0).astype(np.float64) if looks is not None else np.zeros(0)
    return Fragment(m, frames[m], vote_label(labels[m], scores[m]), look, sub, triangulate(sub))


def join(a: Fragment, b: Fragment, labels: np.ndarray, scores: np.ndarray, rays: Rays) -> Fragment:
    """The fragment of the detections of ``a`` and ``b`` (``labels``, ``scores``, ``rays``: of the clip)."""
    m = np.concatenate([a.members, b.members])
    order = np.argsort(m)
    m = m[order]
    sub = rays.subset(m)
    return Fragment(m, np.concatenate([a.frames, b.frames])[order], vote_label(labels[m], scores[m]), a.look + b.look,
                    sub, triangulate(sub))


def plain_cues(a: Fragment, b: Fragment) -> np.ndarray:
    """Cues float[6] (:data:`CUES`) of two fragments but those that need their joint 3D point
    (``ray_misfit``, ``size_ratio``: NaN)."""
    norms = np.linalg.norm(a.look) * np.linalg.norm(b.look)
    cos = float(a.look @ b.look / norms) if norms > 0 else 0.0
    other = np.sort(b.frames)
    at = np.searchsorted(other, a.frames)  # the nearest frame of b is just before or at
    last = len(other) - 1
    gap = int(np.minimum(np.abs(a.frames - other[np.clip(at - 1, 0, last)]),
                         np.abs(a.frames - other[np.clip(at, 0, last)])).min())
    return np.array([np.nan, cos, float(a.label == b.label), np.log1p(gap), np.nan,
                     np.log(min(len(a.members), len(b.members)))])


def pair_cues(a: Fragment, b: Fragment, plain: np.ndarray | None = None) -> np.ndarray:
    """Cues float[6] (:data:`CUES`) of two fragments with no frame in common (``plain``: their
    :func:`plain_cues`, when known)."""
    x = plain_cues(a, b) if plain is None else plain.copy()
    joint = triangulate(a.rays + b.rays)
    x[0] = np.log1p(np.sqrt(max(joint.cost - a.point.cost - b.point.cost, 0.0)))
    na = len(a.members)
    size_a = object_size(a.rays, joint.depth[:na])
    size_b = object_size(b.rays, joint.depth[na:])
    x[4] = abs(np.log(max(size_a, 1e-3) / max(size_b, 1e-3)))
    return x


def compatible(a: Fragment, b: Fragment) -> bool:
    """Whether two fragments may be one object: they never hold two boxes in one frame."""
    return not np.intersect1d(a.frames, b.frames).size


def merge_fragments(fragments: list[Fragment], model: MergeModel, min_probability: float, labels: np.ndarray,
                    scores: np.ndarray, rays: Rays) -> tuple[list[Fragment], int]:
    """Join fragments greedily, most probable pair first (ties: the smaller indices), while a
    compatible pair reaches ``min_probability`` (module docstring). Returns the fragments left (a
    joined one takes the place of its first part) and the number of joins.

    The pairs that reach the threshold wait in a heap; a pair whose fragment has changed since it
    was scored is passed over when it comes up (the join scored its new pairs): each join costs the
    new fragment's pairs, not a pass over every pair of the clip."""
    frags = list(fragments)
    version = [0] * len(frags)
    heap: list[tuple[float, int, int, int, int]] = []

    def score(i: int, j: int) -> None:
        plain = plain_cues(frags[i], frags[j])
        if model.bound(plain) < min_probability - 1e-9:  # no 3D cue could lift it: triangulate nothing
            return
        if compatible(frags[i], frags[j]):
            p = float(model.probability(pair_cues(frags[i], frags[j], plain))[0])
            if p >= min_probability:  # below it a pair is never joined: only a join rescores it
                heapq.heappush(heap, (-p, i, j, version[i], version[j]))

    for i in range(len(frags)):
        for j in range(i + 1, len(frags)):
            score(i, j)
    alive = set(range(len(frags)))
    joins = 0
    while heap:
        _, i, j, vi, vj = heapq.heappop(heap)
        if i not in alive or j not in alive or vi != version[i] or vj != version[j]:
            continue
        frags[i] = join(frags[i], frags[j], labels, scores, rays)
        alive.discard(j)
        version[i] += 1
        joins += 1
        for k in sorted(alive - {i}):
            score(min(i, k), max(i, k))
    return [frags[k] for k in sorted(alive)], joins


def is_thin(fragment: Fragment, keyframes: np.ndarray, thin_detections: int) -> bool:
    """Too thin to annotate: fewer than ``thin_detections`` detections and none on a key-frame
    (``keyframes``: frame indices int[K])."""
    return len(fragment.members) < thin_detections and not np.isin(fragment.frames, keyframes).any()


def merge_step(groups: list[np.ndarray], frames: np.ndarray, labels: np.ndarray, scores: np.ndarray,
               looks: np.ndarray | None, rays: Rays, keyframes: np.ndarray, model: MergeModel | None,
               min_probability: float, min_detections: int, thin_detections: int) -> MergeResult:
    """Join the partition's ``groups`` (detection indices int64[M] each) in 3D (``model`` None: no
    joining), then leave out the groups shorter than ``min_detections`` and, counted as ``thin``,
    those too thin to annotate (:func:`is_thin`). ``frames``, ``labels``, ``scores``, ``looks``
    (centred descriptors float[N,D] or None) and ``rays`` are of the clip's N detections."""
    frags = [make_fragment(g, frames, labels, scores, looks, rays) for g in groups]
    joins = 0
    if model is not None:
        frags, joins = merge_fragments(frags, model, min_probability, labels, scores, rays)
    kept = [f for f in frags if len(f.members) >= min_detections]
    annotatable = [f for f in kept if not is_thin(f, keyframes, thin_detections)]
    return MergeResult([f.members for f in annotatable], joins, len(kept) - len(annotatable))
