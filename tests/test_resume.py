"""Pause and resume end where an uninterrupted run ends (issue 8).

A benchmark clip, taken as val, runs through the real flow with a real (small) CAD library: it
pauses at each of the four human tasks, the simulated annotators answer through label files, ``labels ingest`` resumes it.
The uninterrupted run is the same clip in a fresh warehouse that holds every answer before the
clip runs (the label tables copied over; task ids depend only on what a task shows, so the
answers fit): it must go straight through, pausing nowhere, to the same tables.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

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


@dataclasses.dataclass(frozen=True)
class Answered:
    """A val benchmark clip run to its end in ``config``'s warehouse, the simulated annotators
    answering each task as it paused (``reports``: every run's stage reports)."""

    config: object  # cadestate.config.Config
    folder: Path
    clip: str
    source: object  # tasks.video.ingest.ClipSource
    reports: list
    waiting: list[str]


@pytest.fixture(scope="module")
def answered(small_library_warehouse, tmp_path_factory) -> Answered:
    tmp = tmp_path_factory.mktemp("resume")
    folder = tmp / "bench"
    manifest, _ = generate(folder, SEED, 1, Warehouse(small_library_warehouse.warehouse.root), SPEC, show_progress=False)
    clip, source = manifest.clips[0], dataclasses.replace(clip_sources(folder)[0], split="val")  # all four tasks
    resumed = warehouse_copy(small_library_warehouse, tmp / "resumed")
    wa = Warehouse(resumed.warehouse.root)
    reports, waiting = annotate_until_done(folder, wa, [clip], lambda _: run_clips([source], resumed, show_progress=False))
    return Answered(resumed, folder, clip, source, reports, waiting)


def test_resumed_clip_equals_an_uninterrupted_run(small_library_warehouse, answered, tmp_path):
    library, folder, clip, source = small_library_warehouse, answered.folder, answered.clip, answered.source
    wa = Warehouse(answered.config.warehouse.root)
    reports, waiting = answered.reports, answered.waiting
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


def test_a_rerun_that_asks_again_leaves_no_stale_pose(answered, tmp_path):
    """Retrieval rerun with other scores (a config change) gives cad_selection a new task, unanswered:
    pose, which runs on the answered correspondences, poses nothing in that run. Once the same
    models are chosen again, the clicks given before hold and pose must run again, so the poses
    come back. Its inputs are taken after the stages before it ran. Taken before the run, they were
    the old answers': pose was found cached on them (old poses kept while nothing is chosen), or
    when it ran its empty result was recorded under them and found cached once the same models were
    chosen again (a rerun of the default benchmark with another detector lost a clip's poses so)."""
    from tasks.pose.inputs import answered_correspondences

    config = warehouse_copy(answered.config, tmp_path / "w")
    wh = Warehouse(config.warehouse.root)
    clip, source = answered.clip, answered.source
    posed = _content(wh, "poses", clip)
    assert posed.num_rows >= 1
    changed = dataclasses.replace(config, retrieval=dataclasses.replace(config.retrieval, class_exponent=0.2))
    first = {r.stage: r for r in run_clips([source], changed, show_progress=False)}
    assert first["cad_selection"].state == "paused" and first["pose"].state == "completed"
    assert wh.read("poses", [clip]).num_rows == 0, "no model is chosen: nothing is posed"
    reports, waiting = annotate_until_done(answered.folder, wh, [clip],
                                           lambda _: run_clips([source], changed, show_progress=False))
    assert waiting == [] and not [r for r in reports if r.state == "failed"]
    assert set(wh.read("poses", [clip]).column("track_id").to_pylist()) == \
        set(answered_correspondences(wh, clip).column("track_id").to_pylist())
    assert _content(wh, "poses", clip).equals(posed), "the same models chosen, the same clicks: the same poses"
