"""The padded tensors of a batch of pose problems, shared by the solver (:mod:`tasks.pose.solver`)
and its Levenberg-Marquardt refinement (:mod:`tasks.pose.lm`).

Frames (see :mod:`cadestate.geometry`): CAD points in the canonical CAD frame (metres, +Y up,
front +Z, bbox-centred, *unmirrored*); clicks in pixels (origin top-left, x right, y down);
cameras world->camera ``X_cam = Rc X_world + tc`` with OpenCV axes; world +Y up.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch

DTYPE = torch.float64


@dataclass
class Batch:
    """B objects padded to P points and F key-frames (padding: zeros, masked out).

    Fields: pts float[B, P, 3] CAD frame; uv float[B, P, 2] clicks, px; xn float[B, P, 2]
    normalised image coordinates K^-1 (u, v, 1); kf int[B, P] key-frame of each point; pmask
    bool[B, P]; K float[B, F, 3, 3] px; Rc float[B, F, 3, 3], tc float[B, F, 3] world->camera;
    fmask bool[B, F]; mirror float[B] (-1 mirrored, else 1); sym int[B] symmetry order about +Y;
    upright bool[B] (the up-axis term applies); axis int[B] co-planar CAD axis (-1 none); tied
    bool[B, 3] the CAD axes whose scale is tied to the others (:func:`tasks.pose.initial.tie_scales`:
    the co-planar axis); loose bool[B, 3] the axes the points hardly span and prior float[B, 3, 3]
    the scale prior (:func:`tasks.pose.lm.axis_prior`: its residuals are ``(prior @ log s)^2``, px;
    rows for the loose axes and, with a proportion prior, the other untied ones); half
    float[B, 3] half the CAD bounding-box size (canonical CAD frame, 0 when unknown); floor_y
    float[B] the support-plane (floor) height on world +Y and floor_w float[B] the weight of the
    floor term (px per world unit; 0: no floor term, see :func:`tasks.pose.lm.support_bottom`);
    unit float[B] world units per metre of the object's CAD model (the geometric mean of its
    linear fit's scales, :func:`tasks.pose.solver.world_unit`; 1 until that fit): the front term's
    ``min_depth`` and ``beta`` are per metre of it, so a world of any scale gets the same pose
    (RealEstate10K's and SfM's are arbitrary).

    Derived per point (not fields; recomputed by :meth:`repeat` and :meth:`select`): Rp float[B, P,
    3, 3], tp float[B, P, 3], Kp float[B, P, 3, 3] its key-frame's camera; npts float[B] points per
    object (at least 1); mvec float[B, 3] the mirror as a vector (mirror, 1, 1).
    """

    pts: torch.Tensor
    uv: torch.Tensor
    xn: torch.Tensor
    kf: torch.Tensor
    pmask: torch.Tensor
    K: torch.Tensor
    Rc: torch.Tensor
    tc: torch.Tensor
    fmask: torch.Tensor
    mirror: torch.Tensor
    sym: torch.Tensor
    upright: torch.Tensor
    axis: torch.Tensor
    tied: torch.Tensor
    loose: torch.Tensor
    prior: torch.Tensor
    half: torch.Tensor
    floor_y: torch.Tensor
    floor_w: torch.Tensor
    unit: torch.Tensor

    def __post_init__(self) -> None:
        B, P = self.kf.shape
        self.Rp = torch.gather(self.Rc, 1, self.kf[..., None, None].expand(B, P, 3, 3))
        self.tp = torch.gather(self.tc, 1, self.kf[..., None].expand(B, P, 3))
        self.Kp = torch.gather(self.K, 1, self.kf[..., None, None].expand(B, P, 3, 3))
        self.npts = self.pmask.sum(1).clamp(min=1).to(DTYPE)
        self.mvec = torch.stack([self.mirror, torch.ones_like(self.mirror), torch.ones_like(self.mirror)], -1)

    def repeat(self, n: int) -> Batch:
        """Every object repeated ``n`` times in a row (object-major: b0, b0, ..., b1, ...)."""
        return Batch(*(getattr(self, f.name).repeat_interleave(n, 0) for f in fields(self)))

    def select(self, idx: torch.Tensor) -> Batch:
        """The objects ``idx`` int[b] (in that order)."""
        return Batch(*(getattr(self, f.name)[idx] for f in fields(self)))
