"""Support prior of pose solving: an upright object rests on the floor or on the top of another object.

Why: with the small baselines of real-estate walkthroughs (the camera moves about a metre past
objects 3-5 m away) the clicks barely fix an object's depth; the solver slides it along the
viewing ray and scales it in proportion (the depth/scale ambiguity), and that moves its bottom up
or down. Furniture rests on something: the floor (shared by all of a clip's floor objects: the
well-observed ones fix its height) or the top of another piece of furniture (a display on a
cabinet, a lamp on a table). Pinning the bottom to that support height fixes the depth the clicks
leave loose.

Frames: world up is +Y (:data:`cadestate.geometry.WORLD_UP`, the axis the up-axis term uses; the
paper relies on RealEstate10K's known up axis); "height" is a world +Y coordinate; a footprint is
the posed bounding box seen from above (world XZ). Camera extrinsics are world->camera.
RealEstate10K worlds have an arbitrary scale, so every threshold here is relative to the object's
own height (its posed bounding box's extent along +Y).

Procedure (:func:`solve_with_support`), per group of objects (a clip):

1. every object is solved without the prior (:func:`tasks.pose.solver.solve_poses`);
2. the floor height is estimated from the bottoms (lowest point of the posed CAD bounding box
   along +Y, :func:`tasks.pose.lm.support_bottom`) of the objects of floor classes (``on_floor``)
   with status ``ok`` and a known bounding box, each weighted by its inverse variance 1 /
   ``bottom_sd``^2 (how loosely its own fit holds its bottom: the Gauss-Newton approximation,
   :func:`tasks.pose.lm.bottom_sd`; it grows as parallax and clicks shrink): the weighted mean of
   the bottoms within ``floor_max_gap`` object heights of their weighted median
   (:func:`weighted_median`; the objects that rest on it: one standing on something else, or
   badly solved, does not pull it). Fewer than :data:`MIN_FLOOR_OBJECTS` such objects before that
   cut: no floor (a median of one object is no check on it), and no prior in that clip;
3. candidate supports of an object that rests (``on_floor`` or ``rests``, with a known bounding
   box and a pose): the floor, and the top (bottom + height) of every other object of the clip
   that can hold it (:func:`can_hold`: status ``ok``, upright, and the object's bottom centre,
   slid along its viewing ray to that top's height, lies over the host's footprint: its centre
   of mass is above the top face, the static condition for resting on it). The object takes the
   nearest candidate (by height) within ``floor_max_gap`` object heights of its own bottom, or the
   floor when its bottom lies below it (nothing of a room is below its floor: :func:`nearest_support`);
4. pass 1: objects whose support is the floor are solved again (all groups in one batch, from the
   same starts) with the term ``floor_prior / height · |bottom - support|`` (px per object height,
   L1: robust); with ``host_supports`` off, the floor is the only candidate (no pass 2);
5. pass 2: objects whose support was a host choose again among the floor and the hosts that pass 1
   put on the floor (a host's top is only as good as its own depth, so only floor-supported hosts
   count), with their pass-1 poses, and are solved again the same way (one more batch);
6. a re-solved pose is kept only if its reprojection loss grew by at most ``floor_max_growth``
   times the loss without the prior (at least that of a 1 px click error, :func:`allowed_loss`)
   and its status is no worse (:data:`STATUS_RANK`): an object that hangs on a wall or stands on
   something unseen is not dragged onto a support the clicks contradict.

``PoseResult.floor_prior`` records the outcome per object: ``none`` (prior off, a class that does
not rest, unknown bounding box or no pose), ``no_floor`` (its clip has no floor estimate),
``off_floor`` (no support within the gap: own pose kept), ``rejected`` (the re-solve grew the
reprojection loss too much, or ended with a worse status: own pose kept), ``used`` (solved on the floor) or ``host`` (solved on
the top of object ``PoseResult.support``); ``support_height`` is the height it was pulled to (or
tried). Status: a pose kept on its support whose key-frames see it under too little parallax
(``low_parallax``) becomes ``ok`` when the support observes its depth instead: the ray from the
cameras to its bottom is inclined by at least ``min_parallax_deg`` (:func:`supported_status`), so
sliding it along the ray would move it off the support. The depth then rests on the support
height (the floor estimate, or the host's re-solved top), not on the clicks' parallax; the message
says so.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from cadestate.geometry import quaternion_to_matrix
from tasks.pose.batch import DTYPE
from tasks.pose.lm import robust, support_bottom
from tasks.pose.solver import ObjectCorrespondences, PoseResult, SolverOptions, solve_poses

MIN_FLOOR_OBJECTS = 2
"""Fewest solved floor-class objects in a clip for it to get a floor estimate."""

FLOOR = -1
"""The support index of the floor (a host is the index of an object)."""


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
                    bottom: np.ndarray, height: np.ndarray, max_gap: float) -> dict[str, float]:
    """Floor height (world +Y) per group that has at least :data:`MIN_FLOOR_OBJECTS` usable objects
    (module docstring, step 2): the inverse-variance weighted mean of their ``bottom`` float[N]
    within ``max_gap`` · ``height`` float[N] of the weighted median (those that rest on it)."""
    samples: dict[str, list[tuple[float, float, float]]] = {}
    for o, r, g, y, h in zip(objects, results, groups, bottom, height):
        if o.on_floor and r.status == "ok" and np.isfinite(y) and np.isfinite(r.bottom_sd) and r.bottom_sd > 0:
            samples.setdefault(g, []).append((float(y), 1.0 / r.bottom_sd**2, float(h)))
    floors = {}
    for g, s in sorted(samples.items()):
        if len(s) < MIN_FLOOR_OBJECTS:
            continue
        y, w, h = (np.array(c) for c in zip(*s))
        near = np.abs(y - weighted_median(y, w)) <= max_gap * h
        floors[g] = float((y[near] * w[near]).sum() / w[near].sum())
    return floors


def camera_centre(o: ObjectCorrespondences) -> np.ndarray:
    """float[3] the mean centre (world) of the object's key-frame cameras, -R^T t each."""
    return np.mean(-np.einsum("fji,fj->fi", np.asarray(o.R, np.float64), np.asarray(o.t, np.float64)), 0)


def slid_centre(o: ObjectCorrespondences, r: PoseResult, bottom: float, y: float) -> np.ndarray:
    """float[3] (world) the centre of the object's bounding box moved along the ray from its
    cameras' mean centre c, with its scale (the depth/scale ambiguity: X -> c + k (X - c)), so far
    that its bottom reaches height ``y``: k = (y - c_y) / (bottom - c_y). When no positive finite k
    does (the bottom at the cameras' height, or ``y`` across it), the centre stays where it is."""
    c, T = camera_centre(o), np.asarray(r.translation, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        k = (y - c[1]) / (bottom - c[1])
    if not (np.isfinite(k) and k > 0):
        k = 1.0
    return c + k * (T - c)


def over_footprint(host: ObjectCorrespondences, r: PoseResult, point: np.ndarray) -> bool:
    """Whether ``point`` float[3] (world) lies over the posed bounding box of ``host`` seen from
    above: its horizontal offset from the host's centre, in the host's (rotated) CAD axes, is within
    the box's half-sizes along CAD x and z (an upright host: the top face's own rectangle)."""
    R = quaternion_to_matrix(r.rotation)
    d = np.asarray(point, np.float64) - np.asarray(r.translation, np.float64)
    local = R.T @ np.array([d[0], 0.0, d[2]])
    half = np.asarray(r.scale, np.float64) * np.asarray(host.extent, np.float64) / 2
    return bool(abs(local[0]) <= half[0] and abs(local[2]) <= half[2])


def can_hold(j: int, i: int, objects: list[ObjectCorrespondences], results: list[PoseResult],
             pose_i: PoseResult, bottom_i: float, top_j: float) -> bool:
    """Whether object ``j`` (pose ``results[j]``, top at height ``top_j``) can hold object ``i``
    (pose ``pose_i``, bottom ``bottom_i``): ``j`` is solved (status ok), upright with a known
    bounding box, and ``i``'s centre slid to rest at ``top_j`` (:func:`slid_centre`) lies over
    ``j``'s footprint (:func:`over_footprint`)."""
    h, r = objects[j], results[j]
    if j == i or r.status != "ok" or not h.upright or h.extent is None or not np.isfinite(top_j):
        return False
    return over_footprint(h, r, slid_centre(objects[i], pose_i, bottom_i, top_j))


def nearest_support(i: int, floor: float, hosts: list[int], objects: list[ObjectCorrespondences],
                    results: list[PoseResult], pose_i: PoseResult, bottom_i: float, height_i: float,
                    tops: np.ndarray, max_gap: float) -> tuple[int, float] | None:
    """(support, height): the nearest (by height) of the floor (:data:`FLOOR`) and the ``hosts``
    that can hold object ``i`` (:func:`can_hold`; ``tops`` float[N] every object's top) within
    ``max_gap`` · ``height_i`` of its bottom; ties go to the floor, then the lower index. None: no
    support within the gap. The gap bounds how far *above* the floor a bottom may be (it may stand
    on something unseen), not below: nothing of a room lies below its floor, so a bottom sunk into
    it takes the floor at any depth (the reprojection test of :func:`resolve` still applies)."""
    cands = [(FLOOR, floor)] + [(j, float(tops[j])) for j in hosts
                                if can_hold(j, i, objects, results, pose_i, bottom_i, tops[j])]
    within = [c for c in cands if abs(bottom_i - c[1]) <= max_gap * height_i or (c[0] == FLOOR and bottom_i < c[1])]
    return min(within, key=lambda c: (abs(bottom_i - c[1]), c[0])) if within else None


CLICK_PX = 1.0
"""Precision of a human click (px): a reprojection loss below that of clicks this far off (in x and
y) is no measure of how well a pose fits, so the reprojection test of :func:`resolve` grants at
least ``floor_max_growth`` times that loss (noise-free clicks would otherwise reject any change)."""


STATUS_RANK = {"ok": 0, "low_parallax": 1}
"""Statuses a re-solve may end with, best first: it is kept only if its status is no worse than
the pose's own (after :func:`supported_status`); any other status (high_residual, behind_camera)
ranks last, so a re-solve never turns a usable pose into an unusable one."""


def allowed_loss(before: float, opts: SolverOptions) -> float:
    """The largest reprojection loss (the solver's robust loss per point) a pose re-solved on its
    support may have, given its loss ``before`` without the support: before + floor_max_growth ·
    max(before, the loss of a click off by :data:`CLICK_PX` in x and y)."""
    click = 2 * float(robust(torch.tensor(CLICK_PX, dtype=DTYPE), opts.huber_px))
    return before + opts.floor_max_growth * max(before, click)


def resolve(objects: list[ObjectCorrespondences], before: list[PoseResult], todo: list[tuple[int, int, float]],
            heights: np.ndarray, opts: SolverOptions) -> dict[int, PoseResult]:
    """Solve the objects ``todo`` [(index, support, support height)] again, in one batch, with the
    support term; each keeps the new pose only if its reprojection loss grew by at most
    ``floor_max_growth`` over ``before`` (module docstring, step 6) and its status is no worse
    (:data:`STATUS_RANK`). Index -> result, its
    ``floor_prior`` ``used`` / ``host`` / ``rejected``."""
    again = solve_poses([dataclasses.replace(objects[i], floor_height=y, floor_weight=opts.floor_prior / heights[i])
                         for i, _, y in todo], opts)
    out = {}
    for (i, s, y), r in zip(todo, again):
        r = supported_status(objects[i], r, y, opts.min_parallax_deg) if r.translation is not None else r
        kept = (r.translation is not None and r.loss_reprojection <= allowed_loss(before[i].loss_reprojection, opts)
                and STATUS_RANK.get(r.status, len(STATUS_RANK)) <= STATUS_RANK.get(before[i].status, len(STATUS_RANK)))
        outcome = ("used" if s == FLOOR else "host") if kept else "rejected"
        r = r if kept else before[i]
        out[i] = dataclasses.replace(r, floor_prior=outcome, support=s, support_height=y)
    return out


def support_angle(o: ObjectCorrespondences, r: PoseResult, y: float) -> float:
    """The elevation (degrees) of the ray from the object's cameras' mean centre to its bottom
    centre resting at height ``y``: the angle under which the support observes its depth (sliding
    it along the ray by dd moves its bottom by dd · sin(angle))."""
    c, T = camera_centre(o), np.asarray(r.translation, np.float64)
    return float(np.degrees(np.arctan2(abs(c[1] - y), np.hypot(T[0] - c[0], T[2] - c[2]))))


def supported_status(o: ObjectCorrespondences, r: PoseResult, y: float, min_parallax_deg: float) -> PoseResult:
    """``r`` re-solved resting at height ``y``, its status ``low_parallax`` lifted to ``ok`` when the
    support observes its depth (:func:`support_angle` at least ``min_parallax_deg``): its key-frames
    alone could not tell the depth, the support height does."""
    if r.status != "low_parallax":
        return r
    angle = support_angle(o, r, y)
    if angle < min_parallax_deg:
        return r
    return dataclasses.replace(r, status="ok", message=f"depth fixed by its support, its bottom seen {angle:.1f} deg "
                                                         f"below/above the cameras ({r.message})")


def solve_with_support(objects: list[ObjectCorrespondences], groups: list[str],
                       opts: SolverOptions = SolverOptions()) -> list[PoseResult]:
    """Solve every object, then re-solve the resting objects of each group on their supports
    (module docstring); ``groups`` str[N] names each object's clip. One result per object."""
    first = solve_poses(objects, opts)
    if opts.floor_prior <= 0 or not objects:
        return first
    bottom, height = bottoms(objects, first)
    floors = estimate_floors(objects, first, groups, bottom, height, opts.floor_max_gap)
    out = [dataclasses.replace(r, floor_height=floors.get(g, float("nan"))) for r, g in zip(first, groups)]
    members: dict[str, list[int]] = {}
    for i, g in enumerate(groups):
        members.setdefault(g, []).append(i)
    resting = [i for i, o in enumerate(objects) if (o.on_floor or o.rests) and np.isfinite(bottom[i]) and height[i] > 0]
    on_floor, deferred = [], []
    for i in resting:
        g = groups[i]
        if g not in floors:
            out[i] = dataclasses.replace(out[i], floor_prior="no_floor")
            continue
        s = nearest_support(i, floors[g], members[g] if opts.host_supports else [], objects, first, first[i],
                            bottom[i], height[i], bottom + height, opts.floor_max_gap)
        if s is None:
            out[i] = dataclasses.replace(out[i], floor_prior="off_floor")
        elif s[0] == FLOOR:
            on_floor.append((i, FLOOR, s[1]))
        else:
            deferred.append(i)
    out = _merge(out, resolve(objects, first, on_floor, height, opts))
    if not deferred:
        return out
    b1, h1 = bottoms(objects, out)
    todo = []
    for i in deferred:
        g = groups[i]
        hosts = [j for j in members[g] if out[j].floor_prior == "used"]
        s = nearest_support(i, floors[g], hosts, objects, out, first[i], bottom[i], height[i], b1 + h1,
                            opts.floor_max_gap)
        if s is None:
            out[i] = dataclasses.replace(out[i], floor_prior="off_floor")
        else:
            todo.append((i, *s))
    return _merge(out, resolve(objects, first, todo, height, opts))


def _merge(results: list[PoseResult], update: dict[int, PoseResult]) -> list[PoseResult]:
    """``results`` with the entries of ``update`` replaced, each keeping its ``floor_height``."""
    return [dataclasses.replace(update[i], floor_height=r.floor_height) if i in update else r
            for i, r in enumerate(results)]
