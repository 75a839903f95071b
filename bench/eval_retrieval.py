"""CAD retrieval: recall@k of the true CAD model and of the true class among a track's candidates.

Input per track (any hashable key, e.g. (clip, track_id)): the ranked candidate list, best first,
as (cad_id, class) pairs (the pipeline offers 10 to the annotator), and the ground truth
(cad_id, class). A track with no candidate list counts as a miss at every k.
Class recall@k: the true class is the class of one of the first k candidates.
"""

from __future__ import annotations

from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class RetrievalReport:
    """Recalls in [0, 1], keyed by k."""

    cad_recall: dict[int, float]
    class_recall: dict[int, float]
    num_tracks: int

    def as_dict(self) -> dict:
        return {"num_tracks": self.num_tracks, **{f"cad_recall@{k}": v for k, v in self.cad_recall.items()},
                **{f"class_recall@{k}": v for k, v in self.class_recall.items()}}


def retrieval_recall(ranked: Mapping[Hashable, Sequence[tuple[str, str]]],
                     truth: Mapping[Hashable, tuple[str, str]], ks: Sequence[int] = (1, 10)) -> RetrievalReport:
    """Recall@k over the tracks of ``truth`` (tracks only in ``ranked`` are ignored).

    ``ranked[key]``: [(cad_id, class), ...] best first; ``truth[key]``: (cad_id, class).
    """
    if not truth:
        raise ValueError("no ground-truth tracks")
    cad_hits = {k: 0 for k in ks}
    cls_hits = {k: 0 for k in ks}
    for key, (cad_id, cls) in truth.items():
        cands = list(ranked.get(key, ()))
        for k in ks:
            top = cands[:k]
            cad_hits[k] += any(c == cad_id for c, _ in top)
            cls_hits[k] += any(c == cls for _, c in top)
    n = len(truth)
    return RetrievalReport({k: cad_hits[k] / n for k in ks}, {k: cls_hits[k] / n for k in ks}, n)
