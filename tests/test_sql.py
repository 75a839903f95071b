"""`cadestate sql`: reads the warehouse's tables and nothing else, writes nothing, installs nothing,
answers from the warehouse it is given (copied or not, whatever its catalog file holds) and streams
its results."""

from __future__ import annotations

import contextlib
import io
import json
import shutil
import sys
import tracemalloc
from pathlib import Path

import duckdb
import pytest

from conftest import table_rows
from fuzz.harness import CliResult, assert_clean_error, run_cli, warehouse_digest
from warehouse import Warehouse


def clips(clip: str, cameras: int):
    return table_rows("clips", [{"clip": clip, "num_cameras": cameras}])


@pytest.fixture
def w(tmp_path) -> Path:
    """A warehouse with two clips (num_cameras 1 and 2) and a run."""
    wh = Warehouse(tmp_path / "w")
    wh.write("clips", "a", clips("a", 1))
    wh.write("clips", "b", clips("b", 2))
    wh.write("runs", "a", table_rows("runs", [{"clip": "a", "run_id": "r1"}]))
    return wh.root


def sql(w: Path, query: str, *options: str) -> CliResult:
    return run_cli("-w", str(w), "sql", *options, "--", query)


def refused(result: CliResult, mentions: str | None = None) -> str:
    """A clean refusal, and nothing but its one line on stderr."""
    line = assert_clean_error(result, mentions=mentions)
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    return line


def cameras(w: Path) -> list[dict]:
    result = sql(w, "SELECT clip, num_cameras FROM clips ORDER BY clip", "-f", "json")
    assert result.code == 0, result.stderr
    return json.loads(result.stdout)


def test_copy_cannot_replace_a_table_partition(w):
    part = next((w / "tables" / "clips" / "clip=a").glob("*.parquet"))
    before = warehouse_digest(w)
    refused(sql(w, f"COPY (SELECT 'x' AS clip) TO '{part}' (FORMAT parquet)"), mentions="COPY")
    assert warehouse_digest(w) == before
    assert cameras(w) == [{"clip": "a", "num_cameras": 1}, {"clip": "b", "num_cameras": 2}]


def test_copy_cannot_replace_the_catalog(w):
    before = warehouse_digest(w)
    refused(sql(w, f"COPY (SELECT 1 AS i) TO '{w / 'catalog.duckdb'}' (FORMAT csv)"), mentions="COPY")
    assert warehouse_digest(w) == before
    assert cameras(w)[0] == {"clip": "a", "num_cameras": 1}


def test_files_outside_the_tables_cannot_be_read(w, tmp_path):
    secret = tmp_path / "secret.csv"
    secret.write_text("password\nhunter2\n")
    (w / "inputs").mkdir()
    shutil.copy(secret, w / "inputs" / "secret.csv")
    for path in (secret, w / "inputs" / "secret.csv", w / "tables" / ".." / "inputs" / "secret.csv"):
        for reader in ("read_csv", "read_text", "read_blob"):
            result = sql(w, f"SELECT * FROM {reader}('{path}')", "-f", "csv")
            refused(result)
            assert "hunter2" not in result.stdout + result.stderr
    result = sql(w, "SELECT * FROM read_csv('/etc/passwd')")
    refused(result)
    assert "root" not in result.stdout


def test_extensions_are_neither_installed_nor_loaded(w):
    refused(sql(w, "INSTALL httpfs"), mentions="INSTALL")
    refused(sql(w, "LOAD httpfs"), mentions="LOAD")
    refused(sql(w, "SELECT * FROM read_parquet('https://example.com/x.parquet')"))


def test_one_statement_of_a_read_only_kind(w):
    part = next((w / "tables" / "clips" / "clip=a").glob("*.parquet"))
    before = warehouse_digest(w)
    refused(sql(w, "SELECT 1; SELECT 2"), mentions="one statement")
    refused(sql(w, f"SELECT 1; COPY (SELECT 'x' AS clip) TO '{part}' (FORMAT parquet)"))
    refused(sql(w, f"EXPLAIN ANALYZE COPY (SELECT 'x' AS clip) TO '{part}' (FORMAT parquet)"), mentions="COPY")
    refused(sql(w, "PRAGMA table_info('clips')"), mentions="DESCRIBE")
    refused(sql(w, "CREATE TABLE t (i INT)"), mentions="read-only")
    refused(sql(w, "   -- nothing"), mentions="no statement")
    refused(sql(w, "UPDATE EXTENSIONS"), mentions="UPDATE")  # a kind DuckDB's Python client has no name for
    refused(sql(w, "WITH x AS (DELETE FROM runs RETURNING 1) SELECT * FROM x"))  # a SELECT that would change: the views cannot
    refused(sql(w, "WITH x AS (DELETE FROM warehouse.snapshot.runs RETURNING 1) SELECT * FROM x"))
    assert warehouse_digest(w) == before
    for ok in ("DESCRIBE clips", "SHOW TABLES", "SUMMARIZE runs", "EXPLAIN SELECT * FROM clips",
               "FROM clips", "WITH c AS (FROM clips) SELECT count(*) FROM c", "VALUES (1)"):
        result = sql(w, ok)
        assert result.code == 0, (ok, result.stderr)


def test_help_says_what_is_allowed():
    result = run_cli("sql", "--help")
    assert result.code == 0
    for word in ("read-only", "SELECT", "DESCRIBE", "EXPLAIN", "COPY", "--limit"):
        assert word in result.stdout


def test_errors_are_one_short_line(w):
    refused(sql(w, "SELECT nope FROM clips"), mentions="SQL error")
    line = refused(sql(w, "SELECT '" + "x" * 100_000 + "' + nope FROM clips"))
    assert len(line) < 1000
    refused(sql(w, "SELECT * FROM clips WHERE\n\n"), mentions="SQL error")
    refused(sql(w, "SELECT '\udcff'"), mentions="UTF-8")  # an argument that is not UTF-8 (surrogate-escaped)


def test_a_copied_warehouse_answers_from_itself(w, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(w, copy)
    Warehouse(w).write("clips", "a", clips("a", 9))
    assert cameras(copy)[0] == {"clip": "a", "num_cameras": 1}
    assert cameras(w)[0] == {"clip": "a", "num_cameras": 9}


@pytest.mark.parametrize("damage", ["garbage", "truncated", "directory"])
def test_a_broken_catalog_file_does_not_break_sql(w, damage):
    catalog = w / "catalog.duckdb"
    if damage == "directory":
        catalog.unlink()
        catalog.mkdir()
    elif damage == "truncated":
        catalog.write_bytes(catalog.read_bytes()[:5000])
    else:
        catalog.write_bytes(b"not a database\n" * 100)
    assert cameras(w)[1] == {"clip": "b", "num_cameras": 2}
    if damage == "directory":
        refused(run_cli("-w", str(w), "catalog"), mentions=str(catalog))
    else:
        assert run_cli("-w", str(w), "catalog").code == 0


def test_a_warehouse_that_is_a_file_is_named_in_one_line(tmp_path):
    (tmp_path / "w").write_text("not a folder")
    refused(run_cli("-w", str(tmp_path / "w"), "sql", "SELECT 1"), mentions=str(tmp_path / "w"))


def test_table_format_shows_a_limited_number_of_rows(w):
    result = sql(w, "SELECT * FROM range(5000)")
    assert result.code == 0 and "4,000 more rows not shown" in result.stdout
    assert " 999 " in result.stdout and " 1000 " not in result.stdout
    result = sql(w, "SELECT * FROM range(5000)", "--limit", "10")
    assert result.code == 0 and "4,990 more rows not shown" in result.stdout
    assert "not shown" not in sql(w, "SELECT * FROM range(1000)").stdout
    csv_rows = sql(w, "SELECT * FROM range(5000)", "-f", "csv", "--limit", "10").stdout.splitlines()
    assert csv_rows == ["range", *map(str, range(10))]


def test_json_is_valid_json(w):
    def strict(text: str):
        return json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} is not JSON"))

    query = "SELECT range AS i, CASE WHEN range = 1 THEN 'nan'::DOUBLE ELSE range END AS x, ['inf'::DOUBLE] AS l FROM range(3)"
    rows = strict(sql(w, query, "-f", "json").stdout)
    assert rows == [{"i": 0, "x": 0.0, "l": [None]}, {"i": 1, "x": None, "l": [None]}, {"i": 2, "x": 2.0, "l": [None]}]
    assert strict(sql(w, "SELECT * FROM clips WHERE false", "-f", "json").stdout) == []
    # a join's columns of one name: each kept, under a name of its own
    assert strict(sql(w, "SELECT 1 AS a, 2 AS a, 3 AS a_1", "-f", "json").stdout) == [{"a": 1, "a_2": 2, "a_1": 3}]
    # a BLOB: base64, not Python's repr (b'ab'); in lists too, and in CSV
    assert strict(sql(w, "SELECT 'ab'::BLOB AS b, ['\\xFF'::BLOB] AS l", "-f", "json").stdout) == [{"b": "YWI=", "l": ["/w=="]}]
    assert sql(w, "SELECT 'ab'::BLOB AS b", "-f", "csv").stdout.splitlines() == ["b", "YWI="]


def test_csv_is_for_unix_tools(w):
    """Unix line ends; lists and maps as JSON, not Python's repr; a non-finite number empty."""
    out = sql(w, "SELECT 1 AS n, ['a', 'b'] AS l, MAP {'k': 'v'} AS m, 'nan'::DOUBLE AS x", "-f", "csv").stdout
    assert "\r" not in out and out.splitlines() == ["n,l,m,x", '1,"[""a"", ""b""]","{""k"": ""v""}",']


class Sink(io.TextIOBase):
    """A text stream that counts what is written to it and keeps nothing."""

    def __init__(self) -> None:
        self.chars = 0

    def writable(self) -> bool:
        return True

    def write(self, text: str) -> int:
        self.chars += len(text)
        return len(text)


def test_csv_streams_in_bounded_memory(w, monkeypatch):
    from cadestate.cli import main

    assert sql(w, "SELECT 1", "-f", "csv").code == 0  # every module imported before counting
    sink = Sink()
    query = "SELECT range, range * 2 AS twice FROM range(200000)"
    monkeypatch.setattr(sys, "argv", ["cadestate", "-w", str(w), "sql", "-f", "csv", query])
    tracemalloc.start()
    try:
        with contextlib.redirect_stdout(sink), pytest.raises(SystemExit) as end:
            main()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert end.value.code == 0 and sink.chars > 200_000 * 4
    assert peak < 8 * 2**20, f"{peak / 2**20:.0f} MiB of Python objects at once for 200,000 rows"


def test_a_current_catalog_is_attached_else_rebuilt_else_views_are_made_in_memory(w, tmp_path):
    """The catalog file is attached (read-only) when it is current for the warehouse. A copied
    warehouse's (views of the original's paths) is rebuilt for the copy first; one that cannot be
    rebuilt (a folder in its place) leaves the session to make its own views. Each answers from its
    own files."""
    def database(where: Path) -> str:
        result = sql(where, "SELECT current_database() AS db", "-f", "csv")
        assert result.code == 0, result.stderr
        return result.stdout.split()[-1]

    assert database(w) == "warehouse"
    copy = tmp_path / "copy"
    shutil.copytree(w, copy)
    Warehouse(w).write("clips", "b", clips("b", 7))
    assert database(copy) == "warehouse"
    assert cameras(copy)[1] == {"clip": "b", "num_cameras": 2}
    assert cameras(w)[1] == {"clip": "b", "num_cameras": 7}
    (copy / "catalog.duckdb").unlink()
    (copy / "catalog.duckdb").mkdir()
    assert database(copy) == "memory"
    assert cameras(copy)[1] == {"clip": "b", "num_cameras": 2}
    writer = duckdb.connect(str(w / "catalog.duckdb"))  # another client holds the catalog open for writing
    try:
        assert cameras(w)[1] == {"clip": "b", "num_cameras": 7}
    finally:
        writer.close()


def test_ctrl_c_interrupts_a_long_query_at_once(w):
    """SIGINT while DuckDB runs a long query: 'interrupted', status 130, within seconds (DuckDB alone
    noticed it after ~20 s, then with a traceback)."""
    import signal
    import subprocess
    import time

    query = "SELECT sum(a.range * b.range) FROM range(100000) a, range(100000) b"
    proc = subprocess.Popen([sys.executable, "-m", "cadestate", "-w", str(w), "sql", query], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,  # Ctrl-C as in a terminal (a background job ignores it)
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    time.sleep(5)  # started and in the query (it runs for minutes)
    sent = time.monotonic()
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and err == "interrupted\n" and out == "", err
    assert time.monotonic() - sent < 5
    proc = subprocess.Popen([sys.executable, "-m", "cadestate", "-w", str(w), "sql", query], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    time.sleep(5)
    proc.send_signal(signal.SIGTERM)  # an exit: the query stops before its connection closes (DuckDB aborted)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 143 and err == "" and out == "", err


def test_a_partition_rewritten_while_a_statement_reads_it_is_read_again(w):
    """A replace-mode write swaps a partition's file while a statement is planned but has not opened
    it yet (the statement's subquery runs first): the statement runs again and answers from the new
    file, where it was 'Cannot open file ...: No such file or directory'."""
    import threading
    import time

    from warehouse.query import run_query

    wh = Warehouse(w)
    statement = ("SELECT num_cameras FROM clips WHERE clip = 'a' AND (SELECT count(*) FROM range(1000000) x, "
                 "range(1000) y WHERE x.range + y.range < 0) = 0")  # seconds of work before clips is opened
    started = time.monotonic()
    with run_query(wh, statement) as result:
        assert list(result.batches) == [[(1,)]]
    took = time.monotonic() - started
    rewrite = threading.Timer(took / 5, lambda: wh.write("clips", "a", clips("a", 5)))
    rewrite.start()
    try:
        with run_query(wh, statement) as result:
            rows = list(result.batches)
    finally:
        rewrite.join()
    assert rows == [[(5,)]]


def test_a_partition_swapped_while_a_statement_lists_it_is_not_left_out(w):
    """DuckDB lists a partition folder's names, then checks each by its path: a replace-mode write
    that swaps the folder in between (strace holds DuckDB's check of clip a's file until the write
    is done) left clip a out of the answer, with no error ('1' clips of 2). The statement is
    planned again, as a table's folder changed meanwhile, and counts both."""
    import subprocess
    import time

    strace = shutil.which("strace")
    options = ["-f", "-qq", "--seccomp-bpf", "-e", "trace=%%stat", "-e", "inject=%%stat:delay_enter=3s:when=1"]
    trace = w.parent / "trace.txt"
    if strace is None or subprocess.run([strace, *options, "-P", str(trace), "true"], capture_output=True).returncode:
        pytest.skip("needs strace (5.3 or later), allowed to trace")
    wh = Warehouse(w)
    [listed] = wh.file_paths("clips", ["a"])
    proc = subprocess.Popen([strace, *options, "-o", str(trace), "-P", listed, sys.executable, "-m", "cadestate",
                             "-w", str(w), "sql", "-f", "csv", "--", "SELECT count(*) AS n FROM clips"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        while proc.poll() is None and not (trace.is_file() and listed in trace.read_text()):
            time.sleep(0.01)  # until DuckDB checks the file it listed (held there for 3 s)
        wh.write("clips", "a", clips("a", 1))
    finally:
        out, err = proc.communicate(timeout=120)
    assert listed in trace.read_text(), "DuckDB never checked clip a's file"
    assert (proc.returncode, out) == (0, "n\n2\n"), err


def test_table_format_shortens_long_lists_and_csv_keeps_them(w):
    """A row of ``embeddings`` printed its 768 floats whole in the table format (187 KB, ~200 lines
    at 80 columns); csv and json are for scripts and keep every item."""
    query = "SELECT range(768)::DOUBLE[] AS descriptor, [1, 2, 3] AS short"
    result = sql(w, query)
    assert result.code == 0, result.stderr
    assert "[0.0, 1.0, 2.0, 3.0, 4.0, 5.0, ... (768 items)]" in result.stdout
    assert "[1, 2, 3]" in result.stdout and "767.0" not in result.stdout
    assert len(result.stdout) < 1000
    [row] = json.loads(sql(w, query, "-f", "json").stdout)
    assert row["descriptor"] == [float(i) for i in range(768)]
    assert sql(w, query, "-f", "csv").stdout.count("767.0") == 1
