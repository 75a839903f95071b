"""The signed graph of clique partitioning (:mod:`tasks.tracking.partition`): its canonical form,
the objective and the cannot-link check, canonical labels, and the split into the connected components
of the positive edges, which every solver solves one at a time.

Determinism starts here: nodes are renumbered by ``keys`` (stable ids, e.g. detection ids; default:
their index), edges are merged and sorted, and labels are numbered by the smallest key of each cluster.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

EPS = 1e-9
"""Smallest gain that counts as an improvement (guards against float round-off loops)."""


@dataclass(frozen=True)
class Graph:
    """A canonical graph: ``i < j``, each pair once (parallel edges summed), sorted by (i, j)."""

    n: int
    i: np.ndarray  # int64[E]
    j: np.ndarray  # int64[E]
    w: np.ndarray  # float64[E]
    groups: np.ndarray | None  # int64[n] or None


def make_graph(n: int, i, j, w, groups=None) -> Graph:
    """Validate and canonicalise an edge list (self-loops dropped, parallel edges summed, zeros dropped)."""
    i = np.asarray(i, dtype=np.int64).ravel()
    j = np.asarray(j, dtype=np.int64).ravel()
    w = np.asarray(w, dtype=np.float64).ravel()
    if not (len(i) == len(j) == len(w)):
        raise ValueError("i, j and w must have the same length")
    if len(i) and (min(i.min(), j.min()) < 0 or max(i.max(), j.max()) >= n):
        raise ValueError(f"edge endpoints must lie in [0, {n})")
    if not np.all(np.isfinite(w)):
        raise ValueError("edge weights must be finite (use groups for cannot-links)")
    a, b = np.minimum(i, j), np.maximum(i, j)
    keep = a != b
    a, b, w = a[keep], b[keep], w[keep]
    code = a * n + b
    order = np.lexsort((w, code))  # sum parallel edges in a fixed order
    code, w = code[order], w[order]
    uniq, start = np.unique(code, return_index=True)
    w = np.add.reduceat(w, start) if len(w) else w
    nz = w != 0
    uniq, w = uniq[nz], w[nz]
    g = None if groups is None else np.asarray(groups, dtype=np.int64).ravel()
    if g is not None and len(g) != n:
        raise ValueError("groups must have one entry per node")
    return Graph(n, uniq // n, uniq % n, w, g)


def objective(labels, i, j, w) -> float:
    """Summed weight of the edges whose endpoints share a label (what the solvers maximise)."""
    labels = np.asarray(labels)
    i, j, w = np.asarray(i, dtype=np.int64), np.asarray(j, dtype=np.int64), np.asarray(w, dtype=np.float64)
    return float(w[labels[i] == labels[j]].sum())


def feasible(labels, groups) -> bool:
    """Whether no cluster holds two nodes of one group."""
    if groups is None:
        return True
    pairs = np.stack([np.asarray(labels, dtype=np.int64), np.asarray(groups, dtype=np.int64)], axis=1)
    return len(np.unique(pairs, axis=0)) == len(pairs)


def canonical_labels(labels, keys=None) -> np.ndarray:
    """Relabel clusters 0, 1, ... in the order of the smallest key of each (keys default: index)."""
    labels = np.asarray(labels, dtype=np.int64)
    keys = np.arange(len(labels)) if keys is None else np.asarray(keys)
    order = np.lexsort((keys,))
    first: dict[int, int] = {}
    for lab in labels[order].tolist():
        if lab not in first:
            first[lab] = len(first)
    return np.array([first[lab] for lab in labels.tolist()], dtype=np.int64)


def renumber(n: int, i, j, w, groups, keys) -> tuple[np.ndarray, Graph]:
    """Renumber nodes by ``keys`` (rank order); returns (rank of each original node, canonical graph)."""
    keys = np.arange(n) if keys is None else np.asarray(keys)
    if len(keys) != n:
        raise ValueError("keys must have one entry per node")
    order = np.lexsort((keys,))
    if len(np.unique(keys)) != n:
        raise ValueError("keys must be unique")
    rank = np.empty(n, dtype=np.int64)
    rank[order] = np.arange(n)
    i = rank[np.asarray(i, dtype=np.int64)] if len(np.asarray(i)) else np.asarray(i, dtype=np.int64)
    j = rank[np.asarray(j, dtype=np.int64)] if len(np.asarray(j)) else np.asarray(j, dtype=np.int64)
    g = None if groups is None else np.asarray(groups, dtype=np.int64)[order]
    return rank, make_graph(n, i, j, w, g)


def positive_components(g: Graph) -> tuple[int, np.ndarray]:
    """Connected components of the positive edges (an optimal cluster lies inside one)."""
    pos = g.w > 0
    m = sp.coo_matrix((np.ones(int(pos.sum())), (g.i[pos], g.j[pos])), shape=(g.n, g.n))
    return connected_components(m, directed=False)


def subgraphs(g: Graph):
    """Yield (nodes, subgraph) per positive component with at least one edge; nodes ascending."""
    k, comp = positive_components(g)
    if k == 0:
        return
    sizes = np.bincount(comp, minlength=k)
    same = comp[g.i] == comp[g.j]
    ei, ej, ew = g.i[same], g.j[same], g.w[same]
    ec = comp[ei]
    order = np.argsort(ec, kind="stable")
    ei, ej, ew, ec = ei[order], ej[order], ew[order], ec[order]
    bounds = np.searchsorted(ec, np.arange(k + 1))
    node_order = np.argsort(comp, kind="stable")  # nodes ascending within each component
    node_bounds = np.concatenate([[0], np.cumsum(sizes)])
    local = np.empty(g.n, dtype=np.int64)
    for c in range(k):
        if sizes[c] < 2:
            continue
        nodes = node_order[node_bounds[c]:node_bounds[c + 1]]
        local[nodes] = np.arange(len(nodes))
        s, e = bounds[c], bounds[c + 1]
        groups = None if g.groups is None else g.groups[nodes]
        yield nodes, Graph(len(nodes), local[ei[s:e]], local[ej[s:e]], ew[s:e], groups)


def solve_components(g: Graph, solver) -> np.ndarray:
    """Labels of ``g`` from ``solver`` (a canonical graph -> labels) run on each positive component
    with an edge; every other node is a cluster of its own. A label is its cluster's smallest node id."""
    labels = np.arange(g.n, dtype=np.int64)
    for nodes, sub in subgraphs(g):
        cl = canonical_labels(solver(sub))
        first = np.unique(cl, return_index=True)[1]
        labels[nodes] = nodes[first[cl]]  # label = the cluster's smallest node id
    return labels
