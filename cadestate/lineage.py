"""Digests that tie every stage run to what it read and what it wrote.

A stage run records ``config_hash`` (its config section), ``inputs_hash`` (its input files or its
upstream stages' output hashes), ``code_hash`` (its source: :mod:`tasks.registry`) and ``output_hash`` (what it wrote).
A stage is stale when any of the first three differs from what it would be now
(:mod:`tasks.status`). Digests are 16 hex characters of SHA-256.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
from collections.abc import Iterator
from contextvars import ContextVar
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # pyarrow is imported by table_digest alone: `cadestate status` digests without it where it can
    import pyarrow as pa


def digest(*parts: str) -> str:
    """Digest of an ordered sequence of strings."""
    h = hashlib.sha256()
    for p in parts:
        h.update(p.encode())
        h.update(b"\0")
    return h.hexdigest()[:16]


_READS: ContextVar[list[tuple[str, ...]] | None] = ContextVar("cadestate_reads", default=None)


def note_read(*what: str) -> None:
    """Tell the :func:`recording_reads` block in force, if any, that something was read: the
    warehouse notes its listings (``"files", table, partitions`` and ``"partitions", table``), and a
    stage's ``config_inputs`` notes a file outside the warehouse that it digests (``"file", path``)."""
    reads = _READS.get()
    if reads is not None:
        reads.append(what)


@contextlib.contextmanager
def recording_reads() -> Iterator[list[tuple[str, ...]]]:
    """The list of what :func:`note_read` is told inside the block (in this thread or task), in order.
    ``cadestate status`` keeps a stage's input digests with what they read, and digests again only
    when that changed (:mod:`tasks.inputs_memo`)."""
    reads: list[tuple[str, ...]] = []
    token = _READS.set(reads)
    try:
        yield reads
    finally:
        _READS.reset(token)


def file_sha256(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    """Full hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def table_digest(table: pa.Table) -> str:
    """Digest of a table's content (Arrow IPC bytes of its columns, schema metadata excluded; the
    columns' own metadata, their descriptions, counts: the ids of the tasks people answer are such
    digests, so changing what they count would leave the answers of existing warehouses unmatched)."""
    import pyarrow as pa

    table = table.replace_schema_metadata(None)
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, table.schema) as writer:
        writer.write_table(table)
    return hashlib.sha256(sink.getvalue().to_pybytes()).hexdigest()[:16]

