"""What people said about tracks acts downstream: "track N is not an object" (manual_track
``not_objects``) and "same object as track N" (cad_selection, verification and manual_track ``same_as_track``),
through real label files and the real ingest, on a hand-built val clip: only the answers in force
count, the later human tasks leave those tracks out, and the dataset export has one object per
physical object."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow.compute as pc
import pytest

from cadestate.config import (CadSelectionConfig, CorrespondenceTaskConfig, EmbedConfig, ManualTracksConfig,
                              VerificationConfig)
from conftest import table_rows
from tasks.dataset.objects import clip_dataset
from tasks.detection.models import nanodet as nd
from tasks.human.cad_selection import cad_selection_stage, selected_models
from tasks.human.correspondence_task import correspondence_task_stage
from tasks.human.label_ingest import ingest_labels
from tasks.human.labels import label_document
from tasks.human.manual_tracks import manual_tracks_stage
from tasks.human.verification import verification_stage
from tasks.registry import clip_inputs
from tasks.stage import run_stage
from tasks.tracking.relations import TrackRelations, manual_statements, relations_in_force, resolve_fragments
from warehouse import Warehouse

CLIP = "c1"
W, H = 320, 192
STAMPS = [i * 100_000 for i in range(20)]
LABELS = ("chair", "dining table")
SPANS = {0: range(0, 10), 1: range(10, 15), 2: range(5, 13)}
"""Automatic tracks: 0 and 1 chairs (1 continues 0), 2 a dining table (a false detection)."""
MODELS = ("lib.chair_a", "lib.chair_b", "lib.table_a")


@pytest.fixture
def rwh(tmp_path) -> Warehouse:
    """A val clip of 20 frames (noise images, identity cameras) with the tracks of :data:`SPANS`
    and two CAD candidates each."""
    from PIL import Image

    wh = Warehouse(tmp_path / "wh")
    wh.write("clips", CLIP, table_rows("clips", [{"clip": CLIP, "split": "val", "url": "https://example.com/v", "fps": 10.0,
                                                 "width": W, "height": H, "up_rotation": [1.0, 0, 0, 0, 1, 0, 0, 0, 1]}]))
    rng = np.random.default_rng(0)
    frames = []
    for i, t in enumerate(STAMPS):
        path = f"media/frames/{CLIP}/v/{i:04d}.jpg"
        (wh.root / path).parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(rng.integers(0, 255, (H, W, 3), np.uint8)).save(wh.root / path)
        frames.append({"clip": CLIP, "timestamp_us": t, "frame_index": i, "width": W, "height": H, "image_path": path,
                       "K": [300.0, 0, W / 2, 0, 300.0, H / 2, 0, 0, 1], "world_to_camera_R": [1.0, 0, 0, 0, 1, 0, 0, 0, 1],
                       "world_to_camera_t": [0.0, 0, 0]})
    wh.write("frames", CLIP, table_rows("frames", frames))
    dets, members = [], []
    for track, span in SPANS.items():
        for f in span:
            dets.append({"clip": CLIP, "det_id": f * 100 + track, "timestamp_us": STAMPS[f], "frame_index": f,
                         "box": [0.1 + 0.2 * track, 0.1, 0.4 + 0.2 * track, 0.5], "label": LABELS[track // 2]})
            members.append({"clip": CLIP, "track_id": track, "det_id": f * 100 + track, "frame_index": f, "timestamp_us": STAMPS[f]})
    wh.write("detections", CLIP, table_rows("detections", dets))
    wh.write("track_detections", CLIP, table_rows("track_detections", members))
    wh.write("tracks", CLIP, table_rows("tracks", [{"clip": CLIP, "track_id": t, "label": LABELS[t // 2]} for t in SPANS]))
    wh.write("cad_models", "lib", table_rows("cad_models", [
        {"library": "lib", "cad_id": m, "class": m.split(".")[1][:-2], "symmetry": 1, "extent": [1.0, 1.0, 1.0],
         "mesh_path": f"media/cad/lib/{m}.glb"} for m in MODELS]))
    _candidates(wh, list(SPANS))
    return wh


def _candidates(wh: Warehouse, tracks: list[int]) -> None:
    wh.write("cad_candidates", CLIP, table_rows("cad_candidates", [
        {"clip": CLIP, "track_id": t, "rank": r + 1, "library": "lib", "cad_id": m, "cad_class": m.split(".")[1][:-2],
         "score": 0.9 - 0.1 * r} for t in tracks for r, m in enumerate(MODELS[:2] if t != 2 else MODELS[2:] * 2)]))


def _label(folder: Path, kind: str, task_id: str, answers: list[dict], when: str, **extra) -> Path:
    """A label file written as the annotation pages write it (``extra``: e.g. ``not_objects``)."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{kind}-{when[:10]}.json"
    path.write_text(json.dumps({**label_document(kind, CLIP, task_id, answers, annotator="t", created_at=when), **extra}))
    return path


def _ingest(wh: Warehouse, path: Path) -> None:
    report = ingest_labels(wh, path)
    assert report.ok and report.ingested == [str(path)], report.errors


def _run(wh: Warehouse, stage: str, body):
    return run_stage(wh, CLIP, stage, config_hash="c", inputs_hash="i", code_hash="k", body=body)


def _manual_task(wh: Warehouse) -> str:
    out = _run(wh, "manual_tracks", lambda rid: manual_tracks_stage(wh, ManualTracksConfig(), EmbedConfig(), LABELS, CLIP, rid))
    return json.loads((wh.root / out.message.split(" task ", 1)[1].split(";")[0]).read_text())["task_id"]


def _cad_task(wh: Warehouse) -> tuple[object, dict]:
    """The cad_selection run and its task document."""
    out = _run(wh, "cad_selection", lambda rid: cad_selection_stage(wh, CadSelectionConfig(), CLIP, rid))
    task = json.loads((wh.root / out.message.split(" task ", 1)[1].split(";")[0]).read_text()) if " task " in out.message else {}
    return out, task


def _objects(wh: Warehouse) -> dict[int, tuple[int, ...]]:
    """The exported objects: track id -> the tracks merged into it."""
    return {o.track_id: o.merged for o in clip_dataset(wh, CLIP).objects}


def test_resolve_fragments_follows_chains_and_drops_cycles():
    assert resolve_fragments({1: 0, 2: 1, 5: 2}) == ({1: 0, 2: 0, 5: 0}, [])
    roots, warnings = resolve_fragments({3: 4, 4: 3, 6: 3, 7: 8})
    assert roots == {6: 3, 7: 8} and warnings == ["tracks 3 -> 4 -> 3 are each said to be a fragment of the next, a cycle: "
                                                   "these statements are ignored"]
    rel = TrackRelations(frozenset({0}), {1: 0, 2: 5})
    assert not rel.is_object(0) and not rel.is_object(1) and rel.is_object(2) and rel.root(2) == 5 and rel.root(9) == 9


def test_a_fragment_of_a_fragment_of_no_object_is_no_object():
    """1 is a fragment of 2, 2 of 3, and 2 is said to be no object: 1 is none either (it was, its
    root 3 being an object); cycles leave their tracks roots."""
    from tasks.tracking.relations import no_object_chains

    edges = {1: 2, 2: 3, 5: 6, 6: 5, 7: 6}
    fragments, _ = resolve_fragments(edges)
    assert no_object_chains({2}, edges, fragments) == {1, 2}
    assert no_object_chains({6}, edges, fragments) == {6, 7}
    relations = TrackRelations(frozenset(no_object_chains({2}, edges, fragments)), fragments)
    assert not relations.is_object(1) and relations.is_object(3)


def test_not_objects_and_fragments_act_downstream_while_in_force(rwh, tmp_path):
    manual = _manual_task(rwh)
    _, first = _cad_task(rwh)
    assert [it["track_id"] for it in first["items"]] == [0, 1, 2]
    before = clip_inputs("cad_selection", rwh, CLIP)

    # "track 2 is not an object": CAD selection no longer asks about it; the stage's inputs say so
    _ingest(rwh, _label(tmp_path / "m1", "manual_track", manual, [], "2026-01-01T00:00:00+00:00", not_objects=[2]))
    assert relations_in_force(rwh, CLIP).not_objects == {2}
    inputs = clip_inputs("cad_selection", rwh, CLIP)
    assert inputs != before and clip_inputs("cad_selection", rwh, CLIP) == inputs
    run, task = _cad_task(rwh)
    assert task["task_id"] == first["task_id"] and [it["track_id"] for it in task["items"]] == [0, 1]
    assert run.status == "paused" and "1 left out" in run.message and "2 of 2 tracks unanswered" in run.message
    # a pose solved for it before is not shown for verification (nothing to render, nothing to ask)
    rwh.write("poses", CLIP, table_rows("poses", [{"clip": CLIP, "track_id": "2", "cad_id": "lib.table_a", "class": "table",
                                                   "status": "ok", "translation": [0.0, 0, 4], "rotation": [1.0, 0, 0, 0],
                                                   "scale": [1.0, 1, 1], "is_mirrored": False,
                                                   "keyframe_timestamps_us": STAMPS[5:8]}]))
    verified = _run(rwh, "verification", lambda rid: verification_stage(rwh, VerificationConfig(), CLIP, rid))
    assert verified.status == "completed" and "no solved pose to verify" in verified.message

    # "track 1 is the same object as track 0": it gets no model, so no correspondences are asked about it
    _ingest(rwh, _label(tmp_path / "c1", "cad_selection", task["task_id"], [
        {"track_id": 0, "cad_id": "lib.chair_a"}, {"track_id": 1, "cad_id": None, "same_as_track": 0}], "2026-01-02T00:00:00+00:00"))
    done, again = _cad_task(rwh)
    assert done.status == "completed" and _cad_task(rwh)[0].output_hash == done.output_hash  # a rerun changes nothing
    assert selected_models(rwh, CLIP) == {0: "lib.chair_a", 1: None}
    corr = _run(rwh, "correspondence_task", lambda rid: correspondence_task_stage(rwh, CorrespondenceTaskConfig(), CLIP, rid))
    assert "1 of 1 tracks unanswered" in corr.message
    ds = clip_dataset(rwh, CLIP)
    [obj] = ds.objects  # track 2 is not exported; track 1 joined track 0's object
    assert (obj.track_id, obj.merged, obj.cad_id) == (0, (1,), "lib.chair_a")
    assert sorted(obj.boxes) == [STAMPS[f] for f in range(15)]

    # a newer manual-track answer supersedes the first: track 2 is an object again and asked about
    _ingest(rwh, _label(tmp_path / "m2", "manual_track", manual, [], "2026-01-03T00:00:00+00:00"))
    assert relations_in_force(rwh, CLIP).not_objects == frozenset()
    assert clip_inputs("cad_selection", rwh, CLIP) != inputs
    assert _objects(rwh) == {0: (1,), 2: ()}
    assert [it["track_id"] for it in _cad_task(rwh)[1]["items"]] == [0, 1, 2]

    # track 0, chosen before, said not to be an object: no correspondences asked; its fragment goes with it
    _ingest(rwh, _label(tmp_path / "m3", "manual_track", manual, [], "2026-01-04T00:00:00+00:00", not_objects=[0]))
    assert selected_models(rwh, CLIP) == {1: None}
    corr = _run(rwh, "correspondence_task", lambda rid: correspondence_task_stage(rwh, CorrespondenceTaskConfig(), CLIP, rid))
    assert corr.status == "completed" and "no track has a chosen CAD model" in corr.message
    assert corr.message.endswith("withdrawn")  # the task that waited for track 0's clicks
    assert _objects(rwh) == {2: ()}


def test_chains_resolve_and_a_ring_with_the_answers_in_force_is_refused(rwh, tmp_path):
    _manual_task(rwh)
    _, task = _cad_task(rwh)
    _ingest(rwh, _label(tmp_path / "a", "cad_selection", task["task_id"], [
        {"track_id": 0, "cad_id": "lib.chair_a"}, {"track_id": 1, "cad_id": None, "same_as_track": 0},
        {"track_id": 2, "cad_id": None, "same_as_track": 1}], "2026-01-01T00:00:00+00:00"))
    assert relations_in_force(rwh, CLIP).fragments == {1: 0, 2: 0}
    assert _objects(rwh) == {0: (1, 2)}

    # a newer answer for track 0 would close a ring with the answer in force for track 1: refused at
    # ingest (it was taken, and the ring ignored with a log line: both tracks left the dataset); the
    # relations stay as they were (rings across kinds, still possible, are dropped: resolve_fragments)
    ring = _label(tmp_path / "b", "cad_selection", task["task_id"], [{"track_id": 0, "cad_id": None, "same_as_track": 1}],
                  "2026-01-02T00:00:00+00:00")
    report = ingest_labels(rwh, ring)
    assert not report.ingested and "tracks 0 -> 1 -> 0 each name the next as the same object (1 -> 0 answered before)" \
        in report.errors[0], report.errors
    assert relations_in_force(rwh, CLIP).fragments == {1: 0, 2: 0} and _objects(rwh) == {0: (1, 2)}


@pytest.mark.skipif(not nd.is_built(nd.default_cache_dir()),
                    reason="the NanoDet-m model is not built (`make models`, which `make test` runs)")
def test_a_drawn_object_said_to_be_a_track_joins_it(rwh, tmp_path):
    manual = _manual_task(rwh)
    boxes = [{"timestamp_us": STAMPS[f], "box": [0.3, 0.1, 0.6, 0.5]} for f in (15, 19)]  # track 1 after it was lost
    _ingest(rwh, _label(tmp_path / "m", "manual_track", manual, [{"label": "chair", "boxes": boxes, "source_id": "h:1",
                                                                    "same_as_track": 1}], "2026-01-01T00:00:00+00:00"))
    assert _run(rwh, "manual_tracks", lambda rid: manual_tracks_stage(rwh, ManualTracksConfig(), EmbedConfig(), LABELS, CLIP,
                                                                      rid)).status == "completed"
    [drawn] = set(rwh.read("manual_tracks", [CLIP]).column("track_id").to_pylist())
    _candidates(rwh, [*SPANS, drawn])  # retrieval ranks every track, the drawn one too
    _, task = _cad_task(rwh)
    assert [it["track_id"] for it in task["items"]] == [0, 1, 2]  # the drawn object is track 1: not asked about
    _ingest(rwh, _label(tmp_path / "c", "cad_selection", task["task_id"], [{"track_id": 1, "cad_id": None, "same_as_track": 0}],
                        "2026-01-02T00:00:00+00:00"))
    rel = relations_in_force(rwh, CLIP)
    assert rel.fragments == {1: 0, drawn: 0} and rel.drawn == {drawn}  # drawn -> 1 -> 0
    objects = {o.track_id: o for o in clip_dataset(rwh, CLIP).objects}
    assert sorted(objects) == [0, 2] and objects[0].merged == (1, drawn)
    assert sorted(objects[0].boxes) == [STAMPS[f] for f in (*range(16), 19)]  # 0's, then 1's, then the drawn boxes


@pytest.mark.skipif(not nd.is_built(nd.default_cache_dir()),
                    reason="the NanoDet-m model is not built (`make models`, which `make test` runs)")
def test_an_answered_manual_track_task_shows_its_whole_answer_again(rwh, tmp_path):
    """Reopened, a manual-track task carries every statement of its answer in force (what each drawn
    object is, the tool's id, the tracks that are no object): a page that sends it back unchanged
    loses nothing, since a new answer replaces the whole old one."""
    manual = _manual_task(rwh)
    boxes = [{"timestamp_us": STAMPS[f], "box": [0.3, 0.1, 0.6, 0.5]} for f in (15, 19)]
    new = [{"timestamp_us": STAMPS[3], "box": [0.1, 0.1, 0.2, 0.2]}]
    _ingest(rwh, _label(tmp_path / "m", "manual_track", manual, [{"label": "chair", "boxes": boxes, "source_id": "cvat:7",
                                                                    "same_as_track": 1}, {"label": "chair", "boxes": new}],
                        "2026-01-01T00:00:00+00:00", not_objects=[2]))
    _run(rwh, "manual_tracks", lambda rid: manual_tracks_stage(rwh, ManualTracksConfig(), EmbedConfig(), LABELS, CLIP, rid))
    tasks = rwh.read("label_tasks", [CLIP]).filter(pc.equal(pc.field("kind"), "manual_track"))
    task = json.loads(tasks.sort_by([("created_at", "descending")]).column("document")[0].as_py())
    assert task["task_id"] == manual and task["previous_not_objects"] == [2]
    assert [(a["same_as_track"], a["source_id"], len(a["boxes"])) for a in task["previous"]] == [(1, "cvat:7", 2), (None, None, 1)]
    again = {k: task["previous"] if k == "answers" else v for k, v in json.loads(
        _label(tmp_path / "a", "manual_track", manual, [], "2026-01-02T00:00:00+00:00").read_text()).items()}
    again["not_objects"] = task["previous_not_objects"]  # what the page sends back untouched
    (tmp_path / "again.json").write_text(json.dumps(again))
    _ingest(rwh, tmp_path / "again.json")
    assert manual_statements(rwh, CLIP)[0] == {2} and list(manual_statements(rwh, CLIP)[1].values()) == [1]


def _verification(wh: Warehouse, cfg: VerificationConfig = VerificationConfig(keyframes=2)) -> tuple[object, dict]:
    """The verification run and its task document (the newest version of its file)."""
    out = _run(wh, "verification", lambda rid: verification_stage(wh, cfg, CLIP, rid))
    tasks = wh.read("label_tasks", [CLIP]).filter(pc.equal(pc.field("kind"), "verification"))
    return out, json.loads(tasks.sort_by([("created_at", "descending")]).column("document")[0].as_py())


def test_duplicate_poses_are_flagged_in_verification_and_join_the_track_named(rwh, tmp_path):
    import trimesh

    from bench.pose_bench import accepted_predictions

    for m in MODELS:
        (rwh.root / f"media/cad/lib/{m}.glb").parent.mkdir(parents=True, exist_ok=True)
        trimesh.creation.box(extents=(1, 1, 1)).export(rwh.root / f"media/cad/lib/{m}.glb")
    pose = {"clip": CLIP, "status": "ok", "rotation": [1.0, 0, 0, 0], "scale": [1.0, 1, 1], "is_mirrored": False,
            "keyframe_timestamps_us": STAMPS[5:9]}
    rwh.write("poses", CLIP, table_rows("poses", [  # tracks 0 and 1: one chair posed twice, 4 cm apart; 2 a table
        {**pose, "track_id": "0", "cad_id": "lib.chair_a", "class": "chair", "translation": [0.0, 0, 4]},
        {**pose, "track_id": "1", "cad_id": "lib.chair_b", "class": "chair", "translation": [0.03, 0, 4.02]},
        {**pose, "track_id": "2", "cad_id": "lib.table_a", "class": "table", "translation": [2.5, 0, 6]}]))

    # no pair reaches the threshold: the items are written as before the flags existed
    _, plain = _verification(rwh, VerificationConfig(keyframes=2, duplicate_overlap=1.0))
    assert [it["track_id"] for it in plain["items"]] == [0, 1, 2] and all("maybe_same_as" not in it for it in plain["items"])
    run, task = _verification(rwh)
    assert run.status == "paused" and task["task_id"] == plain["task_id"]  # the task id digests the poses only
    assert {it["track_id"]: it.get("maybe_same_as") for it in task["items"]} == {0: [1], 1: [0], 2: None}
    assert _objects(rwh) == {0: (), 1: (), 2: ()}  # nothing accepted yet

    # "track 1's pose shows the object of track 0" (both poses good): the export keeps track 0's pose only
    _ingest(rwh, _label(tmp_path / "v1", "verification", task["task_id"], [
        {"track_id": 0, "verdict": "accept"}, {"track_id": 1, "verdict": "accept", "same_as_track": 0},
        {"track_id": 2, "verdict": "reject"}], "2026-01-01T00:00:00+00:00"))
    assert relations(rwh) == {("same_object", 1, 0)}
    done, again = _verification(rwh)
    assert done.status == "completed" and "2 of 3 poses accepted" in done.message
    assert {it["track_id"]: it["previous"].get("same_as_track") for it in again["items"]} == {0: None, 1: 0, 2: None}
    assert "same_as_track" not in again["items"][0]["previous"]
    assert relations_in_force(rwh, CLIP).fragments == {1: 0}
    objects = {o.track_id: o for o in clip_dataset(rwh, CLIP).objects}
    assert {t: o.merged for t, o in objects.items()} == {0: (1,), 2: ()}
    assert objects[0].pose.translation == (0.0, 0.0, 4.0) and objects[0].cad_id == "lib.chair_a" and objects[2].pose is None
    assert [p.track_id for p in accepted_predictions(rwh, [CLIP])] == ["0"]  # what bench report scores

    # a newer answer for track 1 says it is an object of its own: both poses are exported again
    _ingest(rwh, _label(tmp_path / "v2", "verification", task["task_id"], [{"track_id": 1, "verdict": "accept"}],
                        "2026-01-02T00:00:00+00:00"))
    assert relations_in_force(rwh, CLIP).fragments == {} and _objects(rwh) == {0: (), 1: (), 2: ()}
    assert sorted(p.track_id for p in accepted_predictions(rwh, [CLIP])) == ["0", "1"]

    # track 0's pose rejected, track 1's accepted as the same object: track 1's pose speaks for it (the
    # export kept track 0's, none, and the object lost its only accepted pose)
    _ingest(rwh, _label(tmp_path / "v3", "verification", task["task_id"], [
        {"track_id": 0, "verdict": "reject"}, {"track_id": 1, "verdict": "accept", "same_as_track": 0}],
        "2026-01-03T00:00:00+00:00"))
    assert relations_in_force(rwh, CLIP).fragments == {1: 0}
    assert "1 of 3 poses accepted" in _verification(rwh)[0].message
    objects = {o.track_id: o for o in clip_dataset(rwh, CLIP).objects}
    assert {t: o.merged for t, o in objects.items()} == {1: (0,), 2: ()}
    assert objects[1].pose.translation == (0.03, 0.0, 4.02) and objects[1].cad_id == "lib.chair_b"
    assert [p.track_id for p in accepted_predictions(rwh, [CLIP])] == ["1"]


def relations(wh: Warehouse) -> set[tuple]:
    """The clip's verification statements in ``track_relations``: (relation, track_id, other_track_id)."""
    return {(r["relation"], r["track_id"], r["other_track_id"]) for r in wh.read("track_relations", [CLIP]).to_pylist()
            if r["kind"] == "verification"}


def test_clicks_on_a_camera_sfm_now_interpolates_are_asked_again(rwh, tmp_path):
    """Clicks given on every key-frame of track 0; SfM run again then interpolates the cameras of
    its first frames. The new task leaves those frames out, and the clicks given there no longer
    hold (they went on to the pose solver, through made-up cameras): the track is asked again."""
    import pyarrow.compute as pc

    _, task = _cad_task(rwh)
    _ingest(rwh, _label(tmp_path / "c", "cad_selection", task["task_id"], [{"track_id": 0, "cad_id": "lib.chair_a"}],
                        "2026-01-01T00:00:00+00:00"))
    _cad_task(rwh)

    def clicks_task():
        out = _run(rwh, "correspondence_task", lambda rid: correspondence_task_stage(rwh, CorrespondenceTaskConfig(), CLIP, rid))
        rows = rwh.read("label_tasks", [CLIP]).filter(pc.equal(pc.field("kind"), "correspondences"))
        return out, json.loads(rows.sort_by([("created_at", "descending")]).column("document")[0].as_py())

    out, first = clicks_task()
    stamps = [k["timestamp_us"] for k in first["items"][0]["keyframes"]]
    points = [{"x": 0.2 + 0.05 * i, "y": 0.2 + 0.03 * i * i, "xyz": [0.1 * i - 0.2, 0.05 * i, 0.1 * (i % 2)]} for i in range(4)]
    _ingest(rwh, _label(tmp_path / "k", "correspondences", first["task_id"], [
        {"track_id": 0, "cad_id": "lib.chair_a", "is_mirrored": False, "keyframes": [{"timestamp_us": t, "points": points}
                                                                                  for t in stamps]}], "2026-01-02T00:00:00+00:00"))
    assert clicks_task()[0].status == "completed"
    frames = rwh.read("frames", [CLIP]).to_pylist()
    for f in frames:
        f["camera_interpolated"] = f["frame_index"] < 3
    rwh.write("frames", CLIP, table_rows("frames", frames))
    made_up = {f["timestamp_us"] for f in frames if f["camera_interpolated"]}
    assert made_up & set(stamps)  # clicks were given on frames now interpolated
    out, second = clicks_task()
    assert second["task_id"] != first["task_id"] and not made_up & {k["timestamp_us"] for k in second["items"][0]["keyframes"]}
    assert out.status == "paused" and second["items"][0].get("previous") is None
    assert not made_up & set(rwh.read("correspondences", [CLIP]).column("timestamp_us").to_pylist())
