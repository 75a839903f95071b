"""Values kept with the state of the warehouse files they were computed from (warehouse/kept.py):
served while those files stay, computed again as soon as one comes or goes, never stored from
files that changed while they were read, and never in the way of a warehouse that cannot keep them."""

from __future__ import annotations

import os
import time

from conftest import table_rows
from warehouse import Warehouse
from warehouse.catalog import row_counts as counted
from warehouse.kept import SETTLE_NS, KeptInMemory, kept_read, row_counts


def _settle(wh: Warehouse) -> None:
    """Date every table file back past the settling time (as if written a while ago), then wait it
    out: what changed a file's status (a rename, this dating) counts too, and cannot be dated back."""
    old = time.time_ns() - 10 * SETTLE_NS
    for folder, _, names in os.walk(wh.root / "tables"):
        for name in names:
            os.utime(os.path.join(folder, name), ns=(old, old))
    time.sleep(2 * SETTLE_NS / 1e9)


def _clip(wh: Warehouse, name: str, split: str) -> None:
    wh.write("clips", name, table_rows("clips", [{"clip": name, "video_sha256": "v" * 64, "split": split}]))


def test_a_kept_read_serves_while_its_files_stay_and_only_once_settled(tmp_path):
    wh = Warehouse(tmp_path / "w")
    reads = [("files", "clips", "c1")]
    calls = []

    def splits() -> list[str]:
        calls.append(1)
        return [r["split"] for r in wh.read("clips", ["c1"]).to_pylist()]

    _clip(wh, "c1", "train")
    later = time.time_ns() + 10 * SETTLE_NS  # as if written while it was read: not kept
    os.utime(wh.files("clips", ["c1"])[0], ns=(later, later))
    assert kept_read(wh, "splits", reads, splits) == ["train"]
    assert not (wh.root / "_cache" / "reads" / "splits.json").exists()
    _settle(wh)
    assert kept_read(wh, "splits", reads, splits) == kept_read(wh, "splits", reads, splits) == ["train"]
    assert len(calls) == 2  # the third served from what the second kept
    _clip(wh, "c1", "val")  # the partition rewritten: another file
    _settle(wh)
    assert kept_read(wh, "splits", reads, splits) == ["val"] and len(calls) == 3
    (wh.root / "_cache" / "reads" / "splits.json").write_text("{not json")  # damaged: computed again
    assert kept_read(wh, "splits", reads, splits) == ["val"] and len(calls) == 4


def test_a_file_renamed_in_while_a_value_was_computed_is_not_kept_whatever_its_time(tmp_path):
    """A file's time is when its data was written: written, flushed for a while (a loaded disk), then
    renamed into its partition while a value was computed, it looked settled, and the value computed
    without it was kept and served until another file came (`tables` missing a run's rows)."""
    wh = Warehouse(tmp_path / "w")
    _clip(wh, "c1", "train")
    _settle(wh)
    reads = [("files", "clips", "*")]

    def clips_as_another_comes() -> list[str]:
        seen = sorted(wh.partitions("clips"))
        _clip(wh, "c2", "val")  # renamed in just after the listing ...
        old = time.time_ns() - 10 * SETTLE_NS
        os.utime(wh.files("clips", ["c2"])[0], ns=(old, old))  # ... its data written long before
        return seen

    assert kept_read(wh, "clips", reads, clips_as_another_comes) == ["c1"]
    assert kept_read(wh, "clips", reads, lambda: sorted(wh.partitions("clips"))) == ["c1", "c2"]


def test_row_counts_are_kept_until_a_file_of_any_table_comes(tmp_path):
    wh = Warehouse(tmp_path / "w")
    _clip(wh, "c1", "train")
    wh.write("frames", "c1", table_rows("frames", [{"clip": "c1", "timestamp_us": t} for t in (0, 1)]))
    _settle(wh)
    first = row_counts(wh)
    assert first == counted(wh) and first["frames"] == 2 and first["clips"] == 1
    kept = wh.root / "_cache" / "reads" / "row-counts.json"
    kept.write_text(kept.read_text().replace('"frames": 2', '"frames": 7'))
    assert row_counts(wh)["frames"] == 7  # served as kept: no file came
    wh.write("runs", "c1", table_rows("runs", [{"clip": "c1", "stage": "frames", "status": "completed"}]))
    _settle(wh)
    assert row_counts(wh) == counted(wh) == {**first, "runs": 1}


def test_a_warehouse_without_room_to_keep_still_answers(tmp_path):
    wh = Warehouse(tmp_path / "w")
    _clip(wh, "c1", "train")
    _settle(wh)
    (wh.root / "_cache").write_text("not a folder")  # nothing can be kept (as in a read-only warehouse)
    for _ in range(2):
        assert kept_read(wh, "splits", [("files", "clips", "c1")], lambda: ["train"]) == ["train"]
        assert row_counts(wh)["clips"] == 1


def _settle_folders(wh: Warehouse) -> None:
    """Date every table folder back past the settling time (as if its files came a while ago)."""
    old = time.time_ns() - 10 * SETTLE_NS
    for folder, _, _ in os.walk(wh.root / "tables"):
        os.utime(folder, ns=(old, old))
    time.sleep(2 * SETTLE_NS / 1e9)  # as _settle


def test_a_value_kept_in_memory_serves_while_its_partitions_stay(tmp_path):
    """The annotation app's start page worked out every clip's tasks on each refresh; kept in memory,
    a value is served for a listing of each partition it read, and computed again once a file came into
    one (an answer, a run) or the folder was swapped (a replace-mode write), never kept from folders
    that changed while it was computed, nor when it read a whole table."""
    wh = Warehouse(tmp_path / "w")
    kept = KeptInMemory()
    calls = []

    def frames() -> int:
        calls.append(1)
        return wh.read("runs", ["c1"]).num_rows + wh.read("clips", ["c1"]).num_rows

    _clip(wh, "c1", "train")
    wh.write("runs", "c1", table_rows("runs", [{"clip": "c1", "run_id": "r0"}]))
    assert kept.get(wh, "c1", frames) == 2 and kept.get(wh, "c1", frames) == 2
    assert len(calls) == 2  # its folders had just changed: the first not kept; the second listed them alike before and after
    assert kept.get(wh, "c1", frames) == 2 and len(calls) == 2
    wh.write("runs", "c1", table_rows("runs", [{"clip": "c1", "run_id": "r1"}]))  # a file more
    assert kept.get(wh, "c1", frames) == kept.get(wh, "c1", frames) == 3 and len(calls) == 3
    _clip(wh, "c1", "val")  # swapped in: a new folder
    assert kept.get(wh, "c1", frames) == 3 and len(calls) == 4
    assert kept.get(wh, "c1", frames) == 3 and len(calls) == 4
    kept.keep_only([])
    assert kept.get(wh, "c1", frames) == 3 and len(calls) == 5  # a key first seen: its folders' times decide
    _settle_folders(wh)
    kept.keep_only([])
    assert kept.get(wh, "c1", frames) == kept.get(wh, "c1", frames) == 3 and len(calls) == 6
    every = lambda: calls.append(1) or wh.read("runs").num_rows  # noqa: E731
    assert kept.get(wh, "all", every) == kept.get(wh, "all", every) == 2 and len(calls) == 8


def test_a_value_whose_partition_changed_while_it_was_computed_again_is_not_kept(tmp_path):
    """A clip's tasks worked out again (a file came) while another write lands in a partition they
    read, on a filesystem whose folder times are coarse (the folder's time then reads as before the
    computation): the value was kept with the listing taken after it, the new file in it, and
    served stale until the next write; a value is now kept when its partitions list the same files
    before and after it was computed."""
    wh = Warehouse(tmp_path / "w")
    kept = KeptInMemory()
    late = []

    def runs() -> int:
        n = wh.read("runs", ["c1"]).num_rows
        for run_id in late:  # another process's write, just after the read
            wh.write("runs", "c1", table_rows("runs", [{"clip": "c1", "run_id": run_id}]))
            _settle_folders(wh)  # a coarse clock: the folder's time reads as before the computation
        late.clear()
        return n

    wh.write("runs", "c1", table_rows("runs", [{"clip": "c1", "run_id": "r0"}]))
    _settle_folders(wh)
    assert kept.get(wh, "c1", runs) == 1
    wh.write("runs", "c1", table_rows("runs", [{"clip": "c1", "run_id": "r1"}]))
    late.append("r2")
    assert kept.get(wh, "c1", runs) == 2  # read before r2 came
    assert kept.get(wh, "c1", runs) == 3


def test_a_first_value_is_not_kept_from_a_folder_swapped_in_while_it_was_computed(tmp_path):
    """A replace-mode write swaps a partition's folder in whole, and the folder swapped in keeps the
    time of its making, before the computation: a clip's tasks first worked out from the folder
    swapped out were kept, and served stale by the annotation app (and its copy on disk)."""
    wh = Warehouse(tmp_path / "w")
    kept = KeptInMemory()
    _clip(wh, "c1", "train")
    _settle_folders(wh)
    calls = []

    def split() -> list[str]:
        calls.append(1)
        got = wh.read("clips", ["c1"]).column("split").to_pylist()
        if len(calls) == 1:
            _clip(wh, "c1", "val")  # swapped in just after the read ...
            old = time.time_ns() - 10 * SETTLE_NS
            os.utime(wh.partition_dir("clips", "c1"), ns=(old, old))  # ... made before it
        return got

    assert kept.get(wh, "c1", split) == ["train"]
    assert kept.get(wh, "c1", split) == ["val"]


def test_a_value_kept_on_disk_serves_a_process_started_later_while_its_partitions_stay(tmp_path):
    """The annotation app read every clip's tasks again when it started (1,000 finished clips: 43 s);
    a copy of each kept value on disk serves the next process while the partitions it read list the
    same files, and not for other code, a changed partition, or a copy of the warehouse that changed."""
    import shutil

    from warehouse.kept import OnDisk

    calls = []

    def runs(w: Warehouse):
        return lambda: calls.append(1) or {"runs": w.read("runs", ["c1"]).num_rows}

    def disk(w: Warehouse, version: str = "v1") -> OnDisk:
        return OnDisk(w.root / "_cache" / "reads" / "test", version, lambda v: v, lambda d: d)

    wh = Warehouse(tmp_path / "w")
    wh.write("runs", "c1", table_rows("runs", [{"clip": "c1", "run_id": "r0"}]))
    _settle_folders(wh)
    assert KeptInMemory(disk(wh)).get(wh, "c1", runs(wh)) == {"runs": 1} and len(calls) == 1
    assert (wh.root / "_cache" / "reads" / "test" / "c1.json").is_file()
    later = KeptInMemory(disk(wh))  # another process
    assert later.get(wh, "c1", runs(wh)) == later.get(wh, "c1", runs(wh)) == {"runs": 1} and len(calls) == 1
    assert KeptInMemory(disk(wh, "v2")).get(wh, "c1", runs(wh)) == {"runs": 1} and len(calls) == 2  # other code
    copy = Warehouse(shutil.copytree(wh.root, tmp_path / "copy"))
    copy.write("runs", "c1", table_rows("runs", [{"clip": "c1", "run_id": "r9"}]))  # the copy changed, not the original
    _settle_folders(copy)
    assert KeptInMemory(disk(copy, "v2")).get(copy, "c1", runs(copy)) == {"runs": 2} and len(calls) == 3
    assert KeptInMemory(disk(wh, "v2")).get(wh, "c1", runs(wh)) == {"runs": 1} and len(calls) == 3
    wh.write("runs", "c1", table_rows("runs", [{"clip": "c1", "run_id": "r1"}, {"clip": "c1", "run_id": "r2"}]))
    _settle_folders(wh)
    assert KeptInMemory(disk(wh, "v2")).get(wh, "c1", runs(wh)) == {"runs": 3} and len(calls) == 4
    (wh.root / "_cache" / "reads" / "test" / "c1.json").write_text("{")  # a file cut short: computed again
    assert KeptInMemory(disk(wh, "v2")).get(wh, "c1", runs(wh)) == {"runs": 3} and len(calls) == 5


def test_threads_asking_for_a_value_being_computed_wait_for_it(tmp_path):
    """The start page's first refreshes each read every clip while the first was still at it: every
    clip was computed once per request in flight. Threads asking for a key being computed wait for it."""
    from concurrent.futures import ThreadPoolExecutor

    wh = Warehouse(tmp_path / "w")
    wh.write("runs", "c1", table_rows("runs", [{"clip": "c1", "run_id": "r0"}]))
    _settle_folders(wh)
    kept, calls = KeptInMemory(), []

    def slow() -> int:
        calls.append(1)
        time.sleep(0.3)
        return wh.read("runs", ["c1"]).num_rows

    with ThreadPoolExecutor(4) as pool:
        assert list(pool.map(lambda _: kept.get(wh, "c1", slow), range(4))) == [1] * 4
    assert len(calls) == 1
