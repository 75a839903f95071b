"""Upper bound on the clique partitioning optimum (tasks/tracking/partition_bound.py): bound >= optimum >= heuristic."""

from __future__ import annotations

import numpy as np
import pytest

from tasks.tracking.partition import objective, solve, solve_exact
from tasks.tracking.partition_bound import upper_bound
from tests.test_track_partition import tracking_instance

TOL = 1e-6  # HiGHS's optimality tolerance is 1e-7


@pytest.mark.parametrize("seed", range(8))
def test_bound_is_at_least_the_exact_optimum(seed):
    n, i, j, w, groups = tracking_instance(int(np.random.default_rng(seed).integers(12, 30)), seed, noise=0.5)
    h = objective(solve(n, i, j, w, groups=groups), i, j, w)
    e = objective(solve_exact(n, i, j, w, groups=groups), i, j, w)
    b = upper_bound(n, i, j, w, groups=groups)
    assert b.converged and b.value >= e - TOL and e >= h - TOL
    assert b.value < b.trivial  # the cycle and star inequalities do cut the trivial bound here
    assert b.value <= e * 1.02  # and come close: on these instances the relaxation is nearly tight


def test_negative_group_ids_keep_the_bound_valid():
    """Group-star rows were keyed by node x (max group + 1) + group: negative ids collided, merged
    rows of different nodes into one invalid inequality, and the bound fell below the optimum."""
    i, j, w = [0, 0, 1], [1, 2, 2], [-0.23, 0.87, 0.24]
    e = objective(solve_exact(3, i, j, w, groups=[-3, 1, -1]), i, j, w)
    assert upper_bound(3, i, j, w, groups=[-3, 1, -1]).value >= e - TOL
    assert upper_bound(3, i, j, w, groups=[-3, 1, -1]).value == pytest.approx(upper_bound(3, i, j, w, groups=[0, 2, 1]).value)


def test_bound_equals_the_optimum_when_the_relaxation_is_integral():
    # three cliques of detections over frames, attractive inside, repulsive across: the optimum joins
    # each clique, and so does the LP (no inequality is violated by the integral solution)
    rng = np.random.default_rng(0)
    obj = np.repeat(np.arange(3), 6)
    frame = np.tile(np.arange(6), 3)
    i, j = np.triu_indices(len(obj), 1)
    keep = frame[i] != frame[j]
    i, j = i[keep], j[keep]
    w = np.where(obj[i] == obj[j], rng.uniform(0.5, 2, len(i)), -rng.uniform(0.5, 2, len(i)))
    b = upper_bound(len(obj), i, j, w, groups=frame)
    e = objective(solve_exact(len(obj), i, j, w, groups=frame), i, j, w)
    assert e == pytest.approx(w[w > 0].sum())
    assert b.converged and b.value == pytest.approx(e, abs=TOL)


def test_cycle_inequality_cuts_a_conflicted_triangle():
    # a-b and b-c attract (1 each), a-c repels (-1.5): the best is one pair (1); all positive edges: 2
    b = upper_bound(3, [0, 1, 0], [1, 2, 2], [1.0, 1.0, -1.5])
    assert b.trivial == 2.0 and b.value == pytest.approx(1.0, abs=TOL) and b.cycles >= 1


def test_star_inequality_cuts_half_joins_to_one_frame():
    # c (frame 1) attracts a, b, d (all frame 0) by 1 each: c joins one of them (1). The cycle
    # inequalities of the cannot-links alone allow x = 1/2 on each edge (1.5); the star does not.
    b = upper_bound(4, [3, 3, 3], [0, 1, 2], [1.0, 1.0, 1.0], groups=[0, 0, 0, 1])
    assert b.trivial == 3.0 and b.value == pytest.approx(1.0, abs=TOL)


def test_components_add_up_and_a_spent_time_limit_keeps_a_valid_bound():
    n, i, j, w, groups = tracking_instance(40, 3, noise=0.5)
    shifted = (i + n, j + n)  # a second copy of the graph, disconnected from the first
    both = upper_bound(2 * n, np.concatenate([i, shifted[0]]), np.concatenate([j, shifted[1]]), np.concatenate([w, w]),
                       groups=np.concatenate([groups, groups + groups.max() + 1]))
    one = upper_bound(n, i, j, w, groups=groups)
    assert both.value == pytest.approx(2 * one.value, abs=TOL) and both.components == 2 * one.components
    out_of_time = upper_bound(n, i, j, w, groups=groups, time_limit=0.0)
    assert not out_of_time.converged and out_of_time.value == pytest.approx(out_of_time.trivial)
    assert out_of_time.value >= objective(solve_exact(n, i, j, w, groups=groups), i, j, w)


def test_the_cycle_search_stops_at_the_deadline_and_says_it_did_not_finish():
    """A large graph's search for violated cycles ran 2-3x past the bound's time limit; it now
    stops between batches of sources once past the deadline, and the bound is then not converged."""
    from tasks.tracking.partition_bound import _repulsive_pairs, _separate
    from tasks.tracking.partition_graph import renumber

    _, g = renumber(3, np.array([0, 1, 0]), np.array([1, 2, 2]), np.array([1.0, 1.0, -1.5]), None, None)
    x = (g.w < 0).astype(np.float64)  # a-b, b-c joined, a-c cut (x = 1): the triangle's cycle inequality is violated
    found, complete = _separate(g, _repulsive_pairs(g), x, set())
    assert complete and len(found) == 1
    assert _separate(g, _repulsive_pairs(g), x, set(), deadline=0.0) == ([], False)
