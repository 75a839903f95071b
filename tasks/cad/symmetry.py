"""Symmetry of a CAD model about its up axis (Scan2CAD convention, see
``/work/shared/reference/formats.md``, "Scan2CAD conventions").

The model is in its canonical frame: metres, +Y up, origin at the centre of the bounding box.
Its order K is 1 (none), 2, 4 or 36 (rotationally symmetric, ``__SYM_ROTATE_UP_INF``): the
shape is unchanged by a rotation of 360/K degrees about the vertical axis through the origin.

Method: sample the surface area-uniformly, rotate the samples about +Y and measure, with
nearest-neighbour distances (:class:`scipy.spatial.cKDTree`), how far the rotated copy lies from
the original. The distance of one rotation is the ``QUANTILE``-th percentile of the distances from
the rotated samples to the original ones, minus the same percentile of the distances from each
sample to its nearest *other* sample (the sampling noise: what a perfectly symmetric surface gives,
its rotated samples being just another area-uniform sampling of it), divided by the bounding-box
diagonal. The 97th percentile ignores details covering up to ~3 % of the surface (a knob, a seam,
lamp-shade spokes) but not a backrest, a headboard or the drawers of a desk.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh
from scipy.spatial import cKDTree

SYMMETRY_ORDERS = (1, 2, 4, 36)
"""Orders of symmetry about +Y: 1 none, 2, 4, 36 (stands for rotationally symmetric)."""

DEFAULT_TOLERANCE = 0.008
"""Largest accepted error (a fraction of the bounding-box diagonal). Calibrated on programmatic
meshes and on the hand-checked Sweet Home 3D models of ``tests/data/sh3d_symmetry.csv`` (seeds
0-3): the symmetric ones score <= 0.0031 at their order; the closest asymmetric ones still told
apart score >= 0.0097 (a bed with head- and footboard) and 0.0135 (a square pallet with its boards
one way). A metal bed and a futon whose only asymmetry is pillows and slightly taller head ends
score 0.003-0.007 and come out as 2."""

QUANTILE = 97.0
"""Percentile (0-100) of the nearest-neighbour distances that defines the error of a rotation."""

MAX_QUERIES = 2048
"""At most this many samples (every n-th) are rotated and looked up; all index the tree (speed)."""

STEPS: dict[int, tuple[int, ...]] = {
    2: (1,), 4: (1, 2, 3), 36: (1, 2, 4, 9, 18, 27, 32, 34, 35)}
"""Rotations checked per candidate order K: multiples j of 360/K degrees. Each set is closed
under j -> K - j (a rotation and its inverse), which makes the distance symmetric. For 36,
10/20/40 degrees either way stand for the rest once 90 degrees passes (36 requires 4)."""

IMPLIED: dict[int, tuple[int, ...]] = {2: (), 4: (2,), 36: (2, 4)}
"""Orders whose error must also pass for a candidate order to be accepted."""


@dataclass(frozen=True)
class SymmetryResult:
    """order: int in SYMMETRY_ORDERS; errors: dict[int, float] — for each candidate order K in
    (2, 4, 36), the worst (over the rotations by 360*j/K degrees, j in ``STEPS[K]``) symmetric
    distance between the surface samples and their rotated copy, relative to the model's size
    (the bounding-box diagonal of the samples); see the module docstring."""

    order: int
    errors: dict[int, float] = field(default_factory=dict)


def sample_surface(mesh: trimesh.Trimesh, count: int = 4096, seed: int = 0) -> np.ndarray:
    """Area-uniform samples of ``mesh``'s surface: float64[count, 3]; the same for the same seed."""
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return np.ascontiguousarray(points, dtype=np.float64)


def rotation_y(degrees: float) -> np.ndarray:
    """float64[3, 3]: rotation by ``degrees`` about +Y (right-handed)."""
    a = np.deg2rad(degrees)
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rotation_distance(queries: np.ndarray, tree: cKDTree, degrees: float, floor: float) -> float:
    """``QUANTILE``-th percentile of the distances from ``queries`` (float[M, 3], samples)
    rotated by ``degrees`` about +Y to the samples indexed by ``tree``, minus ``floor``; same unit."""
    d, _ = tree.query(queries @ rotation_y(degrees).T, k=1)
    return float(np.percentile(d, QUANTILE)) - floor


def symmetry_errors(points: np.ndarray) -> dict[int, float]:
    """For K in (2, 4, 36): the worst relative :func:`rotation_distance` (>= 0) over ``STEPS[K]``.
    ``points``: float[N, 3] in the canonical frame."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be float[N, 3], got shape {pts.shape}")
    size = float(np.linalg.norm(np.ptp(pts, axis=0))) if len(pts) else 0.0
    if len(pts) < 2 or size == 0.0:
        return {k: 0.0 for k in STEPS}
    tree = cKDTree(pts)
    queries = pts[:: max(1, len(pts) // MAX_QUERIES)]
    floor = float(np.percentile(tree.query(queries, k=2)[0][:, 1], QUANTILE))
    cache: dict[float, float] = {}  # 180 and 90/270 degrees are shared between orders
    errors = {}
    for k, steps in STEPS.items():
        for angle in (round(360.0 * j / k, 9) for j in steps):
            if angle not in cache:
                cache[angle] = rotation_distance(queries, tree, angle, floor)
        errors[k] = max(0.0, max(cache[round(360.0 * j / k, 9)] for j in steps)) / size
    return errors


def order_from_errors(errors: dict[int, float], tolerance: float) -> int:
    """Largest K whose error, and that of every order it implies (36 -> 4, 2; 4 -> 2), is <= tolerance."""
    for k in (36, 4, 2):
        if all(errors[m] <= tolerance for m in (k, *IMPLIED[k])):
            return k
    return 1


def detect_symmetry(points: np.ndarray, tolerance: float = DEFAULT_TOLERANCE) -> SymmetryResult:
    """Symmetry order of surface samples ``points`` (float[N, 3], canonical frame: +Y up, origin
    at the bounding-box centre), e.g. from :func:`sample_surface`. Deterministic."""
    errors = symmetry_errors(points)
    return SymmetryResult(order=order_from_errors(errors, tolerance), errors=errors)
