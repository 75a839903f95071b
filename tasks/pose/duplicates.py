"""Duplicates caught after pose (issue 18): accepted-to-be poses of one clip that occupy the same space.

Each solved pose places its CAD model's bounding box in the world: an **oriented box**, the
canonical (bbox-centred, metres, +Y up) box of size ``cad_models.extent`` mapped by the pose's
object->world matrix (:func:`cadestate.render.object_to_world`: mirror => scale => rotation =>
translation), so the box is ``{T + A·u : |u_i| <= extent_i / 2}`` with A = R · diag(S) · mirror.

The **overlap** of two boxes is the fraction of the smaller box's volume that lies inside the
other: 1 when one holds the other, 0 when they are apart. It is measured on a fixed grid of
:data:`GRID` ³ points (the centres of equal cells of the smaller box), so it is deterministic and
exact to 1/:data:`GRID` per axis. Pairs whose overlap is at least ``[verification]
duplicate_overlap`` are **duplicate candidates**: the verification task flags each as "may be the
same object as track N" and the annotator resolves it there (``same_as_track``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from cadestate.render import object_to_world

GRID = 20
"""Points per axis of the grid that measures an overlap (GRID³ points in the smaller box)."""
THINNEST = 0.1
"""Least side of a posed box, as a share of its model's largest: a model of one flat face (a rug,
a picture: a side of 0) has a box of no volume, which overlapped nothing, its own twin included;
and two solves of one flat or thin object differ in depth by centimetres (at 1 % of the largest
side, a rug posed twice 2 cm apart was no duplicate). A rug under a coffee table 0.4 m high
overlaps a quarter of the table's box."""


@dataclass(frozen=True)
class OrientedBox:
    """A posed CAD model's bounding box in the world (metres, +Y up): ``centre`` float64[3];
    ``axes`` float64[3, 3] maps box coordinates to world offsets (R · diag(S) · mirror, columns
    along the CAD axes); ``extent`` float64[3] the canonical box size along the CAD axes."""

    centre: np.ndarray
    axes: np.ndarray
    extent: np.ndarray

    @property
    def volume(self) -> float:
        """m³."""
        return float(abs(np.linalg.det(self.axes)) * np.prod(self.extent))

    @property
    def radius(self) -> float:
        """Radius of a sphere about ``centre`` that holds the box (m)."""
        return float(np.linalg.norm(np.abs(self.axes) @ (self.extent / 2)))

    def grid(self, n: int = GRID) -> np.ndarray:
        """float64[n³, 3] world points: the centres of the n³ equal cells of the box."""
        c = (np.arange(n) + 0.5) / n - 0.5
        u = np.stack(np.meshgrid(c, c, c, indexing="ij"), -1).reshape(-1, 3) * self.extent
        return self.centre + u @ self.axes.T

    def contains(self, points: np.ndarray) -> np.ndarray:
        """bool[N]: which of the world ``points`` float64[N, 3] lie in the box (boundary included)."""
        u = np.linalg.solve(self.axes, (points - self.centre).T).T
        return np.all(np.abs(u) <= self.extent / 2 * (1 + 1e-9), axis=1)


def posed_box(extent: Sequence[float], translation: Sequence[float], rotation: Sequence[float], scale: Sequence[float],
              is_mirrored: bool) -> OrientedBox:
    """The oriented box of a CAD model of size ``extent`` (m, canonical CAD axes) under a pose
    (translation m world; rotation (w, x, y, z) CAD -> world; scale along the CAD axes); no side
    thinner than :data:`THINNEST` of the largest."""
    M = object_to_world(translation, rotation, scale, is_mirrored)
    size = np.asarray(extent, np.float64)
    return OrientedBox(M[:3, 3].copy(), M[:3, :3].copy(), np.maximum(size, THINNEST * size.max()))


def overlap(a: OrientedBox, b: OrientedBox, n: int = GRID) -> float:
    """Fraction of the smaller box's volume inside the other, on an n³ grid (module docstring)."""
    if np.linalg.norm(a.centre - b.centre) > a.radius + b.radius:
        return 0.0
    small, big = (a, b) if a.volume <= b.volume else (b, a)
    if small.volume <= 0.0:
        return 0.0
    return float(np.mean(big.contains(small.grid(n))))


def duplicate_candidates(boxes: Mapping[int, OrientedBox], threshold: float) -> dict[int, tuple[int, ...]]:
    """Per track of ``boxes`` (track id -> its posed box), the other tracks whose box overlaps
    its own by at least ``threshold`` (ascending ids; symmetric; tracks with none are absent)."""
    ids = sorted(boxes)
    out: dict[int, list[int]] = {}
    for i, a in enumerate(ids):
        for b in ids[i + 1:]:
            if overlap(boxes[a], boxes[b]) >= threshold:
                out.setdefault(a, []).append(b)
                out.setdefault(b, []).append(a)
    return {t: tuple(sorted(v)) for t, v in sorted(out.items())}
