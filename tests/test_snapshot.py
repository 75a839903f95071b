"""The catalog's snapshot (warehouse.snapshot): a view over its snapshot and the newer files answers
exactly as the files alone, through replaced, emptied, new and compacted partitions, a schema
change, a moved warehouse, older file names, and `cadestate sql`'s locked-down session."""

from __future__ import annotations

import json
import shutil
import time

import duckdb
import pyarrow as pa
import pytest

from conftest import table_rows
from fuzz.harness import run_cli
from warehouse import Warehouse, connect
from warehouse import snapshot as snap
from warehouse.catalog import CATALOG_FILE, VIEWS_MACRO, snapshot_lock, take_snapshots
from warehouse.store import LEGACY_FILE


@pytest.fixture(autouse=True)
def no_margin(monkeypatch):
    """Files written a moment ago count as settled (the default margin is a minute)."""
    monkeypatch.setattr(snap, "MARGIN_NS", 0)


def tracks(clip: str, n: int, label: str = "chair") -> pa.Table:
    return table_rows("tracks", [{"clip": clip, "track_id": i, "label": label} for i in range(n)])


def runs(clip: str, *ids: str) -> pa.Table:
    return table_rows("runs", [{"clip": clip, "run_id": i, "stage": "ingest"} for i in ids])


def through_view(wh: Warehouse, sql: str) -> list[tuple]:
    con = connect(wh)
    try:
        return con.execute(sql).fetchall()
    finally:
        con.close()


def through_files(wh: Warehouse, table: str, sql: str) -> list[tuple]:
    """``sql`` over a view of ``table``'s files alone (no snapshot): what the catalog must answer."""
    con = duckdb.connect()
    files = [str(f) for f in wh.files(table)]
    con.execute(f"CREATE VIEW {table} AS SELECT * FROM read_parquet({files!r})" if files else
                f"CREATE VIEW {table} AS SELECT * FROM read_parquet('{wh.table_dir(table)}/_schema/_schema.parquet')")
    return con.execute(sql).fetchall()


def snapshot(wh: Warehouse) -> list[str]:
    with snapshot_lock(wh):
        return take_snapshots(wh)


def marks(wh: Warehouse) -> dict:
    con = duckdb.connect(str(wh.root / CATALOG_FILE), read_only=True)
    try:
        return {n: t["snapshot"] for n, t in json.loads(con.execute(f"SELECT {VIEWS_MACRO}()").fetchone()[0])["tables"].items()}
    finally:
        con.close()


def snapshot_rows(wh: Warehouse, table: str) -> int:
    con = duckdb.connect(str(wh.root / CATALOG_FILE), read_only=True)
    try:
        return con.execute(f"SELECT count(*) FROM snapshot.{table}").fetchone()[0]
    finally:
        con.close()


TRACKS = "SELECT clip, label, count(*) FROM tracks GROUP BY ALL ORDER BY ALL"
RUNS = "SELECT clip, run_id FROM runs ORDER BY ALL"


def test_a_view_over_its_snapshot_answers_as_the_files_through_every_kind_of_write(wh):
    wh.write("tracks", "a", tracks("a", 3))
    wh.write("tracks", "b", tracks("b", 2))
    for i in range(3):
        wh.write("runs", "a", runs("a", f"r{i}"))
    kept = snapshot(wh)
    assert "tracks" in kept and "runs" in kept and "embeddings" not in kept  # descriptors are not copied
    assert snapshot_rows(wh, "tracks") == 5 and snapshot_rows(wh, "runs") == 3
    assert through_view(wh, TRACKS) == through_files(wh, "tracks", TRACKS) == [("a", "chair", 3), ("b", "chair", 2)]

    wh.write("tracks", "a", tracks("a", 1, "sofa"))  # replaced
    wh.write("tracks", "b", tracks("b", 0))  # emptied
    wh.write("tracks", "c", tracks("c", 4))  # new
    wh.write("runs", "a", runs("a", "r3"))  # appended
    wh.compact("runs", "a")  # merged: the snapshot's files of a are gone, their rows in a newer file
    assert through_view(wh, TRACKS) == through_files(wh, "tracks", TRACKS) == [("a", "sofa", 1), ("c", "chair", 4)]
    assert through_view(wh, RUNS) == through_files(wh, "runs", RUNS) == [("a", f"r{i}") for i in range(4)]

    before = marks(wh)["tracks"]
    time.sleep(0.01)
    snapshot(wh)  # the next one starts from the last
    assert marks(wh)["tracks"] > before
    assert snapshot_rows(wh, "tracks") == 5 and snapshot_rows(wh, "runs") == 4
    assert through_view(wh, TRACKS) == [("a", "sofa", 1), ("c", "chair", 4)]
    assert through_view(wh, RUNS) == [("a", f"r{i}") for i in range(4)]


def test_files_newer_than_the_watermark_are_read_from_themselves(wh, monkeypatch):
    wh.write("tracks", "a", tracks("a", 3))
    monkeypatch.setattr(snap, "MARGIN_NS", 3600 * 10**9)  # an hour: the file is too young to be copied
    snapshot(wh)
    assert snapshot_rows(wh, "tracks") == 0
    assert through_view(wh, TRACKS) == [("a", "chair", 3)]


def test_a_file_named_in_the_past_is_caught_by_the_next_snapshot(wh, monkeypatch):
    """A file that appears under a name older than the last snapshot's watermark (a writer's clock
    behind, or a backup copied back into a partition) is missed by the view until the next
    snapshot, which reads the files named before its last watermark that the last one lacks (it
    was missed by every snapshot but one from the files alone, `compact --whole`)."""
    wh.write("tracks", "a", tracks("a", 3))
    snapshot(wh)
    (late,) = wh.files("tracks", ["a"])
    wh.write("tracks", "b", tracks("b", 2))
    (b,) = wh.files("tracks", ["b"])
    past = f"{int(late.name[:20]) - 120 * 10**9:020d}"  # named two minutes before: a writer's clock behind
    b.rename(b.with_name(past + b.name[20:]))
    assert through_view(wh, TRACKS) == [("a", "chair", 3)]  # older than the watermark, and not in the snapshot
    snapshot(wh)
    assert through_view(wh, TRACKS) == through_files(wh, "tracks", TRACKS) == [("a", "chair", 3), ("b", "chair", 2)]
    restored = wh.partition_dir("tracks", "c")  # a partition restored from a backup taken before
    shutil.copytree(wh.partition_dir("tracks", "b"), restored)  # its file under its old name (its rows say b: counts only)
    snapshot(wh)
    assert snapshot_rows(wh, "tracks") == 7
    assert through_view(wh, "SELECT count(*) FROM tracks") == [(7,)]
    result = run_cli("-w", str(wh.root), "compact", "--whole")
    assert result.code == 0 and through_view(wh, "SELECT count(*) FROM tracks") == [(7,)], result.stderr


def test_a_watermark_never_goes_back_from_the_last_snapshot(wh, monkeypatch):
    wh.write("tracks", "a", tracks("a", 3))
    snapshot(wh)
    before = marks(wh)["tracks"]
    monkeypatch.setattr(snap, "MARGIN_NS", 3600 * 10**9)  # as if the clock went back an hour
    snapshot(wh)
    assert marks(wh)["tracks"] == before
    assert through_view(wh, TRACKS) == [("a", "chair", 3)]  # not read twice (snapshot and file)


def test_a_rebuild_racing_a_snapshot_copies_the_snapshot_of_the_watermark_it_records(wh, monkeypatch):
    """A catalog rebuild (any command's, after a schema change) while another process takes a
    snapshot: the rebuild must copy the snapshot of the catalog whose watermark it records, or the
    files named between the two watermarks are read twice (from the new snapshot and from themselves)."""
    from warehouse import catalog

    wh.write("tracks", "a", tracks("a", 3))
    snapshot(wh)
    wh.write("tracks", "b", tracks("b", 2))
    plan_views, raced = catalog.plan_views, []

    def then_another_process_snapshots(*args, **kwargs):
        plan = plan_views(*args, **kwargs)
        if not raced:  # the rebuild has read the catalog's watermarks; the other process replaces the catalog now
            raced.append(True)
            snapshot(wh)
        return plan

    monkeypatch.setattr(catalog, "plan_views", then_another_process_snapshots)
    catalog.refresh_catalog(wh)
    assert raced and through_view(wh, TRACKS) == [("a", "chair", 3), ("b", "chair", 2)]
    assert not list(wh.root.glob(".*.pin"))


def test_a_schema_change_drops_that_tables_snapshot_only_and_a_moved_warehouse_keeps_them(wh, tmp_path):
    wh.write("tracks", "a", tracks("a", 3))
    wh.write("runs", "a", runs("a", "r0"))
    snapshot(wh)
    con = duckdb.connect(str(wh.root / CATALOG_FILE))
    record = json.loads(con.execute(f"SELECT {VIEWS_MACRO}()").fetchone()[0])
    record["tables"]["runs"]["schema"] = "an older schema"
    quoted = json.dumps(record).replace("'", "''")
    con.execute(f"CREATE OR REPLACE MACRO {VIEWS_MACRO}() AS '{quoted}'")
    con.close()
    moved = Warehouse(shutil.copytree(wh.root, tmp_path / "moved"))
    assert through_view(moved, TRACKS) == [("a", "chair", 3)]  # rebuilt for its new root
    assert marks(moved)["runs"] is None and marks(moved)["tracks"] is not None
    assert snapshot_rows(moved, "tracks") == 3
    assert through_view(moved, RUNS) == [("a", "r0")]
    moved.write("tracks", "a", tracks("a", 1))
    assert through_view(moved, TRACKS) == [("a", "chair", 1)] and through_view(wh, TRACKS) == [("a", "chair", 3)]


def test_a_client_holding_the_catalog_open_read_write_costs_no_snapshot(wh, monkeypatch):
    """`duckdb catalog.duckdb` (any client may open it, the catalog's module says) holds it open
    read-write: DuckDB then refuses even a read-only open, and the next write's check and `sql`
    took the catalog for unreadable and rebuilt it from nothing: every snapshot lost, every table's
    footers read again. Its record and snapshots are read from a copy now."""
    import subprocess
    import sys

    from warehouse import catalog

    wh.write("tracks", "a", tracks("a", 3))
    wh.write("runs", "a", runs("a", "r0"))
    snapshot(wh)
    before = marks(wh)
    assert before["runs"] and before["tracks"]
    client = subprocess.Popen([sys.executable, "-c", "import duckdb, sys; c = duckdb.connect(sys.argv[1]); "
                               "print('open', flush=True); sys.stdin.read()", str(wh.root / CATALOG_FILE)],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    checked = []
    monkeypatch.setattr(catalog, "uniform", lambda w, table: checked.append(table) or True)
    try:
        assert client.stdout.readline() == "open\n"
        catalog._ENSURED.clear()
        Warehouse(wh.root).write("runs", "b", runs("b", "r1"))  # a new process's first write checks the catalog
        assert through_view(wh, RUNS) == [("a", "r0"), ("b", "r1")]
    finally:
        client.stdin.close()
        client.wait(60)
    assert marks(wh) == before and snapshot_rows(wh, "tracks") == 3 and checked == []
    assert not list(wh.root.glob(f".{CATALOG_FILE}.*"))  # no copy left


def test_files_of_an_older_layout_are_renamed_and_read_once(wh):
    wh.write("tracks", "a", tracks("a", 3))
    (only,) = wh.files("tracks", ["a"])
    only.rename(only.with_name(LEGACY_FILE))  # as a replace-mode file was named before
    snapshot(wh)  # before the rename: a legacy name sorts after every watermark, read as a new file
    assert through_view(wh, TRACKS) == [("a", "chair", 3)]
    schema_file = wh.table_dir("tracks") / "_schema" / "_schema.parquet"
    schema_file.rename(wh.table_dir("tracks") / "_schema.parquet")  # where an older layout kept it
    result = run_cli("-w", str(wh.root), "compact")
    assert result.code == 0, result.stderr
    assert "tracks: 1 file(s) renamed to this version's layout" in result.stdout.splitlines()
    assert [f.name for f in wh.files("tracks", ["a"])] != [LEGACY_FILE]
    assert schema_file.is_file() and not (wh.table_dir("tracks") / "_schema.parquet").exists()
    assert snapshot_rows(wh, "tracks") == 3 and through_view(wh, TRACKS) == [("a", "chair", 3)]


def test_sql_reads_a_snapshot_in_its_locked_down_session(wh):
    wh.write("tracks", "a", tracks("a", 2))
    snapshot(wh)
    wh.write("tracks", "b", tracks("b", 1))
    result = run_cli("-w", str(wh.root), "sql", TRACKS, "-f", "csv")
    assert result.code == 0, result.stderr
    assert result.stdout.splitlines()[1:] == ["a,chair,2", "b,chair,1"]
    refused = run_cli("-w", str(wh.root), "sql", "SELECT * FROM glob('/etc/*')")
    assert refused.code != 0 and "passwd" not in refused.stdout


def test_every_table_of_a_synthetic_warehouse_answers_the_same_through_its_snapshot(tmp_path):
    from bench.warehouse_scale import build, clip_name

    wh = Warehouse(tmp_path / "w")
    build(wh.root, 24)
    some = wh.info["tracks"]
    assert some.mode == "replace"
    snapshot(wh)
    wh.write("tracks", clip_name(3), wh.read("tracks", [clip_name(3)]).slice(0, 2))  # a partition rewritten
    wh.write("runs", clip_name(5), wh.read("runs", [clip_name(5)]).slice(0, 1))  # and one appended to
    for table in wh.info:
        columns = [c for c in wh.spec(table).schema.names if c not in ("vector", "points", "projection", "mean")]
        sql = f"SELECT {', '.join(columns)} FROM {table} ORDER BY ALL"
        assert through_view(wh, sql) == through_files(wh, table, sql), table
    assert snapshot_rows(wh, "frames") == 24 * 30


def test_the_half_built_catalogs_and_pins_of_killed_rebuilds_are_removed_an_hour_on(wh):
    """A rebuild killed mid-way (kill -9 of `cadestate compact`) leaves its half-built catalog, its
    write-ahead log and its pin beside the catalog: the next rebuild removes them once an hour old
    (a live rebuild's are younger), and nothing else."""
    import os

    from warehouse import catalog

    wh.write("tracks", "a", tracks("a", 3))
    snapshot(wh)
    left = [wh.root / f".{CATALOG_FILE}.{'0' * 32}{end}" for end in (".tmp", ".tmp.wal", ".pin")]
    young = wh.root / f".{CATALOG_FILE}.{'1' * 32}.tmp"
    mine = wh.root / f".{CATALOG_FILE}.notes"
    for f in [*left, young, mine]:
        f.write_bytes(b"x")
    for f in [*left, mine]:
        os.utime(f, (time.time() - catalog.STALE_S - 60,) * 2)
    catalog.refresh_catalog(wh)
    assert sorted(p.name for p in wh.root.glob(f".{CATALOG_FILE}.*")) == sorted([young.name, mine.name])
    assert through_view(wh, TRACKS) == [("a", "chair", 3)]


def test_a_live_pin_of_a_catalog_built_long_ago_is_not_removed_by_another_rebuild(wh):
    """A pin is a hard link to the catalog, so it has the catalog's modification time: with the
    catalog built over an hour before, a rebuild running beside a compaction took the compaction's
    live pin for a killed one's and removed it (the compaction then failed: "database does not
    exist"). A pin's age is now the time in its name."""
    import os

    from warehouse import catalog

    wh.write("tracks", "a", tracks("a", 3))
    snapshot(wh)
    final = wh.root / CATALOG_FILE
    os.utime(final, (time.time() - catalog.STALE_S - 60,) * 2)
    with catalog._pinned(final) as pin:
        assert pin != final and os.path.samefile(pin, final)
        catalog.refresh_catalog(wh, recheck=True)  # another process's rebuild, meanwhile
        assert pin.exists()
    assert not pin.exists()
