"""The annotate_clip / build_dataset flows on real Prefect (ephemeral API): caching and lineage."""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import shutil
import socket
from pathlib import Path

import pytest

from cadestate.config import Config, EmbedConfig, FramesConfig, WarehouseConfig
from flows.annotate_clip import run_clips
from tasks.registry import stages_of
from tasks.status import pipeline_status
from tasks.video.ingest import ClipSource, clip_inputs
from warehouse import Warehouse

pytestmark = pytest.mark.slow


CLIP_STAGES = [s.name for s in stages_of("clip")]


def states(reports):
    return [(r.clip, r.stage, r.state) for r in reports]


def expect(clip: str, **states_by_stage: str) -> list[tuple[str, str, str]]:
    """(clip, stage, state) for every clip stage: the given ones, others ``states_by_stage['rest']``."""
    rest = states_by_stage.pop("rest")
    return [(clip, s, states_by_stage.get(s, rest)) for s in CLIP_STAGES]


def snapshot(root: Path) -> dict[str, int]:
    """mtime of every file the stages write (tables and media)."""
    return {str(p): p.stat().st_mtime_ns for d in ("tables", "media", "inputs") for p in (root / d).rglob("*") if p.is_file()}


def prefect_task_runs(flow_run: str) -> list[str]:
    """The task runs (name and tags) of the latest flow run named ``flow_run``, then its tags, read from Prefect's API."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import FlowRunFilter, FlowRunFilterId, FlowRunFilterName
    from prefect.client.schemas.sorting import FlowRunSort, TaskRunSort

    with get_client(sync_client=True) as client:
        latest = client.read_flow_runs(flow_run_filter=FlowRunFilter(name=FlowRunFilterName(any_=[flow_run])),
                                       sort=FlowRunSort.START_TIME_DESC, limit=1)
        tasks = client.read_task_runs(flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=[latest[0].id])),
                                      sort=TaskRunSort.EXPECTED_START_TIME_ASC, limit=100)
    return sorted(f"{t.name} {sorted(t.tags)}" for t in tasks) + [f"flow {sorted(latest[0].tags)}"]


@pytest.fixture
def config(tmp_path) -> Config:
    return Config(warehouse=WarehouseConfig(root=str(tmp_path / "warehouse")))


@pytest.fixture
def source(small_clip) -> ClipSource:
    return ClipSource("small", small_clip.video_path, small_clip.cameras_path)


def test_unchanged_rerun_does_nothing(config, source):
    first = run_clips([source], config, show_progress=False)
    assert states(first) == expect("small", rest="completed")
    # one Prefect task for the clip's stages, untagged (no concurrency slots asked for); the flow run is tagged
    assert prefect_task_runs("annotate_clip/small") == ["clip/small []", "flow ['clip:small', 'split:train']"]
    wh = Warehouse(config.warehouse.root)
    before, runs_before = snapshot(wh.root), wh.read("runs").num_rows
    again = run_clips([source], config, show_progress=False)
    assert states(again) == expect("small", rest="cached")
    assert snapshot(wh.root) == before and wh.read("runs").num_rows == runs_before == len(CLIP_STAGES)
    # Rerunning from the warehouse's own copies (what `cadestate run` does) is the same clip: cached.
    video, cameras, _ = clip_inputs(wh, "small")
    assert {r.state for r in run_clips([ClipSource("small", video, cameras)], config, show_progress=False)} == {"cached"}
    # A process killed within detect (its marker left, no row): status says detect and what follows
    # it are stale, as the next run finds (it said "fresh" while that run redid detect).
    marker = wh.root / "_running" / "small" / "detect.r9.json"
    marker.parent.mkdir(parents=True, exist_ok=True)
    marker.write_text(json.dumps({"clip": "small", "stage": "detect", "run_id": "r9", "pid": 2 ** 22 + 7,
                                  "host": socket.gethostname(), "process_start": 0.0, "process_ticks": 1,
                                  "started_at": dt.datetime.now(dt.timezone.utc).isoformat()}))
    stale = {r.stage: r.stale_reasons for r in pipeline_status(wh, config) if r.stale_reasons}
    assert stale["detect"] == ("last run interrupted",) and stale["embed"] == ("upstream stale",), stale
    assert {r.stage: r.state for r in run_clips([source], config, show_progress=False)}["detect"] == "completed"
    assert all(not r.stale_reasons for r in pipeline_status(wh, config))


def test_a_copied_or_moved_warehouse_reruns_nothing(config, source, tmp_path):
    run_clips([source], config, show_progress=False)
    copy = tmp_path / "elsewhere" / "copied"
    shutil.copytree(config.warehouse.root, copy)
    moved = dataclasses.replace(config, warehouse=WarehouseConfig(root=str(copy)))
    wh = Warehouse(copy)
    before, runs_before = snapshot(copy), wh.read("runs").num_rows
    assert states(run_clips([source], moved, show_progress=False)) == expect("small", rest="cached")
    assert snapshot(copy) == before and wh.read("runs").num_rows == runs_before
    assert all(r.status == "completed" and not r.stale_reasons for r in pipeline_status(wh, moved))


def test_back_to_an_earlier_config_reruns_what_a_later_one_overwrote(config, source):
    """Config A, then B (tracking writes other tracks), then A again: A's cached tracking result
    would name tracks the table no longer holds, so tracking runs again and the table is A's."""
    from cadestate.config import TrackingConfig

    run_clips([source], config, show_progress=False)
    wh = Warehouse(config.warehouse.root)
    first = wh.read("tracks", ["small"])
    assert first.num_rows
    other = dataclasses.replace(config, tracking=TrackingConfig(min_detections=1_000_000))  # drops every track
    assert {r.stage: r.state for r in run_clips([source], other, show_progress=False)}["tracking"] == "completed"
    assert wh.read("tracks", ["small"]).num_rows == 0
    back = {r.stage: r.state for r in run_clips([source], config, show_progress=False)}
    assert back["tracking"] == "completed"
    assert wh.read("tracks", ["small"]).equals(first)
    assert {r.state for r in run_clips([source], config, show_progress=False)} == {"cached"}


def test_changed_stage_config_reruns_that_stage_only(config, source):
    run_clips([source], config, show_progress=False)
    wh = Warehouse(config.warehouse.root)
    changed = dataclasses.replace(config, frames=FramesConfig(seek_threshold_us=0))  # seeks, same frames
    status = {r.stage: r.stale_reasons for r in pipeline_status(wh, changed)}
    assert status == {s: ("config changed",) if s == "frames" else ("upstream stale",) if s not in ("cameras", "ingest") else ()
                      for s in CLIP_STAGES}
    reports = run_clips([source], changed, show_progress=False)
    # frames reran and wrote the same frames: nothing downstream reruns
    assert states(reports) == expect("small", frames="completed", rest="cached")
    runs = wh.read("runs", filters=[("stage", "==", "frames")]).to_pylist()
    assert [r["config_hash"] for r in runs] == [config.section_hash("frames"), changed.section_hash("frames")]
    assert all(not r.stale_reasons for r in pipeline_status(wh, changed))
    assert len(list((wh.root / "media" / "frames" / "small").iterdir())) == 1  # old images pruned
    # Back to the first config: its cached results are reused, no work, and status says so beforehand
    # (it finds the first run as the chain's cache does, not only the last one)
    assert all(not r.stale_reasons for r in pipeline_status(wh, config))
    assert {r.state for r in run_clips([source], config, show_progress=False)} == {"cached"}


def test_changed_images_rerun_what_reads_them(config, source):
    run_clips([source], config, show_progress=False)
    lower = dataclasses.replace(config, frames=FramesConfig(jpeg_quality=60))  # other pixels: detect must look again
    reports = {r.stage: r.state for r in run_clips([source], lower, show_progress=False)}
    assert reports["ingest"] == "cached" and reports["frames"] == reports["detect"] == "completed"


def test_a_bad_clip_does_not_stop_the_others(config, source, tmp_path):
    bad_dir = tmp_path / "bad"
    bad_dir.mkdir()
    (bad_dir / "broken.mp4").write_bytes(b"\x00" * 1000)
    shutil.copy(source.cameras, bad_dir / "broken.txt")
    broken = ClipSource("broken", bad_dir / "broken.mp4", bad_dir / "broken.txt")
    reports = run_clips([broken, source], config, show_progress=False)
    # the cameras stage passes a given camera file on; ingest is the first to read the video
    assert states(reports) == (expect("broken", cameras="completed", ingest="failed", rest="skipped")
                               + expect("small", rest="completed"))
    assert "broken.mp4: cannot open video" in reports[1].message
    wh = Warehouse(config.warehouse.root)
    failed = wh.read("runs", partitions=["broken"]).to_pylist()
    assert [(r["stage"], r["status"]) for r in failed] == [("cameras", "completed"), ("ingest", "failed")]
    assert "cannot open video" in failed[1]["message"]
    assert wh.partitions("frames") == ["small"]


def test_a_stage_listed_after_a_skipped_one_is_skipped_too(config, source):
    """pose runs after correspondence_task without reading its output: when a stage before that one
    fails, pose (and verification after it) are skipped as well, not run on the correspondences
    there were and recorded completed while the clip has not reached them."""
    wh = Warehouse(config.warehouse.root)
    blocker = wh.partition_dir("embeddings", "small")
    blocker.parent.mkdir(parents=True)
    blocker.write_text("")  # a file where the partition's folder goes: embed's write fails (as on a full disk)
    reports = run_clips([source], config, show_progress=False)
    assert states(reports) == expect("small", cameras="completed", ingest="completed", frames="completed",
                                     detect="completed", embed="failed", rest="skipped")
    assert {r["stage"] for r in wh.read("runs", partitions=["small"]).to_pylist()} == {
        "cameras", "ingest", "frames", "detect", "embed"}


def test_cad_library_flow_caches_per_stage(config, tmp_path):
    import trimesh

    from cadestate.config import CadViewsConfig
    from flows.cad_library import run_cad_library
    from tasks.cad.sources import folder_items

    folder = tmp_path / "meshes"
    folder.mkdir()
    trimesh.creation.box((1.0, 0.5, 0.6)).export(folder / "box.obj")
    trimesh.creation.cone(0.3, 0.8).export(folder / "cone.ply")
    (folder / "models.csv").write_text("id,class\nbox,table\ncone,lamp\n")
    items = list(folder_items(folder, "lib"))
    small = dataclasses.replace(config, cad_views=CadViewsConfig(views=2, size=64))
    names = [s.name for s in stages_of("library")]
    assert states(run_cad_library(items, small, show_progress=False)) == [("lib", s, "completed") for s in names]
    assert states(run_cad_library(items, small, show_progress=False)) == [("lib", s, "cached") for s in names]
    bigger = dataclasses.replace(small, cad_views=CadViewsConfig(views=3, size=64))
    rerun = {"cad_views", "cad_embed"}  # the renders changed; the classes (label_similarity) did not
    assert states(run_cad_library(items, bigger, show_progress=False)) == [
        ("lib", s, "completed" if s in rerun else "cached") for s in names]
    wh = Warehouse(config.warehouse.root)
    assert wh.read("cad_views").num_rows == wh.read("cad_embeddings").num_rows == 6
    # [embed] is read by cad_embed too: changing it makes the library's descriptors stale
    status = {(r.clip, r.stage): r.stale_reasons for r in pipeline_status(wh, bigger, scope="library")}
    assert status == {("lib", s): () for s in names}
    crops = dataclasses.replace(bigger, embed=EmbedConfig(crop_size=96))
    status = {r.stage: r.stale_reasons for r in pipeline_status(wh, crops, scope="library")}
    assert status["cad_embed"] == ("config changed",) and status["cad_views"] == ()
    assert pipeline_status(wh, bigger, ["lib"], scope="clip") == []  # a library is not a clip
    # a model's class changed in models.csv: its renders come out the same, yet its descriptors take the new class
    (folder / "models.csv").write_text("id,class\nbox,cabinet\ncone,lamp\n")
    relabelled = list(folder_items(folder, "lib"))
    assert states(run_cad_library(relabelled, bigger, show_progress=False)) == [("lib", s, "completed") for s in names]
    classes = {r["cad_id"]: r["class"] for r in wh.read("cad_model_embeddings", columns=["cad_id", "class"]).to_pylist()}
    assert classes == {"lib.box": "cabinet", "lib.cone": "lamp"}


def test_library_flows_run_on_threads_whatever_task_runner_says(config, tmp_path):
    """``task_runner = "dask"`` sends clips to Dask whole (:mod:`flows.dask_clips`); the CAD library's
    flow went through prefect_dask's DaskTaskRunner: a local cluster of its own (40.8 s against 24.3 s
    for one model), its logs, ``max_workers`` ignored, and library units shipped to a cluster though
    the library is built before the clips. It runs here, on ``max_workers`` threads."""
    import sys

    import trimesh
    from prefect.task_runners import ThreadPoolTaskRunner

    from cadestate.config import CadViewsConfig, PrefectConfig
    from flows.cad_library import build_cad_library, run_cad_library
    from flows.runtime import configured
    from tasks.cad.sources import folder_items

    folder = tmp_path / "meshes"
    folder.mkdir()
    trimesh.creation.box((1.0, 0.5, 0.6)).export(folder / "box.obj")
    (folder / "models.csv").write_text("id,class\nbox,table\n")
    on_dask = dataclasses.replace(config, cad_views=CadViewsConfig(views=2, size=64),
                                  prefect=PrefectConfig(task_runner="dask", max_workers=3))
    names = [s.name for s in stages_of("library")]
    assert states(run_cad_library(list(folder_items(folder, "lib")), on_dask, show_progress=False)) == [
        ("lib", s, "completed") for s in names]
    assert "prefect_dask" not in sys.modules
    runner = configured(build_cad_library, on_dask.prefect).task_runner
    assert isinstance(runner, ThreadPoolTaskRunner) and runner._max_workers == 3


def test_clip_pauses_for_labels_and_ingest_resumes_it(small_library_warehouse, source, tmp_path):
    """The clip with a real (small) CAD library: retrieval ranks it, CAD selection pauses."""
    import json

    from conftest import warehouse_copy
    from tasks.human.cad_selection import selected_models
    from tasks.human.label_ingest import ingest_labels
    from tasks.human.labels import label_document

    config = warehouse_copy(small_library_warehouse, tmp_path / "warehouse")
    first = run_clips([source], config, show_progress=False)
    wh = Warehouse(config.warehouse.root)
    tracks = wh.read("tracks", ["small"], columns=["track_id"]).column("track_id").to_pylist()
    assert tracks, "the small clip has tracks"
    assert states(first) == expect("small", cad_selection="paused", correspondence_task="waiting", pose="waiting",
                                         verification="waiting", rest="completed")  # no pose before any click
    paused = {r.stage: r for r in first}["cad_selection"]
    assert f"{len(tracks)} of {len(tracks)} tracks unanswered in cad_selection task label_tasks/small/" in paused.message
    status = {r.stage: r for r in pipeline_status(wh, config)}
    assert status["cad_selection"].status == "paused" and not status["cad_selection"].stale_reasons
    assert "unanswered" in status["cad_selection"].message
    assert [r["status"] for r in wh.read("runs", filters=[("stage", "==", "cad_selection")]).to_pylist()] == ["paused"]
    # an unchanged rerun stays paused, doing no work
    again = run_clips([source], config, show_progress=False)
    assert states(again) == expect("small", cad_selection="paused", correspondence_task="waiting", pose="waiting",
                                         verification="waiting", rest="cached")

    task_path = wh.root / paused.message.split(" task ", 1)[1].split(";")[0]
    task = json.loads(task_path.read_text())
    chosen = {it["track_id"]: it["candidates"][1]["cad_id"] for it in task["items"]}  # each track's second candidate
    answers = [{"track_id": t, "cad_id": chosen[t]} for t in tracks]
    label = tmp_path / "labels" / "sel.json"
    label.parent.mkdir()
    label.write_text(json.dumps(label_document("cad_selection", "small", task["task_id"], answers)))
    assert ingest_labels(wh, label.parent).clips == ["small"]
    assert {r.stage: r.stale_reasons for r in pipeline_status(wh, config)}["cad_selection"] == ("inputs changed",)
    resumed = run_clips([source], config, show_progress=False)
    # upstream work is reused; the selection completes, the correspondences task now waits for clicks
    assert states(resumed) == expect("small", cad_selection="completed", correspondence_task="paused", pose="waiting",
                                           verification="waiting", rest="cached")
    assert selected_models(wh, "small") == {t: chosen[t] for t in tracks}
    clicks = {r.stage: r for r in resumed}["correspondence_task"]
    assert f"{len(tracks)} of {len(tracks)} tracks unanswered in correspondences task" in clicks.message
    # nothing changed since: a rerun does no work
    assert {r.state for r in run_clips([source], config, show_progress=False)} == {"cached", "paused", "waiting"}


def test_labels_ingest_again_resumes_the_clip_a_killed_ingest_left_unrun(small_library_warehouse, source, tmp_path):
    """`labels ingest` killed after its file was in, before the clip's resume ran: the same command
    again finds the file ingested and still resumes the clip; once it has run, again resumes nothing."""
    from conftest import warehouse_copy
    from fuzz.harness import run_cli

    from cadestate.config import to_toml
    from tasks.human.label_ingest import ingest_labels
    from tasks.human.labels import label_document

    config = warehouse_copy(small_library_warehouse, tmp_path / "warehouse")
    paused = {r.stage: r for r in run_clips([source], config, show_progress=False)}["cad_selection"]
    wh = Warehouse(config.warehouse.root)
    task = json.loads((wh.root / paused.message.split(" task ", 1)[1].split(";")[0]).read_text())
    label = tmp_path / "sel.json"
    label.write_text(json.dumps(label_document("cad_selection", "small", task["task_id"],
                                               [{"track_id": it["track_id"], "cad_id": it["candidates"][0]["cad_id"]} for it in task["items"]])))
    assert ingest_labels(wh, label).clips == ["small"]  # what the killed command did
    (tmp_path / "c.toml").write_text(to_toml(config))
    cli = ("-c", str(tmp_path / "c.toml"), "labels", "ingest", str(label), "--no-progress")
    again = run_cli(*cli)
    assert again.code == 0, again.stdout + again.stderr
    assert f"{label}: already ingested" in again.stdout and "not yet run (a resume was stopped): small" in again.stdout
    assert {r.stage: r.status for r in pipeline_status(wh, config)}["cad_selection"] == "completed"
    done = run_cli(*cli)
    assert done.code == 0 and "not yet run" not in done.stdout and "running" not in done.stderr, done.stdout + done.stderr
    # another detector makes detect's inputs change: the clip is stale, not left unrun by a killed
    # ingest (the labels tick ran every labelled clip again, saying its labels were never run)
    import dataclasses

    from tasks.status import clips_left_unrun

    coco = dataclasses.replace(config, detect=dataclasses.replace(config.detect, model="coco"))
    assert any("inputs changed" in r.stale_reasons for r in pipeline_status(wh, coco) if r.stage == "detect")
    assert clips_left_unrun(wh, coco, ["small"]) == [] and clips_left_unrun(wh, config, ["small"]) == []
    # the answers in force again, in other bytes: ingested, but no stage's inputs change, so its run
    # records nothing; it stayed "answered since its last run" and was resumed on every labels tick
    same = tmp_path / "same.json"
    same.write_text(json.dumps(json.loads(label.read_text()), indent=2))
    assert ingest_labels(wh, same).clips == ["small"]
    assert clips_left_unrun(wh, config, ["small"]) == []


def test_flow_state_names_the_paused_tasks():
    from flows.reports import final_state
    from tasks.stage_chain import StageReport

    state = final_state([StageReport("a", "cad_selection", "paused", message="waits for labels: 2 of 3 tracks"),
                         StageReport("a", "correspondence_task", "waiting")], "1 clip(s)")
    assert state.is_completed() and state.name == "Paused"
    assert "a cad_selection: waits for labels: 2 of 3 tracks" in state.message
    assert final_state([StageReport("a", "pose", "completed")], "x").name == "Completed"



def test_a_flow_runs_reports_survive_a_final_state_handed_back_without_its_data(tmp_path):
    """flows.reports.state_reports: Prefect once handed a Dask worker a clip's final state without its
    data (MissingResult: the server's copy), and the clip's reports were lost. The run keeps them in
    its process; a state that carries them is read as before, and either way the kept copy goes."""
    from prefect import flow
    from prefect.exceptions import MissingResult

    from flows.reports import final_state, state_reports
    from flows.runtime import run_flow
    from tasks.stage_chain import StageReport

    reports = [StageReport("a", "pose", "completed"), StageReport("a", "verification", "paused", message="waits")]

    @flow
    def tiny():
        return final_state(reports, "1 clip(s)")

    config = Config(warehouse=WarehouseConfig(root=str(tmp_path / "w")))
    assert run_flow(tiny, config, run_name="tiny/a", tags=[]) == reports  # also prepares Prefect here
    state = tiny(return_state=True)
    bare = state.model_copy(update={"data": None})  # what the server keeps of it
    assert state_reports(bare) == reports
    with pytest.raises(MissingResult):
        state_reports(bare)  # kept once, for the run that made it

    @flow
    def broken():
        raise LookupError("the flow's own error")

    with pytest.raises(LookupError, match="the flow's own error"):  # was: 'LookupError' object is not iterable, later
        run_flow(broken, config, run_name="broken/a", tags=[])

def test_a_val_clip_waits_for_its_manual_tracks(config, source, tmp_path):
    """Changing the split reruns ingest (frames rerun and write the same frames) and manual_tracks,
    which pauses; what follows waits; an empty answer ("nothing missing") resumes the clip."""
    import json

    from tasks.video.ingest import registered_source
    from tasks.human.label_ingest import ingest_labels
    from tasks.human.labels import label_document

    assert states(run_clips([source], config, show_progress=False)) == expect("small", rest="completed")  # train
    val = dataclasses.replace(source, split="val")
    reports = run_clips([val], config, show_progress=False)
    assert states(reports) == expect("small", ingest="completed", frames="completed", manual_tracks="paused",
                                     retrieval="waiting", cad_selection="waiting", correspondence_task="waiting",
                                     pose="waiting", verification="waiting", rest="cached")
    wh = Warehouse(config.warehouse.root)
    assert registered_source(wh, "small").split == "val"  # what `cadestate run` reruns
    status = {r.stage: r for r in pipeline_status(wh, config)}
    assert status["manual_tracks"].status == "paused" and not status["manual_tracks"].stale_reasons
    assert "key-frames unanswered in manual_track task" in status["manual_tracks"].message
    paused = {r.stage: r for r in reports}["manual_tracks"]
    task = json.loads((wh.root / paused.message.split(" task ", 1)[1].split(";")[0]).read_text())
    label = tmp_path / "labels" / "none.json"
    label.parent.mkdir()
    label.write_text(json.dumps(label_document("manual_track", "small", task["task_id"], [])))
    assert ingest_labels(wh, label).clips == ["small"]
    assert {r.stage: r.stale_reasons for r in pipeline_status(wh, config)}["manual_tracks"] == ("inputs changed",)
    # nothing missing: the same (empty) manual tracks as before, so retrieval's earlier result is reused
    resumed = run_clips([val], config, show_progress=False)
    assert states(resumed) == expect("small", manual_tracks="completed", rest="cached")
