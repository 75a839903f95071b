"""An upper bound on the optimum of clique partitioning (:mod:`tasks.tracking.partition`): what a
heuristic partition of a whole clip is measured against when the exact MILP is out of reach.

The problem as a multicut of the sparse graph: a variable ``x_e`` in [0, 1] per edge (1 = cut: the
two detections in different tracks), objective ``sum_e w_e (1 - x_e)``. A partition is a 0/1 ``x``
satisfying every cycle inequality ``x_e <= sum_{f in C - e} x_f`` (C a cycle through e); missing pairs
weigh 0, so the best such multicut has the optimum's value. Cannot-links (two nodes of one group)
are the same inequality with ``x_e`` fixed to 1: every path between the two nodes is cut somewhere;
and a node joins at most one node of a group: ``sum (1 - x_e) <= 1`` over its positive edges to
that group (the group-star inequalities, without which the LP half-joins a detection to every
detection of a neighbouring frame).

Relaxing ``x`` to [0, 1] and keeping only some cycle inequalities can only raise the maximum, so the
optimum of any such LP is an upper bound. :func:`upper_bound` solves it per connected component of
the positive edges (an optimal cluster lies inside one, and an edge between two components is
negative: cut for free) with ``scipy.optimize.linprog`` (HiGHS), adding violated cycle inequalities
round by round: for every repulsive pair (a negative edge, or a cannot-link) whose cut value exceeds
the shortest path between its nodes over the positive edges (lengths ``x``), the inequality of that
cycle (the conflicted cycles of Lange et al. 2018: one repulsive edge, the others attractive, are
the only ones the optimum of the relaxation needs); inequalities left slack are dropped between
rounds. Every round's LP solved to optimality is a valid bound (a relaxation), and the smallest is
reported; when the time or round limit stops the separation first, ``converged`` is False. Values are HiGHS's, within its optimality
tolerance (1e-7).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from tasks.tracking.partition_graph import Graph, renumber, subgraphs

MAX_ROUNDS = 100
"""Separation rounds per component, at most."""
VIOLATION = 1e-6
"""A cycle inequality counts as violated when it fails by more than this."""
NEW_CYCLES = (1000, 10)
"""Cycle inequalities added per round, the most violated first: at most the larger of 1000 and 10
per node of the component (an LP grows by a bounded step; on a 1000-node random instance, 1 per
node needed more rounds than the time limit allowed, unbounded rounds made each LP slow)."""
DROP_SLACK = 0.5
"""A cycle inequality is dropped from the next LP when its slack exceeds this."""
SOURCES_PER_BATCH = 256
"""Shortest-path searches run at once (memory: this many float[n] distance rows)."""
PATH_LENGTH_FLOOR = 1e-9
"""Added to every path length, so that edges with x = 0 stay edges (scipy.sparse may drop explicit zeros)."""


@dataclass(frozen=True)
class Bound:
    """:func:`upper_bound`'s result: ``value`` >= the optimum (sum over the positive components);
    ``trivial``: the sum of the positive weights (the bound with no cycle inequality); ``cycles``:
    inequalities in the final LPs; ``converged``: every component's last LP violates none."""

    value: float
    trivial: float
    components: int
    rounds: int
    cycles: int
    converged: bool
    seconds: float


@dataclass(frozen=True)
class _Repulsive:
    """The repulsive pairs of a component: nodes ``u``, ``v`` int[R], their edge int[R] (-1: a
    cannot-link that is no edge, its cut fixed to 1)."""

    u: np.ndarray
    v: np.ndarray
    edge: np.ndarray


def _repulsive_pairs(g: Graph) -> _Repulsive:
    """Negative edges between two groups, and every pair of nodes of one group (cannot-links, with
    edge -1: their cut is 1 whether or not they share an edge) of a component graph."""
    neg = np.flatnonzero((g.w < 0) if g.groups is None else (g.w < 0) & (g.groups[g.i] != g.groups[g.j]))
    u, v, e = [g.i[neg]], [g.j[neg]], [neg]
    if g.groups is not None:
        order = np.argsort(g.groups, kind="stable")
        for nodes in np.split(order, np.flatnonzero(np.diff(g.groups[order])) + 1):
            a, b = np.triu_indices(len(nodes), 1)
            u.append(nodes[a]), v.append(nodes[b]), e.append(np.full(len(a), -1, dtype=np.int64))
    return _Repulsive(np.concatenate(u), np.concatenate(v), np.concatenate(e))


def _paths(pred: np.ndarray, sources: np.ndarray, targets: np.ndarray, row_of: dict[int, int]) -> list[list[tuple[int, int]]]:
    """Node pairs along each shortest path from ``sources[k]`` to ``targets[k]`` (``pred``: Dijkstra's
    predecessors, one row per source, ``row_of``: source -> row)."""
    out = []
    for s, t in zip(sources.tolist(), targets.tolist()):
        row, path, x = pred[row_of[s]], [], t
        while x != s:
            p = int(row[x])
            path.append((p, x))
            x = p
        out.append(path)
    return out


def _separate(g: Graph, rep: _Repulsive, x: np.ndarray, current: set,
              deadline: float = float("inf")) -> tuple[list[tuple[float, int, tuple[int, ...]]], bool]:
    """(violated conflicted-cycle inequalities at ``x`` float[E]: (violation, repulsive pair index,
    its path's positive edges), one per violated pair (its shortest path), those not in ``current``;
    whether every pair was searched: the search stops between batches of sources once past
    ``deadline``, time.monotonic())."""
    pos = np.flatnonzero(g.w > 0)
    cut = np.where(rep.edge >= 0, x[np.maximum(rep.edge, 0)], 1.0)
    todo = np.flatnonzero(cut > VIOLATION)
    if len(todo) == 0 or len(pos) == 0:
        return [], True
    lengths = x[pos] + PATH_LENGTH_FLOOR
    G = sp.csr_matrix((np.concatenate([lengths, lengths]), (np.concatenate([g.i[pos], g.j[pos]]),
                                                          np.concatenate([g.j[pos], g.i[pos]]))), shape=(g.n, g.n))
    edge_of = {(int(a), int(b)): int(k) for a, b, k in zip(g.i[pos], g.j[pos], pos)}
    found = []
    sources = np.unique(rep.u[todo])
    for s in range(0, len(sources), SOURCES_PER_BATCH):
        if time.monotonic() > deadline:
            return found, False
        batch = sources[s:s + SOURCES_PER_BATCH]
        dist, pred = dijkstra(G, indices=batch, return_predecessors=True, limit=float(cut[todo].max()))
        row_of = {int(b): k for k, b in enumerate(batch.tolist())}
        mine = todo[np.isin(rep.u[todo], batch)]
        d = dist[[row_of[int(a)] for a in rep.u[mine].tolist()], rep.v[mine]]
        hit = mine[d + VIOLATION < cut[mine]]
        for k, path in zip(hit.tolist(), _paths(pred, rep.u[hit], rep.v[hit], row_of)):
            edges = tuple(sorted(edge_of[(min(a, b), max(a, b))] for a, b in path))
            violation = float(cut[k] - x[list(edges)].sum())
            if (k, edges) not in current and violation > VIOLATION:
                found.append((violation, k, edges))
    return found, True


def _component_bound(g: Graph, deadline: float, max_rounds: int) -> tuple[float, int, int, bool]:
    """(bound, rounds, inequalities, converged) of one positive component (see module docstring)."""
    from scipy.optimize import linprog

    rep = _repulsive_pairs(g)
    m = len(g.w)
    lb = _cannot_link_edges(g, m)
    bound = float(g.w[(g.w > 0) & (lb == 0)].sum())  # the optimum with no inequality
    stars, star_b = _star_rows(g)
    rows: list[tuple[int, tuple[int, ...]]] = []  # the cycle inequalities of the LP: (repulsive pair, path)
    for r in range(max_rounds):
        if time.monotonic() > deadline:
            return bound, r, len(rows), False
        A, b = _cycle_rows(rows, rep, m)
        res = linprog(g.w, A_ub=sp.vstack([stars, A]).tocsr(), b_ub=np.concatenate([star_b, b]),
                      bounds=np.stack([lb, np.ones(m)], axis=1), method="highs",
                      options={"time_limit": max(deadline - time.monotonic(), 1.0)})
        if res.status != 0:
            return bound, r, len(rows), False
        x = np.clip(res.x, 0.0, 1.0)
        bound = min(bound, float(g.w.sum() - res.fun))
        slack = res.ineqlin.residual[stars.shape[0]:]
        rows = [row for row, s in zip(rows, slack.tolist()) if s <= DROP_SLACK]  # drop the clearly inactive ones
        if time.monotonic() > deadline:
            return bound, r + 1, len(rows), False
        new, complete = _separate(g, rep, x, set(rows), deadline)
        if not new:
            return bound, r + 1, len(rows), complete
        new.sort(key=lambda t: (-t[0], t[1], t[2]))
        rows += [(k, path) for _, k, path in new[:max(NEW_CYCLES[0], NEW_CYCLES[1] * g.n)]]
    return bound, max_rounds, len(rows), False


def _cannot_link_edges(g: Graph, m: int) -> np.ndarray:
    """Lower bound float[E] of each edge's cut: 1 for edges between two nodes of one group, else 0."""
    if g.groups is None:
        return np.zeros(m)
    return (g.groups[g.i] == g.groups[g.j]).astype(np.float64)


def _star_rows(g: Graph) -> tuple[sp.csr_matrix, np.ndarray]:
    """Group-star inequalities: a node joins at most one node of any group, so over the positive
    edges from node c to the nodes of group G, ``sum (1 - x) <= 1``, i.e. ``-sum x <= 1 - k`` (k
    edges; rows only where k >= 2). Valid for every partition; they cut off the half-joins that the
    cycle inequalities of a cannot-link allow (x = 1/2 on both edges of c to two nodes of one frame)."""
    m = len(g.w)
    if g.groups is None:
        return sp.csr_matrix((0, m)), np.zeros(0)
    pos = np.flatnonzero(g.w > 0)
    node = np.concatenate([g.i[pos], g.j[pos]])
    other = np.concatenate([g.j[pos], g.i[pos]])
    edge = np.concatenate([pos, pos])
    dense = np.unique(g.groups, return_inverse=True)[1]  # 0..G-1: any group ids (negative ones collided)
    key = node * (int(dense.max()) + 1) + dense[other]
    uniq, row, count = np.unique(key, return_inverse=True, return_counts=True)
    keep = count[row] >= 2
    rows_kept, row = np.unique(row[keep], return_inverse=True)
    A = sp.csr_matrix((-np.ones(int(keep.sum())), (row, edge[keep])), shape=(len(rows_kept), m))
    return A, 1.0 - count[rows_kept]


def _cycle_rows(rows: list[tuple[int, tuple[int, ...]]], rep: _Repulsive, m: int) -> tuple[sp.csr_matrix, np.ndarray]:
    """The inequalities ``x_e - sum_path x_f <= 0`` (``<= -1`` for a cannot-link with no edge) as A x <= b."""
    r, c, val, b = [], [], [], np.zeros(len(rows))
    for k, (pair, path) in enumerate(rows):
        e = int(rep.edge[pair])
        if e >= 0:
            r.append(k), c.append(e), val.append(1.0)
        else:
            b[k] = -1.0
        r += [k] * len(path)
        c += list(path)
        val += [-1.0] * len(path)
    return sp.csr_matrix((val, (r, c)), shape=(len(rows), m)), b


def upper_bound(n: int, i, j, w, *, groups=None, time_limit: float = 60.0, max_rounds: int = MAX_ROUNDS) -> Bound:
    """Upper bound on the best objective of clique partitioning (same arguments as
    :func:`tasks.tracking.partition.solve`): the cycle LP relaxation per positive component, summed
    (module docstring). ``time_limit``: seconds for the whole graph; a component reached after it
    keeps the bound of its last LP solved (at worst the sum of its positive weights)."""
    t0 = time.monotonic()
    _, g = renumber(n, i, j, w, groups, None)
    deadline = t0 + time_limit
    value = trivial = 0.0
    comps = rounds = cycles = 0
    converged = True
    for _, sub in subgraphs(g):
        b, r, c, ok = _component_bound(sub, deadline, max_rounds)
        value, trivial = value + b, trivial + float(sub.w[sub.w > 0].sum())
        comps, rounds, cycles, converged = comps + 1, max(rounds, r), cycles + c, converged and ok
    return Bound(value, trivial, comps, rounds, cycles, converged, time.monotonic() - t0)
