"""Input checks, co-planarity detection and the final verdict of the pose solver (:mod:`tasks.pose.solver`).

Every object gets a status; only ``ok`` poses are fit for use. Before solving:

- ``invalid_input``: a non-finite click, 3D point or camera value, a camera K of no positive
  focal length or an R that is no rotation (a reflection), a key-frame index that names no
  camera, or a symmetry order the solver does not know (:data:`SYMMETRY_ORDERS`) (the object is
  not solved: no silent repair);
- ``too_few_points``: fewer than ``min_points`` clicks (9 unknowns, 2 equations per click);
- ``single_keyframe``: every click on one key-frame: one view cannot tell the depth, hence the
  size, of the object (scaling it about the camera centre leaves every projection unchanged);
- ``collinear_points``: the 3D points lie on a line (the rotation about it is not observed).

After solving (the pose is kept, for inspection, but must not be used):

- ``behind_camera``: a point lies at depth <= 0 in a camera that clicked it;
- ``high_residual``: mean reprojection error above ``max_reprojection_px``;
- ``low_parallax``: the key-frame cameras see the object under less than ``min_parallax_deg``
  of angle, so its depth is unobservable (unless the support prior of :mod:`tasks.pose.support`
  rests it on a support that observes its depth: then ``ok``, and its message says so).
"""

from __future__ import annotations

import numpy as np

from cadestate.geometry import rotation_error

SYMMETRY_ORDERS = (1, 2, 4, 36)
"""The symmetry orders about +Y the solver knows (those :mod:`tasks.cad.symmetry` detects): its
offset tables hold 1, 2 or 4 turns, and 36 is a round model (x and z one scale). Another order (6)
was solved with some of its turns, differently alone and beside a 36-way model in a batch."""

ROTATION_TOL = 1e-2
"""Largest :func:`rotation_error` of a key-frame camera's R the solver takes: ten times what a
camera file may hold (tasks.video.camera_file), far below a reflection's (2)."""


def _normal(points: np.ndarray, tol: float) -> np.ndarray | None:
    """Unit normal of float[N, 3] points if they are co-planar (smallest singular value of the
    centred points <= tol x the largest), else None."""
    sv, vt = np.linalg.svd(points - points.mean(0), full_matrices=False)[1:]
    if len(sv) < 3 or sv[0] <= 0:
        return None
    return vt[2] if sv[2] <= tol * sv[0] else None


def coplanar_axis(xyz: np.ndarray, keyframe: np.ndarray, symmetry: int, tol: float) -> int:
    """The CAD axis (0 x, 1 y, 2 z) perpendicular to co-planar annotated points, or -1.

    Co-planar: all points (at least 4) lie on one plane within ``tol`` (relative to their spread);
    the axis is the CAD axis nearest its normal. A 2-way model's key-frames may carry the face and
    its twin under the half turn about +Y (x, z -> -x, -z): there each key-frame with 4 or more
    points must be co-planar with the same nearest axis x or z, and all the points (those of every
    key-frame) must be co-planar once each key-frame's face is turned to the positive side of that axis. Turns about +Y keep
    y, so faces across +Y (a table's top and its feet) tie nothing whatever the symmetry, and a
    4- or 36-way model's faces across x or z may be turned onto each other's neighbours: the
    plain test over all points decides there.
    """
    xyz = np.asarray(xyz, np.float64)
    if len(xyz) >= 4 and (n := _normal(xyz, tol)) is not None:
        return int(np.argmax(np.abs(n)))
    if symmetry != 2:
        return -1
    faces = [xyz[keyframe == f] for f in np.unique(keyframe)]
    axes = []
    for p in faces:
        if len(p) >= 4:
            if (n := _normal(p, tol)) is None:
                return -1
            axes.append(int(np.argmax(np.abs(n))))
    if not axes or len(set(axes)) != 1 or axes[0] == 1:
        return -1
    a = axes[0]  # every key-frame turned, those of fewer than 4 points too: their clicks off the plane untie
    turned = [p * np.array([-1.0, 1.0, -1.0]) if p[:, a].mean() < 0 else p for p in faces]
    return a if _normal(np.concatenate(turned), tol) is not None else -1


def unobserved_axes(xyz: np.ndarray, extent: np.ndarray | None, min_span: float) -> np.ndarray:
    """bool[3]: the CAD axes (x, y, z) along which the annotated points float[N, 3] (canonical CAD
    frame) span less than ``min_span`` of the model's bounding-box size ``extent`` float[3]. The
    clicks barely constrain the scale along such an axis (a few centimetres of a metre-wide model,
    seen through pixels of click error), so the solver holds it to the observed axes' scale
    (:func:`prior_matrix`). None of them with no ``extent``, no points or ``min_span``
    0. The spans are those of the points as clicked on the model: for a symmetric model the solver
    may turn a key-frame's points about +Y, so an axis may be observed through another (36-way
    models count x and z as one axis, :func:`tasks.pose.solver.make_batch`)."""
    if extent is None or min_span <= 0 or len(xyz) == 0:
        return np.zeros(3, bool)
    size = np.asarray(extent, np.float64)
    span = np.ptp(np.asarray(xyz, np.float64), axis=0)
    return (size > 0) & (span < min_span * size)


def prior_matrix(loose: np.ndarray, tied: np.ndarray, weight: float, proportion: float = 0.0,
                 round_: bool = False) -> np.ndarray:
    """float[3, 3] of the scale prior (:func:`tasks.pose.lm.axis_prior`), one row per CAD axis a:

    - a ``loose`` axis (bool[3], :func:`unobserved_axes`): sqrt(``weight``) x (e_a - the mean of e_o
      over the observed axes o, neither loose nor ``tied``; over all three when none is). Its residual
      weight x (log s_a - mean log s_o)^2 (px) pulls the axis towards the observed axes' scale (the
      model's proportions) the more the farther it strays, against what the clicks say;
    - every other axis but the ``tied`` ones (the co-planar tie's): sqrt(``proportion``) x (e_a - the
      mean of e_o over the untied axes): the model's proportions as a weak prior on every scale,
      which decides where the clicks leave the proportions free (co-planar or narrow clicks seen
      with little parallax) and costs a fraction of a pixel where they do not (0: none, free scales
      as the paper).

    ``round_`` (a 36-way model): x and z are one scale, so z's row stays 0 (x's counts once)."""
    seen = ~loose & ~tied
    ref = seen / seen.sum() if seen.any() else np.full(3, 1 / 3)
    untied = ~tied
    if round_:
        untied[2] = False
    P = np.zeros((3, 3))
    for a in np.flatnonzero(loose):
        P[a] = np.sqrt(weight) * (np.eye(3)[a] - ref)
    if proportion > 0 and untied.sum() > 1:
        for a in np.flatnonzero(untied & ~loose):
            P[a] = np.sqrt(proportion) * (np.eye(3)[a] - untied / untied.sum())
    if round_:
        P[2] = 0.0
    return P


def check_object(o, opts) -> tuple[str, str] | None:
    """(status, message) when the object cannot be solved, else None (``o``: ObjectCorrespondences)."""
    xy, xyz, kf = np.asarray(o.xy, float), np.asarray(o.xyz, float), np.asarray(o.keyframe)
    F = len(o.K)
    if xy.ndim != 2 or xy.shape[1:] != (2,) or xyz.shape != (len(xy), 3) or kf.shape != (len(xy),):
        return "invalid_input", f"shapes do not match: xy {xy.shape}, xyz {xyz.shape}, keyframe {kf.shape}"
    K, R, t = np.asarray(o.K, float), np.asarray(o.R, float), np.asarray(o.t, float)
    if K.shape != (F, 3, 3) or R.shape != (F, 3, 3) or t.shape != (F, 3):
        return "invalid_input", f"camera shapes do not match: K {K.shape}, R {R.shape}, t {t.shape} (F, 3, 3 / F, 3)"
    for name, a in (("2D click", xy), ("3D point", xyz), ("camera K", K), ("camera R", R), ("camera t", t)):
        if not np.isfinite(a).all():
            return "invalid_input", f"non-finite {name} value(s)"
    if F and not ((K[:, 0, 0] > 0) & (K[:, 1, 1] > 0)).all():
        return "invalid_input", "a camera K whose focal length is not positive"
    if F and not ((K[:, 2] == [0.0, 0.0, 1.0]).all() and (K[:, 1, 0] == 0).all()):
        return "invalid_input", "a camera K that is not upper triangular with last row (0, 0, 1) (a pinhole camera's)"
    if any(rotation_error(r) > ROTATION_TOL for r in R):
        return "invalid_input", "a camera R that is not a rotation (not orthonormal, or a reflection)"
    if len(kf) and (kf.min() < 0 or kf.max() >= F):
        return "invalid_input", f"key-frame index outside 0..{F - 1}"
    if o.symmetry not in SYMMETRY_ORDERS:
        return "invalid_input", f"symmetry order {o.symmetry}: the solver knows {', '.join(map(str, SYMMETRY_ORDERS))}"
    if len(xy) < opts.min_points:
        return "too_few_points", f"{len(xy)} correspondence(s), at least {opts.min_points} needed"
    if len(np.unique(kf)) < 2:
        return "single_keyframe", "all correspondences are on one key-frame: depth and size are not observable"
    sv = np.linalg.svd(xyz - xyz.mean(0), compute_uv=False)
    if sv[0] <= 0 or sv[1] <= opts.coplanar_tol * sv[0]:
        return "collinear_points", "the 3D points are collinear (or all equal): the pose is not observable"
    return None


def final_status(depth: np.ndarray, kf_px: np.ndarray, parallax_deg: float, opts) -> tuple[str, str]:
    """(status, message) of a solved object from its points' depths float[N] (world units: only
    their sign counts), the errors float[F] (px) of its clicked key-frames and parallax (degrees)."""
    if not (np.isfinite(depth).all() and np.isfinite(kf_px).all()):
        return "high_residual", "the solution is not finite"
    if (depth <= 0).any():
        return "behind_camera", f"{int((depth <= 0).sum())} point(s) behind the camera that clicked them"
    if kf_px.mean() > opts.max_reprojection_px:
        return "high_residual", f"mean reprojection error {kf_px.mean():.1f} px > {opts.max_reprojection_px} px"
    if not parallax_deg >= opts.min_parallax_deg:  # NaN too
        return "low_parallax", f"key-frames see the object under {parallax_deg:.2f} deg < {opts.min_parallax_deg} deg"
    return "ok", f"mean reprojection error {kf_px.mean():.2f} px"
