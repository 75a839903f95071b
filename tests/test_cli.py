"""The cadestate command line: help everywhere, SQL formats, clear one-line errors."""

from __future__ import annotations

import csv
import io
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import click
import pytest
from typer.main import get_command
from typer.testing import CliRunner

from cadestate.cli import app
from tasks.registry import stages_of

runner = CliRunner()


def commands(group: click.Group, prefix=()):
    for name, cmd in group.commands.items():
        yield prefix + (name,)
        if isinstance(cmd, click.Group):
            yield from commands(cmd, prefix + (name,))


@pytest.mark.parametrize("path", [()] + list(commands(get_command(app))))
def test_every_command_has_help(path):
    result = runner.invoke(app, [*path, "--help"], terminal_width=80)
    assert result.exit_code == 0 and "Usage:" in result.output
    assert len(result.output.split("\n\n")[1].strip()) > 20  # a real description
    wide = [line for line in result.output.splitlines() if len(line) > 80]
    assert not wide, wide  # its examples and tables too fit 80 columns


def cli(*args, env: dict[str, str] | None = None):
    """Run the real command in a fresh process, with a user's environment (no test log level) and ``env``."""
    env = {**{k: v for k, v in os.environ.items() if k != "PREFECT_LOGGING_LEVEL"}, **(env or {})}
    return subprocess.run([sys.executable, "-m", "cadestate", *args], capture_output=True, text=True, env=env)


@pytest.mark.slow
def test_ingest_then_sql_status_tables(tmp_path, small_clip, monkeypatch):
    from warehouse import snapshot

    monkeypatch.setattr(snapshot, "MARGIN_NS", 0)  # files written a moment ago count as settled (in-process commands)
    w = str(tmp_path / "w")
    result = runner.invoke(app, ["-w", w, "ingest", str(small_clip.video_path), str(small_clip.cameras_path),
                                 "--clip", "small_0"])  # the official <video_id>_<start_us> of its camera file
    assert result.exit_code == 0, result.output
    assert "completed" in result.output
    rows = json.loads(cli("-w", w, "sql", "SELECT clip, count(*) AS n FROM frames GROUP BY clip", "--format", "json").stdout)
    assert rows == [{"clip": "small_0", "n": 30}]
    out = cli("-w", w, "sql", "SELECT stage, status FROM runs ORDER BY started_at", "-f", "csv").stdout
    stages = [s.name for s in stages_of("clip")]
    rows = list(csv.reader(io.StringIO(out)))
    assert rows[0] == ["stage", "status"] and sorted(rows[1:]) == sorted([s, "completed"] for s in stages)
    status = runner.invoke(app, ["-w", w, "status"])
    assert status.exit_code == 0 and status.output.count("yes") == len(stages) and "small_0" in status.output
    named = runner.invoke(app, ["-w", w, "status", "small_0"])  # a clip named: no line saying no CAD library has that name
    assert named.exit_code == 0 and "small_0" in named.output and "named" not in named.output, named.output
    tables = runner.invoke(app, ["-w", w, "tables"])
    assert "frames" in tables.output and "30" in tables.output
    for name, column in (("frames", "clip"), ("cad_models", "library")):  # cad_models was said partitioned by clip
        assert f"partitioned by {column}" in runner.invoke(app, ["-w", w, "tables", name]).output.splitlines()[-1]
    (tmp_path / "c.toml").write_text("[warehouse]\nsnapshot_after_clips = 1\n")
    again = runner.invoke(app, ["-w", w, "-c", str(tmp_path / "c.toml"), "run"])  # a batch big enough for a snapshot
    assert again.exit_code == 0 and again.output.count("cached") == len(stages)
    in_snapshot = "SELECT count(*) FROM warehouse.snapshot.frames"
    assert json.loads(cli("-w", w, "sql", in_snapshot.replace("count(*)", "count(*) AS n"), "-f", "json").stdout) == [{"n": 30}]
    args = ["-w", w, "ingest", str(small_clip.video_path), str(small_clip.cameras_path)]  # named small_0 again
    val = runner.invoke(app, [*args, "--split", "val"])
    assert val.exit_code == 0 and "manual_tracks" in val.output and "paused" in val.output
    kept = runner.invoke(app, args)  # no --split: the registered clip keeps its split
    assert kept.exit_code == 0 and "completed" not in kept.output
    assert json.loads(cli("-w", w, "sql", "SELECT split FROM clips", "--format", "json").stdout) == [{"split": "val"}]


def test_sql_errors_and_read_only(tmp_path):
    w = str(tmp_path / "w")
    (tmp_path / "w").mkdir()
    bad = cli("-w", w, "sql", "SELECT nope FROM frames")
    assert bad.returncode == 2 and bad.stderr.startswith("error: SQL error:") and "Traceback" not in bad.stderr
    write = cli("-w", w, "sql", "CREATE TABLE t (i INT)")
    assert write.returncode == 2 and "read-only" in write.stderr


@pytest.mark.slow
def test_stage_failures_are_one_clear_line(tmp_path, small_clip):
    # Cameras half a frame off the video's frames but for the first and the last: ingest checks
    # every camera against the frames' times under [frames] max_timestamp_error_us, so they pass
    # under a loose tolerance; run again under the default one, a stage fails.
    lines = small_clip.cameras_path.read_text().splitlines()
    shifted = [*lines[:2]] + [" ".join([str(int(ln.split()[0]) + 15_000), *ln.split()[1:]]) for ln in lines[2:-1]] + lines[-1:]
    cams = tmp_path / "c.txt"
    cams.write_text("\n".join(shifted) + "\n")
    (tmp_path / "loose.toml").write_text("[frames]\nmax_timestamp_error_us = 20000\n")
    refused = cli("-w", str(tmp_path / "w"), "ingest", str(small_clip.video_path), str(cams))
    assert refused.returncode == 2 and f"{cams}:3: timestamp" in refused.stderr, refused.stderr
    loose = cli("-c", str(tmp_path / "loose.toml"), "-w", str(tmp_path / "w"), "ingest", str(small_clip.video_path), str(cams))
    assert loose.returncode == 0, loose.stderr
    result = cli("-w", str(tmp_path / "w"), "run", "small_0")  # the ingest stage checks its inputs again, under 3 ms
    assert result.returncode == 1
    placed = tmp_path / "w" / "inputs" / "small_0" / "cameras.txt"  # the warehouse's copy of c.txt
    assert f"error: clip small_0, stage ingest: {placed}:3: timestamp" in result.stderr, result.stderr
    assert "Traceback" not in result.stderr


def test_usage_errors_are_one_clear_line(tmp_path):
    result = cli("-w", str(tmp_path / "w"), "ingest", str(tmp_path / "nowhere"))
    assert result.returncode == 2 and "nowhere: no such file or folder" in result.stderr and "Traceback" not in result.stderr
    (tmp_path / "room.mp4").write_bytes(b"")
    result = cli("-w", str(tmp_path / "w"), "ingest", str(tmp_path / "room.mp4"), str(tmp_path / "room.txt"))
    assert result.returncode == 2 and result.stderr.strip() == f"error: {tmp_path / 'room.txt'}: no such file or folder"
    table = tmp_path / "lib" / "models.csv"  # a library's models.csv given for its folder: "folder not found"
    table.parent.mkdir()
    table.write_text("id,class\n")
    result = cli("-w", str(tmp_path / "w"), "cad", "ingest", str(table))
    assert result.returncode == 2 and result.stderr.strip() == (f"error: {table}: a file, not a CAD source folder: "
                                                               f"give its folder ({table.parent})")
    from fuzz.harness import assert_clean_error, run_cli

    (tmp_path / "file").write_text("x")
    for command in (["status"], ["run"], ["annotate"], ["server", "start"], ["cad", "ingest"]):  # before Prefect starts
        assert_clean_error(run_cli("-w", str(tmp_path / "file"), *command),
                           mentions=f"{tmp_path / 'file'}: the warehouse is not a folder")
    (tmp_path / "w").mkdir()
    result = cli("-w", str(tmp_path / "w"), "tables", "nope")
    assert result.returncode == 2 and "unknown table 'nope'" in result.stderr
    # one table's columns are the code's data model: shown before any warehouse exists, and none made
    result = cli("-w", str(tmp_path / "none"), "tables", "poses")
    assert result.returncode == 0 and "key: clip, track_id" in result.stdout and not (tmp_path / "none").exists(), result.stderr


def test_config_check_names_the_key(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text("[frames]\njpeg_quality = 500\n")
    result = cli("config", "check", str(f))
    assert result.returncode == 2 and "[frames] jpeg_quality: must be <= 100, got 500" in result.stderr
    f.write_text("[frames]\njpeg_quality = 50\n")
    assert cli("config", "check", str(f)).returncode == 0
    assert "jpeg_quality = 50" in cli("-c", str(f), "config", "show").stdout
    # no path: the config the other commands read (-c, then $CADESTATE_CONFIG), as `config show` reads it
    assert cli("-c", str(f), "config", "check").stdout == f"{f}: ok\n"
    assert cli("config", "check", env={"CADESTATE_CONFIG": str(f)}).stdout == f"{f}: ok\n"
    f.write_text("[frames]\njpeg_quality = 500\n")
    result = cli("-c", str(f), "config", "check")
    assert result.returncode == 2 and "[frames] jpeg_quality: must be <= 100, got 500" in result.stderr


def test_bench_generate_refuses_no_clips(tmp_path):
    result = cli("-w", str(tmp_path / "w"), "bench", "generate", "--out", str(tmp_path / "b"), "--clips", "0")
    assert result.returncode == 2 and "Invalid value for '--clips'" in result.stderr and not (tmp_path / "b").exists()


@pytest.mark.parametrize("option", [("--seed", "-1"), ("--frames", "0")])
def test_bench_generate_refuses_a_negative_seed_or_no_frames(tmp_path, option):
    """A negative seed was a numpy traceback after a clip folder (``bench--1-00_0``) was made; no frames, a traceback."""
    result = cli("-w", str(tmp_path / "w"), "bench", "generate", "--out", str(tmp_path / "b"), *option)
    assert result.returncode == 2 and f"Invalid value for '{option[0]}'" in result.stderr and not (tmp_path / "b").exists()


def test_bench_run_refuses_no_rounds(tmp_path):
    """--max-rounds 0 ran no clip and printed an empty table, exit status 0."""
    result = cli("-w", str(tmp_path / "w"), "bench", "run", str(tmp_path / "b"), "--max-rounds", "0")
    assert result.returncode == 2 and "Invalid value for '--max-rounds'" in result.stderr


@pytest.mark.parametrize(("where", "name", "says"), [("f", "demo", "f: cannot write the demo clip there: File exists"),
                                                    ("d", "../x", "invalid clip name '../x'")])
def test_bench_demo_refuses_a_file_as_its_folder_or_a_name_with_a_path(tmp_path, where, name, says):
    """A file as the folder was a FileExistsError traceback; --name ../x wrote ../x.mp4 beside the folder."""
    (tmp_path / "f").write_text("notes")
    result = cli("bench", "demo", str(tmp_path / where), "--name", name, "--frames", "4")
    assert result.returncode == 2 and "Traceback" not in result.stderr and says in result.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f"] and (tmp_path / "f").read_text() == "notes"


def test_annotate_on_a_taken_port_is_one_line(tmp_path):
    """`cadestate annotate` where nothing can listen: one error line naming the address, before Prefect
    starts or the app's address is printed; a port out of range is refused by the option (and by
    `server start`'s)."""
    import socket

    from fuzz.harness import assert_clean_error, run_cli

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        result = run_cli("-w", str(tmp_path / "w"), "annotate", "--port", str(port))
    assert_clean_error(result, mentions=f"--host 127.0.0.1 --port {port}: cannot listen there: ")
    assert "another app on it? choose another --port" in result.stderr and "http://" not in result.stderr
    out_of_range = cli("-w", str(tmp_path / "w"), "annotate", "--port", "99999")
    assert out_of_range.returncode == 2 and "Traceback" not in out_of_range.stderr and "--port" in out_of_range.stderr
    server = cli("-w", str(tmp_path / "w"), "server", "start", "--port", "99999")  # not handed to Prefect to fail on
    assert server.returncode == 2 and "Invalid value for '--port'" in server.stderr


@pytest.mark.slow
def test_annotate_stopped_by_sigterm_stops_the_prefect_api_it_started(tmp_path):
    """A service manager stops the app with SIGTERM: the app shuts down and so does the Prefect
    API process it launched (it was left running, reparented to init)."""
    import signal
    import socket
    import urllib.request

    from flows.server import free_port

    (tmp_path / "w").mkdir()
    port = free_port("127.0.0.1")
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    app = subprocess.Popen([sys.executable, "-m", "cadestate", "-w", str(tmp_path / "w"), "annotate", "--port", str(port)],
                           stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            try:
                urllib.request.urlopen(f"http://127.0.0.1:{port}/api/clips", timeout=2).read()
                break
            except OSError:
                time.sleep(0.5)
        children = [int(c) for c in Path(f"/proc/{app.pid}/task/{app.pid}/children").read_text().split()]
        assert children, "the app launched no Prefect API process"
        app.send_signal(signal.SIGTERM)
        assert app.wait(60) == 128 + signal.SIGTERM, app.stderr.read()[-4000:]
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and any(Path(f"/proc/{c}").exists() for c in children):
            time.sleep(0.2)
        alive = [c for c in children if Path(f"/proc/{c}").exists() and "zombie" not in Path(f"/proc/{c}/status").read_text()]
        assert not alive, f"left running: {alive}"
    finally:
        app.kill()
        app.wait()
    with socket.socket() as s:  # the app's port is free again (TIME_WAIT aside, as uvicorn binds)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", port))


def box_library(tmp_path, bad: bool = False):
    """A folder of meshes with its models.csv (a 1 x 0.5 x 0.6 m box, a table; with ``bad``, also an
    unreadable chair) and a small-render config ``tmp_path/c.toml``."""
    import trimesh

    folder = tmp_path / "meshes"
    folder.mkdir()
    trimesh.creation.box((1.0, 0.5, 0.6)).export(folder / "box.obj")
    if bad:
        (folder / "bad.obj").write_text("f 1 2 3\n")
    (folder / "models.csv").write_text("id,class\nbox,table\n" + ("bad,chair\n" if bad else ""))
    (tmp_path / "c.toml").write_text("[cad_views]\nviews = 2\nsize = 64\n")
    return folder


@pytest.mark.slow
def test_cad_ingest_failure_names_the_library(tmp_path):
    """A CAD library's failed stage is reported as the library's, not as a clip's."""
    folder = box_library(tmp_path)
    result = cli("-w", str(tmp_path / "w"), "-c", str(tmp_path / "c.toml"), "cad", "ingest", str(folder), "--library", "mine",
                 "--no-progress", env={"CADESTATE_MODELS": str(tmp_path / "no-models")})  # no model there: cad_embed fails
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert "error: library mine, stage cad_embed: " in result.stderr and "run `make models`" in result.stderr
    assert "clip mine" not in result.stderr and result.stderr.startswith("1 model from ")


def test_cad_sheet_where_is_one_condition(tmp_path):
    """`cad sheet --where` is one SQL condition on cad_models: a clause reaching past it (its own
    ORDER BY and LIMIT after a closing parenthesis, a second statement) is one error line naming
    --where, as a condition that fails is; it ran as part of the query."""
    from fuzz.harness import assert_clean_error, run_cli
    from warehouse import Warehouse, connect

    connect(Warehouse(tmp_path / "w")).close()  # a warehouse with no model: its catalog made
    for where, says in (("true) ORDER BY m.cad_id LIMIT 1000 --", "not one SQL condition: "),
                        ("true; SELECT 1", "not one SQL condition: "), ("no_such_column = 1", "SQL error: ")):
        result = run_cli("-w", str(tmp_path / "w"), "cad", "sheet", str(tmp_path / "s.png"), "--where", where)
        assert_clean_error(result, mentions=f"error: --where {where!r}: {says}")
    assert not (tmp_path / "s.png").exists()


def test_cad_sheet_names_a_rendered_view_that_is_missing_or_damaged(tmp_path):
    """A model's rendered view in the warehouse missing or damaged: one line naming it, not the
    sheet (it said "<sheet>: cannot write the sheet there: No such file or directory"); no sheet."""
    from PIL import Image

    from conftest import table_rows
    from fuzz.harness import assert_clean_error, run_cli
    from warehouse import Warehouse

    wh = Warehouse(tmp_path / "w")
    wh.write("cad_models", "lib", table_rows("cad_models", [{"library": "lib", "cad_id": "m1", "name": "chair",
                                                             "class": "chair", "symmetry": 1}]))
    wh.write("cad_views", "lib", table_rows("cad_views", [{"library": "lib", "cad_id": "m1", "view": 0,
                                                           "image_path": "media/cad/m1_0.png"}]))
    view = wh.root / "media" / "cad" / "m1_0.png"
    view.parent.mkdir(parents=True)
    Image.new("RGB", (8, 8)).save(view)
    assert run_cli("-w", str(wh.root), "cad", "sheet", str(tmp_path / "s.png")).code == 0
    (tmp_path / "s.png").unlink()
    for damage, why in ((lambda: view.write_bytes(b"not a png"), "not an image"), (view.unlink, "No such file or directory")):
        damage()
        result = run_cli("-w", str(wh.root), "cad", "sheet", str(tmp_path / "s.png"))
        line = assert_clean_error(result, mentions=f"error: {view}: cannot read this CAD model's rendered view (missing or damaged: {why})")
        assert "cannot write" not in line and not (tmp_path / "s.png").exists(), line


@pytest.mark.slow
def test_cad_ingest_sheet_export(tmp_path):
    folder = box_library(tmp_path, bad=True)
    w = str(tmp_path / "w")
    result = runner.invoke(app, ["-w", w, "-c", str(tmp_path / "c.toml"), "cad", "ingest", str(folder), "--library", "mine"])
    assert result.exit_code == 0, result.output
    assert result.output.count("completed") == len(stages_of("library"))
    issues = json.loads(cli("-w", w, "sql", "SELECT item, severity FROM cad_issues", "-f", "json").stdout)
    assert issues == [{"item": "bad", "severity": "skipped"}]
    sheet = runner.invoke(app, ["-w", w, "cad", "sheet", str(tmp_path / "s.png")])
    assert sheet.exit_code == 0 and (tmp_path / "s.png").stat().st_size > 1000
    none = cli("-w", w, "cad", "sheet", str(tmp_path / "none.png"), "--where", "class = 'zzz'")  # was a blank sheet, exit 0
    assert none.returncode == 2 and "no CAD model with rendered views matches" in none.stderr
    assert not (tmp_path / "none.png").exists()
    export = runner.invoke(app, ["-w", w, "cad", "export-official", str(tmp_path / "official")])
    assert export.exit_code == 0 and (tmp_path / "official" / "04379243" / "mine.box.npz").is_file()
    credits = (tmp_path / "official" / "ATTRIBUTION.csv").read_text().splitlines()
    assert credits == ["cad_id,library,name,licence,creator,source,notice", "mine.box,mine,box,unknown,unknown,folder,"]
    unknown = cli("-w", w, "cad", "export-official", str(tmp_path / "o2"), "--library", "nosuch")
    assert unknown.returncode == 2 and "no CAD library 'nosuch'" in unknown.stderr and "(libraries: mine)" in unknown.stderr
    import trimesh

    trimesh.creation.box((0.5, 0.5, 0.5)).export(folder / "Box.obj")  # slugs like the held "box": which keeps its id
    (folder / "models.csv").write_text("id,class\nBox,table\nbox,table\nbad,chair\n")
    assert cli("-w", w, "-c", str(tmp_path / "c.toml"), "cad", "ingest", str(folder), "--library", "mine",
               "--no-progress").returncode == 0
    ids = json.loads(cli("-w", w, "sql", "SELECT cad_id, name FROM cad_models ORDER BY name", "-f", "json").stdout)
    assert ids[1] == {"cad_id": "mine.box", "name": "box"} and ids[0]["cad_id"].startswith("mine.box-"), ids
    (tmp_path / "elsewhere").mkdir()
    other = box_library(tmp_path / "elsewhere")  # another folder under the same library name: refused before Prefect starts
    clash = cli("-w", w, "cad", "ingest", str(other), "--library", "mine", "--no-progress")
    assert clash.returncode == 2 and clash.stderr.count("\n") == 1, clash.stderr
    assert f"library 'mine' already holds models from {folder}, not {other}: " in clash.stderr
    again = cli("-w", w, "cad", "export-official", str(tmp_path / "official"))
    assert again.returncode == 2 and "exists and is not empty" in again.stderr
    onto_file = cli("-w", w, "cad", "export-official", str(tmp_path / "s.png"))
    assert onto_file.returncode == 2 and f"{tmp_path / 's.png'}: exists and is not a folder" in onto_file.stderr


@pytest.mark.slow
@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_ctrl_c_ends_a_run_at_once_and_run_resumes_it(tmp_path, small_clip, sig):
    """Ctrl-C (SIGINT to the command's process group, as a terminal sends it) or SIGTERM (to the
    command, as `kill` or a service manager sends it) while a stage runs: the command ends within
    seconds, status 128 + the signal, saying so; the Prefect API it launched (in a session of its
    own) goes with it; the stage reads as interrupted and `cadestate run` finishes the clip; the flow
    run reads as Cancelled. Before, every queued stage of every clip ran to the end first (SIGTERM:
    over a minute of `cad ingest`)."""
    import signal
    import sqlite3

    signum = getattr(signal, sig)

    w = tmp_path / "w"
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_LOGGING_LEVEL"}
    proc = subprocess.Popen([sys.executable, "-m", "cadestate", "-w", str(w), "ingest", str(small_clip.video_path),
                             str(small_clip.cameras_path), "--clip", "small_0", "--no-progress"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # as in a terminal
    deadline = time.monotonic() + 120
    while not list((w / "_running" / "small_0").glob("detect.*.json")) and time.monotonic() < deadline \
            and proc.poll() is None:
        time.sleep(0.01)  # until the detect stage runs (its run marker)
    assert proc.poll() is None, proc.communicate()
    sent = time.monotonic()
    os.killpg(proc.pid, signum) if signum == signal.SIGINT else proc.send_signal(signum)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signum and time.monotonic() - sent < 10, err
    said = "interrupted" if signum == signal.SIGINT else "terminated"
    assert f"{said}: the stages in progress stop unfinished" in err and "Traceback" not in err, err
    deadline = time.monotonic() + 10
    while prefect_apis_of(w) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not prefect_apis_of(w)
    with sqlite3.connect(Path(os.environ["PREFECT_HOME"]) / "prefect.db") as db:  # not left "Running" in the UI
        states = db.execute("SELECT state_type FROM flow_run WHERE name = 'annotate_clip/small_0' AND parameters "
                            "LIKE ?", (f"%{w}%",)).fetchall()  # the tests share one Prefect home
    assert states == [("CANCELLED",)]
    status = cli("-w", str(w), "status", "small_0")
    assert "small_0 was interrupted at detect" in status.stdout, status.stdout
    assert cli("-w", str(w), "run", "small_0", "--no-progress").returncode == 0
    rows = json.loads(cli("-w", str(w), "sql", "SELECT DISTINCT status FROM runs WHERE clip = 'small_0' AND stage = "
                          "'verification'", "-f", "json").stdout)
    assert rows == [{"status": "completed"}]


@pytest.mark.slow
@pytest.mark.parametrize("sig, wait_s", [("SIGINT", 3.0), ("SIGTERM", 3.0), ("SIGINT", 0.0)])
def test_ctrl_c_ends_cad_ingest_with_its_render_pool(tmp_path, sig, wait_s):
    """Ctrl-C or SIGTERM while `cad ingest` renders on its process pool (``wait_s`` after its first
    worker appeared; 0: while its workers start): the pool's worker processes end with the
    command, which says its one line last, and no traceback. They went on, orphaned, holding the
    command's stderr (a reader of it waited for them), and with them multiprocessing's resource
    tracker, which warned of the pool's "leaked" semaphores once they had ended; a Ctrl-C while
    they started printed each one's KeyboardInterrupt traceback."""
    import contextlib
    import signal

    import psutil

    signum = getattr(signal, sig)
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_LOGGING_LEVEL"}
    proc = subprocess.Popen([sys.executable, "-m", "cadestate", "-w", str(tmp_path / "w"), "cad", "ingest",
                             "--no-progress"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env,
                            start_new_session=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 180
        pool: list[psutil.Process] = []
        while not pool and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
            pool = [p for p in psutil.Process(proc.pid).children(recursive=True)
                    if "multiprocessing.spawn" in " ".join(p.cmdline())]
        time.sleep(wait_s)
        assert proc.poll() is None and pool, proc.returncode
        family = psutil.Process(proc.pid).children(recursive=True)
        os.killpg(proc.pid, signum) if signum == signal.SIGINT else proc.send_signal(signum)
        _, err = proc.communicate(timeout=30)
        _, alive = psutil.wait_procs(family, timeout=10)
        assert proc.returncode == 128 + signum and not alive, alive
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)  # its session: the pool's workers too
    said = "interrupted" if signum == signal.SIGINT else "terminated"
    assert err.strip().splitlines()[-1] == f"{said}: the stages in progress stop unfinished (the command run again " \
                                           "resumes them)", err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err


def prefect_apis_of(w: Path) -> list[int]:
    """Pids of the Prefect API processes (uvicorn) whose Prefect home is under warehouse ``w``."""
    pids = []
    for proc in Path("/proc").iterdir():
        try:
            if b"prefect.server.api.server" in (proc / "cmdline").read_bytes() and \
                    str(w).encode() in (proc / "environ").read_bytes():
                pids.append(int(proc.name))
        except (OSError, ValueError):
            continue
    return pids


def test_a_sigterm_while_a_finished_command_exits_prints_no_traceback(tmp_path):
    """SIGTERM (a group kill, `timeout`) that comes while a finished command's exit handlers run (the
    Prefect API it launched being stopped, up to 5 s): the exit goes on quietly, as it was ending."""
    script = ("import atexit, os, signal, sys, time\n"
              "from cadestate.cli import main\n"
              "atexit.register(lambda: (os.kill(os.getpid(), signal.SIGTERM), time.sleep(0.5)))  # a handler under way\n"
              "sys.argv = ['cadestate', 'stages']\n"
              "main()\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=tmp_path,
                          env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])})
    assert done.returncode == 0 and "pose" in done.stdout, done.stderr
    assert "Traceback" not in done.stderr and not done.stderr.strip(), done.stderr


def test_version_prints_the_installed_version():
    """`cadestate --version` (a new user's first check) was "No such option: --version"."""
    from importlib.metadata import version

    from fuzz.harness import run_cli

    result = run_cli("--version")
    assert result.code == 0 and result.stdout == f"cadestate {version('cadestate')}\n" and result.stderr == "", result
