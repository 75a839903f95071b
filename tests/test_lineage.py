"""Content digests (cadestate.lineage) stay what they were: task ids and stage outputs of existing
warehouses are such digests, so a change of what they count orphans people's answers."""

from __future__ import annotations

import pyarrow as pa

from cadestate.lineage import digest, table_digest


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
