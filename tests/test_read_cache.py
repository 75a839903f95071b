"""The read cache file by file: a read opens only the files it has not seen, a file this process
wrote is kept as written, and every cached read equals an uncached one (warehouse.read_cache)."""

from __future__ import annotations

import datetime as dt
import os

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from tests.test_warehouse import clip_rows, run_rows
from warehouse import Warehouse
from warehouse.read_cache import ReadCache
from warehouse.store import data_files


@pytest.fixture
def opened(monkeypatch) -> list[str]:
    """The paths of the Parquet files the warehouse opens from now on."""
    paths: list[str] = []
    real = pq.ParquetFile

    def counting(source, *args, **kwargs):
        paths.append(os.path.basename(str(source)))
        return real(source, *args, **kwargs)

    monkeypatch.setattr(pq, "ParquetFile", counting)
    return paths


def names(wh: Warehouse, table: str, part: str) -> list[str]:
    return [os.path.basename(f) for f in wh.file_paths(table, [part])]


def test_a_read_opens_only_the_files_it_has_not_read(wh, opened):
    wh.write("runs", "a", run_rows("a", 2))
    wh.write("runs", "a", run_rows("a", 3, "frames"))
    cached = Warehouse(wh.root).cache_reads(cache=ReadCache())
    assert cached.read("runs", ["a"]).num_rows == 5 and sorted(opened) == sorted(names(wh, "runs", "a"))
    wh.write("runs", "a", run_rows("a", 1, "detect"))  # another process's write
    new = sorted(set(names(wh, "runs", "a")) - set(opened))
    opened.clear()
    got = cached.read("runs", ["a"])
    assert opened == new  # the two files read before come from the cache
    assert got.equals(Warehouse(wh.root).read("runs", ["a"]))


def test_a_file_written_through_the_cache_is_not_opened_and_reads_as_an_uncached_read(wh, opened):
    """Append-mode (runs) and replace-mode (clips: a list column, UTC timestamps) tables."""
    cached = Warehouse(wh.root).cache_reads(cache=ReadCache())
    cached.write("runs", "a", run_rows("a", 3))
    cached.write("clips", "a", clip_rows("a", 2))
    cached.write("clips", "a", clip_rows("a", 4))  # swapped in whole: the new file is kept, the old one gone
    runs, clips = cached.read("runs", ["a"]), cached.read("clips", ["a"])
    subset = cached.read("clips", ["a"], columns=["up_rotation", "ingested_at"])  # cut from the whole file kept
    assert opened == []
    plain = Warehouse(wh.root)
    assert runs.equals(plain.read("runs", ["a"])) and clips.equals(plain.read("clips", ["a"]))
    assert subset.equals(plain.read("clips", ["a"], columns=["up_rotation", "ingested_at"]))
    assert clips.column("num_cameras").to_pylist() == [4]
    [path] = cached.file_paths("clips", ["a"])
    schema = pa.schema([plain.spec("clips").schema.field(n) for n in ("up_rotation", "ingested_at")])
    cut = cached._cache.get_file(path, schema)
    assert cut.equals(subset) and cached._cache.get_file(path, schema) is cut  # the cut is kept, not made again


@pytest.mark.parametrize("filters", [
    [("rows_written", ">=", 2)],
    [("stage", "=", "frames"), ("rows_written", "in", [0, 2])],
    [[("stage", "=", "detect")], [("rows_written", "<", 1)]],  # or
])
def test_filtered_reads_from_the_cache_equal_the_dataset_reads(wh, opened, filters):
    for stage, n in (("ingest", 3), ("frames", 4), ("detect", 2)):
        wh.write("runs", "a", run_rows("a", n, stage))
    cached = Warehouse(wh.root).cache_reads(cache=ReadCache())
    cached.read("runs", ["a"])
    opened.clear()
    got = cached.read("runs", ["a"], filters=filters, columns=["stage", "rows_written"])
    assert opened == []
    want = Warehouse(wh.root).read("runs", ["a"], filters=filters, columns=["stage", "rows_written"])
    assert got.equals(want) and got.num_rows > 0


def test_the_store_never_shows_a_path_twice_so_a_cache_keyed_by_paths_stays_right(wh):
    """The cache keys files by path alone: every write, replace and compaction shows new names, and
    a cached read after each equals an uncached one."""
    cached, plain, seen = Warehouse(wh.root).cache_reads(cache=ReadCache()), Warehouse(wh.root), set()

    def wrote(table: str, rows=None) -> None:
        if rows is None:
            plain.compact(table, "a")
        else:
            plain.write(table, "a", rows)
        paths = set(plain.file_paths(table, ["a"]))
        assert paths - seen  # a new name for what was written
        seen.update(paths)
        assert cached.read(table, ["a"]).equals(plain.read(table, ["a"]))

    for n in (2, 3):
        wrote("runs", run_rows("a", n))
        wrote("clips", clip_rows("a", n))  # replace-mode: swapped in whole
    wrote("runs")  # compacted


def test_files_kept_are_bounded_in_bytes(wh, opened):
    for i in range(4):
        wh.write("runs", "a", run_rows("a", 50, f"s{i}"))
    for file_bytes, opened_again in ((1, 4), (2**20, 0)):  # room for one file (each read evicts the next), for all
        cached = Warehouse(wh.root).cache_reads(cache=ReadCache(entries=0, file_bytes=file_bytes))
        cached.read("runs", ["a"])
        opened.clear()
        cached.read("runs", ["a"])
        assert len(opened) == opened_again


def test_read_results_kept_are_bounded_in_bytes_too(wh):
    """A long-lived process whose stages read large tables through the cache (the annotation app)."""
    wh.write("runs", "a", run_rows("a", 50))
    small, tight = ReadCache(), ReadCache(file_bytes=1)
    cached = Warehouse(wh.root).cache_reads(cache=small)
    assert cached.read("runs", ["a"]) is cached.read("runs", ["a"])
    cached.cache_reads(cache=tight)
    assert cached.read("runs", ["a"]) is not cached.read("runs", ["a"])  # larger than the bound: not kept
    assert cached.read("runs", ["a"]).equals(Warehouse(wh.root).read("runs", ["a"]))


def test_runs_read_through_a_cache_equal_the_duckdb_read(wh):
    """tasks.status.read_runs: DuckDB for a command, the cache in a long-lived process; the same rows."""
    from tasks.status import read_runs

    for stage, n in (("ingest", 2), ("frames", 3)):  # run ids unique, as a run's are
        rows = run_rows("a", n, stage)
        wh.write("runs", "a", rows.set_column(1, "run_id", pa.array([f"{stage}-{i}" for i in range(n)])))
    wh.write("runs", "b", run_rows("b", 1))
    cached = Warehouse(wh.root).cache_reads(cache=ReadCache())
    for names_ in (["a"], ["a", "b", "nope"], None):
        assert read_runs(cached, names_) == read_runs(Warehouse(wh.root), names_)
    assert read_runs(cached, ["a"])[0]["started_at"].tzinfo is not None


def test_data_files_lists_parquet_files_sorted_and_nothing_for_a_missing_folder(tmp_path):
    for name in ("b.parquet", "a.parquet", ".x1.tmp", "notes.txt"):
        (tmp_path / name).write_bytes(b"")
    assert [os.path.basename(f) for f in data_files(tmp_path)] == ["a.parquet", "b.parquet"]
    assert data_files(tmp_path / "missing") == [] and data_files(tmp_path / "a.parquet") == []


def test_a_run_marker_is_written_whole_without_forcing_it_to_disk(wh, monkeypatch):
    """A marker (tasks.stage) a power loss may take back: atomic, no fsync (about 1 ms each)."""
    from tasks.stage import _start_marker, run_markers

    synced: list[int] = []
    monkeypatch.setattr(os, "fsync", lambda fd: synced.append(fd))
    _start_marker(wh, "a", "frames", "r1", dt.datetime(2026, 1, 1, tzinfo=dt.timezone.utc))
    assert synced == [] and [m.stage for m in run_markers(wh, "a")] == ["frames"]
