"""Pause and resume end where an uninterrupted run ends (issue 8).

A benchmark clip, taken as val, runs through the real flow with a real (small) CAD library: it
pauses at each of the four human tasks, the simulated annotators answer through label files, ``labels ingest`` resumes it.
The uninterrupted run is the same clip in a fresh warehouse that holds every answer before the
clip runs (the label tables copied over; task ids depend only on what a task shows, so the
answers fit): it must go straight through, pausing nowhere, to the same tables.
"""

from __future__ import annotations

import dataclasses

import pyarrow as pa
import pytest

from bench.benchmark import clip_sources, generate
from bench.pose_bench import pose_accuracy
from bench.simulated_labels import annotate_until_done
from bench.walkthrough import WalkthroughSpec
from flows.annotate_clip import run_clips
from conftest import warehouse_copy
from warehouse import Warehouse

pytestmark = pytest.mark.slow

SPEC = WalkthroughSpec(width=480, height=270, num_video_frames=60, sample_every=2, alone_scale=0.5)
SEED = 3
LABEL_TABLES = ("label_tasks", "label_files", "manual_track_labels", "cad_selection_labels", "correspondence_labels",
                "verification_labels", "correspondences")
RESULT_TABLES = ("tracks", "manual_tracks", "cad_candidates", "poses", "verified_poses")
VOLATILE = {"run_id", "created_at", "ingested_at"}  # when and by which run, not what


def _content(wh: Warehouse, table: str, clip: str) -> pa.Table:
    t = wh.read(table, [clip])
    t = t.drop_columns([c for c in t.column_names if c in VOLATILE])
    return t.sort_by([(k, "ascending") for k in wh.spec(table).key if k in t.column_names])


def test_resumed_clip_equals_an_uninterrupted_run(small_library_warehouse, tmp_path):
    library = small_library_warehouse
    folder = tmp_path / "bench"
    manifest, _ = generate(folder, SEED, 1, Warehouse(library.warehouse.root), SPEC, show_progress=False)
    clip, source = manifest.clips[0], dataclasses.replace(clip_sources(folder)[0], split="val")  # all four tasks

    resumed = warehouse_copy(library, tmp_path / "resumed")
    wa = Warehouse(resumed.warehouse.root)
    reports, waiting = annotate_until_done(folder, wa, [clip], lambda _: run_clips([source], resumed, show_progress=False))
    assert waiting == [] and not [r for r in reports if r.state == "failed"]
    paused_at = {r.stage for r in reports if r.state == "paused"}
    assert {"manual_tracks", "cad_selection", "correspondence_task", "verification"} <= paused_at, "it paused at each task"
    assert wa.read("verified_poses", [clip]).num_rows >= 1, "some poses went all the way to verification"
    scored = pose_accuracy(folder, wa)  # pipeline tracks mapped to ground-truth objects
    assert scored["annotated_objects"] >= 1 and scored["verification"]["verdicts"] == wa.read("verified_poses", [clip]).num_rows

    straight = warehouse_copy(library, tmp_path / "straight")
    wb = Warehouse(straight.warehouse.root)
    for table in LABEL_TABLES:
        if clip in wa.partitions(table):
            wb.write(table, clip, wa.read(table, [clip]))
    once = run_clips([source], straight, show_progress=False)
    assert {r.state for r in once} == {"completed"}, [(r.stage, r.state, r.message) for r in once if r.state != "completed"]
    for table in RESULT_TABLES:
        assert _content(wa, table, clip).equals(_content(wb, table, clip)), table
    ids = lambda wh: set(wh.read("label_tasks", [clip]).column("task_id").to_pylist())  # noqa: E731
    assert ids(wb) == ids(wa), "the same tasks (their files differ only in the media paths of each warehouse)"
