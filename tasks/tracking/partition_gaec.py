"""Greedy additive edge contraction (GAEC, Keuper et al. 2015), the start of the heuristic solver
(:func:`tasks.tracking.partition.solve`): contract the most attractive edge, sum parallel edges,
repeat while one is positive; two nodes of one group (cannot-link) are never contracted."""

from __future__ import annotations

import heapq

import numpy as np

from tasks.tracking.partition_graph import Graph


def _masks(g: Graph) -> list[int]:
    """Per node a Python int bit set of its group (cannot-link test = bitwise and)."""
    if g.groups is None:
        return [0] * g.n
    _, dense = np.unique(g.groups, return_inverse=True)
    return [1 << int(x) for x in dense.tolist()]


def gaec(g: Graph) -> np.ndarray:
    """Greedy additive edge contraction: labels (cluster representatives) of a canonical graph."""
    n = g.n
    rows = np.concatenate([g.i, g.j])
    order = np.argsort(rows, kind="stable")
    ptr = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=n))]).tolist()
    nb, wt = np.concatenate([g.j, g.i])[order].tolist(), np.concatenate([g.w, g.w])[order].tolist()
    adj: list[dict[int, float]] = [dict(zip(nb[ptr[v]:ptr[v + 1]], wt[ptr[v]:ptr[v + 1]])) for v in range(n)]
    mask = _masks(g)
    start = g.w > 0
    if g.groups is not None:
        start &= g.groups[g.i] != g.groups[g.j]
    heap = list(zip((-g.w[start]).tolist(), g.i[start].tolist(), g.j[start].tolist()))
    heapq.heapify(heap)
    parent = list(range(n))
    alive = [True] * n
    push, pop = heapq.heappush, heapq.heappop
    while heap:
        negx, a, b = pop(heap)
        if not (alive[a] and alive[b]) or adj[a].get(b) != -negx:
            continue  # stale entry
        if mask[a] & mask[b]:
            continue
        # merge the node with fewer neighbours into the other (ties: the larger id into the smaller)
        if len(adj[a]) < len(adj[b]) or (len(adj[a]) == len(adj[b]) and a > b):
            a, b = b, a
        keep, gone = a, b
        ak, ag = adj[keep], adj[gone]
        del ak[gone]
        del ag[keep]
        m = mask[keep] | mask[gone]
        mask[keep] = m
        for c, x in ag.items():
            ac = adj[c]
            del ac[gone]
            y = ak.get(c, 0.0) + x
            ak[c] = y
            ac[keep] = y
            if y > 0 and not (m & mask[c]):
                push(heap, (-y, keep, c) if keep < c else (-y, c, keep))
        ag.clear()
        alive[gone] = False
        parent[gone] = keep
    labels = np.array(parent, dtype=np.int64)
    while True:  # path compression
        nxt = labels[labels]
        if np.array_equal(nxt, labels):
            return labels
        labels = nxt
