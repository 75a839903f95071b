"""Output meant for scripts is never hard-wrapped: lines naming files stay whole at 80 columns and
without a terminal; in a terminal, tables fit its width."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

LONG = "x" * 120


def cli(*args: str, cwd, columns: int = 80) -> subprocess.CompletedProcess:
    """The real command in a fresh process whose output is a pipe (no terminal), at ``columns``."""
    env = {**os.environ, "COLUMNS": str(columns)}
    return subprocess.run([sys.executable, "-m", "cadestate", *args], capture_output=True, text=True, env=env, cwd=cwd)


def test_lines_naming_files_stay_whole_without_a_terminal(tmp_path):
    folder = tmp_path / ("schemas_" + "a" * 90)
    result = cli("labels", "schema", "--write", str(folder), cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert lines and all(line.startswith(str(folder)) and line.endswith(".json") for line in lines), result.stdout
    for narrowed in (("verification",), ("--file", "task")):  # it wrote every schema, silently ignoring these
        refused = cli("labels", "schema", *narrowed, "--write", str(folder), cwd=tmp_path)
        assert refused.returncode == 2 and refused.stderr.strip() == \
            "error: --write writes every kind's task and label schemas: give it without KIND and --file", refused.stderr
    bad = folder / "bad.json"
    bad.write_text(json.dumps({"format": "cadestate-label/1", "kind": "verification"}))
    result = cli("labels", "validate", "--offline", str(bad), cwd=tmp_path)
    errors = [ln for ln in result.stderr.splitlines() if ln.strip()]
    assert result.returncode == 1 and len(errors) == 1 and errors[0].startswith(f"error: {bad}"), result.stderr
    result = cli("labels", "validate", "--offline", str(folder), str(tmp_path / "none"), cwd=tmp_path)
    errors = [ln for ln in result.stderr.splitlines() if ln.strip()]
    assert result.returncode == 2 and errors[0] == f"error: {tmp_path / 'none'}: no such label file or folder", result.stderr
    assert sum(ln.startswith(f"error: {folder}/") for ln in errors) == len(list(folder.glob("*.json"))), result.stderr


def test_paths_with_brackets_are_printed_as_they_are(tmp_path):
    """A path is text, not rich markup: '[x]' stayed out of the line and '[/]' was a traceback
    after the work was done."""
    folder = tmp_path / "a[/]b" / "c[x]"
    folder.mkdir(parents=True)
    (folder / "cfg[red].toml").write_text("[detect]\nscore_threshold = 0.4\n")
    result = cli("config", "check", str(folder / "cfg[red].toml"), cwd=tmp_path)
    assert result.returncode == 0 and result.stdout == f"{folder / 'cfg[red].toml'}: ok\n", (result.stdout, result.stderr)


def test_tables_take_their_natural_width_without_a_terminal(tmp_path):
    (tmp_path / "w").mkdir()
    result = cli("-w", str(tmp_path / "w"), "sql", f"SELECT '{LONG}' AS v, 2 AS n", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert any(LONG in line for line in result.stdout.splitlines()), result.stdout


@pytest.mark.skipif(sys.platform != "linux", reason="util-linux `script` gives the command a terminal")
def test_tables_fit_an_80_column_terminal(tmp_path):
    (tmp_path / "w").mkdir()
    command = f"{sys.executable} -m cadestate -w {tmp_path / 'w'} sql \"SELECT '{LONG}' AS v\""
    result = subprocess.run(["script", "-qec", command, "/dev/null"], capture_output=True, text=True, cwd=tmp_path,
                            env={**os.environ, "COLUMNS": "80", "TERM": "dumb"})
    assert result.returncode == 0, result.stdout
    lines = [ln for ln in result.stdout.splitlines() if ln.strip()]
    assert lines and max(len(ln) for ln in lines) <= 80 and LONG not in result.stdout


@pytest.mark.skipif(sys.platform != "linux", reason="util-linux `script` gives the command a terminal")
def test_a_result_too_wide_for_the_terminal_is_shown_as_records(tmp_path):
    """Twelve columns cannot share 80: each row is a record of 'name  value' lines, every value whole
    (Rich had shrunk every cell to nothing)."""
    (tmp_path / "w").mkdir()
    columns = ", ".join(f"'value{i}' AS column_{i}" for i in range(12))
    command = f"{sys.executable} -m cadestate -w {tmp_path / 'w'} sql \"SELECT {columns} FROM range(2)\""
    result = subprocess.run(["script", "-qec", command, "/dev/null"], capture_output=True, text=True, cwd=tmp_path,
                            env={**os.environ, "COLUMNS": "80", "TERM": "dumb"})
    assert result.returncode == 0, result.stdout
    lines = [ln.strip() for ln in result.stdout.splitlines() if ln.strip()]
    assert sum(ln.startswith("row ") for ln in lines) == 2, result.stdout
    assert all(f"column_{i}   value{i}" in lines for i in range(10)) and lines.count("column_11  value11") == 2


def leaf_commands() -> list[tuple[str, ...]]:
    """Every command that runs something (``cadestate cad ingest``, not the group ``cad``)."""
    from typer.main import get_command

    from cadestate.cli import app

    def walk(group, prefix: tuple[str, ...]):  # Typer's own click: a group is what has commands
        for name, cmd in group.commands.items():
            yield from walk(cmd, (*prefix, name)) if hasattr(cmd, "commands") else [(*prefix, name)]

    return list(walk(get_command(app), ()))


@pytest.mark.parametrize("command", leaf_commands(), ids=" ".join)
def test_help_examples_stay_whole_at_80_columns(tmp_path, command):
    """Every command's --help teaches by examples, and an example is a line to copy: never wrapped,
    whatever the width."""
    result = cli(*command, "--help", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    examples = [ln.strip() for ln in lines if ln.strip().startswith("cadestate ")]
    assert examples, result.stdout
    nxt = {ln.strip(): lines[i + 1].strip() if i + 1 < len(lines) else "" for i, ln in enumerate(lines)}
    assert all(not nxt[e].startswith("--") for e in examples), result.stdout  # no option wrapped onto the next line


def test_a_mistyped_warehouse_is_refused_and_not_created(tmp_path):
    """Commands that read a warehouse refuse a folder that is not there, in one line, and make nothing."""
    missing = tmp_path / "typo"
    for args in (("status",), ("sql", "SELECT 1"), ("tables",), ("stats",), ("export", "official", str(tmp_path / "out")),
                 ("annotate", "--port", "8799")):
        result = cli("-w", str(missing), *args, cwd=tmp_path)
        errors = [ln for ln in result.stderr.splitlines() if ln.strip()]
        assert result.returncode != 0 and len(errors) == 1 and f"{missing}: no warehouse there" in errors[0], (args, result.stderr)
        assert not missing.exists() and not (tmp_path / "out").exists(), args
    # A folder that is there but no warehouse (-w data for data/warehouse, -w ~): read as an empty
    # warehouse, exit 0, and a catalog and 29 table schemas were left in it.
    from warehouse.catalog import CATALOG_FILE
    from warehouse.store import TABLES_DIR

    assert (TABLES_DIR, CATALOG_FILE) == ("tables", "catalog.duckdb")  # the names cadestate.cli.common looks for
    other = tmp_path / "data"
    (other / "warehouse").mkdir(parents=True)  # -w data, for data/warehouse
    for args in (("status",), ("sql", "SELECT 1"), ("tables",), ("stats",)):
        result = cli("-w", str(other), *args, cwd=tmp_path)
        errors = [ln for ln in result.stderr.splitlines() if ln.strip()]
        assert result.returncode == 2 and len(errors) == 1 and f"{other}: not a warehouse" in errors[0], (args, result.stderr)
        assert [p.name for p in other.iterdir()] == ["warehouse"], args


def test_a_warehouse_that_cannot_be_written_is_one_line_before_prefect(tmp_path):
    """Runs (here `cad ingest`) and `compact` on a read-only warehouse say so at once (a run waited out
    Prefect's start and blamed it; compact gave a traceback)."""
    folder = tmp_path / "ro"
    (folder / "tables").mkdir(parents=True)
    folder.chmod(0o500)
    try:
        candidates = [folder, Path("/sys/kernel")]
        ro = next((c for c in candidates if c.is_dir() and not _can_write(c)), None)
        if ro is None:
            pytest.skip("no folder here that this user cannot write")
        import trimesh

        source = tmp_path / "meshes"
        source.mkdir()
        trimesh.creation.box((1.0, 0.5, 0.6)).export(source / "box.obj")
        (source / "models.csv").write_text("id,class\nbox,table\n")
        for args in (("cad", "ingest", str(source)), ("compact",)):
            result = cli("-w", str(ro), *args, cwd=tmp_path)
            errors = [ln for ln in result.stderr.splitlines() if ln.strip()]
            assert result.returncode == 2 and len(errors) == 1, (args, result.stderr)
            said = "the warehouse cannot be written (" if args[0] == "cad" or (ro / "tables").is_dir() else "not a warehouse"
            assert errors[0].startswith(f"error: {ro}: {said}"), errors[0]  # as root, /sys/kernel: a folder of other files
    finally:
        folder.chmod(0o700)


def _can_write(folder) -> bool:
    import tempfile

    try:
        with tempfile.TemporaryFile(dir=folder):
            return True
    except OSError:
        return False


def test_status_of_a_clip_that_is_not_there_fails(tmp_path):
    (tmp_path / "w").mkdir()
    result = cli("-w", str(tmp_path / "w"), "status", "nope_0", cwd=tmp_path)
    assert result.returncode == 2 and result.stderr.strip() == f"error: no clip or CAD library named nope_0 in {tmp_path / 'w'}"


def test_a_usage_error_is_one_line_naming_the_help(tmp_path):
    for args, message in ((("sql", "SELECT 1", "-f", "xml"), "error: Invalid value for '--format' / '-f': 'xml' is not "
                                                             "one of 'table', 'csv', 'json'. (`cadestate sql --help`)"),
                          (("--nope",), "error: No such option: --nope (`cadestate --help`)"),
                          (("ingest",), "error: Missing argument 'sources'. (`cadestate ingest --help`)"),
                          (("cad", "ingest", "-w", "wh"), "error: No such option: -w (-w is an option of `cadestate` itself: "
                                                          "give it before the command, `cadestate -w ... cad ingest`)")):
        result = cli(*args, cwd=tmp_path)
        assert result.returncode == 2 and result.stderr.splitlines() == [message], result.stderr


def test_an_output_path_that_cannot_be_written_is_one_line(tmp_path):
    """labels schema --write, cad sheet and stats --html under a file (not a folder): one line each."""
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    (tmp_path / "w").mkdir()
    for args, message in ((("labels", "schema", "--write", str(blocker / "x")), f"{blocker / 'x'}: cannot write the schemas there: "),
                          (("-w", str(tmp_path / "w"), "cad", "sheet", str(blocker / "s.png")),
                           f"{blocker / 's.png'}: cannot write the sheet there: "),
                          (("-w", str(tmp_path / "w"), "stats", "--html", str(blocker / "h")),
                           f"{blocker / 'h'}: cannot write the HTML report there: ")):
        result = cli(*args, cwd=tmp_path)
        errors = [ln for ln in result.stderr.splitlines() if ln.strip()]
        assert result.returncode == 2 and len(errors) == 1 and errors[0].startswith(f"error: {message}"), result.stderr


def test_stale_reasons_too_wide_for_the_terminal_go_under_the_status_table(monkeypatch):
    """At 80 columns the reasons were folded a word a line into a 6-column cell; they are numbered
    there and written out whole under the table. Without a terminal they stay inline."""
    import io
    from types import SimpleNamespace

    import cadestate.cli.pipeline as pipeline
    from cadestate.cli.common import LineConsole

    why = ("code changed", "inputs changed (cameras.txt, video.mp4 of inputs/bench-7-00_0/ edited since ingest)")
    rows = [SimpleNamespace(clip="bench-7-00_0", stage=s, last_run_at="12-06 02:30", status="completed", rows_written=1,
                            stale_reasons=why if s != "frames" else ()) for s in ("cameras", "frames", "correspondence_task")]
    for terminal, inline in ((True, False), (False, True)):
        screen = LineConsole(file=io.StringIO(), force_terminal=terminal, width=80, soft_wrap=True, color_system=None)
        monkeypatch.setattr(pipeline, "out", screen)
        table, notes = pipeline._stage_table(rows, "clip", "clips", inline=True)
        assert pipeline._wider_than_terminal(table) == (not inline)
        if not inline:
            table, notes = pipeline._stage_table(rows, "clip", "clips", inline=False)
            screen.print(table)
            lines = screen.file.getvalue().splitlines()
            assert max(len(ln) for ln in lines) <= 80 and any(ln.endswith("│ no (2) │") for ln in lines), lines
            assert notes == [f"[yellow](1)[/] bench-7-00_0 cameras: {'; '.join(why)}",
                             f"[yellow](2)[/] bench-7-00_0 correspondence_task: {'; '.join(why)}"]


def test_a_status_table_of_long_names_fits_80_columns_with_no_cell_cut_short(monkeypatch):
    """The default CAD libraries' names and the stage names took more than 80 columns: rich cut the
    cells to "sh3d-blendswap-…", row counts to "17…" and the notes' numbers to nothing. Narrow, the
    times lose their year and long names fold over lines; every row count and note number shows."""
    import io
    from types import SimpleNamespace

    import cadestate.cli.pipeline as pipeline
    from cadestate.cli.common import LineConsole

    rows = [SimpleNamespace(clip="sh3d-blendswap-cc-0-and-more", stage=s, last_run_at="2026-12-07 10:00", status="completed",
                            rows_written=17300 + i, stale_reasons=("code changed",)) for i, s in
            enumerate(("cad_ingest", "label_similarity", "cad_embed"))]
    screen = LineConsole(file=io.StringIO(), force_terminal=True, width=80, soft_wrap=True, color_system=None)
    monkeypatch.setattr(pipeline, "out", screen)
    table, _ = pipeline._stage_table(rows, "library", "CAD libraries", inline=False)
    assert pipeline._wider_than_terminal(table)
    table, notes = pipeline._stage_table(rows, "library", "CAD libraries", inline=False, narrow=True)
    screen.print(table)
    text = screen.file.getvalue()
    assert max(len(ln) for ln in text.splitlines()) <= 80 and "…" not in text, text
    assert all(str(r.rows_written) in text for r in rows) and all(f"no ({i})" in text for i in (1, 2, 3))
    assert "12-07 10:00" in text and "2026-12-07" not in text


def test_progress_bars_are_drawn_on_the_terminal_of_stderr_not_into_stdout(tmp_path):
    """`cmd > log` on a terminal: the bars go to stderr (the terminal); stdout, a file, holds the
    command's output alone (the bars went to stdout: a blank line in the file per bar, none shown)."""
    import pty

    master, slave = pty.openpty()
    code = "from cadestate.progress import progress\nfor _ in progress(range(3), 3, 'frames'): pass\nprint('done')"
    with open(tmp_path / "out.txt", "w") as stdout:
        done = subprocess.run([sys.executable, "-c", code], stdout=stdout, stderr=slave, timeout=120,
                              env={**os.environ, "CADESTATE_PROGRESS": "1"})
    os.close(slave)
    drawn = os.read(master, 1 << 16).decode(errors="replace")
    os.close(master)
    assert done.returncode == 0 and (tmp_path / "out.txt").read_text() == "done\n"
    assert "frames" in drawn, drawn


def test_output_is_utf8_whatever_the_locale_says(tmp_path):
    """Under an ASCII locale (PYTHONIOENCODING=ascii, or C without coercion) an 'é' in a CSV was a
    traceback after its header; a µ in `tables` too."""
    (tmp_path / "w" / "tables").mkdir(parents=True)
    env = {**os.environ, "COLUMNS": "80", "PYTHONIOENCODING": "ascii"}
    for args, shown in ((["sql", "SELECT 'é' AS x", "--format", "csv"], "x\né\n"), (["tables", "frames"], "µs")):
        done = subprocess.run([sys.executable, "-m", "cadestate", "-w", str(tmp_path / "w"), *args], capture_output=True,
                              env=env, cwd=tmp_path)
        assert done.returncode == 0 and shown in done.stdout.decode("utf-8"), done.stderr.decode()
    # A file name that is no UTF-8 (its bytes kept as surrogates) is printed as its bytes, not a traceback.
    folder = os.fsdecode(bytes(tmp_path) + b"/schemas\xff")
    done = subprocess.run([sys.executable, "-m", "cadestate", "labels", "schema", "--write", folder], capture_output=True,
                          env={**os.environ, "COLUMNS": "80"}, cwd=tmp_path)
    assert done.returncode == 0 and done.stdout.startswith(os.fsencode(folder)), done.stderr.decode()


def test_tables_stay_whole_in_a_pipe_when_colour_is_forced(tmp_path):
    """CI sets FORCE_COLOR (or TTY_COMPATIBLE), which makes Rich take a pipe for a terminal: `stages`
    then cut its module names at 80 columns ("tasks.vide…") and broke descriptions a word a line."""
    env = {**os.environ, "COLUMNS": "80", "FORCE_COLOR": "1"}
    result = subprocess.run([sys.executable, "-m", "cadestate", "stages"], capture_output=True, text=True, env=env, cwd=tmp_path)
    assert result.returncode == 0 and "…" not in result.stdout and "tasks.video.cameras" in result.stdout, result.stdout[:2000]
