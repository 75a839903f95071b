"""Near-optimality of the tracker's solver on whole clips (issue 21): the heuristic's objective
(:func:`tasks.tracking.partition.solve`) against an upper bound on the optimum
(:func:`tasks.tracking.partition_bound.upper_bound`, the cycle LP relaxation), where the exact MILP
is out of reach. The ratio objective / bound is a lower bound on objective / optimum."""

from __future__ import annotations

import time

import numpy as np

from tasks.tracking.partition import make_graph, objective, positive_components, solve
from tasks.tracking.partition_bound import upper_bound

TIME_LIMIT = 120.0
"""Seconds of the bound's LPs per graph (past it a graph keeps the bound of its last LP solved)."""


def bound_row(name: str, g, time_limit: float = TIME_LIMIT) -> dict:
    """One graph ``g`` = (n, i, j, w, groups): heuristic objective, upper bound, their ratio."""
    n, i, j, w, groups = g
    _, comp = positive_components(make_graph(n, i, j, w, groups))
    t0 = time.perf_counter()
    h = objective(solve(n, i, j, w, groups=groups), i, j, w)
    th = time.perf_counter() - t0
    b = upper_bound(n, i, j, w, groups=groups, time_limit=time_limit)
    return {"instance": name, "n": int(n), "edges": int(len(w)),
            "largest_component": int(np.bincount(comp).max()) if n else 0,
            "heuristic": round(h, 4), "bound": round(b.value, 4), "positive_weights": round(b.trivial, 4),
            "ratio": round(h / b.value, 6) if b.value > 0 else 1.0, "bound_converged": b.converged,
            "cycle_inequalities": b.cycles, "heuristic_s": round(th, 3), "bound_s": round(b.seconds, 2)}


def run(named_graphs, time_limit: float = TIME_LIMIT) -> dict:
    """:func:`bound_row` of each (name, graph), and the summary: the smallest ratio and the ratio of
    the summed objectives to the summed bounds."""
    rows = [bound_row(name, g, time_limit) for name, g in named_graphs]
    return {"rows": rows, "summary": {
        "graphs": len(rows), "converged": sum(r["bound_converged"] for r in rows),
        "min_ratio": min((r["ratio"] for r in rows), default=None),
        "sum_ratio": round(sum(r["heuristic"] for r in rows) / max(sum(r["bound"] for r in rows), 1e-12), 6) if rows else None}}
