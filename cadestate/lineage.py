"""Digests that tie every stage run to what it read and what it wrote.

A stage run records ``config_hash`` (its config section), ``inputs_hash`` (its input files or its
upstream stages' output hashes), ``code_hash`` (its source: :mod:`tasks.registry`) and ``output_hash`` (what it wrote).
A stage is stale when any of the first three differs from what it would be now
(:mod:`tasks.status`). Digests are 16 hex characters of SHA-256.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import threading
from collections.abc import Callable, Iterator
from contextvars import ContextVar
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

if TYPE_CHECKING:  # pyarrow is imported by table_digest alone: `cadestate status` digests without it where it can
    import pyarrow as pa

T = TypeVar("T")


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


_ONE_READING: ContextVar[dict | None] = ContextVar("cadestate_one_reading", default=None)


@contextlib.contextmanager
def one_reading() -> Iterator[None]:
    """Inside the block (in this thread or task), a function wrapped with :func:`once_per_reading`
    computes once per warehouse and partition: what it read is taken as it was at its first call,
    as a unit's input digests are all taken once before its stages run (three human stages' digests
    say which tracks the manual-track answer leaves out). A repeat notes the first call's reads
    again (:func:`note_read`), so every :func:`recording_reads` block learns what it depends on."""
    token = _ONE_READING.set({})
    try:
        yield
    finally:
        _ONE_READING.reset(token)


def once_per_reading(fn: Callable[[Any, str], T]) -> Callable[[Any, str], T]:
    """``fn(wh, partition)`` computed once per :func:`one_reading` block (each call outside one)."""

    @functools.wraps(fn)
    def wrapper(wh: Any, part: str) -> T:
        memo = _ONE_READING.get()
        if memo is None:
            return fn(wh, part)
        key = (fn, str(wh.root), part)
        if key not in memo:
            with recording_reads() as reads:
                value = fn(wh, part)
            memo[key] = (value, list(reads))
        value, reads = memo[key]
        for what in reads:
            note_read(*what)
        return value

    return wrapper


def file_sha256(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    """Full hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def folder_digest(folder: str | os.PathLike) -> str:
    """Digest of a folder's files: their names (relative, sorted) and bytes."""
    root = Path(folder)
    files = sorted(p for p in root.rglob("*") if p.is_file())
    return digest(*(f"{p.relative_to(root).as_posix()}:{file_sha256(p)}" for p in files))


_KNOWN_SHA256: dict[tuple, str] = {}
_KNOWN_LOCK = threading.Lock()
KNOWN_SHA256_FILES = 4096
"""How many files :func:`known_file_sha256` remembers (the oldest forgotten first)."""


def known_file_sha256(path: str | os.PathLike) -> str:
    """:func:`file_sha256`, remembered in this process while the file keeps its identity (path,
    inode, size, modification and change times: any write changes the change time): a long-lived
    process (the annotation app) hashes a clip's video once, not at every resume (a 100 MB video
    costs ~0.1 s)."""
    st = os.stat(path)
    key = (os.path.realpath(path), st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)
    sha = _KNOWN_SHA256.get(key)
    if sha is None:
        sha = file_sha256(path)
        with _KNOWN_LOCK:
            _KNOWN_SHA256[key] = sha
            while len(_KNOWN_SHA256) > KNOWN_SHA256_FILES:
                del _KNOWN_SHA256[next(iter(_KNOWN_SHA256))]
    return sha


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

