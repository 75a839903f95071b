"""The memo of input digests that ``cadestate status`` keeps (tasks/inputs_memo.py): served while
what the digests read is unchanged, digested again as soon as any of it changes (a file added, a
partition rewritten in place under the same name, a new partition), never stored from reads that
changed while they were digested, and never in the way of a warehouse it cannot write to."""

from __future__ import annotations

import json
import os
import time

from conftest import table_rows
from tasks.inputs_memo import SETTLE_NS, InputsMemo
from tasks.registry import STAGES
from warehouse import Warehouse


def _settle(wh: Warehouse) -> None:
    """Date every file of the warehouse back past the memo's settling time (as if written a while ago)."""
    old = time.time_ns() - 10 * SETTLE_NS
    for folder, _, names in os.walk(wh.root / "tables"):
        for name in names:
            os.utime(os.path.join(folder, name), ns=(old, old))
        os.utime(folder, ns=(old, old))
    time.sleep(2 * SETTLE_NS / 1e9)  # the status changes (renames, this dating) cannot be dated back: waited out


def _tamper(wh: Warehouse, unit: str, stage: str) -> None:
    """Replace the memo's stored digests of ``stage`` by a value no digest has, so that serving
    the memo shows."""
    path = wh.root / "_cache" / "inputs" / f"{unit}.json"
    doc = json.loads(path.read_text())
    doc["stages"][stage]["inputs"] = ["tampered"]
    path.write_text(json.dumps(doc))


def _clip(wh: Warehouse, name: str, split: str) -> None:
    wh.write("clips", name, table_rows("clips", [{"clip": name, "video_sha256": "v" * 64, "split": split}]))


def test_the_memo_serves_until_a_partition_is_rewritten_in_place(tmp_path):
    """``ingest`` digests its clip's ``clips`` row: a replace-mode partition, rewritten under the
    same file name (a new inode, size or time tells)."""
    wh = Warehouse(tmp_path / "w")
    ingest = STAGES["ingest"]
    _clip(wh, "c1", "train")
    _settle(wh)
    memo = InputsMemo(wh, "c1")
    train = memo.clip_inputs(ingest)
    memo.save()
    assert train == ingest.clip_inputs(wh, "c1")
    _tamper(wh, "c1", "ingest")
    assert InputsMemo(wh, "c1").clip_inputs(ingest) == ["tampered"]  # unchanged reads: served
    _clip(wh, "c1", "val")
    _settle(wh)
    val = InputsMemo(wh, "c1").clip_inputs(ingest)
    assert val == ingest.clip_inputs(wh, "c1") != train


def test_a_new_file_and_a_new_partition_are_seen(tmp_path):
    """``retrieval`` digests the libraries' latest descriptor runs: an appended ``runs`` file, and a
    new library's partitions, change it."""
    wh = Warehouse(tmp_path / "w")
    retrieval = STAGES["retrieval"]

    def embedded(library: str, output: str) -> None:
        wh.write("cad_models", library, table_rows("cad_models", [{"library": library, "cad_id": f"{library}/m"}]))
        wh.write("runs", library, table_rows("runs", [{"clip": library, "run_id": output, "stage": "cad_embed",
                                                       "status": "completed", "output_hash": output}]))

    embedded("lib", "a")
    _settle(wh)
    memo = InputsMemo(wh, "c1")
    first = memo.clip_inputs(retrieval)
    memo.save()
    _tamper(wh, "c1", "retrieval")
    assert InputsMemo(wh, "c1").clip_inputs(retrieval) == ["tampered"]
    embedded("lib", "b")  # a second runs file in the library's partition
    _settle(wh)
    memo = InputsMemo(wh, "c1")
    second = memo.clip_inputs(retrieval)
    memo.save()
    assert second == retrieval.clip_inputs(wh, "c1") != first
    _tamper(wh, "c1", "retrieval")
    embedded("other", "c")  # a new library
    _settle(wh)
    assert InputsMemo(wh, "c1").clip_inputs(retrieval) == retrieval.clip_inputs(wh, "c1") != second


def test_digests_of_reads_that_changed_meanwhile_are_not_kept(tmp_path):
    wh = Warehouse(tmp_path / "w")
    _clip(wh, "c1", "train")
    part = wh.files("clips", ["c1"])[0]
    later = time.time_ns() + 10 * SETTLE_NS  # as if written while the digest read it
    os.utime(part, ns=(later, later))
    memo = InputsMemo(wh, "c1")
    assert memo.clip_inputs(STAGES["ingest"]) == STAGES["ingest"].clip_inputs(wh, "c1")
    memo.save()
    assert not (wh.root / "_cache" / "inputs" / "c1.json").exists()
    _settle(wh)
    memo = InputsMemo(wh, "c1")
    memo.clip_inputs(STAGES["ingest"])
    memo.save()
    assert "ingest" in json.loads((wh.root / "_cache" / "inputs" / "c1.json").read_text())["stages"]


def test_digests_of_one_reading_count_from_when_it_began(tmp_path):
    """In :meth:`InputsMemo.reading` a digest may reuse a value computed for an earlier stage, so a
    read changed after the block began keeps its entry out of the memo, however long ago."""
    wh = Warehouse(tmp_path / "w")
    _clip(wh, "c1", "train")
    _settle(wh)
    memo = InputsMemo(wh, "c1")
    with memo.reading():
        _clip(wh, "c1", "val")
        time.sleep(2 * SETTLE_NS / 1e9)  # settled by the time of the digest, not since the block began
        assert memo.clip_inputs(STAGES["ingest"]) == STAGES["ingest"].clip_inputs(wh, "c1")
    memo.save()
    assert not (wh.root / "_cache" / "inputs" / "c1.json").exists()
    memo.clip_inputs(STAGES["ingest"])  # outside a reading: from the digest's own start
    memo.save()
    assert "ingest" in json.loads((wh.root / "_cache" / "inputs" / "c1.json").read_text())["stages"]


def test_a_reading_takes_each_state_once_and_never_keeps_a_stale_digest(tmp_path):
    """In a reading the state of a read is taken once for every stage that read it. A change made
    between two digests of the block (dated back, as a coarse file clock may leave it) is digested
    by the later one, and what the memo keeps serves nothing stale afterwards."""
    wh = Warehouse(tmp_path / "w")
    ingest = STAGES["ingest"]
    _clip(wh, "c1", "train")
    _settle(wh)
    memo = InputsMemo(wh, "c1")
    with memo.reading():
        train = memo.clip_inputs(ingest)
        states = dict(memo._states)
        _clip(wh, "c1", "val")
        _settle(wh)
        val = memo.clip_inputs(ingest, fresh=True)
        assert memo._states == states  # taken once in the block
    memo.save()
    assert train != val == ingest.clip_inputs(wh, "c1")
    assert InputsMemo(wh, "c1").clip_inputs(ingest) == val


def test_a_warehouse_without_room_for_the_memo_still_answers(tmp_path):
    wh = Warehouse(tmp_path / "w")
    _clip(wh, "c1", "train")
    _settle(wh)
    (wh.root / "_cache").write_text("not a folder")  # the memo cannot be written (as in a read-only warehouse)
    for _ in range(2):
        memo = InputsMemo(wh, "c1")
        assert memo.clip_inputs(STAGES["ingest"]) == STAGES["ingest"].clip_inputs(wh, "c1")
        memo.save()
    broken = Warehouse(tmp_path / "v")
    _clip(broken, "c1", "train")
    (broken.root / "_cache" / "inputs").mkdir(parents=True)
    (broken.root / "_cache" / "inputs" / "c1.json").write_text("{not json")  # a damaged memo is digested again
    assert InputsMemo(broken, "c1").clip_inputs(STAGES["ingest"]) == STAGES["ingest"].clip_inputs(broken, "c1")
