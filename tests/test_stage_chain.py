"""The cache of a unit's stage chain (:mod:`tasks.stage_chain`): which recorded run makes a stage's
run needless. The flows' behaviour on real clips is in ``test_flows.py``."""

from __future__ import annotations

import dataclasses
import datetime as dt

from tasks.stage_chain import report_of
from tasks.status import Signature, cached_run
from tasks.stage import StageRun
from warehouse import Warehouse

A, B = Signature("cfgA", "code", "in"), Signature("cfgB", "code", "in")


def row(signature: Signature, output: str, status: str = "completed", stage: str = "tracking", minute: int = 0) -> dict:
    return {"run_id": f"r{minute}", "stage": stage, "status": status, "config_hash": signature.config_hash,
            "code_hash": signature.code_hash, "inputs_hash": signature.inputs_hash, "output_hash": output,
            "started_at": dt.datetime(2026, 1, 1, 0, minute, tzinfo=dt.timezone.utc), "rows_written": 3,
            "duration_s": 1.5, "message": f"run {minute}"}


def test_a_run_with_the_same_signature_is_reused():
    hit = cached_run([row(A, "out1")], "c", "tracking", A)
    assert hit == StageRun("c", "tracking", "r0", "completed", "cfgA", "in", "out1", "code", 3, 1.5, "run 0")
    assert report_of(hit, cached=True).state == "cached"


def test_any_other_digest_or_stage_is_a_miss():
    runs = [row(A, "out1")]
    assert cached_run(runs, "c", "tracking", B) is None
    assert cached_run(runs, "c", "tracking", Signature("cfgA", "other code", "in")) is None
    assert cached_run(runs, "c", "tracking", Signature("cfgA", "code", "other inputs")) is None
    assert cached_run(runs, "c", "detect", A) is None
    assert cached_run([], "c", "tracking", A) is None


def test_a_run_whose_output_a_later_run_replaced_is_not_reused():
    """Config A, then B writes another output: back to A, the tables hold B's output, so A runs again."""
    assert cached_run([row(A, "out1", minute=0), row(B, "out2", minute=1)], "c", "tracking", A) is None
    # B wrote what A had written: the tables hold A's output, A is reused
    assert cached_run([row(A, "out1", minute=0), row(B, "out1", minute=1)], "c", "tracking", A).run_id == "r0"
    # A ran again after B: its latest run counts
    again = [row(A, "out1", minute=0), row(B, "out2", minute=1), row(A, "out1", minute=2)]
    assert cached_run(again, "c", "tracking", A).run_id == "r2"


def test_failed_and_interrupted_runs_are_never_reused_and_hide_what_came_before():
    """A run that failed or was killed may have written some of its tables (each is swapped whole,
    one after another): config A, then B fails after writing `tracks`, then A again runs anew."""
    assert cached_run([row(A, "", "failed")], "c", "tracking", A) is None
    assert cached_run([row(A, "out1", minute=0), row(B, "", "failed", minute=1)], "c", "tracking", A) is None
    assert cached_run([row(A, "out1", minute=0), row(A, "", "interrupted", minute=1)], "c", "tracking", A) is None
    # a run after the failure that wrote the tables whole counts again
    again = [row(A, "out1", minute=0), row(B, "", "failed", minute=1), row(A, "out1", minute=2)]
    assert cached_run(again, "c", "tracking", A).run_id == "r2"
    # another stage's failure is not this stage's
    assert cached_run([row(A, "out1", minute=0), row(B, "", "failed", stage="detect", minute=1)], "c", "tracking", A).run_id == "r0"


def test_a_paused_run_is_reused_as_paused():
    """A human task with nothing new answered stays paused, doing no work."""
    hit = cached_run([row(A, "waits", "paused", stage="cad_selection")], "c", "cad_selection", A)
    assert hit is not None and hit.status == "paused"
    report = report_of(hit, cached=True)
    assert (report.state, report.rows_written, report.message) == ("paused", 3, "run 0")


def test_a_batch_runs_without_prefect_and_an_unchanged_rerun_does_no_work(tmp_path, small_clip):
    """The chain alone (:func:`tasks.stage_chain.run_unit`), as ``bench.cluster_throughput``'s bare
    baseline runs it: in a process that never imports Prefect, every stage of the clip runs and none
    fails; the same chain again finds every stage that ran cached."""
    import shutil
    import subprocess
    import sys

    from cadestate.config import Config, WarehouseConfig
    from tasks.registry import stages_of
    from tasks.stage_chain import run_unit
    from tasks.video.ingest import ClipSource, discover_clips

    batch = tmp_path / "batch"
    batch.mkdir()
    shutil.copy(small_clip.video_path, batch / "room.mp4")
    shutil.copy(small_clip.cameras_path, batch / "room.txt")
    root = tmp_path / "w"
    script = ("import sys; from pathlib import Path; from bench.cluster_throughput import bare_batch; "
              f"failed = bare_batch(Path({str(batch)!r}), Path({str(root)!r})); "
              "assert 'prefect' not in sys.modules, 'Prefect imported'; sys.exit(failed)")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    [(video, cameras)] = discover_clips(batch)
    [clip] = Warehouse(root).read("clips", columns=["clip"]).column("clip").to_pylist()
    again = run_unit(str(root), "clip", clip, Config(warehouse=WarehouseConfig(root=str(root))),
                     ClipSource(clip, video, cameras), show_progress=False)
    assert [r.stage for r in again] == [s.name for s in stages_of("clip")]
    assert {r.state for r in again} <= {"cached", "paused", "waiting"} and "cached" in {r.state for r in again}, again


def test_one_run_of_a_unit_at_a_time(tmp_path):
    """A second run of a clip (an inbox tick beside `cadestate run`) waits for the first's lock
    instead of writing the clip's tables at the same time."""
    import threading

    from cadestate.config import Config
    from tasks.stage_chain import run_unit, unit_lock_path
    from tasks.video.ingest import ClipSource
    from warehouse.store import file_lock

    wh = Warehouse(tmp_path / "w")
    source = ClipSource("c1", tmp_path / "none.mp4", tmp_path / "none.txt", "train")  # fails at once: no camera file
    reports = []
    second = threading.Thread(target=lambda: reports.extend(run_unit(str(wh.root), "clip", "c1", Config(), source, False)))
    with file_lock(unit_lock_path(wh, "c1")):  # the first run
        second.start()
        second.join(1.0)
        assert second.is_alive() and not reports
    second.join(30)
    assert not second.is_alive() and [(r.stage, r.state) for r in reports] == [("cameras", "failed")]
    with file_lock(unit_lock_path(wh, "c1")):  # another clip runs beside a run of c1
        other = run_unit(str(wh.root), "clip", "c2", Config(), dataclasses.replace(source, clip="c2"), False)
    assert [(r.stage, r.state) for r in other] == [("cameras", "failed")]


def test_a_damaged_input_file_is_the_failed_report_of_the_stage_that_reads_it(tmp_path):
    """Only an OSError of a stage's input digests was its failed report: a damaged label file (a
    WarehouseError) escaped the chain, one report named 'stages', the stage not named."""
    from cadestate.config import Config
    from conftest import table_rows
    from tasks.stage_chain import run_unit
    from tasks.video.ingest import ClipSource

    wh = Warehouse(tmp_path / "w")
    wh.write("cad_selection_labels", "c1", table_rows("cad_selection_labels", [{"clip": "c1", "task_id": "t", "track_id": 0}]))
    damaged = wh.files("cad_selection_labels", ["c1"])[0]
    damaged.write_bytes(b"not parquet at all")
    for name in ("v.mp4", "v.txt"):  # digested, never decoded: the chain stops before any stage runs
        (tmp_path / name).write_bytes(b"x")
    source = ClipSource("c1", tmp_path / "v.mp4", tmp_path / "v.txt", "train")
    [report] = run_unit(str(wh.root), "clip", "c1", Config(), source, False)
    assert report.state == "failed" and report.stage != "stages" and str(damaged) in report.message, report


def test_a_failed_stage_reports_the_time_it_took(tmp_path):
    """A stage that failed was reported as taking 0.00 s (an SfM that ran 12 s and registered too
    few frames), though its ``runs`` row had its time."""
    from cadestate.config import Config
    from tasks.stage_chain import run_unit
    from tasks.video.ingest import ClipSource

    (tmp_path / "v.mp4").write_bytes(b"x")
    (tmp_path / "v.txt").write_text("https://example.com/v\n0 not a camera line\n")
    source = ClipSource("c1", tmp_path / "v.mp4", tmp_path / "v.txt", "train")
    [report] = [r for r in run_unit(str(tmp_path / "w"), "clip", "c1", Config(), source, False) if r.state == "failed"]
    [recorded] = [r for r in Warehouse(tmp_path / "w").read("runs", ["c1"]).to_pylist() if r["stage"] == report.stage]
    assert recorded["status"] == "failed", recorded
    assert 0 < report.duration_s and abs(report.duration_s - recorded["duration_s"]) < 0.5, (report, recorded["duration_s"])
