"""A warehouse's identity: a random id written once, in ``<root>/warehouse.id``, on first use.

It travels with the warehouse: a copy or a move keeps it, so whatever is keyed by it (Prefect's
cached stage results, :mod:`flows.stage_tasks`) stays valid at the new path, while two warehouses
made apart never share one. The file is created atomically and never rewritten: the first of
concurrent creators wins (a hard link that fails if the name exists), the others read its id.
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path

from cadestate.atomic import TMP_SUFFIX, fsync_dir

ID_FILE = "warehouse.id"


def warehouse_id(root: Path) -> str:
    """The id of the warehouse at ``root`` (created on first use: 32 hex digits)."""
    path = Path(root) / ID_FILE
    try:
        text = path.read_text(encoding="ascii").strip()
    except FileNotFoundError:
        text = ""
    if text:
        return text
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{ID_FILE}.{uuid.uuid4().hex}{TMP_SUFFIX}")
    try:
        with open(tmp, "w", encoding="ascii") as f:
            f.write(uuid.uuid4().hex + "\n")
            f.flush()
            os.fsync(f.fileno())
        try:
            os.link(tmp, path)  # fails if another process made it first: its id stands
        except FileExistsError:
            pass
        fsync_dir(path.parent)
    finally:
        tmp.unlink(missing_ok=True)
    return path.read_text(encoding="ascii").strip()
