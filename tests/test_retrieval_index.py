"""The retrieval index: built from Arrow columns, equal to the row-wise build it replaces, kept per
process while the library's files are unchanged; the stage's top-k equals a full sort and its
candidates equal a brute-force mean over every (detection, view) pair."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from cadestate.config import RetrievalConfig
from tasks.detection.embed import vectors_array
from tasks.retrieval.index import build_index, clear_cache, list_matrix, load_index
from tasks.retrieval.retrieval import diverse_order, retrieve_clip, top_order
from tasks.retrieval.whitening import fit_whitening, read_whitening, whitening_table

CLASSES = ["chair", "sofa", "table", "bed", "lamp"]
LABELS = ["chair", "couch", "tv"]


def unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float32)


def write_library(wh, library: str, models: int, rng: np.random.Generator, D: int = 16, V: int = 3) -> np.ndarray:
    """A random library (views float32[M,V,D], duplicated models for exact ties); returns its views."""
    views = unit(rng.normal(size=(models, 1, D)) + 0.3 * rng.normal(size=(models, V, D)))
    views[1] = views[0]  # models 0 and 1 look alike: equal scores, ordered by cad_id
    white = fit_whitening(views.reshape(-1, D), "whiten", 8)
    wh.write("embedding_whitening", library, whitening_table(library, white, models * V).cast(wh.spec("embedding_whitening").schema))
    classes = [CLASSES[m % len(CLASSES)] if m != 1 else CLASSES[0] for m in range(models)]
    means = np.stack([white.apply(views[m]).mean(0) for m in range(models)])
    order = rng.permutation(models)  # written unsorted: the warehouse reads them sorted by cad_id
    wh.write("cad_model_embeddings", library, pa.table({
        "library": [library] * models, "cad_id": [f"{library}.m{m:03d}" for m in order],
        "class": [classes[m] for m in order], "vector": vectors_array(means[order]),
        "views": pa.array([V] * models, pa.int32())}, schema=wh.spec("cad_model_embeddings").schema))
    pairs = [(l, c) for l in LABELS for c in CLASSES if (l, c) != ("tv", "lamp")]  # a pair missing: similarity 0
    wh.write("label_similarity", library, pa.table({
        "library": [library] * len(pairs), "detector_label": [l for l, _ in pairs], "cad_class": [c for _, c in pairs],
        "similarity": pa.array(rng.uniform(-0.3, 1, len(pairs)), pa.float32()),  # negatives clip to 0
        "encoder": ["test"] * len(pairs)}, schema=wh.spec("label_similarity").schema))
    return views


def row_wise_index(wh, library: str) -> dict:
    """The index as the previous implementation built it, through Python lists."""
    models = wh.read("cad_model_embeddings", partitions=[library]).to_pylist()
    classes = np.array([m["class"] for m in models], dtype=object)
    table: dict[str, dict[str, float]] = {}
    for r in wh.read("label_similarity", partitions=[library]).to_pylist():
        table.setdefault(r["detector_label"], {})[r["cad_class"]] = max(float(r["similarity"]), 0.0)
    return {"cad_ids": np.array([m["cad_id"] for m in models], dtype=object), "classes": classes,
            "vectors": np.asarray([m["vector"] for m in models], np.float32),
            "class_sim": {l: np.array([b.get(c, 0.0) for c in classes], np.float32) for l, b in table.items()}}


def test_columnar_index_equals_the_row_wise_build(wh):
    write_library(wh, "lib", 40, np.random.default_rng(1))
    index, reference = build_index(wh, "lib"), row_wise_index(wh, "lib")
    assert list(index.cad_ids) == list(reference["cad_ids"]) == sorted(reference["cad_ids"])
    assert list(index.classes) == list(reference["classes"])
    assert index.vectors.dtype == np.float32 and np.array_equal(index.vectors, reference["vectors"])
    assert index.class_sim.keys() == reference["class_sim"].keys()
    for label, sim in reference["class_sim"].items():
        assert index.class_sim[label].dtype == np.float32 and np.array_equal(index.class_sim[label], sim)
    assert np.array_equal(index.whitening.projection, read_whitening(wh, "lib").projection)


def test_list_matrix_reads_the_flat_values_and_refuses_ragged_rows():
    v = np.arange(12, dtype=np.float32).reshape(4, 3)
    assert np.array_equal(list_matrix(pa.chunked_array([vectors_array(v[:1]), vectors_array(v[1:])])), v)
    assert np.array_equal(list_matrix(vectors_array(v).slice(1, 2)), v[1:3])
    assert list_matrix(vectors_array(np.zeros((0, 3)))).shape == (0, 0)
    with pytest.raises(ValueError, match="unequal lengths"):
        list_matrix(pa.array([[1.0, 2.0], [3.0]], pa.list_(pa.float32())))


def test_index_is_kept_until_the_library_is_rewritten(wh):
    clear_cache()
    rng = np.random.default_rng(2)
    write_library(wh, "lib", 12, rng)
    first = load_index(wh, "lib")
    assert load_index(wh, "lib") is first and not first.vectors.flags.writeable
    write_library(wh, "lib", 12, rng)  # re-ingested: other descriptors
    second = load_index(wh, "lib")
    assert second is not first and not np.array_equal(second.vectors, first.vectors)
    assert np.array_equal(second.vectors, row_wise_index(wh, "lib")["vectors"])
    sims = wh.read("label_similarity", partitions=["lib"])
    wh.write("label_similarity", "lib", sims.set_column(3, "similarity", pa.array(np.ones(sims.num_rows), pa.float32())))
    third = load_index(wh, "lib")  # only the label similarity changed
    assert third is not second and np.all(third.class_sim["chair"] == 1.0)
    clear_cache()
    assert load_index(wh, "lib") is not third


def test_top_order_equals_a_full_sort():
    rng = np.random.default_rng(3)
    cad_ids = np.array([f"m{i:03d}" for i in rng.permutation(200)], dtype=object)
    for _ in range(20):
        score = np.round(rng.uniform(size=200), 1).astype(np.float32)  # many ties, some across the k-th place
        for k in (0, 1, 7, 10, 199, 200, 250):
            assert top_order(score, cad_ids, k).tolist() == np.lexsort((cad_ids, -score))[:k].tolist()


def test_diverse_order_caps_a_class_while_others_have_models():
    score = np.array([0.99, 0.98, 0.97, 0.96, 0.95, 0.94, 0.93, 0.92, 0.91, 0.5, 0.4, 0.3, 0.2], np.float32)
    classes = np.array(["table"] * 9 + ["bathtub", "bed", "sink", "sink"], dtype=object)
    cad_ids = np.array([f"m{i:02d}" for i in range(13)], dtype=object)
    # the 7 best tables, then the best of the other classes (the second sink is the 10th)
    assert diverse_order(score, cad_ids, classes, 10, 7).tolist() == [0, 1, 2, 3, 4, 5, 6, 9, 10, 11]
    assert diverse_order(score, cad_ids, classes, 10, 10).tolist() == list(range(10))  # no cap: top_order
    assert diverse_order(score, cad_ids, classes, 10, 2).tolist() == [0, 1, 9, 10, 11, 12, 2, 3, 4, 5]  # filled up
    one = np.array(["table"] * 13, dtype=object)  # a library of one class: the cap cannot hold
    assert diverse_order(score, cad_ids, one, 10, 3).tolist() == top_order(score, cad_ids, 10).tolist()
    assert diverse_order(score[:4], cad_ids[:4], classes[:4], 10, 3).tolist() == [0, 1, 2, 3]  # fewer models than k
    assert diverse_order(score[:0], cad_ids[:0], classes[:0], 10, 3).tolist() == []
    unrelated = np.where(classes == "table", score, 0).astype(np.float32)  # other classes' similarity 0: score 0
    assert diverse_order(unrelated, cad_ids, classes, 10, 7).tolist() == list(range(10))  # no slot for a 0 score


def test_diverse_order_equals_a_greedy_pass_over_a_full_sort():
    """Against a reference: the whole library sorted (ties by cad_id), taken greedily under the cap
    (scores above 0 only), the rest filled from what the cap passed over."""
    rng = np.random.default_rng(5)
    cad_ids = np.array([f"m{i:03d}" for i in rng.permutation(300)], dtype=object)
    for _ in range(30):
        score = np.round(rng.uniform(size=300), 1).astype(np.float32)
        classes = rng.choice(np.array(["chair", "table", "sofa", "bed"], dtype=object), 300, p=[0.85, 0.1, 0.04, 0.01])
        full = np.lexsort((cad_ids, -score)).tolist()
        for k, cap in ((10, 7), (10, 1), (10, 3), (40, 5), (10, 10), (300, 20)):
            taken, kept = {}, []
            for m in full:
                if taken.get(classes[m], 0) < cap and score[m] > 0 and len(kept) < k:
                    kept.append(m)
                    taken[classes[m]] = taken.get(classes[m], 0) + 1
            kept += [m for m in full if m not in kept][:k - len(kept)]
            assert diverse_order(score, cad_ids, classes, k, cap).tolist() == kept, (k, cap)


def test_candidates_equal_the_mean_over_every_detection_and_view(wh):
    """Two libraries, three tracks: ranks, ids and scores against a brute-force reference (the
    configured class exponent), without a class cap and with one that binds (2 per class)."""
    rng = np.random.default_rng(4)
    views = {lib: write_library(wh, lib, 30, rng) for lib in ("a", "b")}
    dets = [(t, LABELS[(t + f) % 2 + (t == 2)], unit(rng.normal(size=16))) for t in range(3) for f in range(4)]
    wh.write("detections", "c", pa.Table.from_pylist([
        {"clip": "c", "det_id": i, "timestamp_us": i, "frame_index": i, "box": [0.1, 0.1, 0.5, 0.5], "label": label,
         "label_id": 0, "score": 0.9, "model_sha256": "x"} for i, (_, label, _) in enumerate(dets)], schema=wh.spec("detections").schema))
    wh.write("embeddings", "c", pa.Table.from_pylist([
        {"clip": "c", "owner": "detection", "owner_id": i, "vector": v.tolist(), "model_sha256": "x"}
        for i, (_, _, v) in enumerate(dets)], schema=wh.spec("embeddings").schema))
    wh.write("track_detections", "c", pa.Table.from_pylist([
        {"clip": "c", "track_id": t, "det_id": i, "frame_index": i, "timestamp_us": i} for i, (t, _, _) in enumerate(dets)],
        schema=wh.spec("track_detections").schema))
    clear_cache()
    cfg = RetrievalConfig(top_k=10, max_per_class=10)
    retrieve_clip(wh, cfg, "c", "r")
    got = {(r["track_id"], r["rank"]): r for r in wh.read("cad_candidates", partitions=["c"]).to_pylist()}
    retrieve_clip(wh, RetrievalConfig(top_k=10, max_per_class=2), "c", "r2")
    capped = {(r["track_id"], r["rank"]): r for r in wh.read("cad_candidates", partitions=["c"]).to_pylist()}
    for t in range(3):
        brute, classes = [], {}
        for lib, v in views.items():
            white, models = read_whitening(wh, lib), wh.read("cad_model_embeddings", partitions=[lib]).to_pylist()
            sim = {(r["detector_label"], r["cad_class"]): max(r["similarity"], 0.0)
                   for r in wh.read("label_similarity", partitions=[lib]).to_pylist()}
            for m in models:
                b = white.apply(v[int(m["cad_id"].split(".m")[1])])
                pairs = [sim.get((label, m["class"]), 0.0) ** cfg.class_exponent * (1 + white.apply(d)[0] @ b[j]) / 2
                         for tt, label, d in dets if tt == t for j in range(len(b))]
                brute.append((-np.mean(pairs), m["cad_id"], lib))
                classes[m["cad_id"]] = m["class"]
        for rank, (neg, cad_id, lib) in enumerate(sorted(brute)[:10], 1):
            row = got[(t, rank)]
            assert (row["cad_id"], row["library"]) == (cad_id, lib)
            assert row["score"] == pytest.approx(-neg, abs=1e-5)
        taken: dict[str, int] = {}
        expected = []
        for neg, cad_id, _ in sorted(brute):  # greedily, at most 2 of a class, scores above 0 (then filled up)
            if taken.get(classes[cad_id], 0) < 2 and -neg > 0 and len(expected) < 10:
                expected.append(cad_id)
                taken[classes[cad_id]] = taken.get(classes[cad_id], 0) + 1
        expected += [cad_id for _, cad_id, _ in sorted(brute) if cad_id not in expected][:10 - len(expected)]
        assert expected != [cad_id for _, cad_id, _ in sorted(brute)[:10]]  # the cap binds
        assert [capped[(t, rank)]["cad_id"] for rank in range(1, 11)] == expected
