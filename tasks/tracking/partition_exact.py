"""The exact clique partitioning solver (:func:`solve_exact`): a MILP (``scipy.optimize.milp``, HiGHS)
with triangle inequalities added lazily (solve, add the violated triangles, re-solve), per positive
component; for small instances: it is the reference of the tests and of ``bench/track_bench.py``."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from tasks.tracking.partition_graph import Graph, canonical_labels, renumber, solve_components


class ExactSolverError(RuntimeError):
    """The MILP did not reach optimality (too large, or out of time)."""


def _exact_component(g: Graph, time_limit: float, max_nodes: int) -> np.ndarray:
    from scipy.optimize import Bounds, LinearConstraint, milp

    n = g.n
    if n > max_nodes:
        raise ExactSolverError(f"a positive component has {n} nodes (> max_nodes = {max_nodes})")
    iu, ju = np.triu_indices(n, 1)
    m = len(iu)
    pid = np.full((n, n), -1, dtype=np.int64)
    pid[iu, ju] = np.arange(m)
    pid[ju, iu] = np.arange(m)
    c = np.zeros(m)
    c[pid[g.i, g.j]] = -g.w  # milp minimises; y = 1: same cluster
    ub = np.ones(m)
    if g.groups is not None:
        ub[g.groups[iu] == g.groups[ju]] = 0.0
    rows: list[tuple[int, int, int]] = []  # (p, q, r): y_p + y_q - y_r <= 1
    seen: set[tuple[int, int, int]] = set()
    for _ in range(200):
        if rows:
            r = np.arange(len(rows)).repeat(3)
            cols = np.array(rows, dtype=np.int64).ravel()
            vals = np.tile([1.0, 1.0, -1.0], len(rows))
            A = sp.csr_matrix((vals, (r, cols)), shape=(len(rows), m))
            cons = [LinearConstraint(A, -np.inf, 1.0)]
        else:
            cons = []
        res = milp(c, integrality=np.ones(m), bounds=Bounds(np.zeros(m), ub), constraints=cons,
                   options={"time_limit": time_limit, "presolve": True, "mip_rel_gap": 0.0})  # optimal, not within 0.01 %
        if res.status != 0 or res.x is None:
            raise ExactSolverError(f"MILP not solved to optimality: {res.message}")
        y = np.round(res.x).astype(bool)
        # violated triangles: u~v, v~w, not u~w
        Y = np.zeros((n, n), dtype=bool)
        Y[iu[y], ju[y]] = True
        Y |= Y.T
        new = 0
        for v in range(n):
            nb = np.flatnonzero(Y[v])
            if len(nb) < 2:
                continue
            a, b = np.triu_indices(len(nb), 1)
            u, x = nb[a], nb[b]
            bad = ~Y[u, x]
            for uu, xx in zip(u[bad].tolist(), x[bad].tolist()):
                t = (int(pid[uu, v]), int(pid[v, xx]), int(pid[uu, xx]))
                if t not in seen:
                    seen.add(t)
                    rows.append(t)
                    new += 1
        if new == 0:
            _, lab = connected_components(sp.csr_matrix(Y), directed=False)
            return lab
    raise ExactSolverError("MILP: triangle separation did not converge")


def solve_exact(n: int, i, j, w, *, groups=None, keys=None, time_limit: float = 60.0,
                max_nodes: int = 120) -> np.ndarray:
    """Optimal clique partitioning by MILP (HiGHS), per positive component; small instances only.

    Raises :class:`ExactSolverError` when a component is larger than ``max_nodes`` or HiGHS does not
    prove optimality within ``time_limit`` seconds (per MILP call)."""
    rank, g = renumber(n, i, j, w, groups, keys)
    lab = solve_components(g, lambda sub: _exact_component(sub, time_limit, max_nodes))
    return canonical_labels(lab[rank], keys)
