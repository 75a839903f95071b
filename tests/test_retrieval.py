"""CAD retrieval: the grouped score equals the paper's mean over all detection x view pairs; the
stage ranks, breaks ties deterministically and names what is missing; label similarity is real."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from cadestate.config import RetrievalConfig
from tasks.retrieval.retrieval import LibraryIndex, RetrievalError, TrackGroups, retrieve_clip, score_tracks
from tasks.retrieval.whitening import fit_whitening, whitening_table


def unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float32)


def test_grouped_score_equals_the_mean_over_all_pairs():
    rng = np.random.default_rng(3)
    D, M, V = 24, 7, 5
    views = unit(rng.normal(size=(M, V, D)) + rng.normal(size=(M, 1, D)))
    white = fit_whitening(views.reshape(-1, D), "whiten", 12)
    b = np.stack([white.apply(views[m]) for m in range(M)])  # [M, V, k]
    classes = np.array(["chair", "sofa", "table", "chair", "bed", "sofa", "table"], dtype=object)
    sim = {"chair": np.array([1.0, 0.6, 0.45, 1.0, 0.3, 0.6, 0.45], np.float32),
           "couch": np.array([0.56, 0.86, 0.4, 0.56, 0.5, 0.86, 0.4], np.float32)}
    index = LibraryIndex("lib", np.array([f"m{i}" for i in range(M)], dtype=object), classes, b.mean(1), white, sim)
    dets = unit(rng.normal(size=(9, D)))
    labels = ["chair"] * 6 + ["couch"] * 3
    track = TrackGroups(["chair", "couch"], np.array([6, 3]), [dets[:6], dets[6:]])
    score, appearance, cls = score_tracks([track], index)
    w = white.apply(dets)
    brute = np.array([[np.mean([sim[labels[f]][m] * (1 + w[f] @ b[m, v]) / 2 for f in range(9) for v in range(V)])
                       for m in range(M)]])
    np.testing.assert_allclose(score, brute, atol=1e-5)
    np.testing.assert_allclose(appearance[0], [np.mean((1 + w @ b[m].T) / 2) for m in range(M)], atol=1e-5)
    np.testing.assert_allclose(cls[0], (6 * sim["chair"] + 3 * sim["couch"]) / 9, atol=1e-6)
    with pytest.raises(RetrievalError, match="detector label 'tv' has no class similarity"):
        score_tracks([TrackGroups(["tv"], np.array([1]), [dets[:1]])], index)


def chair_that_looks_like_a_bed() -> tuple[LibraryIndex, TrackGroups, dict]:
    """A 5-model library (chair, bed, sofa, tv, chair) and a track of three boxes named "chair" that
    look like the bed and the tv; and the library's class similarities to "chair"."""
    rng = np.random.default_rng(4)
    D, M = 16, 5
    views = unit(rng.normal(size=(M, D)))
    white = fit_whitening(views, "centre", 8)
    sim = {"chair": np.array([1.0, 0.2, 0.5, 0.0, 0.8], np.float32)}
    index = LibraryIndex("lib", np.array([f"m{i}" for i in range(M)], dtype=object),
                         np.array(["chair", "bed", "sofa", "tv", "chair"], dtype=object), white.apply(views), white, sim)
    dets = unit(views[[1, 1, 3]] + 0.05 * rng.normal(size=(3, D)))  # look like the bed and the tv
    return index, TrackGroups(["chair"], np.array([3]), [dets]), sim


def test_class_exponent_tempers_the_class_filter():
    """x = 1 is the paper's product to the bit; x = 0 ranks by appearance alone; in between, each
    detection's appearance is weighed by c ** x."""
    index, track, sim = chair_that_looks_like_a_bed()
    paper, appearance, cls = score_tracks([track], index)
    np.testing.assert_array_equal(score_tracks([track], index, 1.0)[0], paper)
    off = score_tracks([track], index, 0.0)
    np.testing.assert_allclose(off[0], appearance, atol=1e-6)
    np.testing.assert_array_equal(off[2], cls)  # the reported class similarity stays the plain one
    half = score_tracks([track], index, 0.5)[0]
    np.testing.assert_allclose(half[0], np.sqrt(sim["chair"]) * appearance[0], atol=1e-6)
    quarter = score_tracks([track], index, 0.25)[0]
    assert np.argmax(paper[0]) == 0 and np.argmax(quarter[0]) == 1  # the bed wins once the filter is tempered enough


def test_a_drawn_class_weighs_as_the_paper_weighs_it():
    """A manual track's label is a person's answer, not a detector's guess: with the detector's labels
    tempered (x = 0.1) the same boxes drawn by a person are scored with ``drawn_class_exponent``
    (1: the paper's product), so the drawn class keeps its candidates."""
    import dataclasses

    index, detected, _ = chair_that_looks_like_a_bed()
    drawn = dataclasses.replace(detected, drawn=True)
    both = score_tracks([detected, drawn], index, 0.1)
    np.testing.assert_array_equal(both[0][0], score_tracks([detected], index, 0.1)[0][0])
    np.testing.assert_array_equal(both[0][1], score_tracks([detected], index, 1.0)[0][0])
    np.testing.assert_array_equal(both[1][0], both[1][1])  # appearance is the boxes'
    assert np.argmax(both[0][0]) == 1 and np.argmax(both[0][1]) == 0  # tempered: the bed; drawn "chair": a chair
    np.testing.assert_array_equal(score_tracks([detected, drawn], index, 0.1, 0.1)[0][1], both[0][0])


def write(wh, name: str, part: str, rows: list[dict]) -> None:
    wh.write(name, part, pa.Table.from_pylist(rows, schema=wh.spec(name).schema))


@pytest.fixture
def clip_and_library(wh):
    rng = np.random.default_rng(0)
    D = 16
    protos = unit(rng.normal(size=(4, D)))  # 4 looks; models 0/1 share look 0 (a tie), 2 = look 1, 3 = look 2
    looks, classes = [0, 0, 1, 2], ["chair", "chair", "sofa", "table"]
    views = np.concatenate([unit(protos[looks[m]] + 0.01 * rng.normal(size=(3, D))) for m in range(4)])
    white = fit_whitening(views, "centre", 8)
    write(wh, "embedding_whitening", "lib", whitening_table("lib", white, len(views)).to_pylist())
    whitened = white.apply(views).reshape(4, 3, -1).mean(1)
    write(wh, "cad_model_embeddings", "lib", [
        {"library": "lib", "cad_id": f"lib.m{m}", "class": classes[m], "vector": whitened[m if m != 1 else 0].tolist(), "views": 3}
        for m in range(4)])
    sims = {("chair", "chair"): 1.0, ("chair", "sofa"): 0.6, ("chair", "table"): 0.45,
            ("couch", "chair"): 0.56, ("couch", "sofa"): 0.86, ("couch", "table"): 0.4}
    write(wh, "label_similarity", "lib", [{"library": "lib", "detector_label": d, "cad_class": c, "similarity": s,
                                           "encoder": "test"} for (d, c), s in sims.items()])
    # track 0: three chair detections that look like look 0; track 1: two couch detections like look 1
    dets = [(0, 0, "chair", protos[0]), (1, 10000, "chair", protos[0]), (2, 20000, "chair", protos[0]),
            (3, 1, "couch", protos[1]), (4, 10001, "couch", protos[1])]
    write(wh, "detections", "c", [{"clip": "c", "det_id": d, "timestamp_us": 0, "frame_index": d // 10000,
                                   "box": [0.1, 0.1, 0.5, 0.5], "label": label, "label_id": 0, "score": 0.9,
                                   "model_sha256": "x"} for _, d, label, _ in dets])
    write(wh, "embeddings", "c", [{"clip": "c", "owner": "detection", "owner_id": d, "vector": v.tolist(),
                                   "model_sha256": "x"} for _, d, _, v in dets])
    write(wh, "track_detections", "c", [{"clip": "c", "track_id": int(i >= 3), "det_id": d, "frame_index": d // 10000,
                                         "timestamp_us": 0} for i, d, _, _ in dets])
    return wh


def test_retrieval_stage_ranks_and_breaks_ties(clip_and_library):
    wh = clip_and_library
    out = retrieve_clip(wh, RetrievalConfig(top_k=3), "c", "r1")
    rows = wh.read("cad_candidates").to_pylist()
    ranked = {t: [r["cad_id"] for r in sorted(rows, key=lambda r: r["rank"]) if r["track_id"] == t] for t in (0, 1)}
    assert ranked[0][:2] == ["lib.m0", "lib.m1"]  # equal scores: ordered by cad_id
    assert ranked[1][0] == "lib.m2" and out.rows_written == 6
    best = [r for r in rows if r["track_id"] == 1 and r["rank"] == 1][0]
    assert best["cad_class"] == "sofa" and best["class_similarity"] == pytest.approx(0.86, abs=1e-6)
    assert 0 <= best["score"] <= best["appearance"] <= 1
    assert retrieve_clip(wh, RetrievalConfig(top_k=3), "c", "r2").output_hash == out.output_hash


def test_retrieval_names_what_is_missing(wh, clip_and_library):
    from warehouse import Warehouse

    empty = Warehouse(wh.root.parent / "empty")
    out = retrieve_clip(empty, RetrievalConfig(), "c", "r")
    assert out.rows_written == 0 and "no CAD library" in out.message and empty.partitions("cad_candidates") == ["c"]
    wh = clip_and_library
    wh.write("embeddings", "c", wh.read("embeddings", partitions=["c"]).slice(0, 2))
    with pytest.raises(RetrievalError, match=r"clip c: detection \d+ has no descriptor"):
        retrieve_clip(wh, RetrievalConfig(), "c", "r")


def test_non_finite_and_mismatched_descriptors_are_named(clip_and_library):
    """One NaN descriptor of a track scored every model NaN: its ten candidates were ranked by name,
    or none was kept (a larger library), and the stage said it succeeded. A library's vector NaN
    did the same for every track; ragged or other-length vectors said neither the table nor the library."""
    from tasks.retrieval.index import clear_cache
    from tasks.retrieval.whitening import Whitening

    wh = clip_and_library
    embeddings = wh.read("embeddings", partitions=["c"]).to_pylist()
    bad = next(e for e in embeddings if e["owner_id"] == 10000)  # track 0's box on frame 1
    bad["vector"] = [float("nan")] * len(bad["vector"])
    write(wh, "embeddings", "c", embeddings)
    with pytest.raises(RetrievalError, match=r"^clip c: track 0: the descriptor of its box on frame 1 is not finite"):
        retrieve_clip(wh, RetrievalConfig(), "c", "r")
    write(wh, "embeddings", "c", [{**e, "vector": [0.25] * len(e["vector"])} for e in embeddings])
    models = wh.read("cad_model_embeddings", partitions=["lib"]).to_pylist()
    models[2]["vector"] = [float("nan")] * len(models[2]["vector"])
    write(wh, "cad_model_embeddings", "lib", models)
    clear_cache()
    with pytest.raises(RetrievalError, match=r"^CAD library 'lib': cad_model_embeddings.vector of lib.m2 \(and 0 more\) is not finite"):
        retrieve_clip(wh, RetrievalConfig(), "c", "r")
    models[2]["vector"] = models[2]["vector"][:4]
    write(wh, "cad_model_embeddings", "lib", models)
    clear_cache()
    with pytest.raises(RetrievalError, match=r"^CAD library 'lib': cad_model_embeddings.vector: vectors of unequal lengths"):
        retrieve_clip(wh, RetrievalConfig(), "c", "r")
    white = Whitening("centre", np.zeros(16, np.float32), np.eye(8, 16, dtype=np.float32))
    with pytest.raises(ValueError, match="^descriptors of 12 values, but the whitening takes 16$"):
        white.apply(np.ones((4, 12)))  # 48 values: read as three descriptors of 16


@pytest.mark.slow
def test_label_similarity_uses_the_packaged_sentence_encoder():
    from tasks.retrieval.label_similarity import similarity

    s = similarity(["couch", "tv", "chair", "potted plant"], ["sofa", "display", "chair", "bed", "plant"])
    assert s[0, 0] == pytest.approx(0.86, abs=0.02)  # measured with sentence-transformers (project notes)
    assert s[2, 2] == pytest.approx(1.0, abs=1e-5) and s[2, 3] == pytest.approx(0.36, abs=0.02)
    assert s[1].argmax() == 1  # "display" is read as "display, television, monitor"
    assert s[3].argmax() == 4
