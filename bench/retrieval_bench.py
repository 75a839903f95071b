"""Retrieval speed on libraries of 12,000 models x 10 views (120,000 views) and 120,000 models x 1 view.

The library's view descriptors are synthetic (768-d unit vectors around one random "look" per
model; rendering 120,000 views would take hours and is not what is measured); everything after
that is the pipeline's own code on a temporary warehouse: the whitening fit and per-model means
that ``cad_embed`` writes (timed once, library side), then the ``retrieval`` stage of one clip
with ``tracks`` tracks of ``per_track`` detections each, read from and written to Parquet, run
``repeats`` times in one process: wall and CPU seconds (all threads) of the first run and the
median of the others (retrieval's cost does not depend on views per model, only on models).

    python -m bench.retrieval_bench
"""

from __future__ import annotations

import json
import statistics
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pyarrow as pa

from bench.eval_retrieval import retrieval_recall
from cadestate.config import RetrievalConfig
from schemas.official import read_objects
from tasks.cad.classes import CLASSES
from tasks.cad.embed import model_embeddings
from tasks.detection.embed import vectors_array
from tasks.retrieval.retrieval import retrieve_clip
from tasks.retrieval.whitening import fit_whitening, whitening_table
from warehouse import Warehouse

D = 768
LABELS = ("chair", "couch", "bed", "dining table", "tv", "potted plant")


def _unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float32)


def build_library(wh: Warehouse, models: int, views: int, rng: np.random.Generator) -> dict:
    """Write a synthetic library's embedding_whitening, cad_model_embeddings and label_similarity."""
    classes = [c.name for c in CLASSES]
    model_class = [classes[i % len(classes)] for i in range(models)]
    cad_ids = [f"synth.m{i:05d}" for i in range(models)]
    raw = _unit(rng.normal(size=(models, 1, D)).astype(np.float32) + 0.3 * rng.normal(size=(models, views, D)).astype(np.float32))
    raw = raw.reshape(-1, D)
    t0 = time.perf_counter()
    white = fit_whitening(raw, "whiten", 128)
    per_model = model_embeddings("synth", dict(zip(cad_ids, model_class)), np.repeat(cad_ids, views).tolist(), white.apply(raw))
    fit_s = time.perf_counter() - t0
    wh.write("embedding_whitening", "synth", whitening_table("synth", white, len(raw)).cast(wh.spec("embedding_whitening").schema))
    wh.write("cad_model_embeddings", "synth", per_model)
    wh.write("label_similarity", "synth", pa.table({
        "library": ["synth"] * (len(LABELS) * len(classes)), "detector_label": np.repeat(LABELS, len(classes)).tolist(),
        "cad_class": classes * len(LABELS), "similarity": pa.array(rng.uniform(0, 1, len(LABELS) * len(classes)), pa.float32()),
        "encoder": ["synthetic"] * (len(LABELS) * len(classes)),
    }, schema=wh.spec("label_similarity").schema))
    return {"models": models, "views": len(raw), "whitening_and_model_means_s": round(fit_s, 2)}


def build_clip(wh: Warehouse, tracks: int, per_track: int, rng: np.random.Generator) -> int:
    """A clip with ``tracks`` x ``per_track`` detections, descriptors and track memberships."""
    n = tracks * per_track
    det_id = np.arange(n, dtype=np.int64) * 7
    labels = [LABELS[(i // per_track) % len(LABELS)] for i in range(n)]
    wh.write("detections", "bench", pa.table({
        "clip": ["bench"] * n, "det_id": det_id, "timestamp_us": det_id, "frame_index": pa.array(np.arange(n) % 138, pa.int32()),
        "box": [[0.1, 0.1, 0.5, 0.5]] * n, "label": labels, "label_id": pa.array(np.zeros(n), pa.int32()),
        "score": pa.array(np.full(n, 0.9), pa.float32()), "model_sha256": ["x"] * n,
    }, schema=wh.spec("detections").schema))
    wh.write("embeddings", "bench", pa.table({
        "clip": ["bench"] * n, "owner": ["detection"] * n, "owner_id": det_id,
        "vector": vectors_array(_unit(rng.normal(size=(n, D)))), "model_sha256": ["x"] * n,
    }, schema=wh.spec("embeddings").schema))
    wh.write("track_detections", "bench", pa.table({
        "clip": ["bench"] * n, "track_id": pa.array(np.arange(n) // per_track, pa.int32()), "det_id": det_id,
        "frame_index": pa.array(np.arange(n) % 138, pa.int32()), "timestamp_us": det_id,
    }, schema=wh.spec("track_detections").schema))
    return n


def run(models: int = 12_000, views: int = 10, tracks: int = 30, per_track: int = 40, repeats: int = 4) -> dict:
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        wh = Warehouse(tmp)
        library = build_library(wh, models, views, rng)
        n = build_clip(wh, tracks, per_track, rng)
        wall, cpu = [], []
        for i in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            retrieve_clip(wh, RetrievalConfig(), "bench", f"r{i}")
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
    return {**library, "tracks": tracks, "detections": n,
            "first_clip_s": round(wall[0], 3), "first_clip_cpu_s": round(cpu[0], 3),
            "retrieval_s_per_clip": round(statistics.median(wall[1:]), 3),
            "retrieval_cpu_s_per_clip": round(statistics.median(cpu[1:]), 3)}


def sizes() -> dict:
    """:func:`run` on the two library sizes of the module docstring."""
    return {"12k_models": run(12_000, 10), "120k_models": run(120_000, 1)}


def track_truth(bench_dir: Path, wh: Warehouse, clip: str, tracks: dict | None = None) -> dict[int, str]:
    """Pipeline track id -> ground-truth track id, for tracks (automatic and manual,
    :func:`tasks.tracking.clip_tracks.clip_tracks`; ``tracks``: its result when the caller has read
    it) whose boxes mostly (> half) match (IoU >= 0.5) boxes of one ground-truth object, matched as
    :func:`bench.track_bench.match_truth` matches boxes (detections through
    :func:`bench.track_bench.detector_clip`)."""
    from bench.track_bench import detector_clip, gt_clip, match_truth
    from tasks.tracking.clip_tracks import clip_tracks

    tracks = clip_tracks(wh, clip) if tracks is None else tracks
    cb = detector_clip(wh, bench_dir, clip)
    detected = dict(zip(cb.det_id.tolist(), cb.truth.tolist())) if cb is not None else {}
    drawn = [(t.track_id, b) for t in tracks.values() for b in t.boxes if b.det_id is None]
    drawn_truth = (match_truth(np.array([b.frame_index for _, b in drawn], np.int64),
                               np.array([b.box for _, b in drawn], np.float64).reshape(-1, 4),
                               gt_clip(bench_dir, clip, embed=False)) if drawn else [])
    members: dict[int, list[str]] = {t: [detected.get(b.det_id, "") for b in track.boxes if b.det_id is not None]
                                     for t, track in tracks.items()}
    for (t, _), truth in zip(drawn, drawn_truth):
        members[t].append(truth)
    result = {}
    for track_id, ids in members.items():
        if not ids:
            continue
        best, count = Counter(ids).most_common(1)[0]
        if best and count * 2 > len(ids):
            result[track_id] = best
    return result


def retrieval_accuracy(bench_dir: Path, wh: Warehouse) -> dict | None:
    """Recall@1 and @10 of the true CAD model and class among the ``cad_candidates`` of the
    tracks that correspond to a ground-truth object (None before retrieval ran)."""
    from bench.benchmark import CLASS_NAMES, read_manifest

    clips = [c for c in read_manifest(bench_dir).clips if c in wh.partitions("cad_candidates")]
    if not clips:
        return None
    ranked, truth, objects_found = {}, {}, set()
    for clip in clips:
        objects = {o.track_id: o for o in read_objects(Path(bench_dir) / clip / "objects.json").objects}
        for track_id, gt in track_truth(bench_dir, wh, clip).items():
            truth[(clip, track_id)] = (objects[gt].cad_id, CLASS_NAMES.get(objects[gt].cls, "other"))
            objects_found.add((clip, gt))
        for r in sorted(wh.read("cad_candidates", partitions=[clip]).to_pylist(), key=lambda r: r["rank"]):
            ranked.setdefault((clip, r["track_id"]), []).append((r["cad_id"], r["cad_class"]))
    if not truth:
        return None
    return {"clips": len(clips), "objects_found": len(objects_found), **retrieval_recall(ranked, truth).as_dict()}


def retrieval_markdown(retrieval: dict | None) -> list[str]:
    """Lines of the report's retrieval section (empty before retrieval ran)."""
    if not retrieval:
        return []
    return [f"## CAD retrieval ({retrieval['clips']} clips, {retrieval['num_tracks']} tracks matched to a ground-truth object)", "",
            "| | @1 | @10 |", "|---|---:|---:|",
            f"| true CAD model among the candidates | {retrieval['cad_recall@1']:.3f} | {retrieval['cad_recall@10']:.3f} |",
            f"| true class among the candidates | {retrieval['class_recall@1']:.3f} | {retrieval['class_recall@10']:.3f} |", ""]


if __name__ == "__main__":
    from bench.script_args import no_arguments

    no_arguments(__doc__)
    print(json.dumps(sizes(), indent=2))
