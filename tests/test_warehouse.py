"""Warehouse: schema checks, atomic and idempotent writes, filtered reads, the DuckDB catalog."""

from __future__ import annotations

import datetime as dt
import multiprocessing as mp
import os
import shutil
import signal
import subprocess
import sys
import time

import duckdb
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from schemas import TableSpec
from warehouse import Warehouse, WarehouseError, check_name, connect, refresh_catalog, store
from warehouse.catalog import CATALOG_FILE, ROOT_MACRO, VIEWS_MACRO, schema_path, view_sql


def run_rows(clip: str, n: int, stage: str = "ingest") -> pa.Table:
    now = dt.datetime(2026, 1, 1, tzinfo=dt.timezone.utc)
    return pa.Table.from_pylist([
        {"clip": clip, "run_id": f"r{i}", "stage": stage, "status": "completed", "config_hash": "c",
         "inputs_hash": "i", "output_hash": "o", "code_hash": "k", "started_at": now,
         "duration_s": float(i), "rows_written": i, "message": ""}
        for i in range(n)
    ])


def clip_rows(clip: str, marker: int = 0, n: int = 1) -> pa.Table:
    return pa.Table.from_pylist([
        {"clip": clip, "url": f"u{marker}-{i}", "source_video": "v", "source_cameras": "c", "video_path": "p",
         "cameras_path": "q", "video_sha256": "s", "cameras_sha256": "t", "num_cameras": marker,
         "first_timestamp_us": i, "last_timestamp_us": 1, "width": 2, "height": 3, "fps": 30.0,
         "duration_us": 4, "codec": "h264", "ingested_at": dt.datetime(2026, 1, 1, tzinfo=dt.timezone.utc), "split": "train",
         "time_offset_us": 0, "cameras_source": "file", "up_rotation": [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0],
         "up_source": "auto", "up_note": "", "up_line_segments": 0}
        for i in range(n)
    ])


def test_replace_write_is_idempotent_and_partitioned(wh):
    assert wh.write("clips", "a", clip_rows("a", 1)) == 1
    wh.write("clips", "b", clip_rows("b", 2))
    wh.write("clips", "a", clip_rows("a", 1))  # same data again
    assert len(wh.files("clips", ["a"])) == 1
    assert wh.read("clips").column("num_cameras").to_pylist() == [1, 2]
    wh.write("clips", "a", clip_rows("a", 5))  # replace touches only partition a
    assert wh.read("clips").column("num_cameras").to_pylist() == [5, 2]
    assert wh.partitions("clips") == ["a", "b"]


def test_a_killed_writers_staging_folders_are_swept(wh):
    """A process killed mid-write leaves its folder in _staging/ (a swap's, or media being made):
    a later swap removes it once it has gone untouched for a day; a live write's stays."""
    staged = wh.root / "_staging"
    (staged / "swap-killed").mkdir(parents=True)
    (staged / "media-killed").mkdir()
    wh.write("clips", "a", clip_rows("a", 1))
    assert sorted(p.name for p in staged.iterdir()) == ["media-killed", "swap-killed"]
    wh._sweep_staging(now=time.time() + 3600)
    assert sorted(p.name for p in staged.iterdir()) == ["media-killed", "swap-killed"]
    wh._sweep_staging(now=time.time() + store.STALE_STAGING_S + 1)
    assert list(staged.iterdir()) == [] and wh.read("clips").column("num_cameras").to_pylist() == [1]


def test_a_read_whose_listing_a_write_overtook_lists_that_partition_again(wh):
    """A whole-table read while a batch writes: files listed, then one partition swapped before its
    file is opened. Only that partition is listed again; the read answers with the new rows."""
    for clip in ("a", "b", "c"):
        wh.write("clips", clip, clip_rows(clip, 1))
    listed = wh.file_paths("clips")
    wh.write("clips", "b", clip_rows("b", 7))
    rows = store._read_listed(listed, wh.spec("clips").schema, ["clip", "num_cameras"])
    assert sorted(zip(rows.column("clip").to_pylist(), rows.column("num_cameras").to_pylist())) == [("a", 1), ("b", 7), ("c", 1)]


def test_append_mode_keeps_history(wh):
    wh.write("runs", "a", run_rows("a", 2))
    wh.write("runs", "a", run_rows("a", 3))
    assert wh.read("runs").num_rows == 5 and len(wh.files("runs")) == 2


def test_a_damaged_table_file_is_named_in_one_line(wh, tmp_path):
    """A table file cut short (a disk full, a copy interrupted) was a pyarrow traceback in every
    reader that reads tables through the warehouse (the exports' datasets, the stages, the annotation
    app); a WarehouseError is one line naming the file (the CLI's input errors)."""
    wh.write("clips", "a", clip_rows("a"))
    [f] = wh.files("clips", ["a"])
    with open(f, "r+b") as damaged:
        damaged.truncate(os.path.getsize(f) // 2)
    with pytest.raises(WarehouseError, match=f"^{f}: damaged table file \\(.*\\): restore it from a backup"):
        wh.read("clips")


def test_read_filters_columns_and_clips(wh):
    wh.write("runs", "a", run_rows("a", 4, "ingest"))
    wh.write("runs", "b", run_rows("b", 3, "frames"))
    assert wh.read("runs", partitions=["b"]).num_rows == 3
    got = wh.read("runs", filters=[("rows_written", ">=", 2)], columns=["clip", "rows_written"])
    assert got.column_names == ["clip", "rows_written"]
    assert sorted(got.column("rows_written").to_pylist()) == [2, 2, 3]
    assert wh.read("frames").num_rows == 0 and wh.read("frames").schema == wh.spec("frames").schema
    assert sorted(wh.read("runs", columns=["stage"]).column("stage").to_pylist()) == ["frames"] * 3 + ["ingest"] * 4


def test_cached_reads_follow_every_write_compaction_and_replacement(wh):
    """Warehouse.cache_reads: a read is given again only while its files are the same files."""
    from cadestate.lineage import recording_reads

    wh.cache_reads(entries=8)
    wh.write("runs", "a", run_rows("a", 2))
    first = wh.read("runs", ["a"])
    assert wh.read("runs", ["a"]) is first  # kept
    with recording_reads() as noted:
        wh.read("runs", ["a"])
    assert noted == [("files", "runs", "a")]  # a kept read is noted as a read (tasks.inputs_memo)
    wh.write("runs", "a", run_rows("a", 3))  # appended
    assert wh.read("runs", ["a"]).num_rows == 5
    filtered = wh.read("runs", ["a"], filters=[("rows_written", ">=", 2)])
    assert filtered.num_rows == 1 and wh.read("runs", ["a"], filters=[("rows_written", ">=", 2)]) is filtered
    assert wh.read("runs", ["a"], filters=[("rows_written", ">=", 1)]).num_rows == 3  # another filter, another read
    assert wh.compact("runs", "a") is not None
    assert sorted(wh.read("runs", ["a"]).column("duration_s").to_pylist()) == [0.0, 0.0, 1.0, 1.0, 2.0]
    wh.write("clips", "a", clip_rows("a", 1))
    wh.read("clips", ["a"])
    wh.write("clips", "a", clip_rows("a", 2))  # replaced
    assert wh.read("clips", ["a"]).column("num_cameras").to_pylist() == [2]
    within = wh.read("runs", ["a"], filters=[("rows_written", "in", [1, 2])])
    assert within.num_rows == 3 and wh.read("runs", ["a"], filters=[("rows_written", "in", [1, 2])]) is within
    assert wh.read("runs", ["a"], filters=[("rows_written", "in", [2])]).num_rows == 1
    wh.cache_reads(0)
    assert wh.read("clips", ["a"]) is not wh.read("clips", ["a"])  # off: read every time


def test_a_read_cache_outlives_the_warehouse_object_that_filled_it(wh):
    """run_unit(read_cache=...): the annotation app's worker keeps one cache from one resume to the next."""
    from warehouse import Warehouse
    from warehouse.read_cache import ReadCache

    cache = ReadCache(8)
    wh.write("runs", "a", run_rows("a", 2))
    first = Warehouse(wh.root).cache_reads(cache=cache).read("runs", ["a"])
    assert Warehouse(wh.root).cache_reads(cache=cache).read("runs", ["a"]) is first
    wh.write("runs", "a", run_rows("a", 1))
    assert Warehouse(wh.root).cache_reads(cache=cache).read("runs", ["a"]).num_rows == 3


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda t: t.drop_columns(["url"]), "missing columns ['url']"),
        (lambda t: t.append_column("extra", pa.array([1])), "unexpected columns ['extra']"),
        (lambda t: t.set_column(0, "clip", pa.array(["other"])), "must have clip = 'a'"),
        (lambda t: t.set_column(1, "url", pa.array([None], pa.string())), "column 'url' has nulls"),
        (lambda t: t.set_column(8, "num_cameras", pa.array(["x"])), "column 'num_cameras' is string, not int"),
        (lambda t: t.set_column(8, "num_cameras", pa.array(["42"])), "column 'num_cameras' is string, not int"),
        (lambda t: t.set_column(16, "ingested_at", pa.array([1764979200])), "column 'ingested_at' is int64, not timestamp"),
        (lambda t: t.set_column(1, "url", pa.array([7])), "column 'url' is int64, not string"),
        (lambda t: t.set_column(8, "num_cameras", pa.array([2**40])), "does not fit the schema"),  # int64 to int32
        (lambda t: pa.concat_tables([t, t]), "duplicate key {'clip': 'a'}"),
    ],
)
def test_write_rejects_data_that_does_not_fit(wh, mutate, message):
    wh.write("clips", "a", clip_rows("a", 1))
    with pytest.raises(WarehouseError) as e:
        wh.write("clips", "a", mutate(clip_rows("a", 7)))
    assert message in str(e.value)
    assert wh.read("clips").column("num_cameras").to_pylist() == [1]  # previous state intact


@pytest.mark.parametrize("name", ["", "../x", "a/b", ".hidden", "-", "--", "-.", "a b", "x" * 201])
def test_clip_names_that_are_not_safe_folder_names_are_rejected(name):
    with pytest.raises(WarehouseError, match="invalid clip name"):
        check_name(name)


def test_a_partition_name_no_folder_can_have_has_no_data(wh):
    wh.write("clips", "a", clip_rows("a", 1))
    assert wh.has_partition("clips", "a") and not wh.has_partition("clips", "b")
    assert not any(wh.has_partition("clips", name) for name in ("", "../a", "a/b", ".a", None))


def test_unknown_table(wh):
    """One line: the nearest name, and where all are (every table was listed: 500 characters)."""
    with pytest.raises(WarehouseError, match=r"^unknown table 'nope': `cadestate tables` lists the \d+ tables$"):
        wh.read("nope")
    with pytest.raises(WarehouseError, match=r"^unknown table 'frame' \(did you mean 'frames'\?\): `cadestate tables` lists"):
        wh.compact_tables(["frame"])


@pytest.mark.parametrize("small_bytes", [store.SMALL_TABLE_BYTES, 0], ids=["encoded-in-memory", "written-to-file"])
def test_failure_mid_write_leaves_previous_state(wh, monkeypatch, small_bytes):
    wh.write("clips", "a", clip_rows("a", 1))

    def broken_write(table, where, **kwargs):
        if isinstance(where, (str, os.PathLike)):
            with open(where, "wb") as f:
                f.write(b"PAR1 half a file")
        else:  # a small table is encoded in memory, into an open temporary file
            where.write(b"PAR1 half a file")
        raise OSError("disk full (injected)")

    monkeypatch.setattr(store, "SMALL_TABLE_BYTES", small_bytes)
    monkeypatch.setattr(pq, "write_table", broken_write)
    with pytest.raises(OSError, match="injected"):
        wh.write("clips", "a", clip_rows("a", 2))
    monkeypatch.undo()
    assert wh.read("clips").column("num_cameras").to_pylist() == [1]
    before = [p.name for p in wh.partition_dir("clips", "a").iterdir()]
    assert len(before) == 1 and before[0].endswith(".parquet")  # the first write's file, and no temporary one
    assert not any((wh.root / "_staging").iterdir())


def test_small_tables_are_written_uncompressed_and_large_ones_with_zstd(tmp_path):
    wh = Warehouse(tmp_path / "w", {"numbers": NUMBERS})
    small, large = numbers(1, 10), numbers(2, 20_000)
    assert small.nbytes < store.SMALL_TABLE_BYTES <= large.nbytes
    for part, table in (("a", small), ("b", large)):
        table = table.set_column(0, "clip", pa.array([part] * table.num_rows))
        wh.write("numbers", part, table)
        assert wh.read("numbers", [part]).equals(table.cast(NUMBERS.schema))
    codec = {p: pq.ParquetFile(wh.files("numbers", [p])[0]).metadata.row_group(0).column(0).compression for p in "ab"}
    assert codec == {"a": "UNCOMPRESSED", "b": "ZSTD"}


NUMBERS = TableSpec(
    name="numbers", mode="replace", key=("clip", "i"), description="test table",
    schema=pa.schema([pa.field("clip", pa.string(), False), pa.field("i", pa.int64(), False), pa.field("marker", pa.int64(), False)]),
)


def numbers(marker: int, n: int = 200_000) -> pa.Table:
    return pa.table({"clip": ["a"] * n, "i": range(n), "marker": [marker] * n})


def _write_forever(root: str, ready) -> None:
    wh = Warehouse(root, {"numbers": NUMBERS})
    ready.set()
    marker = 0
    while True:
        marker += 1
        wh.write("numbers", "a", numbers(marker))


def test_process_killed_mid_write_leaves_a_whole_partition(tmp_path):
    root = tmp_path / "w"
    wh = Warehouse(root, {"numbers": NUMBERS})
    wh.write("numbers", "a", numbers(0))
    ctx = mp.get_context("spawn")
    for delay in (0.9, 1.3, 1.7, 2.1):
        ready = ctx.Event()
        proc = ctx.Process(target=_write_forever, args=(str(root), ready))
        proc.start()
        ready.wait(30)
        time.sleep(delay)
        os.kill(proc.pid, signal.SIGKILL)
        proc.join()
        table = wh.read("numbers")
        # Whatever moment it died, the partition is one complete write (all rows, one marker).
        assert table.num_rows == 200_000
        assert len(set(table.column("marker").to_pylist())) == 1
        con = connect(wh)
        assert con.execute("SELECT count(*), count(DISTINCT marker) FROM numbers").fetchone() == (200_000, 1)
        con.close()


def test_catalog_has_every_table_even_empty_and_follows_writes(wh):
    con = connect(wh)
    for name in wh.tables:
        assert con.execute(f"SELECT count(*) FROM {name}").fetchone() == (0,)
    con.close()
    wh.write("runs", "a", run_rows("a", 3))
    wh.write("runs", "b", run_rows("b", 2, "frames"))
    con = connect(wh)
    assert con.execute("SELECT stage, count(*) FROM runs GROUP BY stage ORDER BY stage").fetchall() == [("frames", 2), ("ingest", 3)]
    with pytest.raises(duckdb.Error):  # opened read-only
        con.execute("CREATE TABLE x (i INT)")
    con.close()


def test_catalog_opens_in_a_plain_duckdb_client(wh):
    wh.write("runs", "a", run_rows("a", 3))
    code = (
        "import duckdb, sys; c = duckdb.connect(sys.argv[1], read_only=True); "
        "print(c.execute('SELECT sum(rows_written) FROM runs').fetchone()[0])"
    )
    out = subprocess.run([sys.executable, "-c", code, str(wh.root / CATALOG_FILE)], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "3"


def test_catalog_leaves_current_schema_files_alone(wh):
    refresh_catalog(wh)
    schemas = {schema_path(wh, t): schema_path(wh, t).stat().st_mtime_ns for t in wh.tables}
    time.sleep(0.01)
    refresh_catalog(wh)
    assert {p: p.stat().st_mtime_ns for p in schemas} == schemas
    schema_path(wh, "runs").write_bytes(b"broken")  # an unreadable one is rewritten
    refresh_catalog(wh)
    assert pq.read_schema(schema_path(wh, "runs")).names == wh.spec("runs").schema.names
    assert wh.partitions("runs") == [] and wh.read("runs").num_rows == 0  # the schema file is no data


def test_a_copied_warehouse_gets_its_own_catalog(wh, tmp_path):
    wh.write("runs", "a", run_rows("a", 3))
    copy = Warehouse(tmp_path / "copy")
    shutil.copytree(wh.root, copy.root)
    wh.write("runs", "a", run_rows("a", 5))
    con = connect(copy)
    assert con.execute(f"SELECT count(*), {ROOT_MACRO}() FROM runs").fetchone() == (3, str(copy.root))
    con.close()


@pytest.mark.parametrize("damage", ["garbage", "truncated", "old"])
def test_a_broken_or_old_catalog_is_rebuilt(wh, damage):
    wh.write("runs", "a", run_rows("a", 3))
    catalog = wh.root / CATALOG_FILE
    if damage == "old":  # a catalog from before warehouse_root(): its views, nothing else
        catalog.unlink()
        con = duckdb.connect(str(catalog))
        con.execute(view_sql(wh, "runs"))
        con.close()
    else:
        catalog.write_bytes(b"not a database" if damage == "garbage" else catalog.read_bytes()[:5000])
    con = connect(wh)
    assert con.execute(f"SELECT count(*), {ROOT_MACRO}() FROM runs").fetchone() == (3, str(wh.root))
    con.close()


def test_a_catalog_that_cannot_be_rebuilt_is_named_in_one_line(wh):
    """To write, that is; to read, views are made in memory (tests/test_catalog.py)."""
    wh.root.mkdir(parents=True)
    (wh.root / CATALOG_FILE).mkdir()
    with pytest.raises(WarehouseError, match=f"cannot rebuild the catalog {wh.root / CATALOG_FILE}: ") as e:
        connect(wh, read_only=False)
    assert "\n" not in str(e.value)


def test_a_streamed_atomic_write_is_whole_or_absent(tmp_path):
    """cadestate.atomic.atomic_writer: the file appears whole when the block ends; a block that
    raises leaves the old file as it was and no temporary file."""
    from cadestate.atomic import atomic_writer

    path = tmp_path / "big.bin"
    with atomic_writer(path) as f:
        f.write(b"first")
        assert not path.exists()  # nothing under the final name while it is written
    assert path.read_bytes() == b"first"
    with pytest.raises(RuntimeError, match="stop"), atomic_writer(path) as f:
        f.write(b"second, half")
        raise RuntimeError("stop")
    assert path.read_bytes() == b"first" and sorted(p.name for p in tmp_path.iterdir()) == ["big.bin"]
