"""Exported poses of symmetric models turned so that their own clicks reproject through them.

The pose solver lets each key-frame's clicks match any of a symmetric model's equivalent turns
about its +Y axis (``tasks.pose.initial.symmetry_offsets``): the model looks the same either way,
and the pose it keeps is one of those turns, not always the one the clicks were made on; each
key-frame may match another. A table's exported clicks could then reproject tens of pixels off
while its silhouette is exact. Before export, each posed object with clicks gets the turn through
which its clicks, every key-frame together, reproject best, and a key-frame whose clicks match
another turn has its 3D points turned to the same point of the symmetric model on that turn
(:func:`turn_to_clicks`): every click then reprojects through the one exported pose; the exported
model, silhouette and pose accuracy are unchanged.

Frames: object->world ``M = T R S F`` (:func:`cadestate.render.object_to_world`; ``F`` the mirror
x -> -x), clicks' 3D points in the CAD frame before the mirror. Turning the model by ``Y(a)``
(about its +Y) gives ``M Y(a) = T (R Y(+-a)) S' F``: ``+a`` unmirrored, ``-a`` mirrored (``F Y(a)
= Y(-a) F``), and ``S'`` the scale with x and z swapped for a quarter turn. For a round (36-way)
model every angle is a turn of the same shape only while its x and z scales agree (the solver ties
them); whole degrees are tried there.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace

import numpy as np

from cadestate.geometry import matrix_to_quaternion, project, quaternion_to_matrix
from tasks.dataset.objects import ClipDataset, DatasetFrame, DatasetObject, Pose

ROUND = 36
"""Symmetry order of a round model (any turn about +Y)."""
SAME_SCALE = 1e-3
"""Relative difference of a round model's x and z scales under which any turn keeps its shape."""
MIN_GAIN_PX2 = 16.0
"""A turn is taken when it brings its clicks' squared reprojection errors down by more than this
per click (px^2, 4 px root-mean-square): less is the clicks' noise fitted (a round model posed
exactly, clicked with 1.5 px of noise, was turned by a few degrees, a key-frame's 3D points moved
8.7 mm off what was clicked, for 0.4-1.4 px^2 a click), where clicks on another turn of a
symmetric model are tens of pixels off (hundreds of px^2 a click)."""


def y_rotation(angle: float) -> np.ndarray:
    """float64[3, 3] rotation by ``angle`` radians about +Y."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def turns(symmetry: int, scale: tuple[float, float, float]) -> np.ndarray:
    """Angles (radians, the first 0) of the turns about +Y that leave a model of ``symmetry`` and
    ``scale`` as it is: multiples of 360/n for n = 2 or 4; whole degrees for a round model whose x
    and z scales agree, else its half turn only."""
    if symmetry >= ROUND:
        sx, _, sz = scale
        same = abs(sx - sz) <= SAME_SCALE * max(abs(sx), abs(sz), 1e-12)
        return np.radians(np.arange(360.0)) if same else np.array([0.0, np.pi])
    return 2 * np.pi * np.arange(max(symmetry, 1)) / max(symmetry, 1)


def turned(pose: Pose, angle: float) -> Pose:
    """``pose`` of the model turned by ``angle`` (a multiple of 90 degrees, or any for equal x and z
    scales) about its +Y: ``matrix()`` is ``pose.matrix() @ Y(angle)`` (module docstring)."""
    R = quaternion_to_matrix(np.asarray(pose.rotation, dtype=np.float64)) @ y_rotation(-angle if pose.is_mirrored else angle)
    sx, sy, sz = pose.scale
    k = angle / (np.pi / 2)
    quarter = abs(k - round(k)) < 1e-9 and round(k) % 2 == 1  # S Y(a) = Y(a) S' with x and z swapped
    scale = (sz, sy, sx) if quarter else (sx, sy, sz)
    return replace(pose, rotation=tuple(float(v) for v in matrix_to_quaternion(R)), scale=scale)


def click_errors(obj: DatasetObject, frames: Mapping[int, DatasetFrame], image_size: tuple[int, int],
                 angles: np.ndarray) -> dict[int, np.ndarray]:
    """Per key-frame timestamp of ``obj``'s clicks (on a frame of ``frames``), float64[A]: per turn,
    the sum of squared pixel distances between its clicks and their 3D points reprojected through
    the object's pose turned by that angle."""
    h, w = image_size
    M = obj.pose.matrix()
    out = {}
    for ts, pairs in obj.correspondences.items():
        f = frames.get(ts)
        if f is None or not pairs:
            continue
        clicked = np.array([xy for xy, _ in pairs], dtype=np.float64) * [w, h]
        xyz = np.array([p for _, p in pairs], dtype=np.float64)
        out[ts] = np.array([float(((project(f.K, f.R, f.t, xyz @ (M[:3, :3] @ y_rotation(a)).T + M[:3, 3])[0] - clicked) ** 2).sum())
                            for a in angles])
    return out


def turn_to_clicks(obj: DatasetObject, frames: Mapping[int, DatasetFrame], image_size: tuple[int, int]) -> DatasetObject:
    """``obj`` with its pose turned (:func:`turned`) to the model's symmetric turn through which its
    clicks reproject best, and each key-frame's 3D points whose clicks fit another turn better
    turned about the model's +Y by the difference (the same point of the symmetric model, so that
    they reproject through the pose); as it is when it has no pose, no clicks, no symmetry, or no
    turn does better."""
    if obj.pose is None or obj.symmetry <= 1 or not obj.correspondences:
        return obj
    angles = turns(obj.symmetry, obj.pose.scale)
    errors = click_errors(obj, frames, image_size, angles)
    if not errors:
        return obj
    total = np.sum(list(errors.values()), axis=0)
    best = int(np.argmin(total))
    clicked = {ts: len(obj.correspondences[ts]) for ts in errors}
    if not total[best] < total[0] - MIN_GAIN_PX2 * sum(clicked.values()):
        best = 0
    clicks = dict(obj.correspondences)
    for ts, e in errors.items():
        own = int(np.argmin(e))
        if e[own] < e[best] - MIN_GAIN_PX2 * clicked[ts]:  # this key-frame's clicks were matched to another turn of the model
            Y = y_rotation(float(angles[own] - angles[best]))
            clicks[ts] = tuple((xy, tuple(float(v) for v in Y @ np.asarray(xyz, np.float64))) for xy, xyz in clicks[ts])
    if best == 0 and clicks == obj.correspondences:
        return obj
    return replace(obj, pose=obj.pose if best == 0 else turned(obj.pose, float(angles[best])), correspondences=clicks)


def turn_poses_to_clicks(ds: ClipDataset) -> ClipDataset:
    """``ds`` with every posed object's pose :func:`turn_to_clicks`."""
    frames = {f.timestamp_us: f for f in ds.frames}
    return replace(ds, objects=tuple(turn_to_clicks(o, frames, ds.image_size) for o in ds.objects))
