"""Levenberg-Marquardt solver of the pose objective (:mod:`tasks.pose.solver`), batched over objects.

The objective is the solver's loss (reprojection + alpha · up + beta · front + the scale prior +
floor). It is minimised by iteratively reweighted least squares (weights 1 / max(|r|, eps), so the
weighted squares equal the L1 terms at the current point; the scale prior, a sum of squares q^2,
enters with its linear residuals q at the fixed weight :data:`PRIOR_WEIGHT`: exact Gauss-Newton)
with Gauss-Newton steps on an *analytic* Jacobian, from the
closed-form start: along the weakly observed depth <-> size direction (small baselines) this lands
on the minimum in a few iterations where fixed-size gradient steps (Adam) crawl.

Parameters per object, relative to the current pose: a rotation increment ``w`` (R <- R exp([w]x),
no singularity), a translation step in units of ``scale_t`` (the distance to the cameras),
log-scales ``ls`` (the scales are ``L exp(ls)`` with ``L`` float[B, 3, 3] the linear scale ties of
:func:`tasks.pose.initial.tie_scales`) and, for 36-way symmetric models, one rotation about +Y per
key-frame ``phi``. The discrete symmetric rotation of every key-frame of a 2/4-way model is
re-chosen at every iteration as the best at the current pose (the min of the objective); a 36-way
model's key-frames have no discrete choice here (their 30-degree grid is the linear start's), only
their angle ``phi``. A step is kept only when it lowers the object's loss (then the damping
shrinks; otherwise it grows), so the loss never increases; an object stops once its steps no
longer help (its later iterations are skipped: per-object convergence mask).

Frames: CAD points in the canonical CAD frame (unmirrored; the mirror ``diag(m, 1, 1)`` applies
after the symmetric rotation), world +Y up, cameras world->camera OpenCV, pixels.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch

from tasks.pose.batch import DTYPE, Batch

IRLS_EPS_PX = 1e-3
"""Smallest residual (px) in the IRLS weights 1/|r| (a smoothed L1 near zero)."""
PRIOR_WEIGHT = 2.0
"""IRLS weight of the scale prior's linear rows q (loss q^2: gradient 2 q dq, Gauss-Newton curvature 2 dq dq^T)."""
PRIOR_ROWS = slice(-4, -1)
"""Where :func:`residuals_jacobian` puts the scale prior's 3 rows (before the floor's last row)."""


def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Rotation matrices float[B, 3, 3] of axis-angle vectors float[B, 3] (Rodrigues)."""
    theta = torch.linalg.norm(w, dim=-1, keepdim=True)[..., None]  # float[B, 1, 1]
    Kx = skew(w)
    small = theta < 1e-8
    t = torch.where(small, torch.ones_like(theta), theta)
    a = torch.where(small, 1 - theta**2 / 6, torch.sin(t) / t)
    b = torch.where(small, 0.5 - theta**2 / 24, (1 - torch.cos(t)) / t**2)
    return torch.eye(3, dtype=w.dtype) + a * Kx + b * (Kx @ Kx)


def skew(v: torch.Tensor) -> torch.Tensor:
    """float[..., 3] -> cross-product matrices float[..., 3, 3] ([v]x u = v x u)."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([torch.stack([o, -z, y], -1), torch.stack([z, o, -x], -1), torch.stack([-y, x, o], -1)], -2)


def scale_ties(tied: torch.Tensor, tie36: torch.Tensor) -> torch.Tensor:
    """The linear map L float[B, 3, 3] of :func:`tasks.pose.initial.tie_scales` (s_tied = L s;
    ``tied`` bool[B, 3] the tied axes: the co-planar one while solving, also the loose ones for the starts)."""
    from tasks.pose.initial import tie_scales

    B = tied.shape[0]
    eye = torch.eye(3, dtype=DTYPE)
    cols = [tie_scales(eye[j].expand(B, 3), tied, tie36) for j in range(3)]
    return torch.stack(cols, -1)


@dataclass
class Problem:
    """What the LM needs per object: the objects' :class:`tasks.pose.batch.Batch` and the run's extras.

    offsets float[B, O] (radians) and omask bool[B, O]: the discrete symmetric rotations about +Y
    each key-frame may take; L float[B, 3, 3] scale ties; free_phi float[B, F] (1: the key-frame's
    rotation about +Y is free, 36-way models); scale_t float[B] translation unit (distance to the
    cameras, world units).
    """

    b: Batch
    offsets: torch.Tensor
    omask: torch.Tensor
    L: torch.Tensor
    free_phi: torch.Tensor
    scale_t: torch.Tensor

    def subset(self, idx: torch.Tensor) -> Problem:
        return Problem(self.b.select(idx), *(getattr(self, f.name)[idx] for f in fields(self)[1:]))


def support_bottom(R: torch.Tensor, s: torch.Tensor, T: torch.Tensor, half: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The lowest point along world +Y (the up axis) of each posed CAD bounding box, bottom
    float[B] (world units), and the box's extent along +Y, height float[B], for poses R float[B,
    3, 3] (CAD -> world), scales s float[B, 3], T float[B, 3] and half-sizes half float[B, 3]
    (canonical CAD frame, bbox-centred, so the mirror does not matter): the corner
    (+-hx, +-hy, +-hz) reaches T_y + sum_j R[1, j] s_j (+-h_j), whose minimum is
    T_y - sum_j |R[1, j]| s_j h_j. (The per-key-frame rotations of 36-way models are ignored: they
    turn about +Y, which moves no corner of an upright box up or down.)"""
    reach = (R[:, 1, :].abs() * s * half).sum(-1)
    return T[:, 1] - reach, 2 * reach


def prior_deviation(b: Batch, s: torch.Tensor) -> torch.Tensor:
    """q = ``b.prior @ log s`` float[B, 3] of scales s float[B, 3]: for an axis the clicks hardly
    span, sqrt(axis_prior) x (its log-scale - the observed axes' mean log-scale); for the other
    untied axes sqrt(proportion_prior) x (its log-scale - the untied axes' mean); 0 for a tied axis
    (:func:`tasks.pose.checks.prior_matrix`)."""
    return torch.einsum("bij,bj->bi", b.prior, torch.log(s.clamp(min=1e-12)))


def axis_prior(b: Batch, s: torch.Tensor) -> torch.Tensor:
    """The scale prior's terms float[B, 3] (px, >= 0): q^2 (:func:`prior_deviation`)."""
    return prior_deviation(b, s) ** 2


def floor_residual(b: Batch, R: torch.Tensor, s: torch.Tensor, T: torch.Tensor) -> torch.Tensor:
    """The signed floor term float[B] (px): floor_w · (bottom - floor_y); 0 where floor_w is 0."""
    bottom, _ = support_bottom(R, s, T, b.half)
    return torch.where(b.floor_w > 0, b.floor_w * (bottom - b.floor_y), torch.zeros_like(bottom))


def _rotate_y(p: torch.Tensor, ang: torch.Tensor, derivative: bool = False) -> torch.Tensor:
    c, s = torch.cos(ang), torch.sin(ang)
    x, y, z = p.unbind(-1)
    if derivative:
        return torch.stack([-s * x + c * z, torch.zeros_like(y), -c * x - s * z], -1)
    return torch.stack([c * x + s * z, y, -s * x + c * z], -1)


def robust(d: torch.Tensor, huber_px: float) -> torch.Tensor:
    """Per-coordinate reprojection loss of residuals d (px): |d| (L1, the paper's) or, with
    ``huber_px`` > 0, the Huber loss d^2 / (2 huber_px) inside +-huber_px and |d| - huber_px / 2 outside."""
    a = d.abs()
    return a if huber_px <= 0 else torch.where(a <= huber_px, a * a / (2 * huber_px), a - huber_px / 2)


def front_gap(b: Batch, z: torch.Tensor, min_depth: float) -> torch.Tensor:
    """How far inside ``min_depth`` of its camera each point lies, float[B, P], in metres of its
    object's CAD model (depths z float[B, P] in world units over ``b.unit``, world units per metre:
    the same for a world of any scale); 0 beyond it and for padding."""
    return torch.relu(min_depth - z / b.unit[:, None]) * b.pmask


def loss_and_choice(pb: Problem, R, s, T, phi, min_depth: float, alpha: float, beta: float, huber_px: float = 0.0):
    """Total loss float[B] (min over each key-frame's symmetric rotations) and the chosen offset
    per key-frame int[B, F]."""
    B, P = pb.b.kf.shape
    F = pb.b.Rc.shape[1]
    ang = pb.offsets[:, None, :] + torch.gather(phi, 1, pb.b.kf)[:, :, None]  # float[B, P, O]
    x = _rotate_y(pb.b.pts[:, :, None, :].expand(-1, -1, ang.shape[2], -1), ang) * pb.b.mvec[:, None, None]
    world = torch.einsum("bij,bpoj->bpoi", R, x * s[:, None, None, :]) + T[:, None, None, :]
    cam = torch.einsum("bpij,bpoj->bpoi", pb.b.Rp, world) + pb.b.tp[:, :, None, :]
    depth = cam[..., 2]
    proj = cam[..., :2] / depth.clamp(min=1e-6)[..., None]
    pix = torch.einsum("bpij,bpoj->bpoi", pb.b.Kp[..., :2, :2], proj) + pb.b.Kp[:, :, None, :2, 2]
    per_point = robust(pix - pb.b.uv[:, :, None, :], huber_px).sum(-1) * pb.b.pmask[..., None]
    per_kf = torch.zeros(B, F, per_point.shape[2], dtype=DTYPE).scatter_add(1, pb.b.kf[..., None].expand_as(per_point), per_point)
    per_kf = torch.where(pb.omask[:, None, :], per_kf, torch.full_like(per_kf, float("inf")))
    best, choice = per_kf.min(-1)  # the rotation is chosen by the reprojection term (as the solver's evaluate)
    best = torch.where(pb.b.fmask, best, torch.zeros_like(best))
    z = torch.gather(depth, 2, torch.gather(choice, 1, pb.b.kf)[..., None])[..., 0]
    front = front_gap(pb.b, z, min_depth).sum(1)
    up = (R[:, :, 1] - torch.tensor([0.0, 1.0, 0.0], dtype=DTYPE)).abs().sum(-1) * pb.b.upright
    floor = floor_residual(pb.b, R, s, T).abs()
    prior = axis_prior(pb.b, s).sum(-1)
    return torch.nan_to_num((best.sum(1) + beta * front) / pb.b.npts + alpha * up + floor + prior, nan=float("inf")), choice


def residuals_jacobian(pb: Problem, R, ls, T, phi, choice, min_depth: float, alpha: float, beta: float):
    """Signed residuals float[B, N] and their Jacobian float[B, N, 9 + F] with respect to (w,
    translation step, ls, phi). The loss at the chosen rotations is the absolute sum of the rows
    but the scale prior's (:data:`PRIOR_ROWS`), which are its linear q and count as q^2."""
    B, P = pb.b.kf.shape
    F = pb.b.Rc.shape[1]
    s = torch.einsum("bij,bj->bi", pb.L, torch.exp(ls))
    ang = torch.gather(pb.offsets, 1, torch.gather(choice, 1, pb.b.kf)) + torch.gather(phi, 1, pb.b.kf)  # float[B, P]
    x = _rotate_y(pb.b.pts, ang) * pb.b.mvec[:, None]
    dx = _rotate_y(pb.b.pts, ang, True) * pb.b.mvec[:, None]
    y = x * s[:, None]
    world = torch.einsum("bij,bpj->bpi", R, y) + T[:, None]
    cam = torch.einsum("bpij,bpj->bpi", pb.b.Rp, world) + pb.b.tp
    z = cam[..., 2]
    zs = z.clamp(min=1e-6)
    proj = cam[..., :2] / zs[..., None]
    K2 = pb.b.Kp[..., :2, :2]
    pix = torch.einsum("bpij,bpj->bpi", K2, proj) + pb.b.Kp[..., :2, 2]
    w = pb.b.pmask.to(DTYPE) / pb.b.npts[:, None]  # float[B, P]
    r_pix = (pix - pb.b.uv) * w[..., None]
    # d proj / d cam: [[1/z, 0, -x/z^2], [0, 1/z, -y/z^2]]
    dproj = torch.zeros(B, P, 2, 3, dtype=DTYPE)
    dproj[..., 0, 0] = 1 / zs
    dproj[..., 1, 1] = 1 / zs
    dproj[..., :, 2] = -proj / zs[..., None]
    dpix_dX = K2 @ dproj @ pb.b.Rp  # float[B, P, 2, 3]
    # d world / d (w, t, ls): -R [y]x, scale_t I, R diag(x) L diag(exp ls)
    G = torch.cat([-R[:, None] @ skew(y),
                   pb.scale_t[:, None, None, None] * torch.eye(3, dtype=DTYPE).expand(B, P, 3, 3),
                   (R[:, None] * x[..., None, :]) @ (pb.L * torch.exp(ls)[:, None, :])[:, None]], -1)  # float[B, P, 3, 9]
    dX_dphi = torch.einsum("bij,bpj->bpi", R, dx * s[:, None])  # float[B, P, 3]
    onehot = torch.nn.functional.one_hot(pb.b.kf, F).to(DTYPE) * torch.gather(pb.free_phi, 1, pb.b.kf)[..., None]
    Jpix = torch.cat([dpix_dX @ G, torch.einsum("bpai,bpi->bpa", dpix_dX, dX_dphi)[..., None] * onehot[:, :, None, :]], -1)
    Jpix = Jpix * w[..., None, None]  # float[B, P, 2, D]
    # front of camera: beta * relu(min_depth - z / unit) / npts (unit: world units per metre)
    gap = front_gap(pb.b, z, min_depth)
    active = (gap > 0).to(DTYPE) * w / pb.b.unit[:, None]
    r_front = beta * gap * w
    dz = torch.cat([pb.b.Rp[..., 2:, :] @ G, (pb.b.Rp[..., 2, :] * dX_dphi).sum(-1)[..., None, None] * onehot[:, :, None, :]], -1)
    J_front = -beta * active[..., None] * dz[:, :, 0]  # float[B, P, D]
    # up axis: alpha * (R e_y - e_y); d/dw = -alpha R [e_y]x
    up = pb.b.upright.to(DTYPE)[:, None]
    r_up = alpha * (R[:, :, 1] - torch.tensor([0.0, 1.0, 0.0], dtype=DTYPE)) * up
    e_y = torch.tensor([0.0, 1.0, 0.0], dtype=DTYPE).expand(B, 3)
    J_up = torch.zeros(B, 3, 9 + F, dtype=DTYPE)
    J_up[..., :3] = -alpha * up[..., None] * (R @ skew(e_y))
    r_floor, J_floor = _floor_jacobian(pb, R, ls, T, s)
    # scale prior, linear rows q = prior @ log s: d log s_i / d ls_k = L_ik exp(ls_k) / s_i
    J_prior = torch.zeros(B, 3, 9 + F, dtype=DTYPE)
    J_prior[..., 6:9] = pb.b.prior @ (pb.L * torch.exp(ls)[:, None, :] / s.clamp(min=1e-12)[..., None])
    r = torch.cat([r_pix.flatten(1), r_front, r_up, prior_deviation(pb.b, s), r_floor], 1)
    J = torch.cat([Jpix.flatten(1, 2), J_front, J_up, J_prior, J_floor], 1)
    return torch.nan_to_num(r), torch.nan_to_num(J)


def bottom_gradient(pb: Problem, R: torch.Tensor, ls: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """d bottom / d (w, translation step, ls, phi) float[B, 9 + F] (:func:`support_bottom`): with
    a = |R[1, :]| and c_j = sign(R[1, j]) s_j h_j, d bottom / dw = -(c x R[1, :]) (as R[1, j] <-
    R[1, j] + w . (e_j x R[1, :])), d bottom / d(translation step) = scale_t e_y and d bottom / d ls_k
    = -sum_j a_j h_j L[j, k] exp(ls_k); 0 for phi (turns about +Y move no corner up or down)."""
    B, F = pb.b.fmask.shape
    row, h = R[:, 1, :], pb.b.half
    g = torch.zeros(B, 9 + F, dtype=DTYPE)
    g[:, :3] = -torch.linalg.cross(torch.sign(row) * s * h, row)
    g[:, 4] = pb.scale_t
    g[:, 6:9] = -torch.einsum("bj,bjk->bk", row.abs() * h, pb.L) * torch.exp(ls)
    return g


def _floor_jacobian(pb: Problem, R, ls, T, s) -> tuple[torch.Tensor, torch.Tensor]:
    """The floor residual float[B, 1] (:func:`floor_residual`) and its Jacobian float[B, 1, 9 + F],
    floor_w times :func:`bottom_gradient`."""
    w = torch.where(pb.b.floor_w > 0, pb.b.floor_w, torch.zeros_like(pb.b.floor_w))[:, None]  # float[B, 1]
    return floor_residual(pb.b, R, s, T)[:, None], w[:, :, None] * bottom_gradient(pb, R, ls, s)[:, None, :]


def irls_weights(r: torch.Tensor, huber_px: float, npts: torch.Tensor) -> torch.Tensor:
    """IRLS weights float[B, N] of :func:`residuals_jacobian`'s rows r: L1 1/|r| (smoothed below
    IRLS_EPS_PX); Huber: 1/huber_px inside +-huber_px; the scale prior's rows :data:`PRIOR_WEIGHT`."""
    wgt = 1.0 / r.abs().clamp(min=max(huber_px, IRLS_EPS_PX) / npts[:, None])
    wgt[:, PRIOR_ROWS] = PRIOR_WEIGHT
    return wgt


def bottom_sd(pb: Problem, R: torch.Tensor, ls: torch.Tensor, T: torch.Tensor, phi: torch.Tensor, min_depth: float,
              alpha: float, beta: float, huber_px: float) -> torch.Tensor:
    """How loosely the fit holds each object's bottom height, float[B] (world units, relative:
    up to the scale of the click noise): sqrt(g^T H^-1 g) with g = :func:`bottom_gradient` and H
    the Gauss-Newton (IRLS) matrix of the loss at the pose, as :func:`lm_solve` builds it (the
    Laplace approximation of the bottom's variance; the scale priors' rows included, as they too
    hold the object's size). Parameters without any residual (the
    key-frame rotations of models that are not 36-way) are left out."""
    s = torch.einsum("bij,bj->bi", pb.L, torch.exp(ls))
    _, choice = loss_and_choice(pb, R, s, T, phi, min_depth, alpha, beta, huber_px)
    r, J = residuals_jacobian(pb, R, ls, T, phi, choice, min_depth, alpha, beta)
    wgt = irls_weights(r, huber_px, pb.b.npts)
    H = torch.einsum("bnd,bn,bne->bde", J, wgt, J)
    diag = H.diagonal(dim1=1, dim2=2)
    H = H + torch.diag_embed((diag <= 0).to(DTYPE) + 1e-12 * diag.amax(-1, keepdim=True))
    g = bottom_gradient(pb, R, ls, s)
    var = (g * torch.linalg.solve(H, g[..., None])[..., 0]).sum(-1)
    return torch.sqrt(torch.nan_to_num(var, nan=float("inf")).clamp(min=0))


def lm_solve(pb: Problem, R: torch.Tensor, ls: torch.Tensor, T: torch.Tensor, phi: torch.Tensor, iterations: int,
             min_depth: float, alpha: float, beta: float, huber_px: float = 0.0, lam0: float = 1e-3, rtol: float = 1e-9
             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Minimise the loss from poses R float[B, 3, 3], log-scales ls float[B, 3] (before the ties
    ``pb.L``), T float[B, 3], phi float[B, F]. Returns the final (R, ls, T, phi) and the number of
    iterations each object ran int[B]."""
    B, F = phi.shape
    R, ls, T, phi = R.clone(), ls.clone(), T.clone(), phi.clone()
    lam = torch.full((B,), lam0, dtype=DTYPE)
    run = torch.zeros(B, dtype=torch.long)
    active = torch.ones(B, dtype=torch.bool)
    s_of = lambda sub, l: torch.einsum("bij,bj->bi", sub.L, torch.exp(l))  # noqa: E731
    loss, choice = loss_and_choice(pb, R, s_of(pb, ls), T, phi, min_depth, alpha, beta, huber_px)
    for _ in range(iterations):
        idx = torch.nonzero(active)[:, 0]
        if len(idx) == 0:
            break
        sub = pb.subset(idx) if len(idx) < B else pb
        Ri, lsi, Ti, phii = R[idx], ls[idx], T[idx], phi[idx]
        r, J = residuals_jacobian(sub, Ri, lsi, Ti, phii, choice[idx], min_depth, alpha, beta)
        wgt = irls_weights(r, huber_px, sub.b.npts)
        H = torch.einsum("bnd,bn,bne->bde", J, wgt, J)
        g = torch.einsum("bnd,bn,bn->bd", J, wgt, r)
        diag = H.diagonal(dim1=1, dim2=2)
        damp = torch.diag_embed(lam[idx, None] * diag + 1e-9 * (diag.amax(-1, keepdim=True) + 1e-12))
        delta = torch.nan_to_num(-torch.linalg.solve(H + damp, g[..., None])[..., 0])
        cand = (Ri @ so3_exp(delta[:, :3]), lsi + delta[:, 6:9], Ti + sub.scale_t[:, None] * delta[:, 3:6],
                phii + delta[:, 9:] * sub.free_phi)
        loss1, choice1 = loss_and_choice(sub, cand[0], s_of(sub, cand[1]), cand[2], cand[3], min_depth, alpha, beta,
                                         huber_px)
        loss0 = loss[idx]
        better = loss1 < loss0
        R[idx] = torch.where(better[:, None, None], cand[0], Ri)
        ls[idx] = torch.where(better[:, None], cand[1], lsi)
        T[idx] = torch.where(better[:, None], cand[2], Ti)
        phi[idx] = torch.where(better[:, None], cand[3], phii)
        loss[idx] = torch.where(better, loss1, loss0)
        choice[idx] = torch.where(better[:, None], choice1, choice[idx])
        lam[idx] = torch.where(better, (lam[idx] * 0.3).clamp(min=1e-9), lam[idx] * 10)
        run[idx] += 1
        tiny = (loss0 - loss1).abs() <= rtol * loss0.abs() + 1e-12
        active[idx] = ~((better & tiny) | (lam[idx] > 1e8))
    return R, ls, T, phi, run
