"""The manual-track human task (paper 3.1): only val/test clips get it; it pauses until a label
(written by hand or imported from CVAT) answers it; the drawn objects become tracks with the embed
stage's descriptors, which retrieval and the later human tasks take like automatic ones."""

from __future__ import annotations

import numpy as np
import pyarrow.compute as pc
import pytest

from cadestate.config import CadSelectionConfig, EmbedConfig, ManualTracksConfig, RetrievalConfig
from conftest import table_rows
from schemas.tracking import MANUAL_TRACK_BASE
from tasks.detection.models import nanodet as nd
from tasks.human.label_ingest import ingest_labels
from tasks.human.manual_tracks import manual_tracks_stage, regular_keyframes
from tasks.registry import clip_inputs
from tasks.stage import run_stage
from test_human_tasks import _label, _task
from warehouse import Warehouse

CLIP = "c1"
W, H = 320, 192
STAMPS = [i * 100_000 for i in range(20)]
LABELS = ("chair", "couch", "dining table")
needs_embedder = pytest.mark.skipif(not nd.is_built(nd.default_cache_dir()),
                                    reason="the NanoDet-m model is not built (`make models`, which `make test` runs)")


def _clip(wh: Warehouse, split: str) -> None:
    wh.write("clips", CLIP, table_rows("clips", [{"clip": CLIP, "split": split, "width": W, "height": H}]))


@pytest.fixture
def mwh(tmp_path) -> Warehouse:
    """A val clip of 20 frames (noise images) with 2 automatic tracks: 0 (chair, every frame) and
    1 (dining table, frames 5-12), no embeddings yet."""
    from PIL import Image

    wh = Warehouse(tmp_path / "wh")
    _clip(wh, "val")
    rng = np.random.default_rng(0)
    frames = []
    for i, t in enumerate(STAMPS):
        path = f"media/frames/{CLIP}/v/{i:04d}.jpg"
        (wh.root / path).parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(rng.integers(0, 255, (H, W, 3), np.uint8)).save(wh.root / path)
        frames.append({"clip": CLIP, "timestamp_us": t, "frame_index": i, "width": W, "height": H, "image_path": path})
    wh.write("frames", CLIP, table_rows("frames", frames))
    dets, members = [], []
    for track, span, label in ((0, range(20), "chair"), (1, range(5, 13), "dining table")):
        for f in span:
            dets.append({"clip": CLIP, "det_id": f * 10000 + track, "timestamp_us": STAMPS[f], "frame_index": f,
                         "box": [0.1 + 0.2 * track, 0.1, 0.4 + 0.2 * track, 0.5], "label": label})
            members.append({"clip": CLIP, "track_id": track, "det_id": f * 10000 + track, "frame_index": f,
                            "timestamp_us": STAMPS[f]})
    wh.write("detections", CLIP, table_rows("detections", dets))
    wh.write("track_detections", CLIP, table_rows("track_detections", members))
    wh.write("tracks", CLIP, table_rows("tracks", [{"clip": CLIP, "track_id": 0, "label": "chair"},
                                              {"clip": CLIP, "track_id": 1, "label": "dining table"}]))
    return wh


def _run(wh: Warehouse, cfg: ManualTracksConfig = ManualTracksConfig()):
    return run_stage(wh, CLIP, "manual_tracks", config_hash="c", inputs_hash="i", code_hash="k",
                     body=lambda run_id: manual_tracks_stage(wh, cfg, EmbedConfig(), LABELS, CLIP, run_id))


COUCH = [{"timestamp_us": STAMPS[f], "box": [0.5, 0.55, 0.9, 0.95]} for f in (0, 4, 8)]


def test_regular_keyframes():
    assert regular_keyframes(STAMPS, 6) == [0, 4, 8, 11, 15, 19]
    assert regular_keyframes([0, 10, 20, 1000], 3) == [0, 2, 3]  # nearest to 0, 500, 1000
    assert regular_keyframes([0, 1, 2, 3, 1000], 4) == [0, 1, 3, 4]  # two targets near 0 share frames: by index
    assert regular_keyframes(STAMPS[:3], 6) == [0, 1, 2]


def test_train_clip_completes_without_a_task(mwh):
    _clip(mwh, "train")
    run = _run(mwh)
    assert run.status == "completed" and run.rows_written == 0
    assert "split 'train' is not one of [manual_tracks] splits (val, test)" in run.message
    assert mwh.partitions("manual_tracks") == [CLIP] and mwh.read("label_tasks").num_rows == 0
    assert _run(mwh, ManualTracksConfig(splits=("train",))).status == "paused"  # the config decides


def test_a_config_that_no_longer_asks_withdraws_the_task(mwh):
    """A train clip asked while [manual_tracks] splits held train: taking train out leaves a newest
    manual-track task that asks nothing (the app and status stop offering the old one), once."""
    from cadestate.webapp.queue import clip_tasks

    _clip(mwh, "train")
    asked = _task(mwh, _run(mwh, ManualTracksConfig(splits=("train",))).message)
    assert [t.kind for t in clip_tasks(mwh, CLIP)] == ["manual_track"]
    run = _run(mwh)
    assert run.status == "completed" and run.message.endswith(f"no manual-track task; task {asked['task_id']} withdrawn")
    assert clip_tasks(mwh, CLIP) == [] and mwh.read("label_tasks").num_rows == 2
    assert not _run(mwh).message.endswith("withdrawn") and mwh.read("label_tasks").num_rows == 2


@needs_embedder
def test_val_clip_pauses_until_a_label_answers_it(mwh, tmp_path):
    from tasks.detection.embed import embed_clip
    from tasks.human.cad_selection import cad_selection_stage
    from tasks.retrieval.retrieval import retrieve_clip

    first = _run(mwh)
    assert first.status == "paused" and first.rows_written == 0
    assert "6 of 6 key-frames unanswered in manual_track task label_tasks/c1/" in first.message
    task = _task(mwh, first.message)
    assert task["kind"] == "manual_track" and task["classes"] == list(LABELS)
    assert [k["frame_index"] for k in task["keyframes"]] == [0, 4, 8, 11, 15, 19]
    assert task["keyframes"][0]["image_path"] == f"media/frames/{CLIP}/v/0000.jpg"
    shown = {t["track_id"]: [b["timestamp_us"] for b in t["boxes"]] for t in task["existing_tracks"]}
    assert shown == {0: [STAMPS[f] for f in (0, 4, 8, 11, 15, 19)], 1: [STAMPS[8], STAMPS[11]]}
    assert task["existing_tracks"][1]["label"] == "dining table" and task["previous"] == []
    assert _task(mwh, _run(mwh).message)["task_id"] == task["task_id"]  # unchanged inputs: the same task

    before = clip_inputs("manual_tracks", mwh, CLIP)
    label = _label(tmp_path / "l", "m.json", "manual_track", task["task_id"],
                   [{"label": "couch", "boxes": COUCH, "source_id": "hand:1"}], "2026-01-01T00:00:00+00:00")
    assert ingest_labels(mwh, label).ok
    assert clip_inputs("manual_tracks", mwh, CLIP) != before  # ingest makes the stage stale
    done = _run(mwh)
    assert done.status == "completed" and done.rows_written == 3 and "1 manual tracks (3 boxes)" in done.message
    rows = mwh.read("manual_tracks", [CLIP]).to_pylist()
    [couch] = {r["track_id"] for r in rows}
    assert couch >= MANUAL_TRACK_BASE and [r["frame_index"] for r in rows] == [0, 4, 8]
    assert {(r["label"], r["source_id"], r["task_id"]) for r in rows} == {("couch", "hand:1", task["task_id"])}
    assert _run(mwh).output_hash == done.output_hash  # idempotent

    # the drawn box's descriptor is the embed stage's for a detection with the same box
    det = {"clip": CLIP, "det_id": 4 * 10000 + 9, "timestamp_us": STAMPS[4], "frame_index": 4, "box": COUCH[1]["box"],
           "label": "couch"}
    mwh.write("detections", CLIP, table_rows("detections", mwh.read("detections", [CLIP]).to_pylist() + [det]))
    embed_clip(mwh, EmbedConfig(), CLIP, "e", show_progress=False)
    vectors = {e["owner_id"]: e["vector"] for e in mwh.read("embeddings", [CLIP]).to_pylist()}
    np.testing.assert_allclose(rows[1]["vector"], vectors[det["det_id"]], atol=1e-5)
    assert rows[1]["model_sha256"] == mwh.read("embeddings", [CLIP]).column("model_sha256")[0].as_py()

    # retrieval ranks the manual track (the couch is a sofa), and CAD selection shows it with its boxes
    _library(mwh)
    retrieve_clip(mwh, RetrievalConfig(top_k=2), CLIP, "r")
    candidates = mwh.read("cad_candidates", [CLIP]).to_pylist()
    ranked = [r["cad_id"] for r in candidates if r["track_id"] == couch]
    assert ranked == ["lib.sofa", "lib.chair"]
    x = RetrievalConfig().class_exponent
    for r in candidates:  # a person's class weighs as the paper weighs it; a detector's is tempered
        power = 1.0 if r["track_id"] == couch else x
        assert r["score"] == pytest.approx(r["class_similarity"] ** power * r["appearance"], abs=1e-5), r
    assert x < 1 and {r["track_id"] for r in candidates} > {couch}
    selection = _task(mwh, _run_cad_selection(mwh, cad_selection_stage).message)
    [item] = [it for it in selection["items"] if it["track_id"] == couch]
    assert item["label"] == "couch" and [k["box"] for k in item["keyframes"]] == [c["box"] for c in COUCH]


def _run_cad_selection(wh, stage):
    return run_stage(wh, CLIP, "cad_selection", config_hash="c", inputs_hash="i", code_hash="k",
                     body=lambda run_id: stage(wh, CadSelectionConfig(), CLIP, run_id))


def _library(wh: Warehouse) -> None:
    """A 3-model library (no whitening) whose label similarities make a couch a sofa."""
    import pyarrow as pa

    from tasks.retrieval.whitening import fit_whitening, whitening_table

    def write(name, rows):
        wh.write(name, "lib", pa.Table.from_pylist(rows, schema=wh.spec(name).schema))

    rng = np.random.default_rng(1)
    looks = rng.normal(size=(3, 768))
    looks /= np.linalg.norm(looks, axis=1, keepdims=True)
    write("embedding_whitening", whitening_table("lib", fit_whitening(looks, "none", 768), 3).to_pylist())
    write("cad_model_embeddings", [{"library": "lib", "cad_id": f"lib.{c}", "class": c, "vector": v.tolist(), "views": 1}
                                   for c, v in zip(("chair", "sofa", "table"), looks)])
    sim = {("chair", "chair"): 1.0, ("chair", "sofa"): 0.5, ("chair", "table"): 0.4, ("couch", "chair"): 0.3,
           ("couch", "sofa"): 0.9, ("couch", "table"): 0.2, ("dining table", "chair"): 0.4,
           ("dining table", "sofa"): 0.2, ("dining table", "table"): 0.9}
    write("label_similarity", [{"library": "lib", "detector_label": d, "cad_class": c, "similarity": s, "encoder": "test"}
                               for (d, c), s in sim.items()])


@needs_embedder
def test_empty_answer_completes_and_a_newer_label_supersedes(mwh, tmp_path):
    task = _task(mwh, _run(mwh).message)
    ingest_labels(mwh, _label(tmp_path / "a", "a.json", "manual_track", task["task_id"],
                              [{"label": "couch", "boxes": COUCH}, {"label": "chair", "boxes": COUCH[:1]}],
                              "2026-01-01T00:00:00+00:00"))
    two = _run(mwh)
    ids = sorted(set(mwh.read("manual_tracks", [CLIP]).column("track_id").to_pylist()))
    assert two.status == "completed" and len(ids) == 2 and min(ids) >= MANUAL_TRACK_BASE
    # a revision that drops the couch keeps the chair's id (clicks given on it still answer it)
    chair = mwh.read("manual_tracks", [CLIP]).filter(pc.equal(mwh.read("manual_tracks", [CLIP]).column("label"), "chair"))
    ingest_labels(mwh, _label(tmp_path / "c", "c.json", "manual_track", task["task_id"],
                              [{"label": "chair", "boxes": COUCH[:1]}], "2026-01-01T12:00:00+00:00"))
    assert _run(mwh).status == "completed"
    assert mwh.read("manual_tracks", [CLIP]).column("track_id").to_pylist() == chair.column("track_id").to_pylist()
    before = clip_inputs("manual_tracks", mwh, CLIP)
    ingest_labels(mwh, _label(tmp_path / "b", "b.json", "manual_track", task["task_id"], [], "2026-01-02T00:00:00+00:00"))
    assert clip_inputs("manual_tracks", mwh, CLIP) != before
    none = _run(mwh)
    assert none.status == "completed" and none.rows_written == 0 and "nothing missing" in none.message
    assert mwh.read("manual_tracks", [CLIP]).num_rows == 0 and none.output_hash != two.output_hash


def test_an_empty_answer_alone_completes(mwh, tmp_path):
    task = _task(mwh, _run(mwh).message)
    ingest_labels(mwh, _label(tmp_path / "a", "a.json", "manual_track", task["task_id"], [], "2026-01-01T00:00:00+00:00"))
    done = _run(mwh)
    assert done.status == "completed" and done.rows_written == 0  # no embedder needed for nothing


def test_new_tracks_make_a_new_task_that_shows_the_answer_before(mwh, tmp_path):
    task = _task(mwh, _run(mwh).message)
    ingest_labels(mwh, _label(tmp_path / "a", "a.json", "manual_track", task["task_id"],
                              [{"label": "couch", "boxes": COUCH, "source_id": "s"}], "2026-01-01T00:00:00+00:00"))
    members = [m for m in mwh.read("track_detections", [CLIP]).to_pylist() if m["track_id"] == 0]
    mwh.write("track_detections", CLIP, table_rows("track_detections", members))  # tracking changed: track 1 is gone
    again = _run(mwh)
    new = _task(mwh, again.message)
    assert again.status == "paused" and new["task_id"] != task["task_id"]
    assert [t["track_id"] for t in new["existing_tracks"]] == [0]
    assert new["previous"] == [{"label": "couch", "boxes": COUCH, "source_id": "s", "same_as_track": None}]
    assert mwh.read("manual_tracks", [CLIP]).num_rows == 0  # the old answer does not answer the new task
    # "nothing is missing" on the new task, then another: the newest earlier answer drew nothing
    ingest_labels(mwh, _label(tmp_path / "b", "b.json", "manual_track", new["task_id"], [], "2026-01-02T00:00:00+00:00"))
    mwh.write("track_detections", CLIP, table_rows("track_detections", [m for m in members if m["frame_index"] < 15]))
    third = _task(mwh, _run(mwh).message)
    assert third["task_id"] not in (task["task_id"], new["task_id"]) and third["previous"] == []


@needs_embedder
def test_a_cvat_import_answers_the_task(mwh, tmp_path):
    from tasks.human.label_import import write_label
    from tasks.human.label_import_cvat import import_cvat

    task = _task(mwh, _run(mwh).message)
    xml = tmp_path / "annotations.xml"
    xml.write_text(f"""<?xml version="1.0" encoding="utf-8"?>
<annotations><version>1.1</version>
 <meta><task><original_size><width>{W}</width><height>{H}</height></original_size></task></meta>
 <track id="3" label="couch" source="manual">
  <box frame="4" xtl="32" ytl="19.2" xbr="160" ybr="96" outside="0" occluded="0" keyframe="1"/>
  <box frame="6" xtl="40" ytl="19.2" xbr="168" ybr="96" outside="0" occluded="0" keyframe="0"/>
  <box frame="8" xtl="48" ytl="19.2" xbr="176" ybr="96" outside="0" occluded="0" keyframe="1"/>
  <box frame="9" xtl="48" ytl="19.2" xbr="176" ybr="96" outside="1" occluded="0" keyframe="1"/>
 </track>
</annotations>""")
    result = import_cvat(mwh, xml, CLIP)
    assert result.document["task_id"] == task["task_id"]  # the clip's newest manual-track task
    assert ingest_labels(mwh, write_label(result.document, tmp_path / "labels", "cvat")).ok
    done = _run(mwh)
    rows = mwh.read("manual_tracks", [CLIP]).to_pylist()
    assert done.status == "completed" and [r["frame_index"] for r in rows] == [4, 8]
    assert rows[0]["source_id"] == "cvat:3" and rows[0]["box"] == pytest.approx([0.1, 0.1, 0.5, 0.5])
    assert np.linalg.norm(rows[0]["vector"]) == pytest.approx(1.0, abs=1e-5)
