"""Content digests (cadestate.lineage): what counts as a table's content."""

from __future__ import annotations

import pyarrow as pa

from cadestate.lineage import table_digest


def _table(description: bytes, values: list[float], meta: dict | None = None) -> pa.Table:
    field = pa.field("x", pa.float64(), metadata={b"description": description})
    return pa.table({"x": values}, schema=pa.schema([field], metadata=meta))


def test_a_table_digest_counts_values_and_types_not_descriptions():
    base = table_digest(_table(b"from tasks/pose_checks.py", [1.0, 2.0]))
    assert table_digest(_table(b"from tasks/pose/checks.py", [1.0, 2.0], {b"k": b"v"})) == base
    assert table_digest(_table(b"from tasks/pose_checks.py", [1.0, 2.5])) != base
    assert table_digest(pa.table({"x": pa.array([1.0, 2.0], pa.float32())})) != base
    assert table_digest(pa.table({"y": [1.0, 2.0]})) != base
