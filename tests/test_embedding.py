"""The appearance embedder (NanoDet-m backbone), whitening, and the detect / embed / cad_embed stages."""

from __future__ import annotations

import numpy as np
import pytest

from cadestate.config import CadEmbedConfig, DetectConfig, EmbedConfig, FramesConfig, IngestConfig
from tasks.detection.models import nanodet as nd
from tasks.retrieval.whitening import fit_whitening, read_whitening, whitening_table

pytestmark = pytest.mark.skipif(not nd.is_built(nd.default_cache_dir()),
                                reason="the NanoDet-m model is not built (`make models`, which `make test` runs)")


@pytest.fixture(scope="module")
def embedder():
    from tasks.detection.models.embedder import load_embedder

    return load_embedder(EmbedConfig())


def photos():
    from skimage import data

    return data.chelsea(), data.stereo_motorcycle()[0]


def test_embedder_is_deterministic_and_unit_norm(embedder):
    from tasks.detection.models.embedder import load_embedder

    cat, moto = photos()
    boxes = np.array([[0, 0, 420, 300], [100, 50, 300, 250], [10, 10, 60, 40]], np.float64)
    a = embedder.embed(cat, boxes)
    assert a.shape == (3, 768) and a.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(a, axis=1), 1, atol=1e-5)
    b = load_embedder(EmbedConfig(batch_size=1, threads=1)).embed(cat, boxes)  # other batching, threads
    np.testing.assert_allclose(a, b, atol=1e-5)
    np.testing.assert_array_equal(a[1], embedder.embed(cat, boxes[1:2])[0])  # alone or with others
    assert load_embedder(EmbedConfig()).sha256 == embedder.sha256  # the cut graph is byte-stable


def test_an_embedder_is_kept_per_thread_until_its_model_file_changes(tmp_path, monkeypatch):
    import os
    import shutil
    import threading
    import time

    from tasks.detection.models.embedder import load_embedder

    for f in (nd.ONNX_NAME, nd.LICENSE_NAME, nd.NOTICE_NAME):  # a models folder of our own, to touch
        shutil.copy2(nd.default_cache_dir() / f, tmp_path / f)
    monkeypatch.setenv("CADESTATE_MODELS", str(tmp_path))
    first = load_embedder(EmbedConfig())
    assert load_embedder(EmbedConfig()) is first
    assert load_embedder(EmbedConfig(batch_size=1)) is not first  # another config: another embedder
    again = load_embedder(EmbedConfig())
    assert again is not first and load_embedder(EmbedConfig()) is again
    elsewhere = []
    worker = threading.Thread(target=lambda: elsewhere.append(load_embedder(EmbedConfig())))
    worker.start()
    worker.join()
    assert elsewhere[0] is not again and load_embedder(EmbedConfig()) is again  # one per thread
    st = os.stat(tmp_path / nd.ONNX_NAME)
    os.utime(tmp_path / nd.ONNX_NAME, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    moved = load_embedder(EmbedConfig())
    assert moved is not again  # the file changed: loaded and verified anew
    changed = os.stat(tmp_path / nd.ONNX_NAME).st_ctime_ns
    while os.stat(tmp_path / nd.ONNX_NAME).st_ctime_ns == changed:  # file times tick coarsely
        time.sleep(0.01)
        os.chmod(tmp_path / nd.ONNX_NAME, 0o600)  # its change time moves, nothing else in the key
    assert load_embedder(EmbedConfig()) is not moved
    (tmp_path / nd.ONNX_NAME).write_bytes(b"not the model")
    with pytest.raises(FileNotFoundError, match="make models"):
        load_embedder(EmbedConfig())


def test_embedder_sees_the_object_not_the_frame(embedder):
    cat, moto = photos()
    cat_v = embedder.embed(cat, [[0, 0, 420, 300]])[0]
    cat_small = embedder.embed(cat[::2, ::2].copy(), [[0, 0, 210, 150]])[0]  # same cat, half the pixels
    moto_v = embedder.embed(moto, [[92, 78, 686, 452]])[0]
    assert cat_v @ cat_small > 0.95 and cat_v @ cat_small > cat_v @ moto_v + 0.1


def test_crops_are_clipped_and_size_checked(embedder):
    from tasks.detection.models.embedder import Embedder, crop_boxes

    np.testing.assert_array_equal(crop_boxes(np.array([[10, 10, 20, 30]]), (40, 50), 0.5),
                                  [[5, 0, 25, 40]])  # grown 5 / 10 px per side, clipped to the image
    np.testing.assert_array_equal(crop_boxes(np.array([[49.5, 39.5, 49.5, 39.5]]), (40, 50), 0.1),
                                  [[49, 39, 50, 40]])  # a degenerate box still gives one pixel
    x = embedder.crops(np.zeros((40, 50, 3), np.uint8), np.array([[0, 0, 50, 40]]))
    assert x.shape == (1, 3, 128, 128)
    with pytest.raises(ValueError, match="multiple of 32"):
        Embedder(nd.default_cache_dir() / nd.ONNX_NAME, crop_size=100)


def test_whitening_centres_and_whitens():
    rng = np.random.default_rng(0)
    v = rng.normal(size=(500, 16)) * np.linspace(5, 0.1, 16) + 3.0
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    none, centre, white = (fit_whitening(v, m, 8) for m in ("none", "centre", "whiten"))
    np.testing.assert_allclose(none.apply(v), v, atol=1e-6)
    assert abs(centre.apply(v).mean(0)).max() < abs(v.mean(0)).max()
    w = (v - white.mean) @ white.projection.T
    eig = np.linalg.eigvalsh(np.cov(w.T))
    assert white.projection.shape == (8, 16) and eig.max() < 1.0 and eig.min() > 0.5  # near-identity (shrunk)
    np.testing.assert_allclose(np.linalg.norm(white.apply(v), axis=1), 1, atol=1e-5)
    again = fit_whitening(v[::-1], "whiten", 8)  # order of the views does not matter
    np.testing.assert_allclose(again.apply(v), white.apply(v), atol=1e-4)
    table = whitening_table("lib", white, len(v))
    assert table.num_rows == 1 and table["dims"][0].as_py() == 8


def test_whitening_keeps_only_the_directions_the_views_span():
    """Views that repeat (one model's renders alike) span fewer directions than 'whiten' kept: the
    others, LAPACK's arbitrary choice, got the largest scale, so a detection's whitened descriptor
    changed with the order of the views (up to 0.5 a component) though the views' did not."""
    rng = np.random.default_rng(0)
    base = rng.normal(size=(4, 64))
    views = np.concatenate([b + 0.05 * rng.normal(size=(3, 64)) for b in base[:3]] + [np.repeat(base[3:], 3, 0)])
    views /= np.linalg.norm(views, axis=1, keepdims=True)
    detection = base[1] + 0.05 * rng.normal(size=64)
    fits = [fit_whitening(views[order], "whiten", 32) for order in (np.arange(12), np.arange(12)[::-1], rng.permutation(12))]
    assert all(f.projection.shape == (9, 64) for f in fits)  # 12 views, 4 of them one: rank 9, not min(32, 11)
    for f in fits[1:]:
        np.testing.assert_allclose(np.abs(f.apply(detection)), np.abs(fits[0].apply(detection)), atol=1e-4)
    same = fit_whitening(np.repeat(views[:1], 5, 0), "whiten", 32)  # no variance at all: centred only
    assert same.method == "centre"


# ---- stages ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def detected(small_clip, tmp_path_factory):
    from tasks.detection.detect import detect_clip
    from tasks.detection.embed import embed_clip
    from tasks.video.frames import extract_frames
    from tasks.video.ingest import ClipSource, ingest_clip
    from cadestate.lineage import file_sha256
    from warehouse import Warehouse

    wh = Warehouse(tmp_path_factory.mktemp("det_wh"))
    source = ClipSource("small", small_clip.video_path, small_clip.cameras_path)
    ingest_clip(wh, IngestConfig(), source, file_sha256(source.video), file_sha256(source.cameras), "r0")
    extract_frames(wh, FramesConfig(), "small", "r1", show_progress=False)
    cfg = DetectConfig(score_threshold=0.2)
    out = detect_clip(wh, cfg, "small", "r2", show_progress=False)
    emb = embed_clip(wh, EmbedConfig(), "small", "r3", show_progress=False)
    return wh, cfg, out, emb


def upstream_of(name: str) -> tuple[str, ...]:
    from tasks.registry import stages_of

    return next(s.definition.upstream for s in stages_of("clip") if s.name == name)


def test_a_librarys_whitened_vectors_do_not_depend_on_the_blas_threads():
    """The whitening's fit and product ran on the process's BLAS threads: one library embedded on
    one core and on two differed in the last bits, so every clip's candidates (and CAD-selection
    task id) changed with the machine. They are made on one thread, whatever the process has."""
    from threadpoolctl import threadpool_limits

    from tasks.cad.embed import whitened

    rng = np.random.default_rng(0)
    v = rng.normal(size=(2000, 768)).astype(np.float32)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    made = []
    for threads in (1, 2):
        with threadpool_limits(threads, user_api="blas"):
            fitted, projected = whitened(v, CadEmbedConfig(whitening="whiten", whitening_dims=128))
            made.append((fitted.projection.tobytes(), projected.tobytes()))
    assert made[0] == made[1]


def test_detect_and_embed_stages(detected):
    from cadestate.lineage import recording_reads
    from tasks.detection.detect import DET_ID_STRIDE, detect_clip
    from tasks.registry import stages_of
    from tasks.detection.embed import embed_clip

    from tasks.detection.model_inputs import detector_labels, model_fingerprint

    wh, cfg, out, emb = detected
    dets = wh.read("detections").to_pylist()
    assert out.rows_written == len(dets) > 0
    frames = {f["frame_index"]: f["timestamp_us"] for f in wh.read("frames").to_pylist()}
    for d in dets:
        ymin, xmin, ymax, xmax = d["box"]
        assert 0 <= ymin < ymax <= 1 and 0 <= xmin < xmax <= 1
        assert d["timestamp_us"] == frames[d["frame_index"]] and d["det_id"] // DET_ID_STRIDE == d["frame_index"]
        assert d["score"] >= cfg.score_threshold and d["label"] == detector_labels(cfg)[d["label_id"]]
        assert d["model_sha256"] == model_fingerprint(cfg)
    per_frame = {}
    for d in sorted(dets, key=lambda d: d["det_id"]):
        per_frame.setdefault(d["frame_index"], []).append(d["score"])
    assert all(s == sorted(s, reverse=True) for s in per_frame.values())  # rank = by score
    vectors = wh.read("embeddings").to_pylist()
    assert sorted(v["owner_id"] for v in vectors) == sorted(d["det_id"] for d in dets) and emb.rows_written == len(dets)
    assert {v["owner"] for v in vectors} == {"detection"} and len(vectors[0]["vector"]) == 768
    # reruns are idempotent: same rows, same output digests
    assert detect_clip(wh, cfg, "small", "r4", show_progress=False).output_hash == out.output_hash
    with recording_reads() as reads:
        assert embed_clip(wh, EmbedConfig(), "small", "r5", show_progress=False).output_hash == emb.output_hash
    # what embed reads is what its upstream stages write: it crops the frames' images, and a frames rerun
    # that left the detections alike (a new [frames] jpeg_quality) left its descriptors stale
    upstream = {t for s in stages_of("clip") if s.name in {"embed", *upstream_of("embed")} for t in s.definition.tables}
    assert {r[1] for r in reads if r[0] == "files"} <= upstream and "frames" in {r[1] for r in reads}
    # the label filter drops other classes before ranking
    only = detect_clip(wh, DetectConfig(score_threshold=0.2, classes=(dets[0]["label"],)), "small", "r6", show_progress=False)
    kept = wh.read("detections").to_pylist()
    assert {d["label"] for d in kept} == {dets[0]["label"]} and only.rows_written == len(kept) <= len(dets)


def test_an_unreadable_frame_image_is_named(tmp_path):
    from PIL import Image

    from tasks.detection.detect import load_rgb

    whole = tmp_path / "whole.jpg"
    Image.new("RGB", (64, 48), (10, 20, 30)).save(whole)
    assert load_rgb(whole).shape == (48, 64, 3)
    (tmp_path / "cut.jpg").write_bytes(whole.read_bytes()[:100])  # PIL says "Truncated File Read" alone
    (tmp_path / "junk.jpg").write_bytes(b"not an image")
    for name in ("cut.jpg", "junk.jpg", "missing.jpg"):
        with pytest.raises(OSError, match=f"^{tmp_path / name}: not a readable image \\("):
            load_rgb(tmp_path / name)


def test_detect_needs_frames(wh):
    from tasks.detection.detect import detect_clip

    with pytest.raises(LookupError, match="clip nope has no frames"):
        detect_clip(wh, DetectConfig(), "nope", "r", show_progress=False)


def test_cad_embed_stage(small_cad_library):
    from cadestate.config import CadViewsConfig
    from tasks.cad.embed import embed_library, object_box
    from tasks.cad.views import render_library

    wh, models = small_cad_library
    render_library(wh, CadViewsConfig(views=2, size=96), "sh3d-small", "v1", show_progress=False)
    out = embed_library(wh, EmbedConfig(), CadEmbedConfig(whitening="whiten", whitening_dims=8), "sh3d-small", "e1",
                        show_progress=False)
    rows = wh.read("cad_embeddings").to_pylist()
    assert len(rows) == 2 * len(models) and out.rows_written == len(rows) + 1 + len(models)  # + whitening + model means
    assert wh.read("cad_model_embeddings").num_rows == len(models)
    w = read_whitening(wh, "sh3d-small")
    assert w.method == "whiten" and w.projection.shape == (8, 768)
    v = np.array([r["vector"] for r in rows], np.float32)
    np.testing.assert_allclose(np.linalg.norm(w.apply(v), axis=1), 1, atol=1e-5)
    white = np.full((10, 12, 3), 255, np.uint8)
    white[2:5, 3:9] = 0
    np.testing.assert_array_equal(object_box(white), [[3, 2, 9, 5]])
    with pytest.raises(LookupError, match="no embedding whitening for CAD library 'other'"):
        read_whitening(wh, "other")
