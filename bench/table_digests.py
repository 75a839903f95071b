"""Content digests of a warehouse's tables, to show that a change leaves the data as it was.

One SHA-256 per table (and per column, to name what differs): the rows of the clip's partitions
(and of every CAD-library partition), order-free, with the columns that record a run rather than
its result left out (run ids, times, durations, media version folders). Issue 14 compared the demo
clip and the default benchmark's first clip before and after the stage-layout change with it::

    python -m bench.table_digests WAREHOUSE --clip bench-7-00_0 --json before.json
    python -m bench.table_digests WAREHOUSE --clip bench-7-00_0 --compare before.json

Exit status 1 when ``--compare`` finds a difference.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import sys
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

VOLATILE = re.compile(r"(^|_)(run_id|started_at|finished_at|created_at|updated_at|written_at|ingested_at|duration_s|"
                      r"seconds|elapsed_s|pid|host|answered_at|received_at|at)$")
"""Columns that describe a run (when, how long, which run), not what it computed."""

MEDIA_VERSION = re.compile(r"(media/[^/]+/[^/]+/)[^/]+/")
"""A media path's version folder is fresh on every write (warehouse.store); it is replaced by ``*``."""


STRIP: list[str] = []
"""Path prefixes replaced by ``<root>`` (``--strip``): two warehouses built in different folders."""


def _normalise(value: object) -> object:
    if isinstance(value, str):
        if value.startswith("{"):  # a JSON document (a task or label file): its volatile keys left out too
            try:
                return _normalise(json.loads(value))
            except ValueError:
                pass
        for prefix in STRIP:
            value = value.replace(prefix, "<root>")
        return MEDIA_VERSION.sub(r"\1*/", value)
    if isinstance(value, float):
        return round(value, 9)
    if isinstance(value, list):
        return [_normalise(v) for v in value]
    if isinstance(value, dict):
        return {k: _normalise(v) for k, v in value.items() if not VOLATILE.search(k)}
    return value


def _digest(values: list[object]) -> str:
    lines = sorted(json.dumps(_normalise(v), sort_keys=True, default=str) for v in values)
    return hashlib.sha256("\n".join(lines).encode()).hexdigest()[:16]


def _partitions(table_dir: Path, clip: str) -> list[Path]:
    return sorted(p for p in table_dir.iterdir() if p.is_dir() and (p.name == f"clip={clip}" or p.name.startswith("library=")))


def table_digests(root: Path, clip: str) -> dict[str, dict[str, object]]:
    """``{table: {"rows": n, "digest": hex, "columns": {column: hex}}}`` for every table with rows of ``clip``
    (or of a CAD library)."""
    out: dict[str, dict[str, object]] = {}
    for table_dir in sorted((root / "tables").iterdir()):
        files = [f for p in _partitions(table_dir, clip) for f in sorted(p.glob("*.parquet"))]
        if not files:
            continue
        table = pa.concat_tables([pq.read_table(f) for f in files], promote_options="default")
        kept = [c for c in table.column_names if not VOLATILE.search(c)]
        rows = table.select(kept).to_pylist()
        out[table_dir.name] = {"rows": table.num_rows, "digest": _digest(rows),
                               "columns": {c: _digest(table.column(c).to_pylist()) for c in kept},
                               "left_out": [c for c in table.column_names if c not in kept]}
    return out


def compare(before: dict, after: dict) -> list[str]:
    """One line per table that differs (or is only on one side), naming the columns that differ."""
    lines = []
    for name in sorted(set(before) | set(after)):
        b, a = before.get(name), after.get(name)
        if b is None or a is None:
            lines.append(f"{name}: only {'after' if b is None else 'before'}")
        elif b["digest"] != a["digest"]:
            cols = sorted(c for c in set(b["columns"]) | set(a["columns"]) if b["columns"].get(c) != a["columns"].get(c))
            lines.append(f"{name}: rows {b['rows']} -> {a['rows']}; columns differing: {', '.join(cols) or '(none)'}")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.table_digests", description=__doc__.split("\n\n")[0])
    parser.add_argument("warehouse", type=Path)
    parser.add_argument("--clip", required=True)
    parser.add_argument("--json", type=Path, help="write the digests here")
    parser.add_argument("--compare", type=Path, help="digests written earlier with --json: print what differs")
    parser.add_argument("--strip", action="append", default=[], metavar="PREFIX",
                        help="a path prefix to replace by <root> in every string (repeatable)")
    args = parser.parse_args(argv)
    STRIP[:] = args.strip
    digests = table_digests(args.warehouse, args.clip)
    if args.json:
        args.json.write_text(json.dumps(digests, indent=1, sort_keys=True))
    for name, d in digests.items():
        print(f"{name}\t{d['rows']}\t{d['digest']}")
    if args.compare:
        differences = compare(json.loads(args.compare.read_text()), digests)
        print("\n".join(differences) if differences else f"all {len(digests)} tables identical")
        return 1 if differences else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
