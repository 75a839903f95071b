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
"""Beside a clip's inputs (``inputs/<clip>/``): each input file's size, modification time and
SHA-256 as ingest placed it (:func:`record_placed`), so that ``cadestate status`` sees a file
edited in place (a hard link to the user's file) without hashing it (:func:`edited_inputs`)."""


def record_placed(folder: Path, files: dict[Path, str]) -> None:
    """Record the size, modification time and SHA-256 (``files``: path -> its SHA-256) of files just
    placed in ``folder`` in :data:`PLACED_FILE`."""
    stats = {f.name: [f.stat().st_size, f.stat().st_mtime_ns, sha] for f, sha in files.items()}
    atomic_write_bytes(folder / PLACED_FILE, json.dumps(stats, sort_keys=True).encode(), durable=False)


def edited_inputs(wh: Warehouse, clip: str) -> list[str]:
    """The clip's input files edited in place since ingest: of another size, or of another
    modification time and other bytes (none when nothing was recorded: a clip ingested before this
    record). A file that only has another time (a warehouse copied without its times, `cp -r`) is
    hashed once against the SHA-256 ingest recorded (in a record made before records kept it, the
    ``clips`` row's): the record takes its new time when the bytes are those ingest placed."""
    folder = wh.inputs_dir(clip)
    try:
        placed = json.loads((folder / PLACED_FILE).read_text())
    except (OSError, ValueError):
        return []
    edited, retimed = [], False
    for name, (size, mtime_ns, *sha) in sorted(placed.items()) if isinstance(placed, dict) else []:
        try:
            st = os.stat(folder / name)
        except OSError:
            edited.append(name)
            continue
        if (st.st_size, st.st_mtime_ns) == (size, mtime_ns):
            continue
        known = sha[0] if sha else _ingested_sha256(wh, clip, name) if st.st_size == size else None
        if known and _same_bytes(folder / name, known):
            placed[name] = [size, st.st_mtime_ns, known]
            retimed = True
        else:
            edited.append(name)
    if retimed:
        try:  # best effort: a read-only warehouse hashes again next time
            atomic_write_bytes(folder / PLACED_FILE, json.dumps(placed, sort_keys=True).encode(), durable=False)
        except OSError:
            pass
    return edited


def _ingested_sha256(wh: Warehouse, clip: str, name: str) -> str | None:
    """The SHA-256 the ``clips`` row holds for input file ``name`` (a record made before records kept
    it; read only then: the read brings pyarrow)."""
    column = "cameras_sha256" if name == "cameras.txt" else "video_sha256" if name.startswith("video.") else None
    if column is None:
        return None
    values = wh.read("clips", [clip], columns=[column]).column(column).to_pylist()
    return values[-1] if values else None


def _same_bytes(path: Path, sha256: str) -> bool:
    from cadestate.lineage import file_sha256

    try:
        return file_sha256(path) == sha256
    except OSError:
        return False
