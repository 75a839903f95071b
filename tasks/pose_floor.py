"""Support-plane (floor) prior of pose solving: one floor height per clip, shared by its floor objects.

Why: with the small baselines of real-estate walkthroughs (the camera moves about a metre past
objects 3-5 m away) the clicks barely fix an object's depth; the solver slides it along the
viewing ray and scales it in proportion (the depth/scale ambiguity), and that moves its bottom up
or down. Furniture of floor-standing classes rests on the floor, and all of a clip's floor objects
share one floor: the well-observed ones fix its height, which then fixes the depth of the others.

Frames: world up is +Y (:data:`cadestate.geometry.WORLD_UP`, the axis the up-axis term uses; the
paper relies on RealEstate10K's known up axis); "height" is a world +Y coordinate. Camera
extrinsics are world->camera. RealEstate10K worlds have an arbitrary scale, so every threshold
here is relative to the object's own height (its posed bounding box's extent along +Y).

Procedure (:func:`solve_with_floor`), per group of objects (a clip):

1. every object is solved without the prior (:func:`tasks.pose_solver.solve_poses`);
2. the floor height is the weighted median (:func:`weighted_median`) of the bottoms (lowest point
   of the posed CAD bounding box along +Y, :func:`tasks.pose_lm.support_bottom`) of the objects
   of floor classes (``on_floor``) with status ``ok`` and a known bounding box; weight =
   points x tan^2(parallax), the inverse variance of a bottom whose depth error shrinks with the
   parallax of its key-frames and the number of clicks. Fewer than :data:`MIN_FLOOR_OBJECTS` such
   objects: no floor (a median of one object is no check on it);
3. every floor-class object with a pose whose own bottom lies within ``floor_max_gap`` object
   heights of the floor is solved again (all groups in one batch, from the same starts) with the
   term ``floor_prior / height · |bottom - floor|`` (px per object height, L1: robust);
4. the re-solved pose is kept only if its reprojection loss grew by at most ``floor_max_growth``
   times the loss without the prior: an object that stands on something else is not dragged down.

``PoseResult.floor_prior`` records the outcome per object: ``none`` (prior off, not a floor
class, unknown bounding box or no pose), ``no_floor`` (its clip has no floor estimate),
``off_floor`` (its bottom is too far from the floor: own pose kept), ``rejected`` (the re-solve
grew the reprojection loss too much: own pose kept) or ``used``.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from cadestate.geometry import quaternion_to_matrix
from tasks.pose_batch import DTYPE
from tasks.pose_lm import support_bottom
from tasks.pose_solver import ObjectCorrespondences, PoseResult, SolverOptions, solve_poses

MIN_FLOOR_OBJECTS = 2
"""Fewest solved floor-class objects in a clip for it to get a floor estimate."""


def weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    """The weighted median of float[N] values with float[N] positive weights: the smallest value
    whose cumulative weight (values sorted ascending, ties in input order) reaches half the total;
    the mean of it and the next value when it reaches exactly half."""
    order = np.argsort(values, kind="stable")
    v, cum = values[order], np.cumsum(weights[order])
    half = cum[-1] / 2
    k = int(np.searchsorted(cum, half))
    if k + 1 < len(v) and np.isclose(cum[k], half, rtol=1e-12, atol=0.0):
        return float((v[k] + v[k + 1]) / 2)
    return float(v[k])


def bottoms(objects: list[ObjectCorrespondences], results: list[PoseResult]) -> tuple[np.ndarray, np.ndarray]:
    """Bottom and height float[N] (world +Y units) of each posed object's CAD bounding box; NaN for
    objects without a pose or a known bounding box."""
    bottom, height = np.full(len(objects), np.nan), np.full(len(objects), np.nan)
    idx = [i for i, (o, r) in enumerate(zip(objects, results)) if o.extent is not None and r.translation is not None]
    if idx:
        t = lambda a: torch.as_tensor(np.asarray(a, np.float64), dtype=DTYPE)  # noqa: E731
        R = t([quaternion_to_matrix(results[i].rotation) for i in idx])
        b, h = support_bottom(R, t([results[i].scale for i in idx]), t([results[i].translation for i in idx]),
                              t([np.asarray(objects[i].extent) / 2 for i in idx]))
        bottom[idx], height[idx] = b.numpy(), h.numpy()
    return bottom, height


def estimate_floors(objects: list[ObjectCorrespondences], results: list[PoseResult], groups: list[str],
                    bottom: np.ndarray) -> dict[str, float]:
    """Floor height (world +Y) per group that has at least :data:`MIN_FLOOR_OBJECTS` usable objects
    (module docstring, step 2)."""
    samples: dict[str, list[tuple[float, float]]] = {}
    for o, r, g, y in zip(objects, results, groups, bottom):
        if o.on_floor and r.status == "ok" and np.isfinite(y):
            weight = len(o.xy) * np.tan(np.radians(min(r.parallax_deg, 89.0))) ** 2
            samples.setdefault(g, []).append((float(y), float(weight)))
    return {g: weighted_median(np.array([y for y, _ in s]), np.array([w for _, w in s]))
            for g, s in sorted(samples.items()) if len(s) >= MIN_FLOOR_OBJECTS}


def solve_with_floor(objects: list[ObjectCorrespondences], groups: list[str],
                     opts: SolverOptions = SolverOptions()) -> list[PoseResult]:
    """Solve every object, then re-solve the floor objects of each group with the support-plane
    prior (module docstring); ``groups`` str[N] names each object's clip. One result per object."""
    first = solve_poses(objects, opts)
    if opts.floor_prior <= 0 or not objects:
        return first
    bottom, height = bottoms(objects, first)
    floors = estimate_floors(objects, first, groups, bottom)
    out = [dataclasses.replace(r, floor_height=floors.get(g, float("nan"))) for r, g in zip(first, groups)]
    todo = []
    for i, (o, g) in enumerate(zip(objects, groups)):
        if not (o.on_floor and np.isfinite(bottom[i]) and height[i] > 0):
            continue
        if g not in floors:
            out[i] = dataclasses.replace(out[i], floor_prior="no_floor")
        elif abs(bottom[i] - floors[g]) > opts.floor_max_gap * height[i]:
            out[i] = dataclasses.replace(out[i], floor_prior="off_floor")
        else:
            todo.append(i)
    again = solve_poses([dataclasses.replace(objects[i], floor_height=floors[groups[i]],
                                             floor_weight=opts.floor_prior / height[i]) for i in todo], opts)
    for i, r in zip(todo, again):
        kept = r.translation is not None and r.loss_reprojection <= first[i].loss_reprojection * (1 + opts.floor_max_growth)
        out[i] = dataclasses.replace(r if kept else out[i], floor_prior="used" if kept else "rejected",
                                     floor_height=floors[groups[i]])
    return out
