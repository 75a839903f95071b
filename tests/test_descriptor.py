"""The learned retrieval descriptor (issue "Recognition", part 2): training rooms never shared with
a benchmark, the training crops, the file and its digest, the 'learned' whitening, the trainer
(it learns, and the same seed gives the same bytes), and cad_embed applying it."""

from __future__ import annotations

import dataclasses
import io

import numpy as np
import pytest

from bench.benchmark import DEFAULT_SEED
from bench.descriptor_data import (
    MIN_BOX_SIDE_PX, MIN_VISIBLE_PX, CropSet, is_training_seed, jitter_boxes, room_seed, visible_boxes,
)
import bench.descriptor_train as descriptor_train
from bench.descriptor_train import LibraryViews, TrainSpec, crops_path, evaluate, train
from tasks.retrieval.descriptor import DescriptorMissing, load_descriptor, save_descriptor
from tasks.retrieval.whitening import fit_whitening


def test_training_rooms_are_never_benchmark_rooms():
    bench_seeds = [S * 1000 + i for S in (0, 1, 7, 5150, DEFAULT_SEED, 999_999_999) for i in range(100)]
    assert not any(is_training_seed(s) for s in bench_seeds)
    rooms = [room_seed(s, r) for s in (0, 1, 2, 7) for r in (0, 1, 999_999)]
    assert all(is_training_seed(s) for s in rooms)
    assert len(set(rooms)) == len(rooms)
    for bad in ((-1, 0), (0, -1), (0, 1_000_000)):
        with pytest.raises(ValueError, match="training seed"):
            room_seed(*bad)


def test_jittered_boxes_stay_near_and_never_collapse():
    rng = np.random.default_rng(0)
    boxes = np.array([[10.0, 20.0, 110.0, 70.0], [5.0, 5.0, 6.0, 6.0]])
    out = np.stack([jitter_boxes(boxes, rng) for _ in range(500)])
    assert out.shape == (500, 2, 4)
    assert np.all(out[:, :, 2:] - out[:, :, :2] >= 4 - 1e-9)
    spread = out[:, 0].std(0)  # N(0, 0.06 * size) per side: 6 px in x, 3 px in y
    np.testing.assert_allclose(spread, [6, 3, 6, 3], rtol=0.15)
    np.testing.assert_allclose(out[:, 0].mean(0), boxes[0], atol=1.0)


def test_visible_boxes_keep_objects_seen_well_enough():
    ids = np.full((120, 200), -1, np.int32)
    ids[:60, :] = 0  # the room
    ids[10:50, 30:80] = 1  # object 0: 40 x 50 px
    ids[70:80, 100:120] = 2  # object 1: 200 px, too few
    ids[0:120, 150:160] = 3  # object 2: 1200 px but 10 px wide
    ids[100:101, 0:1] = 5  # instance of an object beyond ``count``: ignored
    found = visible_boxes(ids, 3)
    assert [(k, b.tolist(), n) for k, b, n in found] == [(0, [30.0, 10.0, 80.0, 50.0], 2000)]
    assert 200 < MIN_VISIBLE_PX <= 2000 and 10 < MIN_BOX_SIDE_PX <= 40


def test_descriptor_file_round_trips_and_its_bytes_depend_on_values_only(tmp_path):
    W = np.random.default_rng(1).normal(size=(16, 32)).astype(np.float32)
    mu = np.random.default_rng(2).normal(size=32)
    a = save_descriptor(tmp_path / "a.npz", W, mu, {"seed": 1, "spec": {"rooms": 3}})
    b = save_descriptor(tmp_path / "b.npz", W.copy(), mu.copy(), {"spec": {"rooms": 3}, "seed": 1})
    assert a.read_bytes() == b.read_bytes()
    got, meta, mean = load_descriptor(a)
    np.testing.assert_array_equal(got, W)
    np.testing.assert_array_equal(mean, mu.astype(np.float32))
    assert meta == {"seed": 1, "spec": {"rooms": 3}}
    buf = io.BytesIO()  # a file from before the mean was kept: made again, not centred on each library's own mean
    np.savez(buf, projection=W, meta=np.array("{}"))
    (tmp_path / "old.npz").write_bytes(buf.getvalue())
    with pytest.raises(DescriptorMissing, match=r"old.npz: mean must be float32\[32\], got none .*run `make models` again"):
        load_descriptor(tmp_path / "old.npz")
    with pytest.raises(DescriptorMissing, match="make models"):
        load_descriptor(tmp_path / "none.npz")
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(DescriptorMissing, match="bad.npz: not a descriptor file"):
        load_descriptor(tmp_path / "bad.npz")
    (tmp_path / "cut.npz").write_bytes(a.read_bytes()[: a.stat().st_size // 2])  # BadZipFile: not caught, `make models` failed on it
    with pytest.raises(DescriptorMissing, match="cut.npz: not a descriptor file .*run `make models` again"):
        load_descriptor(tmp_path / "cut.npz")
    W[3, 5] = np.nan  # every score NaN: every track went without a candidate, unsaid
    save_descriptor(tmp_path / "nan.npz", W, mu, {})
    with pytest.raises(DescriptorMissing, match="nan.npz: holds values that are not finite"):
        load_descriptor(tmp_path / "nan.npz")


def test_learned_whitening_is_the_trained_map_centred_on_the_trained_mean():
    """Every library gets the one trained map: a library of two models centred on its own mean
    would make the two exact opposites, one of them close to almost any object."""
    rng = np.random.default_rng(2)
    v, W, mu = rng.normal(size=(40, 24)), rng.normal(size=(8, 24)).astype(np.float32), rng.normal(size=24)
    fitted = fit_whitening(v, "learned", 128, W, mu)
    expected = (v - mu) @ W.T.astype(np.float64)
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    np.testing.assert_allclose(fitted.apply(v), expected, atol=1e-5)
    assert fitted.method == "learned" and fitted.projection.shape == (8, 24)
    np.testing.assert_array_equal(fit_whitening(v[:2], "learned", 128, W, mu).mean, fitted.mean)
    with pytest.raises(ValueError, match=r"float32\[k, 24\]"):
        fit_whitening(v, "learned", 128, W[:, :10])
    with pytest.raises(ValueError, match="learned projection"):
        fit_whitening(v, "learned", 128)


def synthetic_problem(seed: int = 0, models: int = 40, views: int = 4, D: int = 48):
    """Views of each model near its 'look'; crops = the look, shifted by a domain offset and
    buried in loud noise along a few nuisance directions (what a room adds to a crop), which PCA
    whitening of the views cannot know to suppress."""
    rng = np.random.default_rng(seed)
    looks = rng.normal(size=(models, D))
    nuisance = np.linalg.qr(rng.normal(size=(D, 6)))[0].T  # 6 orthonormal directions
    view_vecs = np.repeat(looks, views, 0) + 0.3 * rng.normal(size=(models * views, D))
    n = 30 * models
    model = rng.integers(models, size=n)
    crops = looks[model] + 0.5 + 0.3 * rng.normal(size=(n, D)) + 6.0 * rng.normal(size=(n, 6)) @ nuisance
    unit = lambda x: (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)  # noqa: E731
    cad_ids = np.array([f"m{i:03d}" for i in range(models)], dtype=object)
    lib = LibraryViews(unit(view_vecs), np.repeat(np.arange(models), views).astype(np.int64), cad_ids)
    crop_set = CropSet(unit(crops), cad_ids[model], np.arange(n) % 12, np.full(n, 1000))
    return lib, crop_set


def test_training_learns_what_whitening_cannot_and_the_same_seed_gives_the_same_bytes(tmp_path):
    lib, crops = synthetic_problem()
    spec = TrainSpec(dims=16, steps=300, batch=128, lr=3e-3, holdout_every=4)
    W, report = train(lib, crops, spec, show_progress=False)
    before, after = report["heldout_before"], report["heldout_after"]
    assert report["heldout_crops"] == np.count_nonzero(crops.rooms % 4 == 3) > 0
    assert after["top1"] > before["top1"] + 0.3, report
    assert after["top1"] >= 0.8, report
    assert evaluate(W, lib.vectors.mean(0), lib, crops)["top10"] >= after["top10"] - 0.1
    again, _ = train(lib, crops, spec, show_progress=False)
    a = save_descriptor(tmp_path / "a.npz", W, lib.vectors.mean(0), {"seed": spec.seed})
    b = save_descriptor(tmp_path / "b.npz", again, lib.vectors.mean(0), {"seed": spec.seed})
    assert a.read_bytes() == b.read_bytes()
    other, _ = train(lib, crops, dataclasses.replace(spec, seed=2), show_progress=False)
    assert not np.array_equal(other, W)


def test_the_kept_crops_are_keyed_by_the_code_that_makes_them_not_by_the_training_knobs(tmp_path, monkeypatch):
    spec = TrainSpec()
    path = crops_path(tmp_path, spec, "lib")
    assert path.parent == tmp_path and path.name.startswith("descriptor-crops-")
    assert crops_path(tmp_path, dataclasses.replace(spec, steps=7, dims=8, lr=1.0), "lib") == path
    for other in (dataclasses.replace(spec, rooms=3), dataclasses.replace(spec, frames=3), dataclasses.replace(spec, seed=2)):
        assert crops_path(tmp_path, other, "lib") != path
    assert crops_path(tmp_path, spec, "another library") != path
    assert "bench/descriptor_train.py" in descriptor_train.RECIPE_SOURCES
    assert "bench/descriptor_train.py" not in descriptor_train.DATA_SOURCES
    monkeypatch.setattr(descriptor_train, "DATA_SOURCES", descriptor_train.DATA_SOURCES[1:])  # other crop code
    assert crops_path(tmp_path, spec, "lib") != path


def test_a_room_without_a_camera_walk_gives_no_crops(small_library_warehouse, models_dir):
    """Some rooms have no collision-free camera walk (room 865 of seed 1 with the embedded library,
    reached since the descriptor trains on 1,440 rooms; room 40 with the small one): such a room
    adds no crop, as the detector's rooms skip it, and the others are rendered as before."""
    from bench.descriptor_data import room_seed
    from bench.scene import generate_scene
    from bench.walkthrough import WalkthroughSpec, camera_path
    from warehouse import Warehouse

    wh = Warehouse(small_library_warehouse.warehouse.root)
    models = wh.read("cad_models").to_pylist()
    with pytest.raises(RuntimeError, match=descriptor_train.NO_WALK):
        camera_path(generate_scene(room_seed(1, 40), models), WalkthroughSpec(), np.random.default_rng(0))
    spec = TrainSpec(frames=2)
    crops = descriptor_train.render_crops(wh, spec, show_progress=False, workers=1, rooms=[39, 40])
    alone = descriptor_train.render_crops(wh, spec, show_progress=False, workers=1, rooms=[39])
    assert len(crops.cad_ids) and set(crops.rooms.tolist()) == {39}
    np.testing.assert_array_equal(crops.vectors, alone.vectors)


@pytest.mark.slow
def test_make_models_trains_on_rooms_and_cad_embed_applies_it(small_library_warehouse, models_dir, tmp_path):
    """The trainer on the small library: rooms rendered and embedded, a projection trained and
    written; cad_embed with whitening 'learned' whitens with it, and the file is an input of the
    stage (retraining it makes the stage stale)."""
    from bench.descriptor_train import build
    from cadestate.config import CadEmbedConfig
    from flows.cad_library import run_cad_library
    from tasks.cad.embed import STAGE as CAD_EMBED
    from tasks.retrieval.descriptor import DESCRIPTOR_NAME
    from tests.conftest import small_library_items, warehouse_copy
    from warehouse import Warehouse

    config = warehouse_copy(small_library_warehouse, tmp_path / "w")
    config = dataclasses.replace(config, cad_embed=CadEmbedConfig(whitening="learned"))
    wh = Warehouse(config.warehouse.root)
    spec = TrainSpec(rooms=3, frames=3, steps=30, holdout_every=3)
    path = build(wh, models_dir, spec, show_progress=False)
    assert path == models_dir / DESCRIPTOR_NAME
    W, meta, mean = load_descriptor(path)
    assert W.shape[1] == 768 and mean.shape == (768,)
    assert meta["spec"]["rooms"] == 3 and meta["train_crops"] + meta["heldout_crops"] > 0
    inputs = CAD_EMBED.config_inputs(config)
    assert inputs and len(inputs[0]) == 64

    reports = run_cad_library(small_library_items(), config, show_progress=False)
    assert {r.state for r in reports} <= {"completed", "cached"}, [r.message for r in reports]
    assert {r.stage: r.state for r in reports}["cad_embed"] == "completed"
    rows = wh.read("embedding_whitening").to_pylist()
    assert rows and {r["method"] for r in rows} == {"learned"}
    for row in rows:
        np.testing.assert_array_equal(np.asarray(row["projection"], np.float32).reshape(W.shape), W)
    views = [v for v in wh.read("cad_embeddings").to_pylist() if v["library"] == rows[0]["library"]]
    raw = np.asarray([v["vector"] for v in views], np.float32)
    fitted = fit_whitening(raw, "learned", 0, W, mean)  # centred on the file's mean: that of every library's views, not its own
    np.testing.assert_array_equal(np.asarray(rows[0]["mean"], np.float32), mean)
    every = np.asarray(wh.read("cad_embeddings").column("vector").to_pylist(), np.float32)
    np.testing.assert_allclose(mean, every.mean(0), atol=1e-5)
    per_model = {r["cad_id"]: np.asarray(r["vector"]) for r in wh.read("cad_model_embeddings").to_pylist()}
    some = views[0]["cad_id"]
    mine = np.array([v["cad_id"] == some for v in views])
    np.testing.assert_allclose(per_model[some], fitted.apply(raw[mine]).mean(0), atol=1e-5)

    from bench.descriptor_eval import whitened_index
    from tasks.retrieval.index import build_index
    library = rows[0]["library"]  # the evaluation's in-memory index is the one the stage wrote
    np.testing.assert_allclose(whitened_index(wh, library, "learned").vectors, build_index(wh, library).vectors, atol=1e-6)

    save_descriptor(path, W * 2, mean, meta)  # retrained: another file
    assert CAD_EMBED.config_inputs(config) != inputs
