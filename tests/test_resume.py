"""Pause and resume end where an uninterrupted run ends (issue 8).

A benchmark clip, taken as val, runs through the real flow with a real (small) CAD library: it
pauses at each of the four human tasks, the simulated annotators answer through label files, ``labels ingest`` resumes it.
The uninterrupted run is the same clip in a fresh warehouse that holds every answer before the
clip runs (the label tables copied over; task ids depend only on what a task shows, so the
answers fit): it must go straight through, pausing nowhere, to the same tables.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pyarrow as pa
import pyarrow.compute  # noqa: F401  (pa.compute)
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


def test_a_stale_correspondences_partition_keeps_the_track_map(answered, tmp_path):
    """A clip answered through label files whose ``correspondences`` partition differs from the
    answers in force by one row (stale): its pipeline track ids were read as ground-truth object
    ids, and the `pose` mode scored its poses against other objects."""
    import shutil

    from bench.pose_bench import _ground_truth_map
    from bench.retrieval_bench import track_truth

    shutil.copytree(answered.config.warehouse.root, tmp_path / "w")
    wh = Warehouse(tmp_path / "w")
    truth = {str(t): gt for t, gt in track_truth(answered.folder, wh, answered.clip).items()}
    assert truth and _ground_truth_map(answered.folder, wh, answered.clip) == truth
    rows = wh.read("correspondences", [answered.clip])
    wh.write("correspondences", answered.clip, rows.slice(0, rows.num_rows - 1))
    assert _ground_truth_map(answered.folder, wh, answered.clip) == truth


def test_pose_accuracy_counts_the_objects_of_a_clip_that_never_reached_the_pose_stage(answered, tmp_path):
    """The pose section scored only clips with a ``poses`` partition: a clip that ran and stopped
    before (SfM found no cameras, still waiting for people) left its objects out of the accuracy's
    denominator, where the yield counts them as missed."""
    import json
    import shutil

    from conftest import table_rows

    folder = tmp_path / "bench"
    shutil.copytree(answered.folder, folder)
    shutil.copytree(folder / answered.clip, folder / "stopped_0")  # the same room: as many objects
    manifest = json.loads((folder / "manifest.json").read_text())
    (folder / "manifest.json").write_text(json.dumps({**manifest, "clips": [answered.clip, "stopped_0"]}))
    shutil.copytree(answered.config.warehouse.root, tmp_path / "w")
    wh = Warehouse(tmp_path / "w")
    alone = pose_accuracy(folder, wh)
    wh.write("runs", "stopped_0", table_rows("runs", [{"clip": "stopped_0", "run_id": "r0", "stage": "cameras",
                                                       "status": "failed"}]))
    both = pose_accuracy(folder, wh)
    assert (alone["clips_run"], both["clips_run"], both["clips"]) == (1, 2, 1)
    assert both["ground_truth_objects"] == 2 * alone["ground_truth_objects"]
    for mode, m in both["accepted"].items():
        assert m["correct"] == alone["accepted"][mode]["correct"] and m["ground_truth"] == 2 * alone["accepted"][mode]["ground_truth"]


def test_a_rerun_that_asks_again_leaves_no_stale_pose(answered, tmp_path):
    """Retrieval reruns with other scores (a config change): cad_selection gets a new task, and the
    choices still among the candidates are carried to it, so the poses stay. A person then says
    "none fits" for one posed track on the new task: pose reruns without it. Back on the first
    config, the first task's answers are in force again and pose must run again, so the poses come
    back. Its inputs are taken after the stages before it ran: taken before the run, they were the
    answers of the task in force then (the second), and pose was found cached with a track missing
    (a rerun of the default benchmark with another detector lost a clip's poses so)."""
    from cadestate.lineage import table_digest
    from tasks.human.cad_selection import cad_selection_task_id, selected_models
    from tasks.human.label_ingest import ingest_labels
    from tasks.human.labels import label_document

    config = warehouse_copy(answered.config, tmp_path / "w")
    wh = Warehouse(config.warehouse.root)
    clip, source = answered.clip, answered.source
    posed = _content(wh, "poses", clip)
    chosen = selected_models(wh, clip)
    assert posed.num_rows >= 1
    changed = dataclasses.replace(config, retrieval=dataclasses.replace(config.retrieval, class_exponent=0.2))
    first = {r.stage: r for r in run_clips([source], changed, show_progress=False)}
    assert first["retrieval"].state == "completed" and first["cad_selection"].state in ("paused", "completed")
    kept = {t: c for t, c in selected_models(wh, clip).items() if c is not None}
    assert kept and kept.items() <= chosen.items(), "choices carried to the new task, none made up"
    assert table_digest(_content(wh, "poses", clip).filter(pa.compute.is_in(
        _content(wh, "poses", clip).column("track_id"), pa.array([str(t) for t in kept])))) == table_digest(
        posed.filter(pa.compute.is_in(posed.column("track_id"), pa.array([str(t) for t in kept])))), "their poses stay"
    dropped = min(int(t) for t in posed.column("track_id").to_pylist() if int(t) in kept)
    doc = label_document("cad_selection", clip, cad_selection_task_id(wh, clip), [{"track_id": dropped, "cad_id": None}],
                         annotator="t", created_at="2026-12-02T00:00:00+00:00")
    (tmp_path / "none.json").write_text(json.dumps(doc))
    assert ingest_labels(wh, tmp_path / "none.json").ok
    second = {r.stage: r for r in run_clips([source], changed, show_progress=False)}
    assert second["pose"].state == "completed" and str(dropped) not in wh.read("poses", [clip]).column("track_id").to_pylist()
    back = {r.stage: r for r in run_clips([source], config, show_progress=False)}
    assert back["pose"].state == "completed", "what pose reads changed after the stages before it ran"
    assert _content(wh, "poses", clip).equals(posed), "the first task's answers: the same poses"
