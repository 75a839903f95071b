"""Local search from a partition (:func:`refine`), in the spirit of Kernighan-Lin: single-node moves
(to a neighbouring cluster or out to a new one, best gain first), group reassignments (all nodes of
one group, e.g. the detections of a frame, moved at once by an optimal linear assignment to the other
clusters: the swaps and eviction chains that single moves cannot make under the cannot-links), KL
between pairs of clusters, and cluster joins, repeated until none improves."""

from __future__ import annotations

import heapq
from collections import Counter

import numpy as np
import scipy.sparse as sp

from tasks.tracking.partition_graph import EPS, Graph, canonical_labels


def _adjacency(W: sp.csr_matrix) -> list[list[tuple[int, float]]]:
    """Per node its (neighbour, weight) list, from the symmetric CSR matrix (built once per refine)."""
    ind, dat, ptr = W.indices.tolist(), W.data.tolist(), W.indptr.tolist()
    return [list(zip(ind[ptr[v]:ptr[v + 1]], dat[ptr[v]:ptr[v + 1]])) for v in range(W.shape[0])]


class _State:
    """Clusters as label array + member sets + group occupancy; adjacency (shared, read-only) for exact gains."""

    def __init__(self, g: Graph, labels: np.ndarray, adj: list[list[tuple[int, float]]]):
        self.g = g
        self.adj = adj
        self.labels = canonical_labels(labels).tolist()
        self.groups = None if g.groups is None else g.groups.tolist()
        self.members: dict[int, set[int]] = {}
        for v, c in enumerate(self.labels):
            self.members.setdefault(c, set()).add(v)
        # nodes per (cluster, group): counted, as a swap moves a node in before its group's other one leaves
        self.occupied: Counter[tuple[int, int]] = Counter()
        if self.groups is not None:
            self.occupied = Counter((c, self.groups[v]) for v, c in enumerate(self.labels))
        self.next_label = g.n  # fresh labels for nodes moved out
        self.local = np.full(g.n, -1, dtype=np.int64)  # scratch of _kl_pair (node -> local index), all -1 between uses
        self.lab_np = np.array(self.labels, dtype=np.int64)  # labels as an array (kept in step by move)
        self.touched: list[int] = []  # nodes moved (read and cleared by refine's group reassignments)

    def weights_to(self, v: int) -> dict[int, float]:
        out: dict[int, float] = {}
        lab = self.labels
        for u, x in self.adj[v]:
            c = lab[u]
            out[c] = out.get(c, 0.0) + x
        return out

    def allowed(self, v: int, c: int) -> bool:
        return self.groups is None or self.occupied[(c, self.groups[v])] == 0

    def move(self, v: int, c: int) -> None:
        old = self.labels[v]
        self.members[old].discard(v)
        if not self.members[old]:
            del self.members[old]
        self.members.setdefault(c, set()).add(v)
        self.labels[v] = c
        self.lab_np[v] = c
        self.touched.append(v)
        if self.groups is not None:
            self.occupied[(old, self.groups[v])] -= 1
            self.occupied[(c, self.groups[v])] += 1

    def best_move(self, v: int) -> tuple[float, int]:
        """(gain, target) of the best move of ``v``; target -1 = a new cluster of its own."""
        wt = self.weights_to(v)
        own_c = self.labels[v]
        own = wt.get(own_c, 0.0)
        best_gain, best_c = (-own, -1) if len(self.members[own_c]) > 1 else (0.0, own_c)
        for c in sorted(wt):
            if c == own_c:
                continue
            gain = wt[c] - own
            if gain > best_gain + EPS and self.allowed(v, c):
                best_gain, best_c = gain, c
        return best_gain, best_c


def _kl_pair(st: _State, W: sp.csr_matrix, a: int, b: int, max_moves: int) -> float:
    """Kernighan-Lin between clusters ``a`` and ``b`` (``b`` may be a fresh, empty label): move
    nodes one at a time to the other side, best gain first (gains may be negative), each node at
    most once; keep the best prefix of the sequence if it improves. Returns the gain applied."""
    lab, groups = st.labels, st.groups
    nodes = np.array(sorted(st.members.get(a, set()) | st.members.get(b, set())), dtype=np.int64)
    m = len(nodes)
    # the submatrix W[nodes][:, nodes] in CSR form (local indices 0..m-1), gathered from W's arrays
    starts, cnt = W.indptr[nodes], W.indptr[nodes + 1] - W.indptr[nodes]
    ends = np.cumsum(cnt)
    idx = np.arange(ends[-1] if m else 0) + np.repeat(starts - ends + cnt, cnt)
    local = st.local
    local[nodes] = np.arange(m)
    cols = local[W.indices[idx]]
    local[nodes] = -1
    keep = cols >= 0
    rows = np.repeat(np.arange(m), cnt)[keep]
    indices, data = cols[keep], W.data[idx][keep]
    indptr = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=m))]).tolist()
    side = np.array([0 if lab[v] == a else 1 for v in nodes.tolist()], dtype=np.int64)
    sign = np.where(side[rows] != side[indices], 1.0, -1.0)
    D = np.bincount(rows, weights=data * sign, minlength=m).tolist()
    side_l = side.tolist()
    indices, data = indices.tolist(), data.tolist()
    gl = None if groups is None else [groups[v] for v in nodes.tolist()]
    owner: list[dict[int, int]] = [{}, {}]  # group -> its node on each side (at most one: feasible)
    if gl is not None:
        for k, s_k in enumerate(side_l):
            owner[s_k][gl[k]] = k
    heap = [(-d, k) for k, d in enumerate(D)]
    heapq.heapify(heap)
    moved: set[int] = set()
    seq: list[int] = []
    total = best = 0.0
    best_len = 0

    def flip(k: int) -> None:
        nonlocal total
        s_k = side_l[k]
        moved.add(k)
        seq.append(k)
        total += D[k]
        side_l[k] = 1 - s_k
        if gl is not None:
            if owner[s_k].get(gl[k]) == k:
                del owner[s_k][gl[k]]
            owner[1 - s_k][gl[k]] = k
        lo, hi = indptr[k], indptr[k + 1]
        for u, x in zip(indices[lo:hi], data[lo:hi]):
            if u in moved:
                continue
            D[u] += 2 * x if side_l[u] == s_k else -2 * x
            heapq.heappush(heap, (-D[u], u))

    while heap and len(seq) < max_moves:
        negd, k = heapq.heappop(heap)
        if k in moved or -negd != D[k]:
            continue
        partner = None if gl is None else owner[1 - side_l[k]].get(gl[k])
        if partner is not None:
            if partner in moved:
                continue  # k would join a node of its own group for good
            flip(k)  # swap: k and the node of its group on the other side change sides together
            flip(partner)
        else:
            flip(k)
        if total > best + EPS:
            best, best_len = total, len(seq)
    nl = nodes.tolist()
    for k in seq[:best_len]:
        v = nl[k]
        st.move(v, b if lab[v] == a else a)
    return best


def _kernighan_lin(st: _State, W: sp.csr_matrix, budget: list[int], tried: set, max_moves: int = 100,
                   max_passes: int = 10) -> bool:
    """KL over every pair of clusters joined by an attractive edge, and every cluster against a
    new empty one; repeated (on the clusters that changed) while it improves. Returns whether
    anything changed.

    ``tried``: the KL runs that found no gain, by the node sets they ran on (a run depends on those
    alone: the edges inside the two clusters), shared by the rounds of :func:`refine`; such a run
    is not repeated (it would find no gain again), nor charged to the budget."""
    g = st.g
    changed_any = False
    dirty = set(st.members)
    for _ in range(max_passes):
        if budget[0] <= 0:
            break
        lab = np.array(st.labels, dtype=np.int64)
        la, lb = lab[g.i], lab[g.j]
        across = (g.w > 0) & (la != lb)
        ca, cb = np.minimum(la[across], lb[across]), np.maximum(la[across], lb[across])
        pairs = np.unique(np.stack([ca, cb], axis=1), axis=0) if across.any() else np.empty((0, 2), np.int64)
        improved: set[int] = set()
        for a, b in pairs.tolist():
            if (a in dirty or b in dirty) and a not in improved and b not in improved \
                    and a in st.members and b in st.members:
                if budget[0] <= 0:
                    break
                key = frozenset((frozenset(st.members[a]), frozenset(st.members[b])))
                if key in tried:
                    continue
                budget[0] -= len(st.members[a]) + len(st.members[b])
                if _kl_pair(st, W, a, b, max_moves) > EPS:
                    improved.update((a, b))
                else:
                    tried.add(key)
        for a in sorted(dirty):
            if a in st.members and len(st.members[a]) > 1 and a not in improved and budget[0] > 0:
                key = frozenset(st.members[a])
                if key in tried:
                    continue
                budget[0] -= len(st.members[a])
                fresh = st.next_label
                st.next_label += 1
                if _kl_pair(st, W, a, fresh, max_moves) > EPS:
                    improved.update((a, fresh))
                else:
                    tried.add(key)
        if not improved:
            break
        changed_any = True
        dirty = improved
    return changed_any


def _candidate_moves(g: Graph, labels: np.ndarray, W: sp.csr_matrix) -> np.ndarray:
    """Nodes that have an improving move allowed by the cannot-links (vectorised screen; gains are
    checked again exactly, one move at a time, after)."""
    n = g.n
    lab = np.asarray(labels, dtype=np.int64)
    M = sp.csr_matrix((np.ones(n), (np.arange(n), lab)), shape=(n, int(lab.max()) + 1))
    S = (W @ M).tocoo()
    own = np.asarray(S.tocsr()[np.arange(n), lab]).ravel()
    other = S.col != lab[S.row]
    gains = S.data[other] - own[S.row[other]]
    rows, cols = S.row[other][gains > EPS], S.col[other][gains > EPS]
    if g.groups is not None and len(rows):  # drop the moves into a cluster that holds the node's group
        _, grp = np.unique(g.groups, return_inverse=True)
        k = int(grp.max()) + 1
        occupied = np.unique(lab * k + grp)
        rows = rows[~np.isin(cols * k + grp[rows], occupied)]
    cand = np.zeros(n, dtype=bool)
    cand[rows] = True
    cand |= own < -EPS  # leaving to a new cluster improves
    return np.flatnonzero(cand)


def _blocked_groups(g: Graph, labels, Wx: sp.csr_matrix) -> list[int]:
    """Groups holding a node that some other cluster (or a cluster of its own) attracts more than
    its own, counting only edges across groups (vectorised screen): outside them the current
    assignment of the group is optimal for :func:`_reassign_group` (each node is at its best)."""
    n = g.n
    lab = np.asarray(labels, dtype=np.int64)
    _, lab = np.unique(lab, return_inverse=True)
    M = sp.csr_matrix((np.ones(n), (np.arange(n), lab)), shape=(n, int(lab.max()) + 1))
    S = (Wx @ M).tocsr()
    own = np.asarray(S[np.arange(n), lab]).ravel()
    best = np.maximum(S.max(axis=1).toarray().ravel(), 0.0)
    return np.unique(g.groups[best > own + EPS]).tolist()


def _gather_rows(W: sp.csr_matrix, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The entries of ``W``'s ``rows``: (position of the row in ``rows``, column, value)."""
    starts, cnt = W.indptr[rows], W.indptr[rows + 1] - W.indptr[rows]
    ends = np.cumsum(cnt)
    idx = np.arange(ends[-1] if len(rows) else 0) + np.repeat(starts - ends + cnt, cnt)
    return np.repeat(np.arange(len(rows)), cnt), W.indices[idx], W.data[idx]


def _reassign_group(st: _State, rows: np.ndarray, entries: tuple[np.ndarray, np.ndarray, np.ndarray]) -> float:
    """Optimal reassignment of all nodes of one group at once, the rest fixed: a linear assignment
    of the nodes to the clusters of the others (or to clusters of their own), since at most one
    node of the group may join each cluster and same-group edges never count. ``entries``: the
    group's rows of the across-group weight matrix (:func:`_gather_rows`). Returns the gain applied
    (0 when the current assignment is optimal)."""
    from scipy.optimize import linear_sum_assignment

    r, nb, x = entries
    k = len(rows)
    cl, inv = np.unique(st.lab_np[nb], return_inverse=True)  # clusters the group's nodes see, ascending
    A = np.bincount(r * len(cl) + inv, weights=x, minlength=k * len(cl)).reshape(k, len(cl))
    own = np.searchsorted(cl, st.lab_np[rows])
    hit = own < len(cl)
    hit[hit] = cl[own[hit]] == st.lab_np[rows][hit]
    cur = float(A[np.flatnonzero(hit), own[hit]].sum())
    keep = (A > EPS).any(axis=0)
    if not keep.any():
        return 0.0
    cols = cl[keep]
    B = np.concatenate([A[:, keep], np.zeros((k, k))], axis=1)  # + a cluster of its own for each node
    ri, ci = linear_sum_assignment(B, maximize=True)
    gain = float(B[ri, ci].sum()) - cur
    if gain <= EPS:
        return 0.0
    rows_l = rows.tolist()
    target = {rows_l[a]: (int(cols[q]) if q < len(cols) else -1) for a, q in zip(ri.tolist(), ci.tolist())}
    lab = st.labels
    for v in rows_l:  # out first (each to a cluster of its own), so the group occupancy stays exact
        if len(st.members[lab[v]]) > 1:
            st.move(v, st.next_label)
            st.next_label += 1
    for v in rows_l:
        if target[v] != -1:
            st.move(v, target[v])
    return gain


def refine(g: Graph, labels: np.ndarray, max_rounds: int = 100, kl: bool = True) -> np.ndarray:
    """Local search from ``labels``: best single-node moves, group reassignments (when ``g`` has
    groups), KL between clusters, then positive cluster joins, repeated while any improves."""
    if g.n < 2 or len(g.w) == 0:
        return canonical_labels(labels)
    W = sp.coo_matrix((np.concatenate([g.w, g.w]), (np.concatenate([g.i, g.j]), np.concatenate([g.j, g.i]))),
                      shape=(g.n, g.n)).tocsr()
    adj = _adjacency(W)
    st = _State(g, labels, adj)
    tried: set = set()  # KL runs that found no gain (see _kernighan_lin)
    if g.groups is not None:  # for the group reassignments: nodes of each group, edges across groups
        cross = g.groups[g.i] != g.groups[g.j]
        ci, cj, cw = g.i[cross], g.j[cross], g.w[cross]
        Wx = sp.coo_matrix((np.concatenate([cw, cw]), (np.concatenate([ci, cj]), np.concatenate([cj, ci]))),
                           shape=(g.n, g.n)).tocsr()
        by_group = np.argsort(g.groups, kind="stable")
        firsts, at = np.unique(g.groups[by_group], return_index=True)
        members_of = dict(zip(firsts.tolist(), np.split(by_group, at[1:])))  # group -> its nodes, ascending
        entries: dict[int, tuple] = {}  # per group: its rows of Wx (built on first use)
        clean: set[int] = set()  # groups whose reassignment found no gain, with no node moved near them since

        def dirty(nodes: list[int]) -> set[int]:
            """Groups of the moved ``nodes`` and of their neighbours: their reassignment may change."""
            if not nodes:
                return set()
            nodes_a = np.unique(np.asarray(nodes, dtype=np.int64))
            return set(np.unique(g.groups[np.concatenate([nodes_a, _gather_rows(Wx, nodes_a)[1]])]).tolist())
    # node visits of all KL pair runs: bounds the time, deterministically (was 20 n + 10,000 before
    # the group reassignments, which now make most of KL's gains on large graphs, at less cost)
    budget = [5 * g.n + 10_000]
    for _ in range(max_rounds):
        changed = False
        # 1. node moves: screen all nodes at once, then move one by one with exact gains
        todo = _candidate_moves(g, np.array(st.labels), W).tolist()
        while todo:
            moved = []
            for v in todo:
                gain, c = st.best_move(v)
                if gain > EPS:
                    if c == -1:
                        c = st.next_label
                        st.next_label += 1
                    st.move(v, c)
                    moved.append(v)
            if not moved:
                break
            changed = True
            todo = _candidate_moves(g, np.array(st.labels), W).tolist()  # gains changed around the moved nodes
        # 1b. group reassignments: all nodes of one group (frame) at once, by linear assignment
        if g.groups is not None:
            clean -= dirty(st.touched)
            st.touched = []
            for x in _blocked_groups(g, st.labels, Wx):
                if x in clean or len(members_of[x]) < 2:
                    continue
                if x not in entries:
                    entries[x] = _gather_rows(Wx, members_of[x])
                if _reassign_group(st, members_of[x], entries[x]) > EPS:
                    changed = True
                    clean -= dirty(st.touched)
                    st.touched = []
                else:
                    clean.add(x)
        # 2. Kernighan-Lin between pairs of clusters (sequences of moves that escape local optima)
        if kl and _kernighan_lin(st, W, budget, tried):
            changed = True
        # 3. cluster joins with positive total weight and no cannot-link
        lab = canonical_labels(st.labels)
        k = int(lab.max()) + 1
        C = sp.coo_matrix((g.w, (lab[g.i], lab[g.j])), shape=(k, k)).tocsr()
        C = (C + C.T).tocoo()
        up = (C.row < C.col) & (C.data > EPS)
        pairs = sorted(zip((-C.data[up]).tolist(), C.row[up].tolist(), C.col[up].tolist()))
        if pairs:
            groups_of: list[set[int]] | None = None
            if g.groups is not None:
                groups_of = [set() for _ in range(k)]
                for v, c in enumerate(lab.tolist()):
                    groups_of[c].add(int(g.groups[v]))
            used: set[int] = set()
            rep = list(range(k))
            for _, a, b in pairs:  # a matching of joins per round (weights change after a join)
                if a in used or b in used:
                    continue
                if groups_of is not None and groups_of[a] & groups_of[b]:
                    continue
                used.update((a, b))
                rep[b] = a
                changed = True
            joined = np.flatnonzero(np.isin(lab, list(used))).tolist()
            lab = np.array(rep, dtype=np.int64)[lab]
            touched = st.touched + joined
            st = _State(g, lab, adj)
            st.touched = touched
        if not changed:
            break
    return canonical_labels(st.labels)
