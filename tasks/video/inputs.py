"""What the ingest stage reads besides its upstream output, as digests: the video, the split, the
time offset. Kept apart from :mod:`tasks.video.ingest` so that ``cadestate status``, which computes
them for every clip, imports none of ingest's dependencies (PyAV, the up estimate), and reads only
the three columns it needs (a timestamp column's values would import pandas through pyarrow).
"""

from __future__ import annotations

from cadestate.lineage import digest
from schemas.core import DEFAULT_SPLIT
from warehouse import Warehouse

REGISTERED = ["video_sha256", "split", "time_offset_us"]
"""The columns of ``clips`` the digest reads."""


def clip_split(row: dict) -> str:
    """The split of a ``clips`` row (``train`` for clips ingested before splits existed)."""
    return row.get("split") or DEFAULT_SPLIT


def ingest_source_digest(video_sha256: str, split: str, time_offset_us: int) -> str:
    """What ingest reads besides the ``cameras`` stage's output: the video, the split, the offset."""
    return digest("ingest-source", video_sha256, split, str(int(time_offset_us)))


def registered_inputs_digest(wh: Warehouse, clip: str) -> str:
    """:func:`ingest_source_digest` of a registered clip (what ``cadestate status`` compares)."""
    rows = wh.read("clips", partitions=[clip], columns=REGISTERED).to_pylist()  # none: not registered
    if not rows:
        return ""
    row = rows[0]
    return ingest_source_digest(row["video_sha256"], clip_split(row), int(row.get("time_offset_us") or 0))


def registered_inputs(wh: Warehouse, clip: str) -> list[str]:
    """The ingest stage's clip inputs (its declaration's ``clip_inputs``)."""
    return [registered_inputs_digest(wh, clip)]
