"""The retrieval index of one CAD library: built from Arrow columns, kept in the process while the library is unchanged.

A library's index is its ``cad_model_embeddings`` (one row per model, sorted by cad_id) as arrays,
its ``embedding_whitening`` and its ``label_similarity`` spread over the models. It is built
without Python lists per model (the vector column's flat float32 buffer reshaped to [M, k]) and
kept per process under the content digest of the library's partitions of those three tables
(SHA-256 of their Parquet files' bytes): a re-ingested library (files rewritten by any process)
gets a new digest and is rebuilt; every clip of an unchanged library reuses the one built.

Measured with ``python -m bench.retrieval_bench`` (2 shared cores, 120,000 models, k = 128):
the row-wise build (``to_pylist``) cost about 2.2 s of the 3.1 s CPU of each clip's retrieval; the
digest of an unchanged library costs about 0.04 s per clip (SHA-256 of 60 MB).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from cadestate.lineage import digest, file_sha256
from tasks.retrieval.whitening import Whitening, read_whitening
from warehouse import Warehouse

LIBRARY_TABLES = ("cad_model_embeddings", "embedding_whitening", "label_similarity")
CACHE_SIZE = 4  # libraries kept per process (about 70 MB each at 120,000 models)

_cache: OrderedDict[str, LibraryIndex] = OrderedDict()
_lock = threading.Lock()


class RetrievalError(LookupError):
    """A CAD library or a label the retrieval needs is missing."""


@dataclass(frozen=True)
class LibraryIndex:
    """One library as retrieval sees it: cad_ids [M], classes [M] (object arrays of str, sorted by
    cad_id), vectors float32[M,k] (mean whitened view descriptors), its whitening, and label ->
    clipped class similarity float32[M]. Arrays of a cached index are read-only."""

    library: str
    cad_ids: np.ndarray
    classes: np.ndarray
    vectors: np.ndarray
    whitening: Whitening
    class_sim: dict[str, np.ndarray]


def list_matrix(column: pa.ChunkedArray | pa.Array) -> np.ndarray:
    """An Arrow list<float32> column of N rows of equal length k -> float32[N,k], from the flat
    values buffer (no Python objects per row)."""
    array = column.combine_chunks() if isinstance(column, pa.ChunkedArray) else column
    lengths = pc.list_value_length(array)
    bounds = pc.min_max(lengths).as_py() if len(array) else {"min": 0, "max": 0}
    if bounds["min"] != bounds["max"] or lengths.null_count:
        raise ValueError(f"vectors of unequal lengths ({bounds['min']} to {bounds['max']}) or missing")
    return pc.list_flatten(array).to_numpy(zero_copy_only=False).astype(np.float32, copy=False).reshape(len(array), bounds["max"])


def build_index(wh: Warehouse, library: str) -> LibraryIndex:
    """The index of ``library`` read now (its cad_embed and label_similarity stages must have run)."""
    models = wh.read("cad_model_embeddings", partitions=[library], columns=["cad_id", "class", "vector"])
    if not models.num_rows:
        raise RetrievalError(f"CAD library {library!r} has no model descriptors: run its cad_embed stage (`cadestate cad ingest`)")
    classes = pc.dictionary_encode(models.column("class").combine_chunks())
    names, codes = classes.dictionary.to_pylist(), classes.indices.to_numpy()
    table: dict[str, dict[str, float]] = {}
    for r in wh.read("label_similarity", partitions=[library], columns=["detector_label", "cad_class", "similarity"]).to_pylist():
        table.setdefault(r["detector_label"], {})[r["cad_class"]] = max(float(r["similarity"]), 0.0)
    class_sim = {label: np.array([by_class.get(c, 0.0) for c in names], np.float32)[codes] for label, by_class in table.items()}
    try:
        vectors = list_matrix(models.column("vector"))
    except ValueError as e:
        raise RetrievalError(f"CAD library {library!r}: cad_model_embeddings.vector: {e}") from None
    if bad := np.flatnonzero(~np.isfinite(vectors).all(axis=1)).tolist():  # NaN scores: ranked by name, or none kept
        raise RetrievalError(f"CAD library {library!r}: cad_model_embeddings.vector of {models.column('cad_id')[bad[0]]} "
                             f"(and {len(bad) - 1} more) is not finite: run its cad_embed stage again")
    return LibraryIndex(library, models.column("cad_id").to_numpy(), np.array(names, dtype=object)[codes],
                        vectors, read_whitening(wh, library), class_sim)


def content_digest(wh: Warehouse, library: str) -> str:
    """Content digest of ``library``'s partitions of :data:`LIBRARY_TABLES` (file names and bytes)."""
    return digest(library, *(f"{t}/{f.name}={file_sha256(f)}" for t in LIBRARY_TABLES for f in wh.files(t, [library])))


def _read_only(index: LibraryIndex) -> LibraryIndex:
    for a in (index.cad_ids, index.classes, index.vectors, *index.class_sim.values()):
        a.setflags(write=False)
    return index


def load_index(wh: Warehouse, library: str) -> LibraryIndex:
    """The index of ``library``: the one this process built for the library's current content
    digest, else built now and kept (the :data:`CACHE_SIZE` most recently used are kept). An index
    whose files changed while it was being read is returned but not kept."""
    key = content_digest(wh, library)
    with _lock:
        if key in _cache:
            _cache.move_to_end(key)
            return _cache[key]
    index = _read_only(build_index(wh, library))
    if content_digest(wh, library) == key:
        with _lock:
            _cache[key] = index
            while len(_cache) > CACHE_SIZE:
                _cache.popitem(last=False)
    return index


def clear_cache() -> None:
    """Forget every kept index (the next :func:`load_index` of each library builds it)."""
    with _lock:
        _cache.clear()
