"""Stage ``retrieval``: the top CAD models of every track (paper, Sec. 3.2).

For a track with detections f (label l_f, whitened unit descriptor w_f) and a CAD model m (class
k_m, whitened unit view descriptors b_mv, V views), the score is the mean over all F x V
(detection, view) pairs of ``c(l_f, k_m) * (1 + w_f . b_mv) / 2``, where ``c`` is the label
similarity of :mod:`tasks.retrieval.label_similarity` clipped at 0 (a soft class filter) and the second
factor maps the cosine to [0, 1]. Because the product is linear in b_mv, the mean over views is
exactly ``c(l_f, k_m) * (1 + w_f . mean_v b_mv) / 2``, and grouping the track's detections by
label gives ``sum_l c(l, k_m) * (n_l + (sum_{f in l} w_f) . b_m) / (2F)``: one small matrix
product per library however many views it has (``cad_model_embeddings`` holds b_m). ``c`` enters
raised to ``[retrieval] class_exponent`` for a detector's labels and to ``drawn_class_exponent``
(1: the paper's product) for a manual track's, whose class a person drew.

Reads: the clip's tracks, automatic and manual (:mod:`tasks.tracking.clip_tracks`: ``tracks``,
``track_detections``, ``detections``, ``embeddings``, ``manual_tracks``); every
library's ``cad_model_embeddings``, ``embedding_whitening`` and ``label_similarity``, as an index
built once per library content per process (:mod:`tasks.retrieval.index`). Writes:
the clip's ``cad_candidates`` (top ``[retrieval] top_k`` per track over all libraries, at most
``[retrieval] max_per_class`` of one class while other classes have models: :func:`diverse_order`;
none while the warehouse has no CAD library). Each library's descriptors are compared after that
library's own whitening.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pyarrow as pa
from threadpoolctl import threadpool_limits

from cadestate.config import RetrievalConfig
from cadestate.lineage import digest, table_digest
from tasks.retrieval.index import LibraryIndex, RetrievalError, load_index
from tasks.stage import StageContext, StageDef, StageOutput
from tasks.tracking.clip_tracks import MissingDescriptor, clip_tracks
from warehouse import Warehouse


@dataclass(frozen=True)
class TrackGroups:
    """One track's detections grouped by label: labels [G], counts int[G], sums of raw descriptors
    float32[G,D]; ``drawn``: a manual track, its label a person's (``manual_tracks``), not a detector's."""

    labels: list[str]
    counts: np.ndarray
    raw: list[np.ndarray]  # per group: raw unit descriptors [n_l, D]
    drawn: bool = False


def score_tracks(tracks: list[TrackGroups], index: LibraryIndex, class_exponent: float = 1.0,
                 drawn_class_exponent: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(score, appearance, class similarity), each float32[T, M], of every track against every model;
    the score weighs each detection's appearance by its class similarity raised to ``class_exponent``
    (1: the paper's product; the class similarity returned is the plain one), a drawn track's
    (:attr:`TrackGroups.drawn`) by it raised to ``drawn_class_exponent``.

    One (track, label) group at a time: its detections whitened and summed, one matrix-vector product
    with the models' vectors float32[M,k]. Batching the groups into one matrix product changed scores
    in their last bit (another summation order), enough to change a CAD-selection task's content and
    leave its answers unmatched, so it stays per group. The products run on one BLAS thread: at
    M = 120,000, OpenBLAS's threads, spinning for a worker that 2 busy cores did not schedule, burnt
    up to 0.8 s of CPU per clip (``python -m bench.retrieval_bench``)."""
    T, M = len(tracks), len(index.cad_ids)
    weights = {x: index.class_sim if x == 1.0 else {label: c ** np.float32(x) for label, c in index.class_sim.items()}
               for x in {class_exponent, drawn_class_exponent}}  # per label, once per call
    score, appearance, cls = (np.zeros((T, M), np.float32) for _ in range(3))
    with threadpool_limits(1, user_api="blas"):
        for t, track in enumerate(tracks):
            weight = weights[drawn_class_exponent if track.drawn else class_exponent]
            F = float(track.counts.sum())
            for label, n, raw in zip(track.labels, track.counts, track.raw):
                if label not in index.class_sim:
                    raise RetrievalError(f"detector label {label!r} has no class similarity in CAD library "
                                         f"{index.library!r}: rerun `cadestate cad ingest` after changing [detect] labels")
                dots = index.whitening.apply(raw).sum(0) @ index.vectors.T  # sum over the group's detections
                part = (n + dots) / 2  # sum over detections of (1 + cos) / 2, per model
                c = index.class_sim[label]
                score[t] += weight[label] * part / F
                appearance[t] += part / F
                cls[t] += c * n / F
    return score, appearance, cls


def top_order(score: np.ndarray, cad_ids: np.ndarray, k: int) -> np.ndarray:
    """Indices of the ``k`` best of M models for one track (scores float[M], cad_ids [M]): by score
    descending, ties by cad_id (deterministic). Equal to ``np.lexsort((cad_ids, -score))[:k]``, but
    only the models scoring at least the k-th best score are sorted."""
    candidates = np.arange(len(score))
    if 0 < k < len(score):
        candidates = np.flatnonzero(score >= np.partition(score, len(score) - k)[len(score) - k])
    return candidates[np.lexsort((cad_ids[candidates], -score[candidates]))[:k]]


def diverse_order(score: np.ndarray, cad_ids: np.ndarray, classes: np.ndarray, k: int, per_class: int) -> np.ndarray:
    """Indices of ``k`` models for one track (scores float[M], cad_ids [M], classes [M]: names, or
    :func:`class_codes`, which a caller ranking many tracks computes once): in the order of
    :func:`top_order`, at most ``per_class`` of one class among the models scoring above 0, then
    the best of those passed over (a library with few classes; models whose class similarity to
    every box's label is 0 score 0 and take no capped slot, as their order would be by cad_id
    alone). ``per_class >= k`` is :func:`top_order`. A detector that names a bathtub a table gives
    its track a table's class similarity; the cap keeps a few of the best-looking models of other
    classes among the candidates (``[retrieval] max_per_class``). Equal to a greedy pass over the
    whole library sorted, but only the best ``4 k`` are sorted, or, when one class fills them, each
    class's best ``per_class``."""
    if per_class >= k:
        return top_order(score, cad_ids, k)
    n = min(len(score), 4 * k)
    order = top_order(score, cad_ids, n)
    ok = (_rank_in_class(class_codes(classes[order])) < per_class) & (score[order] > 0)
    if ok.sum() >= k or n == len(score):
        return np.concatenate([order[ok], order[~ok]])[:k]
    # the best window lacks k models the cap lets in (one class fills it): those are each class's
    # best per_class scoring above 0, taken from the whole library, then the best of the rest
    by_class, starts = _grouped(class_codes(classes))
    groups = np.split(by_class, starts[1:])
    eligible = np.sort(np.concatenate([g[top_order(score[g], cad_ids[g], per_class)] for g in groups]))
    eligible = eligible[score[eligible] > 0]
    first = eligible[top_order(score[eligible], cad_ids[eligible], k)]
    if len(first) == k:
        return first
    passed = np.ones(len(score), bool)
    passed[first] = False
    rest = np.flatnonzero(passed)
    return np.concatenate([first, rest[top_order(score[rest], cad_ids[rest], k - len(first))]])


def class_codes(classes: np.ndarray) -> np.ndarray:
    """int[n]: one code per distinct class of ``classes`` [n] (names; int codes are returned as they are)."""
    return classes if classes.dtype.kind in "iu" else np.unique(classes, return_inverse=True)[1]


def _grouped(codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(indices of ``codes`` [n] grouped by code, stable; where each group starts among them)."""
    by_class = np.argsort(codes, kind="stable")
    sorted_codes = codes[by_class]
    return by_class, np.flatnonzero(np.r_[True, sorted_codes[1:] != sorted_codes[:-1]])


def _rank_in_class(codes: np.ndarray) -> np.ndarray:
    """int[n]: how many earlier entries of ``codes`` [n] have the same code."""
    by_class, starts = _grouped(codes)
    out = np.empty(len(codes), np.int64)
    out[by_class] = np.arange(len(codes)) - np.repeat(starts, np.diff(np.r_[starts, len(codes)]))
    return out


def library_digest(wh: Warehouse) -> str:
    """Digest of the latest completed outputs of every library's cad_embed and label_similarity
    (an input of the retrieval of every clip). Reads the ``runs`` partitions of the libraries only
    (a library's runs use its name as ``runs.clip``), found as the partitions of ``cad_models``: no
    listing of every clip's folder, which a warehouse of 10,000 clips pays per clip."""
    runs = wh.read("runs", wh.partitions("cad_models"), filters=[("stage", "in", ["cad_embed", "label_similarity"]), ("status", "==", "completed")],
                   columns=["clip", "stage", "output_hash", "started_at"]).sort_by("started_at").to_pylist()
    latest = {(r["clip"], r["stage"]): r["output_hash"] for r in runs}
    return digest(*(f"{k[0]}/{k[1]}={v}" for k, v in sorted(latest.items())))


def track_groups(wh: Warehouse, clip: str) -> tuple[list[int], list[TrackGroups]]:
    """The clip's track ids (automatic and manual, :func:`tasks.tracking.clip_tracks.clip_tracks`) and their
    boxes grouped by label, with raw descriptors."""
    try:
        tracks = clip_tracks(wh, clip, vectors=True)
    except MissingDescriptor as e:
        raise RetrievalError(str(e)) from None
    ids, groups = [], []
    for t, track in tracks.items():
        by_label: dict[str, list[np.ndarray]] = {}
        for b in track.boxes:
            if not np.isfinite(b.vector).all():  # a NaN scored every model NaN: ten ranked by name, or none kept
                raise RetrievalError(f"clip {clip}: track {t}: the descriptor of its box on frame {b.frame_index} is not "
                                     "finite (embeddings or manual_tracks): run its embed stage again")
            by_label.setdefault(b.label, []).append(b.vector)
        labels = sorted(by_label)
        ids.append(t)
        groups.append(TrackGroups(labels, np.array([len(by_label[l]) for l in labels]),
                                  [np.asarray(by_label[l], np.float32) for l in labels], drawn=track.manual))
    return ids, groups


def retrieve_clip(wh: Warehouse, cfg: RetrievalConfig, clip: str, run_id: str) -> StageOutput:
    """Write the clip's ``cad_candidates`` (see module docstring)."""
    libraries = wh.partitions("cad_model_embeddings")
    if not libraries:  # nothing to rank against yet; adding a library makes this stage stale
        empty = pa.Table.from_pylist([], schema=wh.spec("cad_candidates").schema)
        wh.write("cad_candidates", clip, empty)
        return StageOutput(0, table_digest(empty), "no CAD library in the warehouse yet: run `cadestate cad ingest`")
    track_ids, groups = track_groups(wh, clip)
    parts = [(index, *score_tracks(groups, index, cfg.class_exponent, cfg.drawn_class_exponent)) for index in (load_index(wh, lib) for lib in libraries)]
    score = np.concatenate([p[1] for p in parts], 1) if parts else np.zeros((len(groups), 0))
    appearance = np.concatenate([p[2] for p in parts], 1)
    cls = np.concatenate([p[3] for p in parts], 1)
    library = np.concatenate([np.full(len(p[0].cad_ids), p[0].library, dtype=object) for p in parts])
    cad_ids = np.concatenate([p[0].cad_ids for p in parts])
    classes = np.concatenate([p[0].classes for p in parts])
    codes = class_codes(classes)
    rows = []
    for t, track_id in enumerate(track_ids):
        order = diverse_order(score[t], cad_ids, codes, cfg.top_k, cfg.max_per_class)
        rows += [{"clip": clip, "track_id": track_id, "rank": r + 1, "library": library[m], "cad_id": cad_ids[m],
                  "cad_class": classes[m], "score": float(score[t, m]), "appearance": float(appearance[t, m]),
                  "class_similarity": float(cls[t, m])} for r, m in enumerate(order)]
    table = pa.Table.from_pylist(rows, schema=wh.spec("cad_candidates").schema)
    written = wh.write("cad_candidates", clip, table)
    return StageOutput(written, table_digest(table), f"top {cfg.top_k} of {len(cad_ids)} models for {len(track_ids)} tracks")


def _run(ctx: StageContext) -> StageOutput:
    """:func:`retrieve_clip`; its message names the CAD libraries the configuration makes stale
    (:func:`tasks.status.stale_libraries`: ranked as their stages last left them)."""
    from tasks.status import stale_libraries

    out = retrieve_clip(ctx.wh, ctx.cfg, ctx.unit, ctx.run_id)
    stale = stale_libraries(ctx.wh, ctx.config)
    if not stale:
        return out
    return replace(out, message=f"{out.message}; stale CAD librar{'y' if len(stale) == 1 else 'ies'} "
                                            f"{', '.join(sorted(stale))} (run `cadestate cad ingest`)")


def _clip_inputs(wh: Warehouse, clip: str) -> list[str]:
    """The CAD libraries' descriptors and label similarities."""
    return [library_digest(wh)]


STAGE = StageDef(
    name="retrieval", section="retrieval", scope="clip", upstream=("tracking", "manual_tracks"), tables=("cad_candidates",),
    description="top CAD models of every track, automatic and manual (appearance x class-label similarity)",
    run=_run, clip_inputs=_clip_inputs,
)
