"""Clique partitioning (correlation clustering) of a sparse signed graph: the solver of ``tracking``.

Problem: nodes ``0..n-1``, undirected edges ``(i, j, w)`` (``w > 0`` attracts, ``w < 0`` repels;
missing pairs weigh 0) and optional ``groups`` (e.g. the frame of each detection: two nodes of one
group may never share a cluster, a hard cannot-link). Find labels maximising
:func:`objective`, the summed weight of the edges inside clusters, under the cannot-links.

Solvers:
- :func:`solve`: the fast heuristic. The graph is first split into the connected components of
  its positive edges (exact: an optimal cluster never spans two of them, since cutting it along
  a cut with no positive edge never lowers the objective); each component is solved by greedy
  additive edge contraction (GAEC, Keuper et al. 2015: contract the most attractive edge, sum
  parallel edges, repeat while one is positive) and refined by local search in the spirit of
  Kernighan-Lin: single-node moves (to a neighbouring cluster or out to a new one, best gain
  first), group reassignments (all nodes of one group, e.g. the detections of a frame, moved at
  once by an optimal linear assignment to the other clusters: the swaps and eviction chains that
  single moves cannot make under the cannot-links), KL between pairs of clusters, and cluster
  joins, until none improves. Components of at most a few hundred nodes are solved again from
  a few deterministic GAEC runs on perturbed weights (:func:`restarts_for`) and the best
  partition is kept; large ones get the single run, so their time stays that of one run.
- :func:`solve_exact`: the MILP (``scipy.optimize.milp``, HiGHS) with triangle inequalities added
  lazily (solve, add the violated triangles, re-solve), per positive component; for small
  instances: it is the reference of the tests and of ``bench/track_bench.py``.

Determinism: the result depends only on the graph, not on the order of nodes or edges. Nodes are
renumbered by ``keys`` (stable ids, e.g. detection ids; default: their index), edges are merged
and sorted, every tie is broken by node ids, and the returned labels are numbered by the smallest
key of each cluster.

Modules: :mod:`tasks.tracking.partition_graph` (the canonical graph, objective, labels, positive
components), :mod:`tasks.tracking.partition_gaec` (GAEC), :mod:`tasks.tracking.partition_local_search`
(:func:`refine`), :mod:`tasks.tracking.partition_exact` (the MILP); this one holds :func:`solve`, its
restarts, and every public name of the four. :mod:`tasks.tracking.partition_bound` bounds the optimum
from above (the cycle LP relaxation), for whole clips where the MILP cannot go.
"""

from __future__ import annotations

import numpy as np

from tasks.tracking.partition_exact import ExactSolverError, solve_exact
from tasks.tracking.partition_gaec import gaec
from tasks.tracking.partition_graph import (EPS, Graph, canonical_labels, feasible, make_graph, objective,
                                            positive_components, renumber, solve_components)
from tasks.tracking.partition_local_search import refine

__all__ = ["EPS", "ExactSolverError", "Graph", "canonical_labels", "feasible", "gaec", "make_graph", "objective",
           "positive_components", "refine", "restarts_for", "solve", "solve_exact"]

MAX_RESTARTS = 8
"""Restarts of GAEC + local search per positive component (perturbed weights), at most."""
RESTART_WORK = 800
"""A component of ``n`` nodes gets ``min(MAX_RESTARTS, RESTART_WORK // n)`` restarts: small ones
(the tracker's usual components: 10-300 detections) all of them, ones over 800 nodes none, so the
time of large graphs stays that of one run."""
RESTART_NOISE = 0.6
"""Std of the log-normal factor applied to each weight for a restart's GAEC (signs kept)."""


def restarts_for(n: int) -> int:
    """Number of perturbed restarts a component of ``n`` nodes gets (see RESTART_WORK)."""
    return min(MAX_RESTARTS, RESTART_WORK // max(n, 1))


def _multistart(g: Graph, lab: np.ndarray) -> np.ndarray:
    """Best of ``lab`` (GAEC + refine) and :func:`restarts_for` restarts: GAEC on the weights times
    ``exp(RESTART_NOISE * z)`` (z standard normal, generator seeded by the restart number and drawn
    in the canonical edge order, so deterministic and independent of the input order), each
    refined on the true weights. Stops early at the bound of all positive weights inside clusters
    (the partition is then optimal); ties keep the earlier result."""
    best = objective(lab, g.i, g.j, g.w)
    bound = float(g.w[g.w > 0].sum())
    for r in range(restarts_for(g.n)):
        if best >= bound - EPS:
            break
        z = np.random.default_rng(r).standard_normal(len(g.w))
        cand = refine(g, gaec(Graph(g.n, g.i, g.j, g.w * np.exp(RESTART_NOISE * z), g.groups)))
        o = objective(cand, g.i, g.j, g.w)
        if o > best + EPS:
            best, lab = o, cand
    return lab


def solve(n: int, i, j, w, *, groups=None, keys=None, refine_result: bool = True,
          multistart: bool = True) -> np.ndarray:
    """Heuristic clique partitioning (GAEC + local search, best of restarts on components of at
    most a few hundred nodes); labels numbered by smallest key.

    Args:
        n: number of nodes; ``i, j, w``: edges (any order, parallel edges are summed);
        groups: int[n], nodes of one group never share a cluster (e.g. detections of one frame);
        keys: unique sortable ids of the nodes (the result does not depend on node order given them);
        refine_result: False for GAEC alone; multistart: False for one GAEC + local search run.
    """
    rank, g = renumber(n, i, j, w, groups, keys)

    def one(sub: Graph) -> np.ndarray:
        lab = gaec(sub)
        if not refine_result:
            return lab
        lab = refine(sub, lab)
        return _multistart(sub, lab) if multistart else lab

    lab_canon = solve_components(g, one)
    return canonical_labels(lab_canon[rank], keys)
