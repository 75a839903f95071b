"""Cost of one partition write, and of a query through the catalog, as a table grows.

Fills a fresh warehouse's ``runs`` table with N clip partitions (written straight as Parquet, so the
setup pays no catalog cost), then times ``Warehouse.write`` (which runs the store's after-write
hooks) and a ``count(*)`` through :func:`warehouse.catalog.connect`. Issue 21 compared the catalog
rebuilt after every write with views created once::

    python -m bench.catalog_writes --partitions 1000 --writes 5

Prints one JSON object: seconds (wall and CPU) per write, and of the query.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import tempfile
import time
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq


def run_row(clip: str, run_id: str) -> dict:
    return {"clip": clip, "run_id": run_id, "stage": "ingest", "status": "completed", "config_hash": "c",
            "inputs_hash": "i", "output_hash": "o", "code_hash": "k",
            "started_at": dt.datetime(2026, 1, 1, tzinfo=dt.timezone.utc), "duration_s": 1.0, "rows_written": 1,
            "message": ""}


def measure(root: Path, partitions: int, writes: int) -> dict:
    """Seconds per write and per catalog query with ``partitions`` clips of ``runs`` under ``root``."""
    from warehouse import Warehouse, connect

    wh = Warehouse(root)
    schema = wh.spec("runs").schema
    for i in range(partitions):
        folder = wh.partition_dir("runs", f"c{i:05d}")
        folder.mkdir(parents=True)
        pq.write_table(pa.Table.from_pylist([run_row(f"c{i:05d}", "r0")], schema=schema), folder / "0-setup.parquet")
    wh.write("runs", "c00000", pa.Table.from_pylist([run_row("c00000", "warm")], schema=schema))  # imports, first catalog
    wall, cpu = time.perf_counter(), time.process_time()
    for k in range(writes):
        wh.write("runs", f"c{k % partitions:05d}", pa.Table.from_pylist([run_row(f"c{k % partitions:05d}", f"w{k}")], schema=schema))
    per_write = ((time.perf_counter() - wall) / writes, (time.process_time() - cpu) / writes)
    wall, cpu = time.perf_counter(), time.process_time()
    con = connect(wh)
    rows = con.execute("SELECT count(*) FROM runs").fetchone()[0]
    con.close()
    query = (time.perf_counter() - wall, time.process_time() - cpu)
    return {"partitions": partitions, "writes": writes, "write_wall_s": round(per_write[0], 4),
            "write_cpu_s": round(per_write[1], 4), "query_wall_s": round(query[0], 4), "query_cpu_s": round(query[1], 4),
            "rows": rows}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--partitions", type=int, default=1000, help="clip partitions of runs (default 1000)")
    parser.add_argument("--writes", type=int, default=5, help="writes timed (default 5)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="cadestate-catalog-bench-") as tmp:
        print(json.dumps(measure(Path(tmp) / "w", args.partitions, args.writes)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
