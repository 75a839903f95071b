"""Centring / PCA whitening of appearance descriptors, fitted on a CAD library's view descriptors.

Raw descriptors of one backbone bunch together (cosines 0.8-0.99 between unrelated objects), so
before comparing descriptors of detections and CAD views both go through the same fitted map
``w = normalise(P (v - mean))``: 'centre' subtracts the library mean (P = identity), 'whiten'
also projects on the top ``k`` principal directions scaled by 1 / sqrt(eigenvalue + shrinkage),
shrinkage = 10 % of the mean kept eigenvalue (so near-empty directions do not explode noise);
'learned' subtracts the mean the training centred on and applies the projection trained by
``make models`` (:mod:`tasks.retrieval.descriptor`), given to :func:`fit_whitening` as
``learned_mean`` and ``learned``: the same map for every library.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from warehouse import Warehouse

METHODS = ("none", "centre", "whiten", "learned")
SHRINKAGE = 0.1
RANK_TOL = 1e-6
"""'whiten' keeps the directions whose variance is above this fraction of the largest: the views
span no more (views that repeat: one model's renders alike, a mesh ingested twice), and a direction
of none got the largest scale, 1 / sqrt(shrinkage), though chosen at random (by the views' order)."""


@dataclass(frozen=True)
class Whitening:
    """w = normalise(projection @ (v - mean)): mean float32[D], projection float32[k,D]."""

    method: str
    mean: np.ndarray
    projection: np.ndarray

    def apply(self, vectors: np.ndarray) -> np.ndarray:
        """float[N,D] -> float32[N,k], unit L2 norm (a zero vector stays zero)."""
        v = np.asarray(vectors, np.float32)
        if v.shape[-1] != self.mean.shape[0]:  # four 12-value vectors were read as three of 16
            raise ValueError(f"descriptors of {v.shape[-1]} values, but the whitening takes {self.mean.shape[0]}")
        v = v.reshape(-1, self.mean.shape[0])
        w = (v - self.mean) @ self.projection.T
        n = np.linalg.norm(w, axis=1, keepdims=True)
        return (w / np.where(n > 0, n, 1)).astype(np.float32)


def fit_whitening(vectors: np.ndarray, method: str, dims: int, learned: np.ndarray | None = None,
                  learned_mean: np.ndarray | None = None) -> Whitening:
    """Fit ``method`` on descriptors float[N,D]; 'whiten' keeps min(dims, D, N - 1) directions, those
    of them the views span (:data:`RANK_TOL`);
    'learned' needs the trained projection ``learned`` float32[k, D] (``dims`` does not apply) and
    is centred on ``learned_mean`` float32[D], the mean the training centred on (None: the mean of
    ``vectors``, which is that mean only for the library the projection was trained on)."""
    if method not in METHODS:
        raise ValueError(f"unknown whitening {method!r} (known: {', '.join(METHODS)})")
    v = np.asarray(vectors, np.float64)
    d = v.shape[1]
    if method == "learned":
        if learned is None or learned.ndim != 2 or learned.shape[1] != d:
            shape = None if learned is None else list(learned.shape)
            raise ValueError(f"the learned projection must be float32[k, {d}] for {d}-d descriptors, got {shape}")
        mean = learned_mean if learned_mean is not None else v.mean(0) if len(v) else np.zeros(d)
        return Whitening("learned", np.asarray(mean, np.float32), np.asarray(learned, np.float32))
    if method == "none" or len(v) == 0:
        return Whitening("none", np.zeros(d, np.float32), np.eye(d, dtype=np.float32))
    mean = v.mean(0)
    if method == "centre" or len(v) < 3:
        return Whitening("centre", mean.astype(np.float32), np.eye(d, dtype=np.float32))
    centred = v - mean
    eig, vecs = np.linalg.eigh(centred.T @ centred / (len(v) - 1))  # ascending; D x D, cheap for many views
    k = min(dims, d, len(v) - 1)
    eig, rows = np.clip(eig[::-1][:k], 0.0, None), vecs[:, ::-1][:, :k].T
    spanned = eig > max(RANK_TOL * eig[0], 1e-12)  # views that repeat span fewer directions: the others are LAPACK's choice
    if not spanned.any():
        return Whitening("centre", mean.astype(np.float32), np.eye(d, dtype=np.float32))
    eig, rows = eig[spanned], rows[spanned]
    k = len(eig)
    basis = rows * np.where(rows[np.arange(k), np.abs(rows).argmax(1)] < 0, -1, 1)[:, None]  # fixed signs
    projection = basis / np.sqrt(eig + SHRINKAGE * eig.mean() + 1e-12)[:, None]
    return Whitening("whiten", mean.astype(np.float32), projection.astype(np.float32))


def whitening_table(library: str, w: Whitening, views: int) -> pa.Table:
    """The library's ``embedding_whitening`` row."""
    return pa.Table.from_pylist([{
        "library": library, "method": w.method, "mean": w.mean.tolist(),
        "projection": w.projection.ravel().tolist(), "dims": int(w.projection.shape[0]), "views": views,
    }])


def read_whitening(wh: Warehouse, library: str) -> Whitening:
    """The whitening fitted on ``library`` (its ``cad_embed`` stage must have run)."""
    rows = wh.read("embedding_whitening", partitions=[library]).to_pylist()
    if not rows:
        raise LookupError(f"no embedding whitening for CAD library {library!r}: run its cad_embed stage first")
    r = rows[0]
    mean = np.asarray(r["mean"], np.float32)
    return Whitening(r["method"], mean, np.asarray(r["projection"], np.float32).reshape(r["dims"], len(mean)))
