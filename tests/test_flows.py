"""The annotate_clip / build_dataset flows on real Prefect (ephemeral API): caching and lineage."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import pytest

from cadestate.config import Config, FramesConfig, WarehouseConfig
from flows.annotate_clip import run_clips
from tasks.ingest import ClipSource, clip_inputs
from tasks.prefect_tasks import STAGE_TASKS
from tasks.registry import STAGES
from tasks.status import pipeline_status
from warehouse import Warehouse

pytestmark = pytest.mark.slow


def states(reports):
    return [(r.clip, r.stage, r.state) for r in reports]


def snapshot(root: Path) -> dict[str, int]:
    """mtime of every file the stages write (tables and media)."""
    return {str(p): p.stat().st_mtime_ns for d in ("tables", "media", "inputs") for p in (root / d).rglob("*") if p.is_file()}


@pytest.fixture
def config(tmp_path) -> Config:
    return Config(warehouse=WarehouseConfig(root=str(tmp_path / "warehouse")))


@pytest.fixture
def source(small_clip) -> ClipSource:
    return ClipSource("small", small_clip.video_path, small_clip.cameras_path)


def test_every_stage_has_one_task_in_pipeline_order():
    assert tuple(STAGE_TASKS) == tuple(STAGES)


def test_unchanged_rerun_does_nothing(config, source):
    first = run_clips([source], config, show_progress=False)
    assert states(first) == [("small", "ingest", "completed"), ("small", "frames", "completed")]
    wh = Warehouse(config.warehouse.root)
    before, runs_before = snapshot(wh.root), wh.read("runs").num_rows
    again = run_clips([source], config, show_progress=False)
    assert states(again) == [("small", "ingest", "cached"), ("small", "frames", "cached")]
    assert snapshot(wh.root) == before and wh.read("runs").num_rows == runs_before == 2
    # Rerunning from the warehouse's own copies (what `cadestate run` does) is the same clip: cached.
    video, cameras, _ = clip_inputs(wh, "small")
    assert {r.state for r in run_clips([ClipSource("small", video, cameras)], config, show_progress=False)} == {"cached"}


def test_changed_stage_config_reruns_that_stage_only(config, source):
    run_clips([source], config, show_progress=False)
    wh = Warehouse(config.warehouse.root)
    changed = dataclasses.replace(config, frames=FramesConfig(jpeg_quality=70))
    status = {r.stage: r.stale_reasons for r in pipeline_status(wh, changed)}
    assert status == {"ingest": (), "frames": ("config changed",)}
    reports = run_clips([source], changed, show_progress=False)
    assert states(reports) == [("small", "ingest", "cached"), ("small", "frames", "completed")]
    runs = wh.read("runs", filters=[("stage", "==", "frames")]).to_pylist()
    assert [r["config_hash"] for r in runs] == [config.section_hash("frames"), changed.section_hash("frames")]
    assert all(not r.stale_reasons for r in pipeline_status(wh, changed))
    assert len(list((wh.root / "media" / "frames" / "small").iterdir())) == 1  # old images pruned
    # Back to the first config: its cached results are reused, no work.
    assert {r.state for r in run_clips([source], config, show_progress=False)} == {"cached"}


def test_a_bad_clip_does_not_stop_the_others(config, source, tmp_path):
    bad_dir = tmp_path / "bad"
    bad_dir.mkdir()
    (bad_dir / "broken.mp4").write_bytes(b"\x00" * 1000)
    shutil.copy(source.cameras, bad_dir / "broken.txt")
    broken = ClipSource("broken", bad_dir / "broken.mp4", bad_dir / "broken.txt")
    reports = run_clips([broken, source], config, show_progress=False)
    assert states(reports) == [
        ("broken", "ingest", "failed"), ("broken", "frames", "skipped"),
        ("small", "ingest", "completed"), ("small", "frames", "completed"),
    ]
    assert "broken.mp4: cannot open video" in reports[0].message
    wh = Warehouse(config.warehouse.root)
    failed = wh.read("runs", partitions=["broken"]).to_pylist()
    assert [(r["stage"], r["status"]) for r in failed] == [("ingest", "failed")]
    assert "cannot open video" in failed[0]["message"]
    assert wh.partitions("frames") == ["small"]


def test_cad_library_flow_caches_per_stage(config, tmp_path):
    import trimesh

    from cadestate.config import CadViewsConfig
    from flows.cad_library import run_cad_library
    from tasks.cad_sources import folder_items

    folder = tmp_path / "meshes"
    folder.mkdir()
    trimesh.creation.box((1.0, 0.5, 0.6)).export(folder / "box.obj")
    trimesh.creation.cone(0.3, 0.8).export(folder / "cone.ply")
    (folder / "models.csv").write_text("id,class\nbox,table\ncone,lamp\n")
    items = list(folder_items(folder, "lib"))
    small = dataclasses.replace(config, cad_views=CadViewsConfig(views=2, size=64))
    assert states(run_cad_library(items, small, show_progress=False)) == [("lib", "cad_ingest", "completed"), ("lib", "cad_views", "completed")]
    assert states(run_cad_library(items, small, show_progress=False)) == [("lib", "cad_ingest", "cached"), ("lib", "cad_views", "cached")]
    bigger = dataclasses.replace(small, cad_views=CadViewsConfig(views=3, size=64))
    assert states(run_cad_library(items, bigger, show_progress=False)) == [("lib", "cad_ingest", "cached"), ("lib", "cad_views", "completed")]
    wh = Warehouse(config.warehouse.root)
    assert wh.read("cad_views").num_rows == 6
    status = {(r.clip, r.stage): r.stale_reasons for r in pipeline_status(wh, bigger, scope="library")}
    assert status == {("lib", "cad_ingest"): (), ("lib", "cad_views"): ()}
    assert pipeline_status(wh, bigger, ["lib"], scope="clip") == []  # a library is not a clip
