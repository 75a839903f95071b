"""The DuckDB catalog's views are made once (writes never rebuild them), follow a table from empty
to full and across a schema change; append-mode partitions are compacted atomically."""

from __future__ import annotations

import json
import shutil
import multiprocessing as mp
import threading

import duckdb
import pyarrow as pa
import pytest

from conftest import table_rows
from fuzz.harness import run_cli
from schemas import TableSpec
from warehouse import Warehouse, WarehouseError, connect
from warehouse.catalog import CATALOG_FILE, VIEWS_MACRO, recorded_views, refresh_catalog, schema_path


def runs(clip: str, *ids: str) -> pa.Table:
    return table_rows("runs", [{"clip": clip, "run_id": i, "stage": "ingest"} for i in ids])


def catalog_state(wh: Warehouse) -> tuple[int, int]:
    st = (wh.root / CATALOG_FILE).stat()
    return st.st_ino, st.st_mtime_ns


def test_writes_leave_the_catalog_alone_and_its_views_follow_them(wh):
    wh.write("runs", "a", runs("a", "r1"))
    before = catalog_state(wh)
    held = connect(wh)  # opened before the writes: views read the files at query time
    assert held.execute("SELECT count(*) FROM clips").fetchone() == (0,)
    wh.write("runs", "a", runs("a", "r2"))
    wh.write("runs", "b", runs("b", "r3"))
    wh.write("clips", "a", table_rows("clips", [{"clip": "a", "num_cameras": 4}]))  # a table's first rows
    assert catalog_state(wh) == before
    assert held.execute("SELECT count(*) FROM runs").fetchone() == (3,)
    assert held.execute("SELECT clip, num_cameras FROM clips").fetchall() == [("a", 4)]
    held.close()
    con = connect(wh)
    assert catalog_state(wh) == before
    sql = con.execute("SELECT sql FROM duckdb_views() WHERE view_name = 'runs'").fetchone()[0]
    assert "union_by_name" not in sql and "_schema.parquet" in sql
    con.close()


def test_schema_files_are_not_partitions_and_add_no_rows(wh):
    wh.write("runs", "a", runs("a", "r1"))
    assert schema_path(wh, "runs").is_file() and wh.partitions("runs") == ["a"]
    con = connect(wh)
    assert con.execute("SELECT count(*) FROM runs").fetchone() == (1,)
    con.close()


V1 = TableSpec(name="numbers", mode="append", key=("clip", "i"), description="test table",
               schema=pa.schema([pa.field("clip", pa.string(), False), pa.field("i", pa.int64(), False)]))
V2 = TableSpec(name="numbers", mode="append", key=("clip", "i"), description="test table",
               schema=V1.schema.append(pa.field("note", pa.string())))


def test_a_column_added_to_a_table_with_data(tmp_path):
    old = Warehouse(tmp_path / "w", {"numbers": V1})
    old.write("numbers", "a", pa.table({"clip": ["a"], "i": [1]}))
    old.write("numbers", "a", pa.table({"clip": ["a"], "i": [2]}))
    assert recorded_views(old.root / CATALOG_FILE)["tables"]["numbers"]["uniform"]
    new = Warehouse(tmp_path / "w", {"numbers": V2})  # the code now has the column
    new.write("numbers", "b", pa.table({"clip": ["b"], "i": [3], "note": ["x"]}))
    con = connect(new)
    assert con.execute("SELECT clip, i, note FROM numbers ORDER BY i").fetchall() == [("a", 1, None), ("a", 2, None), ("b", 3, "x")]
    con.close()
    assert recorded_views(new.root / CATALOG_FILE)["tables"]["numbers"]["uniform"] is False  # read by name
    assert [c.files for c in new.compact_tables(["numbers"])] == [2]  # rewritten with the column
    refresh_catalog(new, recheck=["numbers"])
    assert recorded_views(new.root / CATALOG_FILE)["tables"]["numbers"]["uniform"]
    con = connect(new)
    assert con.execute("SELECT clip, i, note FROM numbers ORDER BY i").fetchall() == [("a", 1, None), ("a", 2, None), ("b", 3, "x")]
    con.close()


def test_a_never_null_column_added_to_a_table_with_data_reads_as_nulls_and_compacts(tmp_path):
    """A column the schema says is never null, added after files were written (a new version's
    column): the old rows read it as null, and a write past ``compact_after`` files compacts, where
    the merge failed (a never-null column holding nulls) and the write raised after its rows were in."""
    v3 = TableSpec(name="numbers", mode="append", key=("clip", "i"), description="test table",
                   schema=V1.schema.append(pa.field("host", pa.string(), False)))
    old = Warehouse(tmp_path / "w", {"numbers": V1})
    old.write("numbers", "a", pa.table({"clip": ["a"], "i": [1]}))
    new = Warehouse(tmp_path / "w", {"numbers": v3}, compact_after=2)
    read = new.read("numbers")
    assert read.column("host").to_pylist() == [None] and read.schema.field("host").nullable
    for i in (2, 3):
        assert new.write("numbers", "a", pa.table({"clip": ["a"], "i": [i], "host": ["h"]})) == 1
    assert len(new.files("numbers", ["a"])) == 1  # compacted
    assert new.read("numbers").to_pydict() == {"clip": ["a"] * 3, "i": [1, 2, 3], "host": [None, "h", "h"]}


def test_partitions_from_before_and_after_a_never_null_column_read_together_and_compact_to_the_fast_view(tmp_path):
    """Partition a holds a file from before the never-null column ``host`` (read as nulls: nullable)
    and one after, partition b only files after (never null): a read of both failed ("Schema at
    index 1 was different"), and once ``a`` was compacted (its merged file holds ``host`` nullable,
    its old row null) the table was never judged uniform again: every query read every footer."""
    v3 = TableSpec(name="numbers", mode="append", key=("clip", "i"), description="test table",
                   schema=V1.schema.append(pa.field("host", pa.string(), False)))
    Warehouse(tmp_path / "w", {"numbers": V1}).write("numbers", "a", pa.table({"clip": ["a"], "i": [1]}))
    new = Warehouse(tmp_path / "w", {"numbers": v3})
    new.write("numbers", "a", pa.table({"clip": ["a"], "i": [2], "host": ["h"]}))
    new.write("numbers", "b", pa.table({"clip": ["b"], "i": [3], "host": ["h"]}))
    rows = {"clip": ["a", "a", "b"], "i": [1, 2, 3], "host": [None, "h", "h"]}
    assert new.read("numbers").to_pydict() == rows
    assert Warehouse(tmp_path / "w", {"numbers": v3}).cache_reads().read("numbers").to_pydict() == rows
    refresh_catalog(new, recheck=["numbers"])
    assert recorded_views(new.root / CATALOG_FILE)["tables"]["numbers"]["uniform"] is False
    assert [c.files for c in new.compact_tables(["numbers"])] == [2]
    refresh_catalog(new, recheck=["numbers"])
    assert recorded_views(new.root / CATALOG_FILE)["tables"]["numbers"]["uniform"]
    con = connect(new)
    assert con.execute("SELECT clip, i, host FROM numbers ORDER BY i").fetchall() == [("a", 1, None), ("a", 2, "h"), ("b", 3, "h")]
    con.close()


@pytest.mark.parametrize("folder", ["br[ab]", "v*1", "g[1]"])
def test_a_warehouse_in_a_folder_whose_name_is_a_pattern_reads_its_own_files(tmp_path, folder):
    """'[ab]' and '*' in the warehouse's path made DuckDB's views read nothing (no file matched) or a
    sibling's files (v*1 matched vX1 too); g[1] read g1's schema file (its digest), so that g[1]'s
    own was never written and its catalog could not be built."""
    from warehouse.catalog import row_counts
    from warehouse.query import read_rows

    for name in ("vX1", "b", "g1", folder):
        Warehouse(tmp_path / name).write("runs", "a", runs("a", *[f"r{i}" for i in range(3 if name == folder else 5)]))
    wh = Warehouse(tmp_path / folder)
    con = connect(wh)
    assert con.execute("SELECT count(*) FROM runs").fetchone() == (3,)
    con.close()
    assert row_counts(wh)["runs"] == 3 and len(read_rows(wh, "runs", ["run_id"])) == 3
    result = run_cli("-w", str(tmp_path / folder), "sql", "SELECT count(*) AS n FROM runs", "-f", "csv")
    assert result.code == 0 and result.stdout.splitlines() == ["n", "3"], result.stderr
    assert run_cli("-w", str(tmp_path / folder), "compact").code == 0
    result = run_cli("-w", str(tmp_path / folder), "sql", "SELECT count(*) AS n FROM runs", "-f", "csv")
    assert result.stdout.splitlines() == ["n", "3"], result.stderr


def test_a_warehouse_whose_path_holds_a_backslash_is_refused_in_one_line(tmp_path):
    """DuckDB splits a pattern at a backslash: a warehouse there wrote its files and every view,
    `tables` and `sql` read none of them. It is refused before anything is written."""
    root = tmp_path / "a\\b"
    with pytest.raises(WarehouseError, match="backslash"):
        Warehouse(root)
    assert not root.exists()
    root.mkdir()
    result = run_cli("-w", str(root), "tables")
    assert result.code == 2 and result.stderr.count("\n") == 1 and "backslash" in result.stderr
    assert list(root.iterdir()) == []


def test_a_warehouse_whose_path_holds_a_question_mark_writes_and_reads_without_a_catalog(tmp_path, capsys):
    """DuckDB cannot keep a catalog there: the write says so once and is not failed by it (its rows
    are in), and reads go on without it."""
    wh = Warehouse(tmp_path / "w?1")
    assert wh.write("runs", "a", runs("a", "r1")) == 1
    assert "cannot build the catalog" in capsys.readouterr().err
    assert wh.write("runs", "a", runs("a", "r2")) == 1
    assert sorted(wh.read("runs").column("run_id").to_pylist()) == ["r1", "r2"]
    result = run_cli("-w", str(wh.root), "sql", "SELECT count(*) AS n FROM runs", "-f", "csv")
    assert result.stdout.splitlines() == ["n", "2"], result.stderr


def test_a_damaged_file_is_one_line_for_status_and_stats(tmp_path):
    wh = Warehouse(tmp_path / "w")
    wh.write("runs", "a", runs("a", "r1"))
    wh.write("runs", "a", runs("a", "r2"))
    wh.files("runs", ["a"])[0].write_bytes(b"not parquet at all")
    for command in (["status"], ["stats"]):
        result = run_cli("-w", str(wh.root), *command)
        assert result.code != 0 and "Traceback" not in result.stderr and result.stderr.count("\n") == 1, result.stderr
        assert "cannot read" in result.stderr, result.stderr


def test_a_damaged_file_when_the_catalog_is_built_is_one_line_naming_it(tmp_path):
    """The catalog built anew (none yet, or outdated) reads every file's footer: a damaged one was a
    pyarrow traceback ("Parquet magic bytes not found in footer") for `sql`, `stats`; now one line
    naming the table and the file."""
    wh = Warehouse(tmp_path / "w")
    for clip in ("a", "b"):
        wh.write("clips", clip, table_rows("clips", [{"clip": clip}]))
    damaged = wh.files("clips", ["a"])[0]
    damaged.write_bytes(b"not parquet at all")
    for command in (["sql", "SELECT 1"], ["stats"]):
        (wh.root / CATALOG_FILE).unlink(missing_ok=True)
        result = run_cli("-w", str(wh.root), *command)
        assert result.code == 2 and "Traceback" not in result.stderr and result.stderr.count("\n") == 1, result.stderr
        assert result.stderr.startswith(f"error: table clips: cannot read its files: {damaged}: "), result.stderr


def test_a_statement_reading_a_file_above_tables_is_the_statements_error(tmp_path):
    """``read_text('<root>/tables/../catalog.duckdb')`` (DuckDB lets a statement read its attached
    catalog) fails as the statement's error: it was blamed on a table ("table ..: cannot read its
    files"), the path taken as under ``tables/``."""
    wh = Warehouse(tmp_path / "w")
    wh.write("runs", "a", runs("a", "r1"))
    result = run_cli("-w", str(wh.root), "sql", f"SELECT * FROM read_text('{wh.root}/tables/../{CATALOG_FILE}')")
    assert result.code != 0 and result.stderr.startswith("error: SQL error: "), result.stderr


def test_a_write_is_not_failed_by_a_damaged_file_of_another_table(tmp_path):
    """A process's first write builds the catalog, which reads every footer: a damaged file of any
    table raised after the write was in, so a retried append wrote its rows twice. The write
    stands; the damage is a warning."""
    import subprocess
    import sys

    wh = Warehouse(tmp_path / "w")
    wh.write("clips", "a", table_rows("clips", [{"clip": "a"}]))
    damaged = wh.files("clips", ["a"])[0]
    damaged.write_bytes(b"not parquet at all")
    (wh.root / CATALOG_FILE).unlink()
    script = ("import sys; sys.path.insert(0, 'tests'); from conftest import table_rows; from warehouse import Warehouse; "
              f"Warehouse({str(wh.root)!r}).write('runs', 'b', table_rows('runs', [{{'clip': 'b', 'run_id': 'r1'}}])); print('written')")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0 and result.stdout == "written\n", result.stderr
    assert f"table clips: cannot read its files: {damaged}" in result.stderr and "the write itself is done" in result.stderr
    assert wh.read("runs", ["b"]).num_rows == 1


def test_temporary_files_of_a_killed_write_go_with_the_next_compaction(tmp_path):
    """A write killed before its rename leaves ``.<uuid>.tmp`` in an append partition: the next
    compaction (past ``compact_after`` files, or ``cadestate compact``) swaps in a folder without it."""
    wh = Warehouse(tmp_path / "w")
    wh.write("runs", "a", runs("a", "r1"))
    left = wh.partition_dir("runs", "a") / ".dead.tmp"
    left.write_bytes(b"half a file")
    wh.write("runs", "a", runs("a", "r2"))
    wh.compact("runs", "a")
    assert not left.exists() and len(wh.files("runs", ["a"])) == 1


def test_a_copied_warehouse_keeps_what_its_catalog_knew_of_its_files(wh, tmp_path, monkeypatch):
    import shutil

    import warehouse.catalog as catalog

    wh.write("runs", "a", runs("a", "r1"))
    shutil.copytree(wh.root, tmp_path / "copy")
    monkeypatch.setattr(catalog, "uniform", lambda *a: pytest.fail("files read again"))
    con = connect(Warehouse(tmp_path / "copy"))  # rebuilt for the new root, no footer read
    assert con.execute("SELECT count(*), warehouse_root() FROM runs").fetchone() == (1, str(tmp_path / "copy"))
    con.close()


def test_an_append_partition_is_compacted_past_the_configured_count(tmp_path):
    wh = Warehouse(tmp_path / "w", compact_after=3)
    for i in range(3):
        wh.write("runs", "a", runs("a", f"r{i}"))
    assert len(wh.files("runs", ["a"])) == 3
    wh.write("runs", "a", runs("a", "r3"))
    assert len(wh.files("runs", ["a"])) == 1
    assert sorted(wh.read("runs").column("run_id").to_pylist()) == ["r0", "r1", "r2", "r3"]
    wh.write("runs", "a", runs("a", "r4"))  # later writes sort after the merged file
    assert wh.files("runs", ["a"])[-1].stat().st_size and len(wh.files("runs", ["a"])) == 2
    assert not list((wh.root / "_staging").iterdir())


def test_compact_command(tmp_path):
    wh = Warehouse(tmp_path / "w")
    for i in range(3):
        wh.write("runs", "a", runs("a", f"r{i}"))
    wh.write("runs", "b", runs("b", "r9"))
    result = run_cli("-w", str(wh.root), "compact")
    assert result.code == 0, result.stderr
    snapshot = f"snapshot of 22 table(s) in {wh.root / 'catalog.duckdb'}"
    assert result.stdout.splitlines() == ["runs a: 3 files -> 1 (3 rows)", "compacted 1 partition(s)", snapshot]
    assert run_cli("-w", str(wh.root), "compact", "runs").stdout.splitlines() == ["compacted 0 partition(s)", snapshot]
    refused = run_cli("-w", str(wh.root), "compact", "clips")
    assert refused.code == 2 and "not append-mode" in refused.stderr and "Traceback" not in refused.stderr
    assert "--min-files" in run_cli("compact", "--help").stdout


def test_an_interrupted_compaction_leaves_the_partition_whole(wh, monkeypatch):
    import warehouse.store as store

    for i in range(3):
        wh.write("runs", "a", runs("a", f"r{i}"))
    before = sorted(p.name for p in wh.files("runs", ["a"]))

    def crash(a, b):
        raise OSError("killed (injected)")

    monkeypatch.setattr(store, "exchange", crash)
    with pytest.raises(OSError, match="injected"):
        wh.compact("runs", "a")
    assert sorted(p.name for p in wh.files("runs", ["a"])) == before
    assert not list((wh.root / "_staging").iterdir())
    monkeypatch.undo()
    assert wh.compact("runs", "a").rows == 3 and wh.read("runs").num_rows == 3


def test_compaction_never_shows_a_reader_rows_twice_or_missing(tmp_path):
    wh = Warehouse(tmp_path / "w")
    for i in range(6):
        wh.write("runs", "a", runs("a", f"r{i}"))
    seen, errors, stop = [], [], threading.Event()

    def read_forever():
        reader = Warehouse(wh.root)
        con = duckdb.connect()
        glob = (wh.table_dir("runs") / "clip=a" / "*.parquet").as_posix()
        while not stop.is_set():
            seen.append(reader.read("runs", ["a"]).num_rows)
            try:
                seen.append(con.execute(f"SELECT count(*) FROM read_parquet('{glob}')").fetchone()[0])
            except duckdb.Error as e:  # a file listed, then compacted away: an error, never a wrong count
                errors.append(str(e))

    threads = [threading.Thread(target=read_forever) for _ in range(2)]
    for t in threads:
        t.start()
    for i in range(6, 30):
        wh.write("runs", "a", runs("a", f"r{i}"))
        wh.compact("runs", "a")
    stop.set()
    for t in threads:
        t.join()
    assert seen and all(6 <= n <= 30 for n in seen), sorted(set(seen))
    assert all("No files found" in e or "No such file" in e or "Cannot open" in e or "could not" in e.lower() for e in errors), errors[:3]
    assert wh.read("runs").num_rows == 30


def _append_many(root: str, clip: str, n: int) -> None:
    wh = Warehouse(root, compact_after=4)
    for i in range(n):
        wh.write("runs", clip, runs(clip, f"{clip}{i}"))


def test_concurrent_writers_and_compaction_lose_no_row(tmp_path):
    ctx = mp.get_context("spawn")
    procs = [ctx.Process(target=_append_many, args=(str(tmp_path / "w"), "a", 15)) for _ in range(3)]
    for p in procs:
        p.start()
    for p in procs:
        p.join()
    assert all(p.exitcode == 0 for p in procs)
    assert Warehouse(tmp_path / "w").read("runs").num_rows == 45


def test_a_catalog_records_its_views(wh):
    wh.write("runs", "a", runs("a", "r1"))
    con = duckdb.connect(str(wh.root / CATALOG_FILE), read_only=True)
    record = json.loads(con.execute(f"SELECT {VIEWS_MACRO}()").fetchone()[0])
    con.close()
    assert record["root"] == str(wh.root) and set(record["tables"]) == set(wh.info)


def test_compacting_a_replace_table_is_refused(wh):
    wh.write("clips", "a", table_rows("clips", [{"clip": "a"}]))
    with pytest.raises(WarehouseError, match="not append-mode"):
        wh.compact("clips", "a")


def test_a_catalog_that_cannot_be_rebuilt_gives_way_to_views_in_memory(wh, tmp_path):
    """A copy whose catalog is out of date and cannot be written (here a folder in its place; a
    read-only copy in life): reading falls back to views made in memory, as `cadestate sql` does
    (`cadestate stats` failed there); opening it to write still fails."""
    import shutil

    from warehouse.catalog import CatalogError

    wh.write("runs", "a", runs("a", "r1"))
    shutil.copytree(wh.root, tmp_path / "copy")
    (tmp_path / "copy" / CATALOG_FILE).unlink()
    (tmp_path / "copy" / CATALOG_FILE / "x").mkdir(parents=True)
    copy = Warehouse(tmp_path / "copy")
    con = connect(copy)
    assert con.execute("SELECT count(*) FROM runs").fetchone() == (1,)
    con.close()
    with pytest.raises(CatalogError, match="cannot rebuild the catalog"):
        connect(copy, read_only=False)


def test_a_partition_or_lock_that_cannot_be_opened_is_one_line_naming_it(tmp_path):
    """A partition folder the warehouse cannot list (here a link to itself: "too many levels of
    symbolic links"; a folder without read permission alike) and a lock whose folder is a file ended
    `tables`, `status` and `compact` in a traceback; now one line naming the path."""
    from fuzz.harness import assert_clean_error

    wh = Warehouse(tmp_path / "w")
    for clip in ("a", "b"):
        wh.write("runs", clip, runs(clip, "r1"))
    loop = wh.partition_dir("runs", "c")
    loop.symlink_to(loop)
    for command in (["tables"], ["status"]):
        assert_clean_error(run_cli("-w", str(wh.root), *command), mentions=f"{loop}: cannot list its files: ")
    loop.unlink()
    shutil.rmtree(wh.root / "_locks")
    (wh.root / "_locks").write_text("not a folder")
    assert_clean_error(run_cli("-w", str(wh.root), "compact"), mentions=f"{wh.root / '_locks'}")


def test_row_counts_list_again_when_a_file_goes_while_they_are_read(tmp_path):
    """`cadestate tables` while the pipeline writes: a file listed, then swapped away (its partition
    rewritten) before its footer was read, failed the command ("No files found that match")."""
    from warehouse.catalog import row_counts

    wh = Warehouse(tmp_path / "w")
    clips = [f"c{i}" for i in range(40)]
    for c in clips:
        wh.write("clips", c, table_rows("clips", [{"clip": c, "video_sha256": "v" * 64, "split": "train"}]))
    stop = threading.Event()

    def rewrite() -> None:  # another process's runs, rewriting the clips one after another
        writer = Warehouse(tmp_path / "w")
        k = 0
        while not stop.is_set():
            c = clips[k % len(clips)]
            writer.write("clips", c, table_rows("clips", [{"clip": c, "video_sha256": "v" * 64, "split": "val"}]))
            k += 1
            stop.wait(0.01)  # 100 writes a second: far more than the pipeline's

    thread = threading.Thread(target=rewrite)
    thread.start()
    try:
        counts = [row_counts(wh)["clips"] for _ in range(25)]
    finally:
        stop.set()
        thread.join()
    assert counts == [40] * 25
