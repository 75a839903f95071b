"""The record of a clip's input files as ingest placed them (``inputs/<clip>/placed.json``), so that
``cadestate status`` sees a file edited in place (a hard link to the user's file) without hashing
it. Apart from :mod:`tasks.video.inputs`: status reads it for every clip and must import nothing
heavy (that module's schema import brought pyarrow and its threads: 2x the CPU of a status).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import TYPE_CHECKING

from cadestate.atomic import atomic_write_bytes

if TYPE_CHECKING:
    from warehouse import Warehouse

PLACED_FILE = "placed.json"
"""Beside a clip's inputs (``inputs/<clip>/``): each input file's size and modification time as
ingest placed it (:func:`record_placed`), so that ``cadestate status`` sees a file edited in place
(a hard link to the user's file) without hashing it (:func:`edited_inputs`)."""


def record_placed(folder: Path, files: list[Path]) -> None:
    """Record the size and modification time of ``files`` (just placed in ``folder``) in :data:`PLACED_FILE`."""
    stats = {f.name: [f.stat().st_size, f.stat().st_mtime_ns] for f in files}
    atomic_write_bytes(folder / PLACED_FILE, json.dumps(stats, sort_keys=True).encode(), durable=False)


def edited_inputs(wh: Warehouse, clip: str) -> list[str]:
    """The clip's input files whose size or modification time differ from what ingest recorded
    (edited in place since; none when nothing was recorded: a clip ingested before this record)."""
    folder = wh.inputs_dir(clip)
    try:
        placed = json.loads((folder / PLACED_FILE).read_text())
    except (OSError, ValueError):
        return []
    edited = []
    for name, (size, mtime_ns) in sorted(placed.items()) if isinstance(placed, dict) else []:
        try:
            st = os.stat(folder / name)
        except OSError:
            edited.append(name)
            continue
        if (st.st_size, st.st_mtime_ns) != (size, mtime_ns):
            edited.append(name)
    return edited
