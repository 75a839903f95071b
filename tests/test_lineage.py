"""Content digests (cadestate.lineage) stay what they were: task ids and stage outputs of existing
warehouses are such digests, so a change of what they count orphans people's answers."""

from __future__ import annotations

from types import SimpleNamespace

import pyarrow as pa

from cadestate.lineage import digest, note_read, once_per_reading, one_reading, recording_reads, table_digest


def _table(description: bytes, values: list[float], meta: dict | None = None) -> pa.Table:
    field = pa.field("x", pa.float64(), metadata={b"description": description})
    return pa.table({"x": values}, schema=pa.schema([field], metadata=meta))


def test_table_digests_are_those_existing_warehouses_hold():
    base = table_digest(_table(b"a column", [1.0, 2.0]))
    assert base == "ede8d0af2b9ad54c"
    assert table_digest(_table(b"a column", [1.0, 2.0], {b"k": b"v"})) == base  # schema metadata: not counted
    assert table_digest(_table(b"a column", [1.0, 2.5])) != base
    assert table_digest(pa.table({"x": pa.array([1.0, 2.0], pa.float32())})) != base
    assert digest("cad_selection", "clip") == "8c4d10e280d50c5e"


def test_a_known_file_is_hashed_again_only_when_it_changes(tmp_path, monkeypatch):
    """cadestate.lineage.known_file_sha256: a clip's video, hashed once per process while it stays the same file."""
    import os
    import time

    from cadestate import lineage

    path = tmp_path / "video.mp4"
    path.write_bytes(b"frames")
    hashed: list[str] = []
    real = lineage.file_sha256
    monkeypatch.setattr(lineage, "file_sha256", lambda p, *a: hashed.append(str(p)) or real(p, *a))
    first = lineage.known_file_sha256(path)
    assert lineage.known_file_sha256(str(path)) == first == real(path) and len(hashed) == 1
    st = path.stat()
    time.sleep(0.05)  # file times come from a coarse clock (a jiffy): the change below gets a later one
    with open(path, "r+b") as f:  # the same size and modification time, other bytes: the change time moves
        f.write(b"FRAMES")
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert lineage.known_file_sha256(path) == real(path) != first and len(hashed) == 2


def test_one_reading_computes_once_per_partition_and_every_recording_learns_its_reads(tmp_path):
    calls: list[str] = []

    @once_per_reading
    def looked_up(wh, part: str) -> int:
        calls.append(part)
        note_read("files", "label_files", part)
        return len(calls)

    wh = SimpleNamespace(root=tmp_path)
    assert [looked_up(wh, "a"), looked_up(wh, "a")] == [1, 2]  # outside a block: every call computes
    with one_reading():
        with recording_reads() as first:
            a = looked_up(wh, "a")
        with recording_reads() as second:
            again = looked_up(wh, "a")
        b = looked_up(wh, "b")
        other = looked_up(SimpleNamespace(root=tmp_path / "other"), "a")
    assert (a, again, b, other) == (3, 3, 4, 5)
    assert first == second == [("files", "label_files", "a")]  # the repeat notes what the value depends on
    assert looked_up(wh, "a") == 6  # the block is over
