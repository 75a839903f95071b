"""Temporal rescoring of a clip's detections (a simplified Seq-NMS, Han et al. 2016).

A detector scores each frame alone, so a real object's box that scores 0.3 on one frame and 0.7 on
the next is kept or lost by chance, and a box on nothing that scores 0.5 on a single frame is kept.
Walkthrough frames change little from one to the next, so the clip says more than a frame: boxes are
linked into chains, frame t to frame t+1, where two boxes of the same label are each other's best
overlap (IoU) and overlap by at least ``link_iou``; each box's score becomes

    weight * chain + (1 - weight) * own,   chain = max(own, mean score of its chain) * min(1, chain length / frames)

so that a weak box on an object seen for many frames rises towards its chain's mean, a sure box on
such an object keeps its score (its chain's weak boxes do not pull it down), and a box whose chain
is shorter than ``frames`` (most often one on nothing, seen on a frame or two) falls.
The detector runs at a lower candidate threshold first, so that weak boxes can join their chains;
:mod:`tasks.detection.detect` keeps the boxes whose new score reaches ``[detect] score_threshold``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FrameDetections:
    """One frame's detections, in the clip's frame order: boxes float[K,4] (x1, y1, x2, y2, any one
    frame shared by the clip's frames, e.g. image pixels), scores float[K] in [0, 1], labels int[K]."""

    boxes: np.ndarray
    scores: np.ndarray
    labels: np.ndarray


def pairwise_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU float[N,M] of boxes float[N,4] and float[M,4] (x1, y1, x2, y2)."""
    lo, hi = np.maximum(a[:, None, :2], b[None, :, :2]), np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.clip(hi - lo, 0, None).prod(-1)
    area_a, area_b = (a[:, 2:] - a[:, :2]).prod(-1), (b[:, 2:] - b[:, :2]).prod(-1)
    union = area_a[:, None] + area_b[None, :] - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1), 0.0)


def mutual_links(a: FrameDetections, b: FrameDetections, link_iou: float) -> list[tuple[int, int]]:
    """Pairs (i, j): box i of ``a`` and box j of ``b`` share a label, are each other's best overlap
    among boxes of that label, and overlap by IoU >= ``link_iou``."""
    if not len(a.scores) or not len(b.scores):
        return []
    iou = pairwise_iou(a.boxes, b.boxes) * (a.labels[:, None] == b.labels[None, :])
    best_j, best_i = iou.argmax(1), iou.argmax(0)
    return [(i, int(j)) for i, j in enumerate(best_j) if best_i[j] == i and iou[i, j] >= link_iou]


def chain_ids(frames: Sequence[FrameDetections], link_iou: float) -> np.ndarray:
    """Chain id int[N] of each of the clip's N boxes (frames concatenated in order): boxes joined by
    :func:`mutual_links` between consecutive frames share one."""
    offsets = np.cumsum([0] + [len(f.scores) for f in frames])
    parent = np.arange(offsets[-1])

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    for t in range(len(frames) - 1):
        for i, j in mutual_links(frames[t], frames[t + 1], link_iou):
            parent[root(offsets[t] + i)] = root(offsets[t + 1] + j)
    return np.array([root(k) for k in range(offsets[-1])], np.int64)


def temporal_scores(frames: Sequence[FrameDetections], weight: float, link_iou: float, chain_frames: int) -> list[np.ndarray]:
    """Each frame's scores float[K] after rescoring (module docstring); ``weight`` 0 returns them unchanged."""
    if weight == 0 or not frames:
        return [np.asarray(f.scores, np.float64) for f in frames]
    own = np.concatenate([np.asarray(f.scores, np.float64) for f in frames])
    _, chain, length = np.unique(chain_ids(frames, link_iou), return_inverse=True, return_counts=True)
    mean = np.bincount(chain, weights=own) / length
    new = weight * np.maximum(own, mean[chain]) * np.minimum(1.0, length / chain_frames)[chain] + (1 - weight) * own
    return np.split(new, np.cumsum([len(f.scores) for f in frames])[:-1])
