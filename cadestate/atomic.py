"""Atomic file writes: a file is written under a temporary name in its final folder, flushed to disk
and renamed into place (``os.replace``), so a reader or a crash sees the old file or the new one,
never half of one. Used by the warehouse (:mod:`warehouse.store`) and by everything that writes a
file beside it (label files, reports, the official annotation files)."""

from __future__ import annotations

import contextlib
import os
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

TMP_SUFFIX = ".tmp"
"""Suffix of a file being written (under a hidden, unique name in its final folder)."""


def fsync_dir(path: Path) -> None:
    """Flush a folder's entries (a rename into it) to disk; a no-op where folders cannot be opened."""
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


@contextlib.contextmanager
def atomic_writer(path: Path, durable: bool = True) -> Iterator[BinaryIO]:
    """A binary file to write ``path`` through, atomically: what is written goes to a temporary file
    in the same folder, flushed and renamed into place when the block ends without an exception
    (nothing is left when it raises). For large files that should not be held in memory whole.
    ``durable=False``: not forced to disk (no ``fsync``, ~1 ms each), for files that a power loss
    may take back without harm (a cache, the marker of a run in progress): still whole or absent."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}{TMP_SUFFIX}")
    try:
        with open(tmp, "wb") as f:
            yield f
            f.flush()
            if durable:
                os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    if durable:
        fsync_dir(path.parent)


def atomic_write_bytes(path: Path, data: bytes, durable: bool = True) -> None:
    """Write ``data`` to ``path`` atomically (temporary file in the same folder, fsync unless not
    ``durable`` (see :func:`atomic_writer`), rename)."""
    with atomic_writer(path, durable) as f:
        f.write(data)


RENAME_EXCHANGE = 2
AT_FDCWD = -100


def exchange(a: Path, b: Path) -> None:
    """Swap the names of the folders ``a`` and ``b`` in one step (Linux ``renameat2`` with
    ``RENAME_EXCHANGE``): whoever opens either path finds one folder or the other, never none. An
    :class:`OSError` where the platform or the file system cannot."""
    import ctypes

    try:
        renameat2 = ctypes.CDLL(None, use_errno=True).renameat2
    except (AttributeError, OSError):
        raise OSError(f"cannot swap {a} and {b} atomically: renameat2 is missing (Linux, glibc 2.28 or later)") from None
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    if renameat2(AT_FDCWD, os.fsencode(a), AT_FDCWD, os.fsencode(b), RENAME_EXCHANGE) != 0:
        errno = ctypes.get_errno()
        raise OSError(errno, f"cannot swap {a} and {b} atomically: {os.strerror(errno)}")
