"""Shadow tracks: a second track on an object a stronger track already follows (issues 18, 19).

A detector may box one object twice under two names (a table also called a desk's cabinet), or box a
large part of it under another name, over many frames. Class-aware NMS keeps both boxes and
``[detect] nms_agnostic_iou`` drops only the closest pairs, so the partition gives the second boxes a
track of their own: it follows an object another track follows, and people would be asked to
annotate that object twice (a duplicate if both get a pose, an item answered "none of these" if
not).

A track is a shadow when at least ``[tracking] shadow_share`` of its boxes overlap a box of a
stronger kept track on the same frame with IoU >= ``[tracking] shadow_iou``, a track whose mean
score is at least its own. Stronger: more detections, then a higher mean score, then the smaller
first detection index. Tracks are visited strongest first and compared with the tracks kept so far
only, so a dropped shadow never drops another track.

Why the score: the shadows worth dropping are weak boxes trailing a confident track. A longer
track can also be less sure of itself because it runs over two objects (a bed, then boxes beside
it): a confident track of one of them, overlapped by the long one on its frames, is that object's
best track. Measured on the tracks of the default benchmark and seeds 60606 and 101 (232 tracks,
23 shadows by count alone): the 18 shadows on no object and 2 of the 3 on an object that another
track follows scored below the track they overlap; the 2 shadows that were an object's only track
(a bed, a table; seed 101) scored above it, and are kept now. Boxes are (ymin, xmin, ymax, xmax)
normalised by the image size (IoU does not depend on the normalisation).
"""

from __future__ import annotations

import numpy as np

from tasks.tracking.affinity import box_iou_pairs, candidate_pairs


def same_frame_overlaps(frames: np.ndarray, boxes: np.ndarray, min_iou: float) -> tuple[np.ndarray, np.ndarray]:
    """Ordered pairs (a, b), both directions, of the N detections (``frames`` int[N], ``boxes``
    float[N,4]) on one frame whose boxes overlap with IoU >= ``min_iou``."""
    a, b = candidate_pairs(frames, 0, min_gap=0)
    hit = box_iou_pairs(boxes[a], boxes[b]) >= min_iou
    a, b = a[hit], b[hit]
    return np.concatenate([a, b]), np.concatenate([b, a])


def shadow_groups(groups: list[np.ndarray], frames: np.ndarray, boxes: np.ndarray, scores: np.ndarray,
                  min_iou: float, min_share: float) -> np.ndarray:
    """bool[G]: which of the ``groups`` (detection indices int64[M] each, disjoint) are shadows
    (module docstring) of the N detections on ``frames`` int[N] with ``boxes`` float[N,4] and
    ``scores`` float[N]. ``min_iou`` >= 1 finds none."""
    shadow = np.zeros(len(groups), bool)
    if min_iou >= 1.0 or len(groups) < 2:
        return shadow
    owner = np.full(len(frames), -1, np.int64)
    for g, members in enumerate(groups):
        owner[members] = g
    a, b = same_frame_overlaps(frames, boxes, min_iou)
    keep = (owner[a] >= 0) & (owner[b] >= 0) & (owner[a] != owner[b])
    a, b = a[keep], b[keep]
    by_group = np.argsort(owner[a], kind="stable")
    cuts = np.searchsorted(owner[a][by_group], np.arange(len(groups) + 1))
    mean = np.array([float(np.mean(scores[g])) for g in groups])
    strength = sorted(range(len(groups)), key=lambda g: (-len(groups[g]), -mean[g], int(np.min(groups[g]))))
    kept = np.zeros(len(groups), bool)
    for g in strength:
        pairs = by_group[cuts[g]:cuts[g + 1]]
        other = owner[b[pairs]]
        covered = np.unique(a[pairs][kept[other] & (mean[other] >= mean[g])])
        if len(covered) >= min_share * len(groups[g]):
            shadow[g] = True
        else:
            kept[g] = True
    return shadow
