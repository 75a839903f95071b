"""9-DoF pose of CAD models from 3D<->2D correspondences (CAD-Estate, section 3.4), batched in torch.

Frames (see :mod:`cadestate.geometry`):

- CAD points ``x``: canonical CAD frame (metres, +Y up, front +Z, origin at the bbox centre),
  *unmirrored* (the points the annotator clicked on the model as stored);
- clicks: pixels, origin at the top-left image corner, x right, y down;
- cameras: world->camera ``X_cam = Rc X_world + tc``, OpenCV axes (x right, y down, z forward);
- the pose maps CAD -> world with the official CAD-Estate order mirror => scale => rotation =>
  translation: ``X_world = T + R · diag(S) · M · x`` with ``M = diag(-1, 1, 1)`` when mirrored.

Objective per object (all key-frames together)::

    L = L_repr + alpha · L_up + beta · L_front + L_prop [+ L_axes] [+ L_floor]
    L_repr  = sum over key-frames of min over symmetric rotations Q of
              sum over the key-frame's points rho(u(T, R, S, M Q x) - u_click) (px), / points
    rho     = per coordinate: |d| (the paper's L1, ``huber_px`` = 0) or Huber(d; huber_px)
    L_up    = |R e_y - e_y|_1                   (upright classes only; world up +Y)
    L_front = sum over points of max(0, min_depth - z_cam / unit) (metres), / points; unit: world
              units per metre of the object's model (:func:`world_unit`, from the linear fit), so
              a world of any scale (RealEstate10K's and SfM's are arbitrary) gets the same pose
    L_prop  = proportion_prior · sum over the untied axes a of (log s_a - their mean log-scale)^2
              (px; not the co-planar tie's axis, nor those L_axes holds): the chosen model's
              proportions, a weak prior beyond the paper (the paper's free scales: 0)
    L_floor = floor_weight · |bottom - floor_height|  (only in the re-solve with the support
              prior of :mod:`tasks.pose.support`; bottom: lowest world-Y of the posed CAD bbox;
              floor_height: the support's height, the floor or a host's top)

Special parameterisations (each can be switched off for the ablation):

- co-planar 3D points (smallest singular value of the centred points <= ``coplanar_tol`` x the
  largest; or, for 2-way models, every key-frame's set planar across x or z and one plane once
  each face is turned to the positive side, :func:`tasks.pose.checks.coplanar_axis`): the scale
  along the CAD axis nearest the plane normal is the mean of the other two (2 DoF). A 2-way tie
  whose pose cannot explain the clicks (``high_residual``: two faces clicked from both sides, not
  one face and its twin) is solved again untied, and that pose kept when it is ``ok``;
- axes the 3D points hardly span (less than ``min_axis_span`` of the model's size along them:
  the clicks all on a leg or a corner): the loss gains ``L_axes`` = sum over them of
  ``axis_prior`` x (log s_a - the observed axes' mean log-scale)^2 (px; all three's mean when none
  is observed), which pulls them towards the model's proportions, and the starts keep those;
- symmetric models (order K = 2, 4 about +Y): each key-frame takes the best of the K rotations
  ``Q = R_y(2 pi i / K)``; 36-way: each key-frame has its own continuous rotation about +Y
  (solved, started from the best of 12) and sx = sz;
- rotation: the continuous 6D representation (two columns, Gram-Schmidt): no singularity;
  scale: log-scale; translation: offset from the start, in units of its distance to the cameras.

Start: the multi-view linear fit of :mod:`tasks.pose.initial` (no randomness), then ``starts``
copies turned by 360/starts degrees about the object's up axis, each with the better (by the loss)
of the fit's scales/translation and those refitted linearly to its own rotation. Every start is
refined by Levenberg-Marquardt (IRLS, analytic Jacobian, :mod:`tasks.pose.lm`) and the lowest loss
wins; objects whose winner is unusable (a point behind its camera, or a mean error above
``max_reprojection_px``) are refined again from their starts with Adam (the paper's optimiser;
learning rate decaying exponentially from ``lr`` to ``lr_final``) then LM, keeping the better.
``lm_iterations`` = 0: Adam alone on every start, as in the paper. Objects are independent (all
updates are per object), so batching does not change a result.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from cadestate.geometry import matrix_to_quaternion
from tasks.pose.batch import Batch
from tasks.pose.checks import check_object, coplanar_axis, final_status, prior_matrix, unobserved_axes
from tasks.pose.initial import DTYPE, fit_scale_translation, linear_init, rotate_y, split_affine, symmetry_offsets, tie_scales, yaw_matrix
from tasks.pose.lm import Problem, axis_prior, bottom_sd, floor_residual, front_gap, lm_solve, robust, scale_ties


@dataclass(frozen=True)
class ObjectCorrespondences:
    """One object's annotation: N clicks on F key-frames.

    Attributes:
        xy: float[N, 2] click positions, pixels (image frame, origin top-left, x right, y down).
        xyz: float[N, 3] the matching points on the CAD model, canonical CAD frame, unmirrored.
        keyframe: int[N] index into the cameras below.
        K: float[F, 3, 3] pixel intrinsics; R: float[F, 3, 3], t: float[F, 3] world->camera.
        mirrored: the CAD model is mirrored (x -> -x in the CAD frame) before scaling.
        symmetry: order of rotational symmetry about +Y (1, 2, 4, 36).
        upright: the class stands upright (the up-axis term applies).
        extent: float[3] size of the CAD model's bounding box (canonical CAD frame, x, y, z), or
            None when unknown (then no floor term can apply, and no axis_prior: the proportion prior
            needs no extent).
        on_floor: the class usually rests on the floor ([pose] floor_classes): it helps estimate
            its clip's floor, and gets the support prior.
        rests: the class rests on a support, the floor or another object's top (upright classes
            but [pose] wall_classes): it gets the support prior (:mod:`tasks.pose.support`).
        floor_height: the height on world +Y of the support the object rests on (the floor or a
            host's top, see :mod:`tasks.pose.support`); floor_weight: weight of the support term,
            px per world unit (0: none).
    """

    xy: np.ndarray
    xyz: np.ndarray
    keyframe: np.ndarray
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    mirrored: bool = False
    symmetry: int = 1
    upright: bool = True
    extent: np.ndarray | None = None
    on_floor: bool = False
    rests: bool = False
    floor_height: float = 0.0
    floor_weight: float = 0.0


@dataclass(frozen=True)
class SolverOptions:
    """Knobs of :func:`solve_poses` (the ``[pose]`` config section maps onto these)."""

    alpha: float = 100.0
    """Weight of the up-axis term (px per unit of L1 axis deviation); 0 disables it."""
    beta: float = 1000.0
    """Weight of the front-of-camera term (px per metre behind ``min_depth``)."""
    min_depth: float = 0.05
    """Depth (m, camera z) below which the front-of-camera term penalises a point: metres of the
    object's CAD model (world units over :func:`world_unit`), whatever the world's scale."""
    iterations: int = 400
    """Adam iterations: the fallback for objects the LM leaves unusable (every object when lm_iterations = 0)."""
    lr: float = 0.02
    lr_final: float = 1e-5
    lm_iterations: int = 20
    """Levenberg-Marquardt (IRLS) iterations from the starts (:mod:`tasks.pose.lm`); 0 = Adam only, as in the paper."""
    starts: int = 4
    """Starts per object: the linear fit turned by 360/starts degrees about its up axis, i = 0..starts-1."""
    coplanar: bool = True
    symmetry: bool = True
    coplanar_tol: float = 0.02
    min_axis_span: float = 0.2
    """Axes along which the points span less than this fraction of the model's size get the scale
    prior (:func:`tasks.pose.checks.unobserved_axes`); 0 = never."""
    axis_prior: float = 0.0
    """Weight of the scale prior on those axes: px per squared unit of log-scale deviation from the
    observed axes' mean (:func:`tasks.pose.checks.prior_matrix`); 0 = none."""
    proportion_prior: float = 1.0
    """Weight of the model's proportions on every other untied axis: px per squared unit of log-scale
    deviation from the untied axes' mean (:func:`tasks.pose.checks.prior_matrix`); 0 = free scales."""
    min_points: int = 6
    max_reprojection_px: float = 20.0
    """A solution whose mean reprojection error (px) exceeds this gets status ``high_residual``."""
    min_parallax_deg: float = 1.0
    """Largest angle between the rays from the object to its key-frame cameras below which the
    depth (and so the scale) is not observable: status ``low_parallax``."""
    threads: int = 1
    huber_px: float = 5.0
    """0: the paper's L1 reprojection loss; > 0: Huber loss with this threshold (px): quadratic
    within it (the efficient estimator for Gaussian click error), L1 beyond (robust to bad clicks)."""
    floor_prior: float = 30.0
    """Weight of the support term of :mod:`tasks.pose.support`, px per object height of distance
    between the object's bottom and its support (its clip's floor or a host's top); 0 disables the prior."""
    floor_max_gap: float = 0.5
    """Objects whose own bottom is farther than this many object heights above the floor and from
    every host top keep their own pose (they stand on something unseen, or hang); a bottom below
    the floor always takes it. The floor estimate averages the floor objects within this gap."""
    floor_max_growth: float = 0.5
    """A pose re-solved with the support term is kept only if its reprojection loss grew by at most
    this fraction of the loss without it (else the data contradict the support)."""
    host_supports: bool = True
    """Besides the floor, the tops of other solved objects are supports (:mod:`tasks.pose.support`);
    False: the floor only."""


@dataclass
class PoseResult:
    """The solver's answer for one object. Pose fields are None when no pose was computed.

    ``translation`` float[3] (world units: metres in a metric world), ``rotation`` float[4] (w, x,
    y, z), ``scale`` float[3]: object-to-world = T · R · S · diag(-1, 1, 1)[mirrored]
    (:func:`cadestate.render.object_to_world`). ``coplanar_axis``: the CAD axis whose scale was
    tied for co-planar 3D points (-1: none; a round model's x or z is not tied). ``keyframe_error_px``
    float[F]: mean Euclidean reprojection error per key-frame (px; 0 on a camera with no click,
    which the status checks and the parallax leave out).
    ``status``: ok | invalid_input | too_few_points | single_keyframe | collinear_points |
    behind_camera | high_residual | low_parallax. ``loss_floor``: the final support term (px; 0
    without it); ``floor_prior``: how the support prior treated the object (none | no_floor |
    off_floor | rejected | used | host, see :mod:`tasks.pose.support`), ``floor_height`` the clip's
    floor height on world +Y (NaN: none); ``support`` the index, among the objects solved
    together, of the host whose top it was pulled to (or tried: rejected) (-1: the floor or none);
    ``support_height`` that height on world +Y (NaN: none); ``bottom_sd`` how loosely the fit
    holds the bottom height (world units, relative: :func:`tasks.pose.lm.bottom_sd`).
    """

    status: str
    message: str
    translation: np.ndarray | None = None
    rotation: np.ndarray | None = None
    scale: np.ndarray | None = None
    coplanar_axis: int = -1
    loss_total: float = float("nan")
    loss_reprojection: float = float("nan")
    loss_up: float = float("nan")
    loss_front: float = float("nan")
    keyframe_error_px: np.ndarray = field(default_factory=lambda: np.zeros(0))
    parallax_deg: float = float("nan")
    iterations: int = 0
    start: int = -1
    loss_floor: float = float("nan")
    floor_prior: str = "none"
    floor_height: float = float("nan")
    support: int = -1
    support_height: float = float("nan")
    bottom_sd: float = float("nan")


def rotation_6d(a: torch.Tensor) -> torch.Tensor:
    """float[B, 6] (two column vectors) -> rotation float[B, 3, 3] by Gram-Schmidt (Zhou et al. 2019)."""
    b1 = torch.nn.functional.normalize(a[:, :3], dim=-1)
    b2 = torch.nn.functional.normalize(a[:, 3:] - (b1 * a[:, 3:]).sum(-1, keepdim=True) * b1, dim=-1)
    return torch.stack([b1, b2, torch.linalg.cross(b1, b2)], -1)


def make_batch(objects: list[ObjectCorrespondences], axes: list[int], opts: SolverOptions) -> Batch:
    B = len(objects)
    P = max(len(o.xy) for o in objects)
    F = max(len(o.K) for o in objects)
    z = lambda *s: np.zeros((B, *s))  # noqa: E731
    pts, uv, xn, kf, pm = z(P, 3), z(P, 2), z(P, 2), np.zeros((B, P), np.int64), np.zeros((B, P), bool)
    K, Rc, tc, fm = np.tile(np.eye(3), (B, F, 1, 1)), np.tile(np.eye(3), (B, F, 1, 1)), z(F, 3), np.zeros((B, F), bool)
    for b, o in enumerate(objects):
        n, f = len(o.xy), len(o.K)
        pts[b, :n], uv[b, :n], kf[b, :n], pm[b, :n] = o.xyz, o.xy, o.keyframe, True
        K[b, :f], Rc[b, :f], tc[b, :f], fm[b, :f] = o.K, o.R, o.t, True
        h = np.linalg.solve(o.K[o.keyframe], np.concatenate([o.xy, np.ones((n, 1))], 1)[..., None])[..., 0]
        xn[b, :n] = h[:, :2] / h[:, 2:]
    T = lambda a: torch.as_tensor(a, dtype=DTYPE)  # noqa: E731
    half = [np.zeros(3) if o.extent is None else np.asarray(o.extent, np.float64) / 2 for o in objects]
    axis = np.asarray(axes if opts.coplanar else [-1] * B)
    tied = (np.arange(3)[None] == axis[:, None]) & (axis[:, None] >= 0)
    unseen = tied | np.stack([unobserved_axes(o.xyz, o.extent, opts.min_axis_span if opts.axis_prior > 0 else 0.0)
                              for o in objects])
    # 36-way models have one horizontal scale (sx = sz): observed when either axis is
    round_ = np.array([opts.symmetry and o.symmetry >= 36 for o in objects])
    for m in (tied, unseen):
        m[round_, 0] = m[round_, 2] = m[round_, 0] & m[round_, 2]
    loose = unseen & ~tied
    prior = np.stack([prior_matrix(lo, ti, opts.axis_prior, opts.proportion_prior, r) for lo, ti, r in zip(loose, tied, round_)])
    return Batch(T(pts), T(uv), T(xn), torch.as_tensor(kf), torch.as_tensor(pm), T(K), T(Rc), T(tc), torch.as_tensor(fm),
                 T([-1.0 if o.mirrored else 1.0 for o in objects]),
                 torch.as_tensor([int(o.symmetry) if opts.symmetry else 1 for o in objects]),
                 torch.as_tensor([bool(o.upright) and opts.alpha > 0 for o in objects]),
                 torch.as_tensor(axis), torch.as_tensor(tied), torch.as_tensor(loose), T(prior), T(np.stack(half)),
                 T([float(o.floor_height) for o in objects]),
                 T([float(o.floor_weight) if o.extent is not None else 0.0 for o in objects]), torch.ones(B, dtype=DTYPE))


def evaluate(b: Batch, R: torch.Tensor, s: torch.Tensor, T: torch.Tensor, phi: torch.Tensor,
             offsets: torch.Tensor, omask: torch.Tensor, opts: SolverOptions) -> dict[str, torch.Tensor]:
    """The loss terms (float[B] each) of poses R float[B, 3, 3], s float[B, 3], T float[B, 3] with
    per-key-frame rotations phi float[B, F] (36-way) and discrete offsets float[B, O]; also the
    per-key-frame mean Euclidean error ``kf_px`` float[B, F] and the chosen-rotation depths ``z``."""
    B, P, _ = b.pts.shape
    F = b.Rc.shape[1]
    ang = offsets[:, None, :] + torch.gather(phi, 1, b.kf)[:, :, None]  # float[B, P, O]
    x = rotate_y(b.pts[:, :, None, :].expand(-1, -1, ang.shape[2], -1), ang)
    x = x * b.mvec[:, None, None]
    world = torch.einsum("bij,bpoj->bpoi", R, x * s[:, None, None, :]) + T[:, None, None, :]
    cam = torch.einsum("bpij,bpoj->bpoi", b.Rp, world) + b.tp[:, :, None, :]
    depth = cam[..., 2]
    proj = cam[..., :2] / depth.clamp(min=1e-6)[..., None]
    pix = torch.einsum("bpij,bpoj->bpoi", b.Kp[..., :2, :2], proj) + b.Kp[:, :, None, :2, 2]
    d = pix - b.uv[:, :, None, :]
    l1 = robust(d, opts.huber_px).sum(-1) * b.pmask[..., None]  # float[B, P, O]
    per_kf = torch.zeros(B, F, l1.shape[2], dtype=DTYPE).scatter_add(1, b.kf[..., None].expand_as(l1), l1)
    per_kf = torch.where(omask[:, None, :], per_kf, torch.full_like(per_kf, float("inf")))
    best_kf, choice = per_kf.min(-1)  # float[B, F], int[B, F]
    best_kf = torch.where(b.fmask, best_kf, torch.zeros_like(best_kf))
    npts = b.npts
    choice_p = torch.gather(choice, 1, b.kf)[..., None]  # int[B, P, 1]
    z = torch.gather(depth, 2, choice_p)[..., 0]
    e = torch.linalg.norm(torch.gather(d, 2, choice_p[..., None].expand(B, P, 1, 2))[:, :, 0], dim=-1) * b.pmask
    cnt = torch.zeros(B, F, dtype=DTYPE).scatter_add(1, b.kf, b.pmask.to(DTYPE))
    kf_px = torch.zeros(B, F, dtype=DTYPE).scatter_add(1, b.kf, e) / cnt.clamp(min=1)
    repr_ = best_kf.sum(1) / npts
    up = (R[:, :, 1] - torch.tensor([0.0, 1.0, 0.0], dtype=DTYPE)).abs().sum(-1) * b.upright
    gap = front_gap(b, z, opts.min_depth)
    front = gap.sum(1) / npts
    d_best = torch.gather(d, 2, choice_p[..., None].expand(B, P, 1, 2))[:, :, 0] * b.pmask[..., None]
    floor = floor_residual(b, R, s, T)
    prior = axis_prior(b, s)
    # Signed residuals whose absolute sum is the total loss (for the IRLS / Levenberg-Marquardt polish).
    residuals = torch.cat([d_best.flatten(1) / npts[:, None],
                           opts.alpha * (R[:, :, 1] - torch.tensor([0.0, 1.0, 0.0], dtype=DTYPE)) * b.upright[:, None],
                           opts.beta * gap / npts[:, None], prior, floor[:, None]], 1)
    return {"total": repr_ + opts.alpha * up + opts.beta * front + floor.abs() + prior.sum(-1), "reprojection": repr_, "up": up,
            "front": front, "floor": floor.abs(), "kf_px": kf_px, "z": torch.where(b.pmask, z, torch.ones_like(z)),
            "residuals": residuals}


def world_unit(s: torch.Tensor) -> torch.Tensor:
    """World units per metre of each object's CAD model, float[B], from the linear fit's scales s
    float[B, 3] (world units per CAD metre along each axis): their geometric mean, 1 where it is
    not a positive finite number. About 1 in a metric world; RealEstate10K's and SfM's worlds have
    an arbitrary scale, which this carries into the front term's metres."""
    g = torch.exp(torch.log(s).mean(-1))
    return torch.where(torch.isfinite(g) & (g > 0), g, torch.ones_like(g))


def _start_scale(b: Batch, T0: torch.Tensor) -> torch.Tensor:
    """Translation unit per object float[B]: the start's mean distance to its key-frame cameras
    (at least a millimetre of its model, :func:`world_unit`)."""
    cam_c = -torch.einsum("bfji,bfj->bfi", b.Rc, b.tc)
    dist = torch.linalg.norm(cam_c - T0[:, None], dim=-1)
    return torch.maximum(torch.where(b.fmask, dist, torch.zeros_like(dist)).sum(1) / b.fmask.sum(1).clamp(min=1), 1e-3 * b.unit)


def _adam(b: Batch, R0, s0, T0, phi0, offsets, omask, scale_t, is36, opts: SolverOptions):
    """Adam from the given starts (the paper's optimiser); returns (R, log-scales, T, phi)."""
    B = b.pts.shape[0]
    a = torch.cat([R0[:, :, 0], R0[:, :, 1]], -1).clone().requires_grad_(True)
    dT = torch.zeros(B, 3, dtype=DTYPE, requires_grad=True)
    ls = torch.log(s0.clamp(min=1e-6)).clone().requires_grad_(True)
    dphi = torch.zeros_like(phi0, requires_grad=True)
    opt = torch.optim.Adam([a, dT, ls, dphi], lr=opts.lr)
    n = max(opts.iterations, 1)
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=(opts.lr_final / opts.lr) ** (1.0 / n))

    def params():
        R = rotation_6d(a)
        s = tie_scales(torch.exp(ls), b.tied, b.sym >= 36)
        return R, s, T0 + scale_t[:, None] * dT, phi0 + dphi * is36

    for _ in range(opts.iterations):
        opt.zero_grad(set_to_none=False)
        R, s, T, phi = params()
        loss = evaluate(b, R, s, T, phi, offsets, omask, opts)["total"]
        torch.nan_to_num(loss, nan=0.0, posinf=0.0).sum().backward()
        opt.step()
        sched.step()
    with torch.no_grad():
        R, _, T, phi = params()
        return R, ls.detach(), T, phi


def optimise(b: Batch, R0: torch.Tensor, s0: torch.Tensor, T0: torch.Tensor, phi0: torch.Tensor,
             opts: SolverOptions, adam: bool = True
             ) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Refine the given starts: Adam (``opts.iterations``, when ``adam``) then Levenberg-Marquardt
    (``opts.lm_iterations``, :func:`tasks.pose.lm.lm_solve`). Returns the final loss terms (and
    ``phi``), R, s, T (float[B, ...]) and the iterations run per object int[B]."""
    pb = _problem(b, T0)
    its = torch.zeros(b.pts.shape[0], dtype=torch.long)
    with torch.no_grad():
        R, ls, T, phi = R0, torch.log(s0.clamp(min=1e-6)), T0, phi0
    if adam and opts.iterations > 0:
        R, ls, T, phi = _adam(b, R0, s0, T0, phi0, pb.offsets, pb.omask, pb.scale_t, (b.sym >= 36).to(DTYPE)[:, None], opts)
        its += opts.iterations
    with torch.no_grad():
        if opts.lm_iterations > 0:
            R, ls, T, phi, run = lm_solve(pb, R, ls, T, phi, opts.lm_iterations, opts.min_depth, opts.alpha, opts.beta,
                                          opts.huber_px)
            its += run
        s = tie_scales(torch.exp(ls), b.tied, b.sym >= 36)
        return {**evaluate(b, R, s, T, phi, pb.offsets, pb.omask, opts), "phi": phi}, R, s, T, its


def _problem(b: Batch, T: torch.Tensor) -> Problem:
    """The :class:`tasks.pose.lm.Problem` of batch ``b``: its discrete symmetric offsets (36-way
    models get a free angle instead), scale ties, and translation unit from the translations T."""
    offsets, omask = symmetry_offsets(torch.where(b.sym >= 36, torch.ones_like(b.sym), b.sym), True)
    return Problem(b, offsets, omask, scale_ties(b.tied, b.sym >= 36), (b.sym >= 36).to(DTYPE)[:, None] * b.fmask,
                   _start_scale(b, T))


def solve_poses(objects: list[ObjectCorrespondences], opts: SolverOptions = SolverOptions()) -> list[PoseResult]:
    """Solve every object (batched); one :class:`PoseResult` per object, in order."""
    results: list[PoseResult | None] = [None] * len(objects)
    todo, axes = [], []
    for i, o in enumerate(objects):
        problem = check_object(o, opts)
        if problem is not None:
            results[i] = PoseResult(*problem)
        else:
            todo.append(i)
            axes.append(coplanar_axis(o.xyz, o.keyframe, o.symmetry if opts.symmetry else 1, opts.coplanar_tol))
    if todo:
        threads = torch.get_num_threads()
        torch.set_num_threads(opts.threads)
        try:
            _solve(objects, todo, axes, opts, results)
            # A 2-way model's tie may be wrong: its key-frames' faces may be one face and its twin
            # (tied: the scale across them is unseen) or two faces clicked from both sides (the
            # scale between them is seen). The clicks decide: a tied pose that cannot explain
            # them is solved again untied and replaced when that one is fit for use.
            again = [i for i, a in zip(todo, axes) if a >= 0 and results[i].status == "high_residual"
                     and coplanar_axis(objects[i].xyz, objects[i].keyframe, 1, opts.coplanar_tol) < 0]
            if again:
                untied: list[PoseResult | None] = [None] * len(objects)
                _solve(objects, again, [-1] * len(again), opts, untied)
                for i in again:
                    if untied[i].status == "ok":
                        results[i] = untied[i]
        finally:
            torch.set_num_threads(threads)
    return results  # type: ignore[return-value]


def _solve(objects, todo, axes, opts, results) -> None:
    b = make_batch([objects[i] for i in todo], axes, opts)
    B, S = len(todo), max(opts.starts, 1)
    offsets, omask = symmetry_offsets(b.sym, opts.symmetry)
    A, T, phi = linear_init(b.pts, b.xn, b.kf, b.pmask, b.Rc, b.tc, b.fmask, b.mirror, offsets, omask, b.upright)
    R, s = split_affine(A, b.axis, b.tied | b.loose, b.sym >= 36, b.upright)  # starts keep the model's proportions
    ok = torch.isfinite(A).all(-1).all(-1) & torch.isfinite(T).all(-1)
    R = torch.where(ok[:, None, None], R, torch.eye(3, dtype=DTYPE))
    s, T = torch.where(ok[:, None], s, torch.ones_like(s)), torch.nan_to_num(T)
    b.unit = world_unit(s)
    angle = torch.gather(phi, 1, b.kf)  # float[B, P]: each point's symmetric rotation in the linear fit
    # 2- and 4-way offsets stay discrete (the min in the loss); 36-way ones become continuous.
    phi = torch.where((b.sym >= 36)[:, None], phi, torch.zeros_like(phi))
    turn = yaw_matrix(torch.arange(S, dtype=DTYPE) * 2 * math.pi / S)  # object frame, about its +Y
    Rs = (R[:, None] @ turn[None]).reshape(B * S, 3, 3)
    bs = b.repeat(S)
    s0, T0, phi0 = s.repeat_interleave(S, 0), T.repeat_interleave(S, 0), phi.repeat_interleave(S, 0)
    with torch.no_grad():
        # Each start also gets the scales and translation that fit its own rotation (linear in (s, T));
        # the better of the two (by the loss) is kept: a poor affine split cannot spoil every start.
        s1, T1 = fit_scale_translation(bs.pts, bs.xn, bs.kf, bs.pmask, bs.Rc, bs.tc, bs.mirror, Rs,
                                       angle.repeat_interleave(S, 0), scale_ties(bs.tied | bs.loose, bs.sym >= 36))
        usable = torch.isfinite(s1).all(-1) & torch.isfinite(T1).all(-1) & (s1 > 1e-3 * bs.unit[:, None]).all(-1)
        s1, T1 = torch.where(usable[:, None], s1, s0), torch.where(usable[:, None], T1, T0)
        off0, om0 = symmetry_offsets(torch.where(bs.sym >= 36, torch.ones_like(bs.sym), bs.sym), True)
        l0 = torch.nan_to_num(evaluate(bs, Rs, s0, T0, phi0, off0, om0, opts)["total"], nan=float("inf"))
        l1 = torch.nan_to_num(evaluate(bs, Rs, s1, T1, phi0, off0, om0, opts)["total"], nan=float("inf"))
        refit = usable & (l1 < l0)
        s0, T0 = torch.where(refit[:, None], s1, s0), torch.where(refit[:, None], T1, T0)
    lm_first = opts.lm_iterations > 0
    terms, Rf, sf, Tf, its = optimise(bs, Rs, s0, T0, phi0, opts, adam=not lm_first)
    total = torch.nan_to_num(terms["total"], nan=float("inf")).view(B, S)
    if lm_first and opts.iterations > 0:
        # Fallback: objects whose best LM solution is unusable (points behind a camera, or a mean
        # reprojection error above max_reprojection_px) are refined again with Adam + LM.
        best = total.argmin(1)
        pick = torch.arange(B) * S + best
        clicked = torch.zeros_like(terms["kf_px"]).scatter_add(1, bs.kf, bs.pmask.to(DTYPE)) > 0  # as final_status counts
        kf_mean = (terms["kf_px"] * clicked).sum(1) / clicked.sum(1).clamp(min=1)
        bad = ((terms["front"] > 0) | ((terms["z"] <= 0) & bs.pmask).any(1) | ~(kf_mean <= opts.max_reprojection_px)
               | ~torch.isfinite(terms["total"]))[pick]
        if bool(bad.any()):
            rows = (torch.nonzero(bad)[:, 0][:, None] * S + torch.arange(S)).flatten()
            t2, R2, s2, T2, i2 = optimise(bs.select(rows), Rs[rows], s0[rows], T0[rows], phi0[rows], opts, adam=True)
            better = torch.nan_to_num(t2["total"], nan=float("inf")) < total.view(-1)[rows]
            for key in terms:
                terms[key][rows] = torch.where(better.view(-1, *[1] * (terms[key].dim() - 1)), t2[key], terms[key][rows])
            Rf[rows] = torch.where(better[:, None, None], R2, Rf[rows])
            sf[rows], Tf[rows] = torch.where(better[:, None], s2, sf[rows]), torch.where(better[:, None], T2, Tf[rows])
            its[rows] += i2
            total = torch.nan_to_num(terms["total"], nan=float("inf")).view(B, S)
    best = total.argmin(1)
    pick = torch.arange(B) * S + best
    sd = _bottom_sd(bs.select(pick), Rf[pick], sf[pick], Tf[pick], terms["phi"][pick], opts)
    cam_c = -torch.einsum("bfji,bfj->bfi", b.Rc, b.tc).numpy()
    for j, i in enumerate(todo):
        k = int(pick[j])
        o = objects[i]
        F = len(o.K)
        Rn, sn, Tn = Rf[k].numpy(), sf[k].numpy(), Tf[k].numpy()
        kf_px = terms["kf_px"][k, :F].numpy()
        z = terms["z"][k, : len(o.xy)].numpy()
        clicked = np.unique(np.asarray(o.keyframe))  # a camera with no click says nothing of the pose
        rays = cam_c[j, clicked] - Tn
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        parallax = float(np.degrees(np.arccos(np.clip(rays @ rays.T, -1, 1)).max()))
        status, message = final_status(z, kf_px[clicked], parallax, opts)
        message += _tie_note(b.loose[j].numpy(), opts.min_axis_span)
        results[i] = PoseResult(
            status, message, Tn.copy(), matrix_to_quaternion(Rn), sn.copy(), int(b.axis[j]) if bool(b.tied[j].any()) else -1,
            float(terms["total"][k]), float(terms["reprojection"][k]), float(terms["up"][k]),
            float(terms["front"][k]), kf_px.copy(), parallax, int(its[k]), int(best[j]), float(terms["floor"][k]),
            bottom_sd=float(sd[j]))


def _tie_note(loose: np.ndarray, min_span: float) -> str:
    """The part of a pose's message naming the axes the scale prior held (``loose`` bool[3]): '' when none."""
    if not loose.any():
        return ""
    names = ", ".join("xyz"[a] for a in np.flatnonzero(loose))
    return f"; scale along {names} held to the model's proportions (the clicks span under {100 * min_span:g} % of the model there)"


def _bottom_sd(b: Batch, R: torch.Tensor, s: torch.Tensor, T: torch.Tensor, phi: torch.Tensor, opts: SolverOptions):
    """:func:`tasks.pose.lm.bottom_sd` float[B] of the final poses."""
    with torch.no_grad():
        return bottom_sd(_problem(b, T), R, torch.log(s.clamp(min=1e-12)), T, phi, opts.min_depth, opts.alpha, opts.beta,
                         opts.huber_px)
