"""Stage runs in progress and interrupted: a process killed mid-stage is shown by `status` and recorded
as an interrupted run by the clip's next run; a clip with nothing detected flows through every stage."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest
from typer.testing import CliRunner

from cadestate.cli import app
from cadestate.config import Config, DetectConfig, WarehouseConfig
from flows.annotate_clip import run_clips
from tasks.registry import stages_of
from tasks.stage import StageOutput, run_markers, run_stage, settle_interrupted
from tasks.status import pipeline_status
from tasks.video.ingest import ClipSource
from warehouse import Warehouse

HASHES = dict(config_hash="c", inputs_hash="i", code_hash="k")


def test_a_run_is_journalled_while_it_runs(wh):
    wh.write("clips", "c1", _clip_row("c1"))
    seen = {}

    def body(run_id: str) -> StageOutput:
        seen["markers"] = [(m.stage, m.run_id, m.alive) for m in run_markers(wh, "c1")]
        seen["status"] = {r.stage: r.status for r in pipeline_status(wh, Config(), ["c1"])}["detect"]
        return StageOutput(0, "h")

    run = run_stage(wh, "c1", "detect", body=body, **HASHES)
    assert seen == {"markers": [("detect", run.run_id, True)], "status": "running"}
    assert run_markers(wh, "c1") == [] and settle_interrupted(wh, "c1") == []
    assert wh.read("runs").column("status").to_pylist() == ["completed"]


def test_a_failed_run_leaves_no_marker(wh):
    with pytest.raises(RuntimeError):
        run_stage(wh, "c1", "detect", body=lambda run_id: (_ for _ in ()).throw(RuntimeError("boom")), **HASHES)
    assert run_markers(wh, "c1") == [] and wh.read("runs").column("status").to_pylist() == ["failed"]


@pytest.mark.parametrize("error, message", [
    (MemoryError(), "MemoryError"), (AssertionError(), "AssertionError"), (KeyError("track_id"), "KeyError: 'track_id'"),
    (ValueError("frames.json: line 3: bad box"), "frames.json: line 3: bad box"),
    (FileNotFoundError(2, "No such file or directory"), "[Errno 2] No such file or directory")])
def test_a_failed_run_says_what_failed_even_when_the_error_has_no_text(wh, error, message):
    """A stage that failed with MemoryError() or a bare assert recorded (and `run` printed) an empty
    message; a KeyError only its key. Errors of the input keep their own words."""
    def fail(run_id: str) -> StageOutput:
        raise error

    with pytest.raises(type(error)):
        run_stage(wh, "c1", "detect", body=fail, **HASHES)
    assert wh.read("runs").column("message").to_pylist() == [message]


def test_a_killed_run_shows_as_interrupted_and_is_recorded_by_the_next_run(wh):
    """A real process runs a stage whose body kills it with SIGKILL (as `kill -9` would)."""
    wh.write("clips", "c1", _clip_row("c1"))
    script = textwrap.dedent(f"""
        import os, signal
        from tasks.stage import run_stage
        from warehouse import Warehouse
        run_stage(Warehouse({str(wh.root)!r}), "c1", "detect", config_hash="c", inputs_hash="i", code_hash="k",
                  body=lambda run_id: os.kill(os.getpid(), signal.SIGKILL))
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert done.returncode == -9, done.stderr
    assert wh.read("runs").num_rows == 0  # the process died before it could record anything
    [marker] = run_markers(wh, "c1")
    assert marker.stage == "detect" and not marker.alive
    status = {r.stage: r for r in pipeline_status(wh, Config(), ["c1"])}
    assert status["detect"].status == "interrupted" and "killed" in status["detect"].message
    shown = CliRunner().invoke(app, ["-w", str(wh.root), "status", "c1"])
    assert shown.exit_code == 0 and "c1 was interrupted at detect" in shown.output, shown.output
    [settled] = settle_interrupted(wh, "c1")
    assert (settled.stage, settled.run_id, settled.status) == ("detect", marker.run_id, "interrupted")
    runs = wh.read("runs").to_pylist()
    assert [(r["stage"], r["run_id"], r["status"]) for r in runs] == [("detect", marker.run_id, "interrupted")]
    assert runs[0]["started_at"] == marker.started_at and run_markers(wh, "c1") == []
    assert settle_interrupted(wh, "c1") == []  # recorded once


def test_a_run_killed_after_its_row_was_written_is_not_recorded_again(wh):
    """A process killed between writing its run's row and removing its marker (the row's write may be
    the process's first, which builds the catalog): the next run appended an interrupted row of the
    same run_id, which hid the completed one, and the stage ran again; and `status` said the stage
    was interrupted (the marker's time is after its row's start), so the labels tick resumed it."""
    import datetime as dt

    from tasks.stage import _start_marker

    done = run_stage(wh, "c1", "detect", body=lambda run_id: StageOutput(1, "o", "ok"), **HASHES)
    _start_marker(wh, "c1", "detect", done.run_id, dt.datetime.now(dt.timezone.utc))  # left by the kill
    assert len(run_markers(wh, "c1")) == 1
    assert {r.stage: r.status for r in pipeline_status(wh, Config(), ["c1"])}["detect"] == "completed"
    assert settle_interrupted(wh, "c1") == [] and run_markers(wh, "c1") == []
    assert [(r["run_id"], r["status"]) for r in wh.read("runs").to_pylist()] == [(done.run_id, "completed")]


def test_status_says_a_killed_library_stage_is_rerun_by_cad_ingest(wh):
    """A CAD library's stage killed mid-run: `cadestate status` names the command that reruns it,
    `cadestate cad ingest` (`cadestate run LIBRARY` refuses: no clip of that name)."""
    import datetime as dt

    from tasks.stage import StageRun, record_run

    record_run(wh, StageRun("lib", "cad_ingest", "r0", "completed", "c", "i", "o", "k", 1, 0.1, ""),
               dt.datetime.now(dt.timezone.utc))
    _killed_in(wh, "lib", "cad_embed")
    shown = CliRunner().invoke(app, ["-w", str(wh.root), "status", "lib"], terminal_width=200)
    assert shown.exit_code == 0 and "lib was interrupted at cad_embed" in shown.output, shown.output
    assert "`cadestate cad ingest` of its source reruns it" in shown.output and "cadestate run" not in shown.output


def _killed_in(wh: Warehouse, unit: str, stage: str) -> None:
    """Run ``stage`` of ``unit`` in a process that its body kills with SIGKILL (as `kill -9` would)."""
    script = textwrap.dedent(f"""
        import os, signal
        from tasks.stage import run_stage
        from warehouse import Warehouse
        run_stage(Warehouse({str(wh.root)!r}), {unit!r}, {stage!r}, config_hash="c", inputs_hash="i", code_hash="k",
                  body=lambda run_id: os.kill(os.getpid(), signal.SIGKILL))
    """)
    assert subprocess.run([sys.executable, "-c", script], capture_output=True).returncode == -9


@pytest.mark.parametrize("unit, stage, title", [("lib", "cad_ingest", "CAD libraries"), ("room_0", "cameras", "clips")])
def test_a_unit_whose_first_stage_was_killed_is_in_the_status(wh, unit, stage, title):
    """The first stage of a CAD library (cad_ingest) or of a clip (cameras, minutes of SfM) killed on
    its first run: nothing but its marker tells of it, and `cadestate status` shows it interrupted
    (it said nothing of it, and 'no clip or CAD library named' it when named)."""
    (wh.root / "tables").mkdir(parents=True)  # as the command that ran it made the warehouse
    _killed_in(wh, unit, stage)
    for args in ([], [unit]):
        shown = CliRunner().invoke(app, ["-w", str(wh.root), "status", *args], terminal_width=200)
        assert shown.exit_code == 0 and f"{unit} was interrupted at {stage}" in shown.output, shown.output
        assert title in shown.output
    rows = pipeline_status(wh, Config(), None, "library" if stage == "cad_ingest" else "clip")
    assert [(r.clip, r.status) for r in rows][:2] == [(unit, "interrupted"), (unit, "never run")]


def test_a_marker_of_another_host_is_alive_while_its_heartbeat_is(wh):
    """A run on a Dask worker: its pid means nothing here, its marker's heartbeat does, for `status`.
    The next run of the clip settles it as interrupted whatever its heartbeat: it holds the clip's
    lock, which the marker's run held while it ran. A later run of the stage recorded meanwhile (a
    Dask retry that finished the clip) is what `status` shows, not the old marker (it showed
    'running', then 'interrupted', for a clip done)."""
    import datetime as dt
    import json
    import os
    import time

    from tasks.stage import STALE_AFTER_S, StageRun, _start_marker, record_run

    wh.write("clips", "c1", _clip_row("c1"))
    marked = dt.datetime(2026, 1, 1, tzinfo=dt.timezone.utc)
    path = _start_marker(wh, "c1", "detect", "r1", marked)
    path.write_text(json.dumps({**json.loads(path.read_text()), "host": "worker-7", "pid": 1}))
    [marker] = run_markers(wh, "c1")
    assert marker.host == "worker-7" and marker.alive
    assert {r.stage: r for r in pipeline_status(wh, Config(), ["c1"])}["detect"].status == "running"
    old = time.time() - STALE_AFTER_S - 1
    os.utime(path, (old, old))
    [marker] = run_markers(wh, "c1")
    assert not marker.alive
    status = {r.stage: r for r in pipeline_status(wh, Config(), ["c1"])}
    assert status["detect"].status == "interrupted" and "worker-7" in status["detect"].message
    record_run(wh, StageRun(clip="c1", stage="detect", run_id="r2", status="completed", config_hash="c", inputs_hash="i",
                            output_hash="o", code_hash="k", rows_written=3, duration_s=1.0, message=""),
               marked + dt.timedelta(seconds=5))
    assert {r.stage: r for r in pipeline_status(wh, Config(), ["c1"])}["detect"].status == "completed"
    os.utime(path, None)  # a fresh heartbeat: still settled by the next run, which holds the clip's lock
    [settled] = settle_interrupted(wh, "c1")
    assert settled.status == "interrupted" and run_markers(wh, "c1") == []


def test_a_running_stage_beats_its_heartbeat_and_stops_when_it_ends(tmp_path):
    import os
    import time

    from tasks.stage import heartbeat

    marker = tmp_path / "m.json"
    marker.write_text("{}")
    os.utime(marker, (1.0, 1.0))
    with heartbeat(marker, every_s=0.02):
        deadline = time.time() + 10
        while marker.stat().st_mtime == 1.0 and time.time() < deadline:
            time.sleep(0.01)
        assert marker.stat().st_mtime > time.time() - 60
    os.utime(marker, (1.0, 1.0))
    time.sleep(0.2)
    assert marker.stat().st_mtime == 1.0
    marker.unlink()
    with heartbeat(marker, every_s=0.02):
        time.sleep(0.1)
    assert not marker.exists()  # a removed marker is not made again


@pytest.mark.slow
def test_a_clip_with_no_detection_flows_through_every_stage(tmp_path, small_clip):
    """An empty room, a dark video or a strict threshold: zero rows everywhere, and a note in status."""
    config = Config(warehouse=WarehouseConfig(root=str(tmp_path / "w")), detect=DetectConfig(score_threshold=0.999))
    reports = run_clips([ClipSource("dark", small_clip.video_path, small_clip.cameras_path)], config, show_progress=False)
    assert [(r.stage, r.state) for r in reports] == [(s.name, "completed") for s in stages_of("clip")]
    rows = {r.stage: r.rows_written for r in reports}
    assert rows["frames"] == 30 and all(rows[s] == 0 for s in ("detect", "embed", "tracking", "retrieval", "pose"))
    shown = CliRunner().invoke(app, ["-w", config.warehouse.root, "status"])
    assert shown.exit_code == 0 and "note: dark: no object detected in any frame" in shown.output, shown.output


def _clip_row(clip: str):
    from conftest import table_rows

    return table_rows("clips", [{"clip": clip, "split": "train"}])


def test_a_clip_line_says_where_it_stands_first_in_pipeline_order():
    """tasks.status.clip_summaries: running before failed before interrupted before paused before never run."""
    from tasks.status import StageStatus, clip_summaries

    def row(clip, stage, status, stale=(), when="2026-11-29 04:08"):
        return StageStatus(clip, stage, status, when if status != "never run" else "", 1, stale)

    rows = [row("a", "ingest", "completed"), row("a", "frames", "paused"), row("a", "detect", "failed", ("upstream stale",)),
            row("b", "ingest", "completed", when="2026-11-29 05:00"), row("b", "frames", "paused"), row("b", "detect", "never run"),
            row("c", "ingest", "completed"), row("c", "frames", "completed", ("code changed",), "2026-11-29 04:09")]
    a, b, c = clip_summaries(rows)
    assert (a.stands, a.done, a.stages, a.stale) == ("failed at detect", 1, 3, ("detect",))
    assert (b.stands, b.last_run_at, b.done) == ("waits at frames", "2026-11-29 05:00", 1)
    assert (c.stands, c.last_run_at, c.done, c.stale) == ("completed", "2026-11-29 04:09", 2, ("frames",))


def test_status_beyond_eight_clips_shows_one_line_each_unless_asked_for_every_stage(tmp_path):
    import datetime as dt

    import pyarrow as pa

    from warehouse import Warehouse

    wh = Warehouse(tmp_path / "w")
    for i in range(9):
        wh.write("runs", f"c{i}", pa.Table.from_pylist([
            {"clip": f"c{i}", "run_id": "r0", "stage": "cameras", "status": "completed", "config_hash": "c", "inputs_hash": "i",
             "output_hash": "o", "code_hash": "k", "started_at": dt.datetime(2026, 1, 1, tzinfo=dt.timezone.utc),
             "duration_s": 1.0, "rows_written": 0, "message": ""}]))
    runner = CliRunner()
    summary = runner.invoke(app, ["-w", str(wh.root), "status"])
    assert summary.exit_code == 0, summary.output
    assert "one line each" in summary.output and "9 clips:" in summary.output
    assert summary.output.count("never run at ingest") == 9 and f"1/{len(stages_of('clip'))}" in summary.output
    every = runner.invoke(app, ["-w", str(wh.root), "status", "--stages"])
    assert "one line each" not in every.output and every.output.count("never run") == 9 * (len(stages_of("clip")) - 1)
    named = runner.invoke(app, ["-w", str(wh.root), "status", "c3"])
    assert "one line each" not in named.output and "c3" in named.output and "c4" not in named.output


def test_a_clips_newest_run_is_its_newest_across_a_new_year(tmp_path):
    """A clip line's newest run was the greatest "%m-%d %H:%M" string: a run of December 31 was
    newer than one of January 1."""
    import datetime as dt

    import pyarrow as pa

    from tasks.status import clip_summaries

    wh = Warehouse(tmp_path / "w")
    wh.write("runs", "c", pa.Table.from_pylist([
        {"clip": "c", "run_id": f"r{i}", "stage": stage, "status": "completed", "config_hash": "c", "inputs_hash": "i",
         "output_hash": "o", "code_hash": "k", "started_at": when, "duration_s": 1.0, "rows_written": 0, "message": ""}
        for i, (stage, when) in enumerate([("ingest", dt.datetime(2026, 12, 31, 23, 0, tzinfo=dt.timezone.utc)),
                                           ("cameras", dt.datetime(2027, 1, 1, 0, 30, tzinfo=dt.timezone.utc))])]))
    [line] = clip_summaries(pipeline_status(wh, Config()))
    assert line.last_run_at == "2027-01-01 00:30"


def test_status_sees_an_input_edited_in_place_after_ingest(wh, small_clip, tmp_path):
    """Inputs are hard-linked into the warehouse: a user who edits their camera file in place edits
    the warehouse's copy. `run` finds it by its digests; `status` (which hashes nothing) by the size
    and modification time that ingest recorded."""
    import json
    import os
    import shutil

    from cadestate.config import IngestConfig
    from cadestate.lineage import file_sha256
    from tasks.video.ingest import ingest_clip

    video, cams = tmp_path / "in.mp4", tmp_path / "in.txt"
    shutil.copy(small_clip.video_path, video)
    shutil.copy(small_clip.cameras_path, cams)
    out = ingest_clip(wh, IngestConfig(up="+y"), ClipSource("small", video, cams), file_sha256(video), file_sha256(cams), "r0")
    run_stage(wh, "small", "ingest", body=lambda run_id: out, **HASHES)

    def edited() -> list[str]:
        status = {r.stage: r for r in pipeline_status(wh, Config(), ["small"])}
        return [why for why in status["ingest"].stale_reasons if "edited since ingest" in why]

    assert edited() == []
    placed = wh.inputs_dir("small") / "video.mp4"
    os.utime(placed, ns=(placed.stat().st_atime_ns, placed.stat().st_mtime_ns + 10**9))  # copied without its times
    assert edited() == [] and edited() == []  # the same bytes: not edited (hashed once, then its new time is recorded)
    record = wh.inputs_dir("small") / "placed.json"  # a record from before records kept the SHA-256: the clips row's
    record.write_text(json.dumps({k: v[:2] for k, v in json.loads(record.read_text()).items()}))
    os.utime(placed, ns=(placed.stat().st_atime_ns, placed.stat().st_mtime_ns + 10**9))
    assert edited() == [] and len(json.loads(record.read_text())["video.mp4"]) == 3
    with open(cams, "a") as f:  # in place: the warehouse's inputs/small/cameras.txt is the same file
        f.write("\n")
    assert (wh.inputs_dir("small") / "cameras.txt").stat().st_ino == os.stat(cams).st_ino
    assert edited() == ["inputs changed (cameras.txt of inputs/small/ edited since ingest)"]


def test_a_live_run_stays_alive_when_the_wall_clock_is_set():
    """Its process's creation time in epoch seconds moves when the clock is stepped (psutil adds the
    boot time, which the kernel shifts with the clock): a live run read as interrupted. The marker
    keeps the start in clock ticks since boot, which no clock setting moves."""
    import datetime as dt
    import os
    import socket
    from pathlib import Path

    import psutil

    from tasks.stage import RunMarker, _start_ticks

    pid, ticks = os.getpid(), _start_ticks(os.getpid())
    stepped = psutil.Process(pid).create_time() - 5.0  # recorded before the clock was set 5 s forward
    marker = lambda start, t: RunMarker("c", "detect", "r", pid, socket.gethostname(), start,  # noqa: E731
                                        dt.datetime.now(dt.timezone.utc), Path("m.json"), 0.0, t)
    assert marker(stepped, ticks).alive and not marker(stepped + 5.0, ticks + 1).alive  # a recycled pid: other ticks
    assert not marker(stepped, None).alive and marker(stepped + 5.0, None).alive  # an older marker: seconds, as before


def test_a_reingest_removes_the_part_copy_a_killed_ingest_left(wh, small_clip, tmp_path):
    """Ctrl-C (which ends a run at once) or kill -9 while ingest copies a video from another file
    system leaves the part copy under its temporary name in inputs/<clip>/: the next ingest of the
    clip removes it (it stayed for ever, a video's size each time)."""
    import shutil

    from cadestate.config import IngestConfig
    from cadestate.lineage import file_sha256
    from tasks.video.ingest import ingest_clip

    video, cams = tmp_path / "in.mp4", tmp_path / "in.txt"
    shutil.copy(small_clip.video_path, video)
    shutil.copy(small_clip.cameras_path, cams)
    inputs = wh.inputs_dir("small")
    inputs.mkdir(parents=True)
    part = inputs / ".video.mp4.0a43f14656394a1bae048ca31069397c.tmp"  # as the killed copy named it
    part.write_bytes(video.read_bytes()[:1000])
    ingest_clip(wh, IngestConfig(up="+y", link_inputs=False), ClipSource("small", video, cams), file_sha256(video),
                file_sha256(cams), "r0")
    assert sorted(p.name for p in inputs.iterdir()) == ["cameras.txt", "placed.json", "video.mp4"]


def test_a_stage_after_a_stale_one_is_stale(tmp_path):
    """pose runs after correspondence_task (``after``: it reads the task's answers, not its output
    table): with correspondence_task's config changed, `status` called pose and verification fresh,
    though a run replaces the task and pose then waits for its clicks."""
    import dataclasses
    import datetime as dt

    from cadestate.config import CorrespondenceTaskConfig
    from tasks.inputs_memo import InputsMemo
    from tasks.registry import config_hash, upstream_inputs_hash
    from tasks.stage import StageRun, record_run

    config = Config(warehouse=WarehouseConfig(root=str(tmp_path / "w")))
    wh, out = Warehouse(config.warehouse.root), {}
    memo, t0 = InputsMemo(wh, "c1"), dt.datetime(2026, 1, 1, tzinfo=dt.timezone.utc)
    for i, s in enumerate(stages_of("clip")):  # every stage completed as things are: hashed as `status` hashes them
        inputs = (upstream_inputs_hash([out[u] for u in s.upstream] + s.config_inputs(config) + memo.clip_inputs(s))
                  if s.upstream else "source")
        out[s.name] = f"out-{s.name}"
        record_run(wh, StageRun("c1", s.name, f"r{i}", "completed", config_hash(s.name, config), inputs, out[s.name],
                                s.code_hash, 1, 0.1, ""), t0 + dt.timedelta(seconds=i))
    assert all(not r.stale_reasons for r in pipeline_status(wh, config, ["c1"]))
    more = dataclasses.replace(config, correspondence_task=CorrespondenceTaskConfig(keyframes=8))
    stale = {r.stage: r.stale_reasons for r in pipeline_status(wh, more, ["c1"]) if r.stale_reasons}
    assert stale == {"correspondence_task": ("config changed",), "pose": ("upstream stale",),
                     "verification": ("upstream stale",)}, stale
