"""Where a track's object is in 3D: the least-squares intersection of the rays through its box
centres (the cameras are known), with an uncertainty from the ray geometry.

Frames: every point and camera centre is in the clip's aligned world (``frames``: metres, +Y up);
rays leave the camera centre ``C = -R^T t`` along ``R^T K^-1 (u, v, 1)``, with (u, v) the box
centre in pixels (OpenCV camera, world->camera ``X_cam = R X_world + t``; ``cadestate.geometry``).

A ray's error is angular: the box centre is not the projection of the object's centre, and it
wanders more the larger the box looks, so ray i has the angular standard deviation
``sigma_i = SIGMA0 + SIGMA_BOX * (box half-diagonal, radians)`` and, at depth ``z_i`` along it, the
perpendicular standard deviation ``sigma_i * z_i`` (metres). The point minimises the weighted sum
of squared perpendicular distances (:func:`triangulate`); its ``cost`` is that sum (a chi-square),
plus each depth behind a camera squared in its ray's weight (a point behind the cameras fits no box). Rays
of too narrow a baseline (a camera that turns on the spot, a single box) leave the point poorly
determined along them: a weak prior (:data:`PRIOR_DEPTH` m along the mean ray, standard deviation
:data:`PRIOR_SIGMA` m) keeps the system solvable and the covariance large along the rays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cadestate.geometry import camera_to_world

SIGMA0 = 0.01
"""Angular noise floor of a box centre (radians)."""
SIGMA_BOX = 0.25
"""Angular noise of a box centre per radian of the box's half-diagonal."""
MIN_DEPTH = 0.3
"""Depths (m) below this count as this when weighting a ray (a point cannot sit on the camera)."""
PRIOR_DEPTH = 2.5
"""Depth (m) along the mean ray of the prior point (a room's typical viewing distance)."""
PRIOR_SIGMA = 10.0
"""Standard deviation (m) of the prior point, per axis: weak, it only bounds what rays leave free."""


@dataclass(frozen=True)
class Rays:
    """N rays in the aligned world: ``origin`` float64[N,3] camera centres (m), ``direction``
    float64[N,3] unit vectors, ``sigma`` float64[N] angular standard deviation (radians),
    ``half_diag`` float64[N] the box's angular half-diagonal (radians)."""

    origin: np.ndarray
    direction: np.ndarray
    sigma: np.ndarray
    half_diag: np.ndarray

    def __len__(self) -> int:
        return len(self.origin)

    def subset(self, index: np.ndarray) -> Rays:
        """The rays at ``index`` (int[M] or bool[N])."""
        return Rays(self.origin[index], self.direction[index], self.sigma[index], self.half_diag[index])

    def __add__(self, other: Rays) -> Rays:
        """The rays of both, ``self``'s first."""
        return Rays(*(np.concatenate([getattr(self, k), getattr(other, k)]) for k in ("origin", "direction", "sigma", "half_diag")))


@dataclass(frozen=True)
class Point3D:
    """A triangulated point: ``X`` float64[3] (m, aligned world), ``cov`` float64[3,3] (m^2),
    ``cost``: chi-square of the rays about it (the prior excluded), plus the weighted squares of the
    depths behind a camera, ``depth`` float64[N] of each
    ray's foot point (m)."""

    X: np.ndarray
    cov: np.ndarray
    cost: float
    depth: np.ndarray


def box_rays(boxes: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray, width: int, height: int) -> Rays:
    """Rays through the centres of ``boxes`` float[N,4] (ymin, xmin, ymax, xmax, normalised by image
    height / width), each seen by the camera ``K`` float[N,3,3] (px), ``R`` float[N,3,3], ``t``
    float[N,3] (world->camera) of its frame."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    u = (boxes[:, 1] + boxes[:, 3]) / 2 * width
    v = (boxes[:, 0] + boxes[:, 2]) / 2 * height
    Kinv = np.linalg.inv(K)
    pix = np.stack([u, v, np.ones_like(u)], axis=1)
    cam = np.einsum("nij,nj->ni", Kinv, pix)
    corner = np.einsum("nij,nj->ni", Kinv, np.stack([boxes[:, 3] * width, boxes[:, 2] * height, np.ones_like(u)], axis=1))
    half = np.arctan2(np.linalg.norm(np.cross(cam, corner), axis=1), np.einsum("ni,ni->n", cam, corner))
    R_cw, origin = camera_to_world(R, t)
    d = np.einsum("nij,nj->ni", R_cw, cam)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return Rays(origin, d, SIGMA0 + SIGMA_BOX * half, half)


def _solve(rays: Rays, w: np.ndarray, prior: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least-squares point and its information matrix float[3,3] (``w``: weight per ray, 1/m^2)."""
    P = np.eye(3)[None] - rays.direction[:, :, None] * rays.direction[:, None, :]  # [N,3,3] perpendicular projectors
    info = np.einsum("n,nij->ij", w, P) + np.eye(3) / PRIOR_SIGMA**2
    rhs = np.einsum("n,nij,nj->i", w, P, rays.origin) + prior / PRIOR_SIGMA**2
    return np.linalg.solve(info, rhs), info


def triangulate(rays: Rays) -> Point3D:
    """The point nearest to ``rays`` (module docstring): solved once with every ray at the prior
    depth, then re-weighted by the depths found (twice)."""
    if len(rays) == 0:
        raise ValueError("triangulate needs at least one ray")
    mean_dir = rays.direction.mean(0)
    mean_dir /= max(np.linalg.norm(mean_dir), 1e-12)
    prior = rays.origin.mean(0) + PRIOR_DEPTH * mean_dir
    depth = np.full(len(rays), PRIOR_DEPTH)
    for _ in range(3):
        w = 1.0 / (rays.sigma * np.maximum(depth, MIN_DEPTH)) ** 2
        X, info = _solve(rays, w, prior)
        depth = np.einsum("ni,ni->n", X[None] - rays.origin, rays.direction)
    off = X[None] - rays.origin
    perp = off - depth[:, None] * rays.direction
    w = 1.0 / (rays.sigma * np.maximum(depth, MIN_DEPTH)) ** 2
    cost = float(np.sum(w * np.einsum("ni,ni->n", perp, perp)) + np.sum(w * np.minimum(depth, 0.0) ** 2))
    return Point3D(X, np.linalg.inv(info), cost, depth)


def object_size(rays: Rays, depth: np.ndarray) -> float:
    """Median size (m) of the object the boxes show: each box's angular diagonal times its ray's
    ``depth`` float[N] (m, e.g. :attr:`Point3D.depth` of a point)."""
    return float(np.median(2 * rays.half_diag * np.maximum(depth, MIN_DEPTH)))
