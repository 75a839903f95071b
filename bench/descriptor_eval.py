"""What the learned descriptor buys in CAD retrieval, next to the PCA whitening it replaces.

Two measures, each for every ``[cad_embed] whitening`` of :data:`METHODS`, on benchmark folders
(:mod:`bench.benchmark`) whose clips were never training rooms (:mod:`bench.descriptor_data`):

- **ground-truth boxes, appearance alone** (the descriptor alone): each ground-truth object in
  view (:func:`bench.ignore.clip_objects_in_view`) is a track of its in-view boxes
  (:func:`bench.ignore.box_in_view`), embedded from the clip's video; models are ranked by the
  appearance term of retrieval, ``mean_f (1 + w_f . b_m) / 2`` (no class filter);
- **the pipeline's tracks** (needs ``cadestate bench run``): the retrieval stage's score
  (appearance x class-label similarity, :func:`tasks.retrieval.retrieval.score_tracks`) of the
  warehouse's tracks against the library whitened each way, scored as ``bench report`` scores
  ``cad_candidates`` (:func:`bench.retrieval_bench.track_truth`).

Both report the true CAD model and the true class among the first 1 and 10 candidates.

    python -m bench.descriptor_eval BENCH_DIR [BENCH_DIR ...] [--warehouse W] [--tracks]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

from bench.eval_retrieval import retrieval_recall
from cadestate.config import RetrievalConfig
from tasks.retrieval.descriptor import load_descriptor
from tasks.retrieval.index import LibraryIndex, build_index, list_matrix
from tasks.retrieval.retrieval import diverse_order, score_tracks
from warehouse import Warehouse

METHODS = ("whiten", "learned")
TOP_K = 10
DEFAULT_EXPONENTS = (1.0, RetrievalConfig().class_exponent)
"""The paper's product and the configured default, side by side."""
DEFAULT_CAP = RetrievalConfig().max_per_class
"""The configured ``[retrieval] max_per_class`` (results under another cap are keyed by it)."""


def whitened_index(wh: Warehouse, library: str, method: str) -> LibraryIndex:
    """``library``'s retrieval index with its views whitened by ``method`` (fitted now on the raw
    view descriptors of ``cad_embeddings``, as ``cad_embed`` fits it with the default
    ``[cad_embed]`` otherwise)."""
    from cadestate.config import CadEmbedConfig
    from tasks.cad.embed import library_whitening, model_embeddings

    base = build_index(wh, library)
    views = wh.read("cad_embeddings", partitions=[library], columns=["cad_id", "vector"])
    raw = list_matrix(views.column("vector"))
    fitted = library_whitening(raw, CadEmbedConfig(whitening=method))
    per_model = model_embeddings(library, dict(zip(base.cad_ids.tolist(), base.classes.tolist())),
                                 views.column("cad_id").to_pylist(), fitted.apply(raw))
    assert per_model.column("cad_id").to_pylist() == base.cad_ids.tolist()
    return dataclasses.replace(base, vectors=list_matrix(per_model.column("vector")), whitening=fitted)


def gt_tracks(bench_dir: Path, clip: str) -> list[tuple[str, str, np.ndarray]]:
    """(cad_id, class name, raw descriptors float32[n, D] of its in-view boxes) of every object in view."""
    from bench.benchmark import CLASS_NAMES
    from bench.ignore import box_fractions, box_in_view, clip_objects_in_view
    from bench.track_bench import gt_clip
    from schemas.official import read_objects

    cb = gt_clip(bench_dir, clip, embed=True)
    fractions = box_fractions(bench_dir, clip)
    good = np.array([box_in_view(*fractions.get((int(t), str(o)), (0.0, 1.0))) for t, o in zip(cb.timestamp_us, cb.truth)], bool)
    objects = {o.track_id: o for o in read_objects(bench_dir / clip / "objects.json").objects}
    return [(objects[o].cad_id, CLASS_NAMES.get(objects[o].cls, "other"), cb.vectors[good & (cb.truth == o)])
            for o in sorted(clip_objects_in_view(bench_dir, clip))]


def ranked(libs: list[LibraryIndex], scores: list[np.ndarray], per_class: int = TOP_K) -> list[tuple[str, str]]:
    """The first :data:`TOP_K` (cad_id, class) over all libraries, given each library's scores
    float[M_l] of one track, ordered as the retrieval stage orders them with ``[retrieval]
    max_per_class`` = ``per_class`` (default: no cap, the descriptor's own ranking)."""
    score = np.concatenate(scores)
    cad_ids = np.concatenate([lib.cad_ids for lib in libs])
    classes = np.concatenate([lib.classes for lib in libs])
    return [(cad_ids[m], classes[m]) for m in diverse_order(score, cad_ids, classes, TOP_K, per_class)]


def gt_box_recall(bench_dirs: list[Path], indexes: dict[str, list[LibraryIndex]]) -> dict[str, dict]:
    """Per method: recall@1/@10 of the true model and class, appearance alone, ground-truth boxes."""
    from bench.benchmark import read_manifest

    tracks = [(d.name, clip, *t) for d in bench_dirs for clip in read_manifest(d).clips for t in gt_tracks(d, clip)]
    out = {}
    for method, libs in indexes.items():
        ranks, truth = {}, {}
        for k, (_, _, cad_id, cls, raw) in enumerate(tracks):
            truth[k] = (cad_id, cls)
            if not len(raw):
                continue
            ranks[k] = ranked(libs, [(len(raw) + lib.whitening.apply(raw).sum(0) @ lib.vectors.T) / (2 * len(raw)) for lib in libs])
        out[method] = retrieval_recall(ranks, truth).as_dict()
    return out


def pipeline_recall(bench_dir: Path, wh: Warehouse, indexes: dict[str, list[LibraryIndex]],
                    class_exponents: tuple[float, ...] = (1.0,), caps: tuple[int, ...] = (DEFAULT_CAP,)) -> dict[str, dict]:
    """Per method and ``[retrieval] class_exponent``: recall@1/@10 of the warehouse's tracks of
    ``bench_dir``'s clips, scored and ordered as the retrieval stage scores and orders them
    (class-label similarity included; a manual track's at the default ``drawn_class_exponent``), per ``[retrieval] max_per_class`` of ``caps``; keyed by the
    method, with ``c^x`` after it for an exponent x other than 1 and ``max N/class`` for a cap
    other than the default."""
    from bench.benchmark import CLASS_NAMES, read_manifest
    from bench.retrieval_bench import track_truth
    from schemas.official import read_objects
    from tasks.retrieval.retrieval import track_groups

    clips = [c for c in read_manifest(bench_dir).clips if c in wh.partitions("tracks")]
    per_clip = []
    for clip in clips:
        objects = {o.track_id: o for o in read_objects(bench_dir / clip / "objects.json").objects}
        truth = {(clip, t): (objects[g].cad_id, CLASS_NAMES.get(objects[g].cls, "other")) for t, g in track_truth(bench_dir, wh, clip).items()}
        per_clip.append((clip, *track_groups(wh, clip), truth))
    out, drawn = {}, RetrievalConfig().drawn_class_exponent  # a person's drawn class, weighed as the stage does
    for (method, libs), x, cap in ((m, x, c) for m in indexes.items() for x in class_exponents for c in caps):
        ranks, truth = {}, {}
        for clip, ids, groups, clip_truth in per_clip:
            truth.update(clip_truth)
            scores = [score_tracks(groups, lib, x, drawn)[0] for lib in libs]
            for t, track_id in enumerate(ids):
                ranks[(clip, track_id)] = ranked(libs, [s[t] for s in scores], cap)
        key = method + ("" if x == 1.0 else f" c^{x:g}") + ("" if cap == DEFAULT_CAP else f" max {cap}/class")
        out[key] = {"clips": len(clips), **retrieval_recall(ranks, truth).as_dict()} if truth else None
    return out


def run(bench_dirs: list[Path], wh: Warehouse, tracks: bool, class_exponents: tuple[float, ...] = DEFAULT_EXPONENTS,
        caps: tuple[int, ...] = (DEFAULT_CAP,)) -> dict:
    libraries = wh.partitions("cad_embeddings")
    indexes = {m: [whitened_index(wh, lib, m) for lib in libraries] for m in METHODS}
    result = {"benchmarks": {d.name: {"gt_boxes": gt_box_recall([d], indexes)} for d in bench_dirs}}
    if tracks:
        for d in bench_dirs:
            result["benchmarks"][d.name]["pipeline_tracks"] = pipeline_recall(d, wh, indexes, class_exponents, caps)
    result["descriptor"] = load_descriptor()[1]
    return result


def markdown(result: dict) -> list[str]:
    lines = ["| benchmark | tracks | whitening | model @1 | model @10 | class @1 | class @10 |", "|---|---|---|---:|---:|---:|---:|"]
    for name, parts in result["benchmarks"].items():
        for kind, by_method in parts.items():
            for method, r in by_method.items():
                if r:
                    lines.append(f"| {name} | {kind} ({r['num_tracks']}) | {method} | {r['cad_recall@1']:.3f} | {r['cad_recall@10']:.3f} "
                                 f"| {r['class_recall@1']:.3f} | {r['class_recall@10']:.3f} |")
    return lines


def main(argv: list[str] | None = None) -> int:
    from bench.track_bench import open_warehouse

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("bench_dirs", type=Path, nargs="+")
    parser.add_argument("--warehouse", type=Path, default=None, help="the warehouse the benchmarks ran in (default: configured)")
    parser.add_argument("--tracks", action="store_true", help="also score the pipeline's tracks (after `cadestate bench run`)")
    parser.add_argument("--class-exponents", default=",".join(f"{x:g}" for x in DEFAULT_EXPONENTS),
                        help="comma-separated [retrieval] class_exponent values to score the tracks with")
    parser.add_argument("--max-per-class", default=str(DEFAULT_CAP),
                        help=f"comma-separated [retrieval] max_per_class values to order the tracks' candidates with "
                             f"(default {DEFAULT_CAP}; {TOP_K} or more: no cap)")
    args = parser.parse_args(argv)
    exponents = tuple(float(x) for x in args.class_exponents.split(","))
    caps = tuple(int(x) for x in args.max_per_class.split(","))
    result = run(args.bench_dirs, open_warehouse(args.warehouse), args.tracks, exponents, caps)
    print(json.dumps(result, indent=1))
    print("\n".join(markdown(result)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
