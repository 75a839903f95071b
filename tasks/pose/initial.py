"""Closed-form start of the 9-DoF pose solver (:mod:`tasks.pose.solver`): a multi-view linear fit.

Frames (see :mod:`cadestate.geometry`): CAD points ``x`` in the canonical CAD frame (metres, +Y
up, front +Z, unmirrored); world +Y up; cameras world->camera ``X_cam = Rc X + tc``, OpenCV axes.
The pose maps CAD -> world as ``X = T + R S M x`` (official order: mirror => scale => rotation
=> translation; ``M = diag(-1, 1, 1)`` when mirrored, else identity).

Linear fit: with ``A = R S`` (a general 3x3 matrix) every click gives two equations that are
*linear* in the 12 unknowns (A, T): for normalised image coordinates (xn, yn) = K^-1 (u, v, 1),
``(Rc[0] - xn Rc[2]) . (T + A M x) = -(tc[0] - xn tc[2])`` and the same with row 1 and yn
(the depth times the reprojection error, in normalised units). All key-frames of an object are
solved at once (their baselines fix the depth, which one view cannot). The 3D points of a
symmetric model may carry a different symmetric rotation on each key-frame
(:mod:`bench.annotators`); the fit then chooses one rotation offset per key-frame: the assignment
with the least linear residual over all of them when there are at most :data:`MAX_ASSIGNMENTS`,
else by coordinate descent (the normal equations of each (key-frame, offset) are summed, so every
trial is one 12x12 solve). Descent alone can stop in a wrong assignment when the key-frames see
the object under little parallax. ``A`` is split into R and S (column norms, nearest rotation),
with the co-planar and 36-way scale ties, and snapped to a rotation about +Y for upright classes.
"""

from __future__ import annotations

import math

import torch

from tasks.pose.batch import DTYPE

ROT36_OFFSETS = 12
"""Rotation offsets (every 30 degrees) tried per key-frame for 36-way symmetric models."""
MAX_ASSIGNMENTS = 4096
"""Symmetric models: up to this many assignments of offsets to key-frames (O^(F-1)) are all tried
(the least linear residual wins); beyond it, coordinate descent over the key-frames."""


def rotate_y(points: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rotate points float[..., 3] about +Y by ``angle`` float[...] radians (right-handed, as
    :func:`tasks.cad.symmetry.rotation_y`: x' = cos x + sin z, z' = -sin x + cos z)."""
    c, s = torch.cos(angle), torch.sin(angle)
    x, y, z = points.unbind(-1)
    return torch.stack([c * x + s * z, y, -s * x + c * z], -1)


def yaw_matrix(angle: torch.Tensor) -> torch.Tensor:
    """float[..., 3, 3] rotations about +Y by ``angle`` float[...] radians."""
    c, s = torch.cos(angle), torch.sin(angle)
    o, z = torch.ones_like(c), torch.zeros_like(c)
    return torch.stack([torch.stack([c, z, s], -1), torch.stack([z, o, z], -1), torch.stack([-s, z, c], -1)], -2)


def nearest_rotation(A: torch.Tensor) -> torch.Tensor:
    """float[B, 3, 3] -> the nearest proper rotations (SVD, det fixed to +1)."""
    U, _, Vh = torch.linalg.svd(A)
    d = torch.sign(torch.linalg.det(U @ Vh))
    d = torch.where(d == 0, torch.ones_like(d), d)
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
    return U @ D @ Vh


def symmetry_offsets(symmetry: torch.Tensor, enabled: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Per object, the rotation offsets about +Y its key-frames may carry: angles float[B, O]
    (radians) and a validity mask bool[B, O]. Order 2 or 4: the multiples of 360/K; 36: every 30
    degrees (refined continuously by the solver); 1 or ``enabled`` False: only 0."""
    B = symmetry.shape[0]
    O = ROT36_OFFSETS if enabled and bool((symmetry >= 36).any()) else (4 if enabled and bool((symmetry > 1).any()) else 1)
    K = torch.where(symmetry >= 36, torch.full_like(symmetry, ROT36_OFFSETS), symmetry.clamp(min=1))
    K = K if enabled else torch.ones_like(K)
    i = torch.arange(O).expand(B, O)
    return 2 * math.pi * i.to(DTYPE) / K[:, None].to(DTYPE), i < K[:, None]


def tie_scales(s: torch.Tensor, tied: torch.Tensor, tie36: torch.Tensor) -> torch.Tensor:
    """Apply the scale constraints to float[B, 3] scales: for 36-way models (``tie36`` bool[B])
    sx = sz = their mean; then each axis the clicks do not observe (``tied`` bool[B, 3]: the axis
    normal to co-planar points, or one the points hardly span, :func:`tasks.pose.checks.unobserved_axes`)
    takes the mean scale of the observed axes, and all three the mean of the three when none is
    observed (one scale, the model's own proportions). Linear in ``s`` (:func:`tasks.pose.lm.scale_ties`)."""
    h = 0.5 * (s[:, 0] + s[:, 2])
    s = torch.where(tie36[:, None], torch.stack([h, s[:, 1], h], -1), s)
    seen = (~tied).to(s.dtype)
    n = seen.sum(-1, keepdim=True)
    mean = torch.where(n > 0, (s * seen).sum(-1, keepdim=True) / n.clamp(min=1), s.mean(-1, keepdim=True))
    return torch.where(tied, mean, s)


def split_affine(A: torch.Tensor, coplanar_axis: torch.Tensor, tied: torch.Tensor, tie36: torch.Tensor,
                 upright: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Split A = R S (float[B, 3, 3], CAD-after-mirror -> world) into R float[B, 3, 3] and S
    float[B, 3]. The column of a co-planar axis is not observed: it becomes the cross product of
    the other two. Upright objects get the rotation about +Y nearest to R. The scales are tied as
    :func:`tie_scales` ties them (``tied`` bool[B, 3])."""
    s = torch.linalg.norm(A, dim=1).clamp(min=1e-9)  # column norms
    cols = A / s[:, None, :]
    k = coplanar_axis.clamp(min=0)
    i, j = (k + 1) % 3, (k + 2) % 3
    ci = torch.gather(cols, 2, i[:, None, None].expand(-1, 3, 1))[..., 0]
    cj = torch.gather(cols, 2, j[:, None, None].expand(-1, 3, 1))[..., 0]
    ck = torch.linalg.cross(ci, cj)
    ck = ck / torch.linalg.norm(ck, dim=-1, keepdim=True).clamp(min=1e-12)
    filled = cols.scatter(2, k[:, None, None].expand(-1, 3, 1), ck[..., None])
    cols = torch.where((coplanar_axis >= 0)[:, None, None], filled, cols)
    R = nearest_rotation(cols)
    yaw = torch.atan2(R[:, 0, 2] - R[:, 2, 0], R[:, 0, 0] + R[:, 2, 2])
    R = torch.where(upright[:, None, None], yaw_matrix(yaw), R)
    # the co-planar column's norm says nothing (its direction was filled in): the other two's mean first
    coplanar = torch.nn.functional.one_hot(k, 3).bool() & (coplanar_axis >= 0)[:, None]
    s = tie_scales(tie_scales(s, coplanar, torch.zeros_like(tie36)), tied, tie36)
    return R, s


def linear_init(pts: torch.Tensor, xn: torch.Tensor, kf: torch.Tensor, pmask: torch.Tensor, Rc: torch.Tensor,
                tc: torch.Tensor, fmask: torch.Tensor, mirror: torch.Tensor, offsets: torch.Tensor,
                omask: torch.Tensor, upright: torch.Tensor, sweeps: int = 3) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Multi-view linear fit of (A, T) per object, with one symmetric offset per key-frame.

    Args:
        pts: float[B, P, 3] CAD points (unmirrored); xn: float[B, P, 2] normalised image
            coordinates K^-1 (u, v, 1); kf: int[B, P] key-frame of each point; pmask: bool[B, P].
        Rc, tc: float[B, F, 3, 3], float[B, F, 3] world->camera of the key-frames; fmask bool[B, F].
        mirror: float[B] -1 when mirrored else 1 (applied to x).
        offsets, omask: from :func:`symmetry_offsets`.
        upright: bool[B]: fit only rotations about +Y (A = [[a, 0, e], [0, sy, 0], [-b, 0, d]]:
            8 unknowns instead of 12, far better conditioned with little parallax).
    Returns:
        A float[B, 3, 3] (R S), T float[B, 3] (world, metres) and the offset angle chosen per
        key-frame float[B, F] (radians).
    """
    B, P, _ = pts.shape
    F, O = Rc.shape[1], offsets.shape[1]
    Rp = torch.gather(Rc, 1, kf[..., None, None].expand(B, P, 3, 3))
    tp = torch.gather(tc, 1, kf[..., None].expand(B, P, 3))
    onehot = torch.nn.functional.one_hot(kf, F).to(DTYPE) * pmask[..., None]  # float[B, P, F]
    M = torch.zeros(B, F, O, 12, 12, dtype=DTYPE)
    v = torch.zeros(B, F, O, 12, dtype=DTYPE)
    c = torch.zeros(B, F, O, dtype=DTYPE)
    for o in range(O):
        x = rotate_y(pts, offsets[:, o, None].expand(B, P))
        x = x * torch.stack([mirror, torch.ones_like(mirror), torch.ones_like(mirror)], -1)[:, None]
        rows, rhs = [], []
        for a in range(2):  # image x and y
            g = Rp[:, :, a] - xn[..., a, None] * Rp[:, :, 2]  # float[B, P, 3]
            rows.append(torch.cat([(g[..., :, None] * x[..., None, :]).flatten(-2), g], -1))
            rhs.append(-(tp[..., a] - xn[..., a] * tp[..., 2]))
        rows_t, rhs_t = torch.stack(rows, 2), torch.stack(rhs, 2)  # float[B, P, 2, 12], float[B, P, 2]
        M[:, :, o] = torch.einsum("bpf,bpri,bprj->bfij", onehot, rows_t, rows_t)
        v[:, :, o] = torch.einsum("bpf,bpri,bpr->bfi", onehot, rows_t, rhs_t)
        c[:, :, o] = torch.einsum("bpf,bpr->bf", onehot, rhs_t**2)
    eye = torch.eye(12, dtype=DTYPE)
    # Upright objects: theta_full = Q theta' with theta' = (a, e, sy, b, d, T, unused x 4).
    Qu = torch.zeros(12, 12, dtype=DTYPE)
    for col, (row, sign) in enumerate([(0, 1), (2, 1), (4, 1), (6, -1), (8, 1), (9, 1), (10, 1), (11, 1)]):
        Qu[row, col] = sign
    Q = torch.where(upright[:, None, None], Qu, eye)  # float[B, 12, 12]
    unused = torch.where(upright[:, None], (torch.arange(12) >= 8).to(DTYPE), torch.zeros(12, dtype=DTYPE))
    M = torch.einsum("bki,bfokl,blj->bfoij", Q, M, Q)
    v = torch.einsum("bki,bfok->bfoi", Q, v)

    def solve(Mt: torch.Tensor, vt: torch.Tensor, ct: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return _solve_normal(Mt, vt, ct, unused)

    assign = torch.zeros(B, F, dtype=torch.long)
    pick = lambda t, a: torch.gather(t, 2, a.view(B, F, 1, *([1] * (t.dim() - 3))).expand(  # noqa: E731
        B, F, 1, *t.shape[3:]))[:, :, 0]
    if O > 1:
        assign, searched = _exhaustive_where_small(M, v, c, omask, fmask, unused)
        for _ in range(sweeps if not bool(searched.all()) else 0):
            for f in range(F):
                Mt, vt, ct = pick(M, assign).sum(1), pick(v, assign).sum(1), pick(c, assign).sum(1)
                Mt = Mt[:, None] - pick(M, assign)[:, f, None] + M[:, f]  # float[B, O, 12, 12]
                vt = vt[:, None] - pick(v, assign)[:, f, None] + v[:, f]
                ct = ct[:, None] - pick(c, assign)[:, f, None] + c[:, f]
                _, res = solve(Mt, vt, ct)
                res = torch.where(omask, res, torch.full_like(res, float("inf")))
                best = torch.nan_to_num(res, nan=float("inf")).argmin(-1)
                assign[:, f] = torch.where(fmask[:, f] & ~searched, best, assign[:, f])
    theta, _ = solve(pick(M, assign).sum(1), pick(v, assign).sum(1), pick(c, assign).sum(1))
    theta = torch.einsum("bij,bj->bi", Q, theta)
    A, T = theta[:, :9].reshape(B, 3, 3), theta[:, 9:]
    return A, T, torch.gather(offsets, 1, assign)


def _solve_normal(Mt: torch.Tensor, vt: torch.Tensor, ct: torch.Tensor, unused: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Solve normal equations Mt float[B, ..., 12, 12] theta = vt float[B, ..., 12] (a tiny ridge;
    ``unused`` float[B, 12] pins unknowns an object does not have to 0); returns theta and the
    residual float[B, ...] (ct: the constant term, float[B, ...])."""
    eye = torch.eye(12, dtype=DTYPE)
    lam = 1e-10 * Mt.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None] / 12 + 1e-15
    pad = torch.diag_embed(unused).view(unused.shape[0], *([1] * (Mt.dim() - 3)), 12, 12)
    theta = torch.linalg.solve(Mt + lam * eye + pad, vt[..., None])[..., 0]
    res = torch.einsum("...i,...ij,...j->...", theta, Mt, theta) - 2 * (theta * vt).sum(-1) + ct
    return theta, res


def _exhaustive_where_small(M: torch.Tensor, v: torch.Tensor, c: torch.Tensor, omask: torch.Tensor, fmask: torch.Tensor,
                            unused: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Offsets int[B, F] of the objects whose assignments number at most :data:`MAX_ASSIGNMENTS`
    (their valid offsets ^ (their key-frames - 1); grouped by offset count and key-frame count) by
    :func:`_exhaustive_assignment`, 0 elsewhere; and which objects those are, bool[B] (objects
    with one offset count as searched). Key-frames and valid offsets are prefixes of F and O
    (:func:`symmetry_offsets`)."""
    n_off, n_frames = omask.sum(1), fmask.sum(1)
    out = torch.zeros(fmask.shape, dtype=torch.long)
    searched = (n_off <= 1) | (n_frames <= 1)
    for k, f in sorted({(int(k), int(f)) for k, f in zip(n_off.tolist(), n_frames.tolist()) if k > 1 and f > 1}):
        if k ** (f - 1) > MAX_ASSIGNMENTS:
            continue
        rows = torch.nonzero((n_off == k) & (n_frames == f))[:, 0]
        out[rows, :f] = _exhaustive_assignment(M[rows, :f, :k], v[rows, :f, :k], c[rows, :f, :k], unused[rows])
        searched[rows] = True
    return out, searched


def _exhaustive_assignment(M: torch.Tensor, v: torch.Tensor, c: torch.Tensor, unused: torch.Tensor,
                           chunk: int = 16) -> torch.Tensor:
    """The symmetric offset per key-frame int[B, F] whose summed linear fit has the least
    residual, over every assignment: the first key-frame keeps offset 0 (the offsets form a group,
    so turning them all by one of them turns A alike and leaves the residual), the others take
    each of the O offsets. Every object has all F key-frames and all O offsets (the caller groups
    them so). M float[B, F, O, 12, 12], v float[B, F, O, 12], c float[B, F, O]: the normal
    equations of each (key-frame, offset); ``unused`` as in :func:`_solve_normal`."""
    B, F, O = c.shape
    grids = [torch.zeros(1, dtype=torch.long)] + [torch.arange(O)] * (F - 1)
    combos = torch.cartesian_prod(*grids)  # int[C, F]
    frames = torch.arange(F)[:, None]
    best_res = torch.full((B,), float("inf"), dtype=DTYPE)
    best = torch.zeros(B, F, dtype=torch.long)
    for start in range(0, len(combos), chunk):
        cc = combos[start:start + chunk].T  # int[F, K]
        _, res = _solve_normal(M[:, frames, cc].sum(1), v[:, frames, cc].sum(1), c[:, frames, cc].sum(1), unused)  # [B, K]
        res = torch.nan_to_num(res, nan=float("inf"))
        k = res.argmin(1)
        better = res[torch.arange(B), k] < best_res
        best_res = torch.where(better, res[torch.arange(B), k], best_res)
        best = torch.where(better[:, None], cc.T[k], best)
    return best


def fit_scale_translation(pts: torch.Tensor, xn: torch.Tensor, kf: torch.Tensor, pmask: torch.Tensor, Rc: torch.Tensor,
                          tc: torch.Tensor, mirror: torch.Tensor, R: torch.Tensor, angle: torch.Tensor,
                          L: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Given rotations R float[B, 3, 3], the scales and translation that fit the clicks best in the
    same linear (depth-weighted) sense as :func:`linear_init`: with R fixed the equations are
    linear in (s, T) (6 unknowns; the scale ties ``L`` float[B, 3, 3] applied: s = L s').
    ``angle`` float[B, P]: the symmetric rotation of each point's key-frame. Returns s float[B, 3]
    and T float[B, 3] (non-finite or non-positive scales where the fit is degenerate)."""
    B, P, _ = pts.shape
    Rp = torch.gather(Rc, 1, kf[..., None, None].expand(B, P, 3, 3))
    tp = torch.gather(tc, 1, kf[..., None].expand(B, P, 3))
    x = rotate_y(pts, angle) * torch.stack([mirror, torch.ones_like(mirror), torch.ones_like(mirror)], -1)[:, None]
    rows, rhs = [], []
    for a in range(2):
        g = Rp[:, :, a] - xn[..., a, None] * Rp[:, :, 2]  # float[B, P, 3]
        # g . (R diag(L s') x) = sum_k s'_k sum_j (g . R[:, j]) L[j, k] x_j
        gs = torch.einsum("bpi,bij,bpj->bpj", g, R, x)  # float[B, P, 3]: (g . R[:, j]) x_j
        rows.append(torch.cat([torch.einsum("bpj,bjk->bpk", gs, L), g], -1))
        rhs.append(-(tp[..., a] - xn[..., a] * tp[..., 2]))
    A = torch.stack(rows, 2) * pmask[..., None, None]  # float[B, P, 2, 6]
    y = torch.stack(rhs, 2) * pmask[..., None]
    M = torch.einsum("bpri,bprj->bij", A, A)
    v = torch.einsum("bpri,bpr->bi", A, y)
    lam = 1e-10 * M.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None] / 6 + 1e-15
    theta = torch.linalg.solve(M + lam * torch.eye(6, dtype=DTYPE), v[..., None])[..., 0]
    return torch.einsum("bij,bj->bi", L, theta[:, :3]), theta[:, 3:]
