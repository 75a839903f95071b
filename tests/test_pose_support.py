"""The support prior (tasks/pose/support.py: the floor and host tops) on small synthetic clips built here."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from cadestate.geometry import look_at, matrix_to_quaternion
from cadestate.render import object_to_world
from tasks.cad.symmetry import rotation_y
from tasks.pose.initial import symmetry_offsets
from tasks.pose.solver import ObjectCorrespondences, PoseResult, SolverOptions, evaluate, make_batch, solve_poses
from tasks.pose.support import (FLOOR, allowed_loss, bottoms, estimate_floors, nearest_support, over_footprint,
                                slid_centre, solve_with_support, supported_status, weighted_median)
from tests.test_pose_solver import K


def eyes(baseline: float = 0.8) -> list[np.ndarray]:
    """Four key-frame camera centres spread over ``baseline`` m along x at eye height 1.5 m (world +Y up)."""
    return [np.array([x, 1.5, 0.0]) for x in np.linspace(-baseline / 2, baseline / 2, 4)]


def observe(rng: np.random.Generator, T: np.ndarray, q: np.ndarray, s: np.ndarray, extent: np.ndarray,
            cams: list[np.ndarray], noise: float, distance: float, **flags) -> ObjectCorrespondences:
    """The problem of an object posed (T, q, s) (world, +Y up) with CAD bbox ``extent``, seen by
    cameras at ``cams`` looking at (0, 0.5, -distance): 6 clicks of ``noise`` px per key-frame."""
    M = object_to_world(T, q, s, False)
    xy, xyz, kf, Rs, ts = [], [], [], [], []
    for f, eye in enumerate(cams):
        Rc, tc = look_at(eye, np.array([0.0, 0.5, -distance]))
        p = rng.uniform(-0.5, 0.5, (6, 3)) * extent
        cam = (p @ M[:3, :3].T + M[:3, 3]) @ Rc.T + tc
        uv = cam @ K.T
        xy.append(uv[:, :2] / uv[:, 2:] + rng.normal(0, noise, (6, 2)))
        xyz.append(p), kf.append(np.full(6, f)), Rs.append(Rc), ts.append(tc)
    return ObjectCorrespondences(np.concatenate(xy), np.concatenate(xyz), np.concatenate(kf), np.array([K] * len(cams)),
                                 np.array(Rs), np.array(ts), extent=extent, **flags)


def clip_objects(seed: int, bottoms: list[float], noise: float = 3.0, baseline: float = 0.8,
                 distance: float = 4.0) -> tuple[list[ObjectCorrespondences], list[tuple]]:
    """Objects of a floor class whose bottoms stand at the given heights (world +Y up, floor at 0),
    ``distance`` m in front of four key-frame cameras spread over ``baseline`` m at eye height 1.5
    m (a low-parallax walkthrough), 6 clicks of ``noise`` px per key-frame. Returns the problems and
    the true (T, q, s)."""
    rng = np.random.default_rng(seed)
    objects, truth = [], []
    for i, bottom in enumerate(bottoms):
        extent = rng.uniform(0.5, 1.2, 3)
        s = rng.uniform(0.85, 1.15, 3)
        q = matrix_to_quaternion(rotation_y(rng.uniform(0, 360)))
        x = (i - (len(bottoms) - 1) / 2) * 1.2
        T = np.array([x, bottom + s[1] * extent[1] / 2, -distance + rng.uniform(-0.5, 0.5)])
        objects.append(observe(rng, T, q, s, extent, eyes(baseline), noise, distance, on_floor=True))
        truth.append((T, q, s))
    return objects, truth


def table_clip(seed: int, noise: float = 3.0, host_x: float = 0.0) -> tuple[list[ObjectCorrespondences], list[tuple]]:
    """Three floor objects and a table (top at 0.75 m, its footprint 0.8 m (x) by 1.2 m (z) centred at
    (``host_x``, -4.0)) of a floor class, and a small upright object of a non-floor class (a display:
    ``rests``, not ``on_floor``) standing on the table at (0, -4.0) (world +Y up, floor at 0).
    Index 3 is the table, 4 the display."""
    objects, truth = clip_objects(seed, [0.0, 0.0, 0.0], noise=noise, baseline=1.5)
    rng = np.random.default_rng(seed + 100)
    cams = eyes(1.5)
    table_q = matrix_to_quaternion(rotation_y(90.0))  # CAD x (1.2 m) along world z: footprint 0.8 (x) x 1.2 (z)
    table = (np.array([host_x, 0.375, -4.0]), table_q, np.array([1.0, 1.0, 1.0]), np.array([1.2, 0.75, 0.8]))
    display = (np.array([0.0, 0.75 + 0.2, -4.0]), matrix_to_quaternion(rotation_y(10.0)), np.ones(3), np.array([0.5, 0.4, 0.15]))
    for (T, q, s, extent), flags in ((table, dict(on_floor=True, rests=True)), (display, dict(rests=True))):
        objects.append(observe(rng, T, q, s, extent, cams, noise, 4.0, **flags))
        truth.append((T, q, s))
    return objects, truth


def translation_errors(results: list[PoseResult], truth: list[tuple]) -> np.ndarray:
    return np.array([np.linalg.norm(r.translation - T) for r, (T, _, _) in zip(results, truth)])


def test_floor_prior_recovers_low_parallax_objects_better():
    """Three clips of five floor objects each, 3 px clicks, 0.6 m of camera travel at 5 m: the
    shared floor fixes the depth the clicks leave loose."""
    objects, truth, groups = [], [], []
    for clip in range(3):
        o, t = clip_objects(10 + clip, [0.0] * 5, baseline=0.6, distance=5.0)
        objects, truth, groups = objects + o, truth + t, groups + [f"c{clip}"] * 5
    without = translation_errors(solve_poses(objects), truth)
    results = solve_with_support(objects, groups)
    with_prior = translation_errors(results, truth)
    assert all(r.floor_prior == "used" for r in results)
    assert all(abs(r.floor_height) < 0.05 for r in results)
    assert with_prior.mean() < 0.85 * without.mean(), (with_prior, without)
    assert with_prior.max() < without.max() and (with_prior > 0.2).sum() < (without > 0.2).sum()


def test_object_on_a_table_keeps_its_own_height():
    """A floor-class object standing 0.8 m up (on an unseen table) among three floor objects: the
    floor estimate leaves it out (it is beyond floor_max_gap of the weighted median) and it keeps
    its own pose. With an unbounded gap it counts as resting on the floor, in the estimate too, and
    the reprojection check is what keeps it up."""
    objects, truth = clip_objects(3, [0.0, 0.0, 0.0, 0.8], noise=1.0, baseline=2.0)
    groups = ["c"] * 4
    alone = solve_poses(objects)
    for opts, outcome in ((SolverOptions(), "off_floor"), (SolverOptions(floor_max_gap=1e9), "rejected")):
        results = solve_with_support(objects, groups, opts)
        assert results[3].floor_prior == outcome
        assert np.array_equal(results[3].translation, alone[3].translation)
        assert np.array_equal(results[3].scale, alone[3].scale)
    results = solve_with_support(objects, groups)
    assert abs(results[3].floor_height) < 0.05
    assert [r.floor_prior for r in results[:3]] == ["used"] * 3


def test_weighted_median_is_robust_to_one_outlier():
    assert weighted_median(np.array([0.01, -0.02, 0.9, 0.0]), np.ones(4)) == pytest.approx(0.005)
    assert weighted_median(np.array([0.01, -0.02, 0.9]), np.ones(3)) == 0.01
    assert weighted_median(np.array([0.01, -0.02, 0.9]), np.array([1.0, 1.0, 1.5])) == 0.01
    assert weighted_median(np.array([0.01, -0.02, 0.9]), np.array([1.0, 1.0, 3.0])) == 0.9  # it outweighs both


def test_floor_estimates_need_two_solved_floor_objects():
    objects, _ = clip_objects(4, [0.0, 0.0, 0.0])
    results = solve_poses(objects)
    bottoms, heights = np.array([0.01, 0.02, 0.5]), np.ones(3)
    floors = estimate_floors(objects, results, ["a", "a", "b"], bottoms, heights, 0.5)
    assert set(floors) == {"a"} and 0.01 <= floors["a"] <= 0.02
    off = [dataclasses.replace(objects[0], on_floor=False), *objects[1:]]
    assert estimate_floors(off, results, ["a", "a", "b"], bottoms, heights, 0.5) == {}


def test_floor_estimate_is_the_inverse_variance_mean_of_the_bottoms_near_the_median():
    """Bottoms 0.0 (sd 0.01), 0.03 (sd 0.02) and 0.9 (sd 0.02, but 0.9 heights from the weighted
    median 0.0: it stands on something else): (0 / 0.01^2 + 0.03 / 0.02^2) / (1 / 0.01^2 + 1 / 0.02^2)."""
    objects, _ = clip_objects(4, [0.0, 0.0, 0.0])
    results = [dataclasses.replace(r, bottom_sd=sd) for r, sd in zip(solve_poses(objects), (0.01, 0.02, 0.02))]
    assert all(np.isfinite(r.bottom_sd) and r.bottom_sd > 0 for r in solve_poses(objects))
    floors = estimate_floors(objects, results, ["a"] * 3, np.array([0.0, 0.03, 0.9]), np.ones(3), 0.5)
    assert floors["a"] == pytest.approx((0.03 / 0.02**2) / (1 / 0.01**2 + 1 / 0.02**2), rel=1e-12)
    # The weighted median is 0.9 when its weight outweighs the others': then it alone is the floor.
    results[2] = dataclasses.replace(results[2], bottom_sd=0.001)
    heavy = estimate_floors(objects, results, ["a"] * 3, np.array([0.0, 0.03, 0.9]), np.full(3, 0.1), 0.5)
    assert heavy["a"] == pytest.approx(0.9)
    out = solve_with_support(objects, ["a", "b", "c"])  # one object per clip: no floor anywhere
    assert [r.floor_prior for r in out] == ["no_floor"] * 3 and all(np.isnan(r.floor_height) for r in out)


def test_floor_term_matches_hand_computation():
    """L_floor = weight · |lowest corner of the posed bbox along +Y - floor|, in the total and in
    the signed residuals; a tilted, mirrored pose so every axis reaches down."""
    objects, _ = clip_objects(5, [0.0])
    o = dataclasses.replace(objects[0], mirrored=True, floor_height=0.3, floor_weight=7.0)
    opts = SolverOptions(huber_px=0.0, proportion_prior=0.0)  # L1: the residuals' absolute sum is the loss
    b = make_batch([o], [-1], opts)
    tilt = np.array([[1, 0, 0], [0, np.cos(0.3), -np.sin(0.3)], [0, np.sin(0.3), np.cos(0.3)]])
    R, s, T = tilt @ rotation_y(40.0), np.array([0.9, 1.1, 1.3]), np.array([0.2, 0.1, -4.0])
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * o.extent / 2
    M = object_to_world(T, matrix_to_quaternion(R), s, True)
    bottom = (corners @ M[:3, :3].T + M[:3, 3])[:, 1].min()
    off, om = symmetry_offsets(b.sym, True)
    t = lambda a: torch.tensor(a, dtype=torch.float64)[None]  # noqa: E731
    e = evaluate(b, t(R), t(s), t(T), torch.zeros(1, 4, dtype=torch.float64), off, om, opts)
    assert float(e["floor"]) == pytest.approx(7.0 * abs(bottom - 0.3), rel=1e-12)
    assert float(e["total"]) == pytest.approx(float(e["reprojection"] + opts.alpha * e["up"] + opts.beta * e["front"]
                                                     + e["floor"]), rel=1e-12)
    assert float(e["residuals"].abs().sum()) == pytest.approx(float(e["total"]), rel=1e-9)


def test_lm_floor_and_prior_jacobian_matches_finite_differences():
    """The floor row and the scale prior's rows (the default proportion prior: all three axes) of the
    LM's Jacobian equal central differences of its residuals."""
    from tasks.pose.lm import PRIOR_ROWS, Problem, residuals_jacobian, scale_ties, so3_exp

    objects, _ = clip_objects(6, [0.0])
    o = dataclasses.replace(objects[0], floor_height=0.2, floor_weight=5.0, upright=False)
    b = make_batch([o], [-1], SolverOptions())
    off, om = symmetry_offsets(b.sym, True)
    pb = Problem(b, off, om, scale_ties(b.tied, b.sym >= 36), torch.zeros(1, 4, dtype=torch.float64),
                 torch.tensor([4.0], dtype=torch.float64))
    R = torch.tensor(rotation_y(30.0), dtype=torch.float64)[None] @ so3_exp(torch.tensor([[0.3, -0.2, 0.1]]).double())
    ls, T = torch.tensor([[0.1, -0.05, 0.2]]).double(), torch.tensor([[0.1, 0.6, -4.0]]).double()
    phi, choice = torch.zeros(1, 4, dtype=torch.float64), torch.zeros(1, 4, dtype=torch.long)

    def rows(d):
        return residuals_jacobian(pb, R @ so3_exp(d[:, :3]), ls + d[:, 6:9], T + 4.0 * d[:, 3:6], phi + d[:, 9:], choice,
                                  0.05, 100.0, 1000.0)[0][:, -4:]

    r, J = residuals_jacobian(pb, R, ls, T, phi, choice, 0.05, 100.0, 1000.0)
    assert float(r[0, -1].abs()) > 0.1 and float(r[0, PRIOR_ROWS].abs().min()) > 0.01
    h = 1e-6
    for k in range(13):
        e = torch.zeros(1, 13, dtype=torch.float64)
        e[0, k] = h
        num = (rows(e) - rows(-e)) / (2 * h)
        assert torch.allclose(J[:, -4:, k], num, atol=1e-6 * (1 + float(num.abs().max()))), k


def test_prior_off_is_the_solver_alone():
    """floor_prior = 0 (or no resting object) gives exactly what the solver gives without the feature."""
    objects, _ = table_clip(7)
    groups = ["c"] * 5
    alone = solve_poses(objects)
    for objs, opts in ((objects, SolverOptions(floor_prior=0.0)),
                       ([dataclasses.replace(o, on_floor=False, rests=False) for o in objects], SolverOptions())):
        out = solve_with_support(objs, groups, opts)
        for a, r in zip(alone, out):
            assert np.array_equal(a.translation, r.translation) and np.array_equal(a.rotation, r.rotation)
            assert np.array_equal(a.scale, r.scale) and a.loss_total == r.loss_total and r.floor_prior == "none"
            assert r.loss_floor == 0.0


def bottom_of(o: ObjectCorrespondences, r: PoseResult) -> float:
    return float(bottoms([o], [r])[0][0])


def test_object_on_a_host_table_rests_on_its_top_not_the_floor():
    """A display standing on a table: pass 1 puts the table on the floor, pass 2 puts the display on
    the table's (re-solved) top; the floor, 0.75 m lower, is not a candidate it could take."""
    objects, truth = table_clip(21)
    results = solve_with_support(objects, ["c"] * 5)
    assert [r.floor_prior for r in results] == ["used"] * 4 + ["host"]
    table, display = results[3], results[4]
    assert display.support == 3 and table.support == FLOOR
    top = bottom_of(objects[3], table) + float(bottoms([objects[3]], [table])[1][0])
    assert display.support_height == pytest.approx(top, abs=1e-9) and abs(top - 0.75) < 0.05
    assert abs(bottom_of(objects[4], display) - top) < 0.02
    assert np.linalg.norm(display.translation - truth[4][0]) < 0.1
    floor_only = solve_with_support(objects, ["c"] * 5, SolverOptions(host_supports=False))
    assert floor_only[4].floor_prior == "off_floor" and np.array_equal(floor_only[4].translation,
                                                                        solve_poses(objects)[4].translation)


def test_object_beside_the_host_is_not_held_by_it():
    """The same clip with the table moved 1.5 m aside: the display's centre is not over it, so the
    table is no support and the display, 0.75 m above the floor, keeps its own pose."""
    objects, _ = table_clip(21, host_x=1.5)
    alone = solve_poses(objects)
    results = solve_with_support(objects, ["c"] * 5)
    assert results[3].floor_prior == "used"
    assert results[4].floor_prior == "off_floor" and results[4].support == FLOOR
    assert np.array_equal(results[4].translation, alone[4].translation)
    assert np.array_equal(results[4].scale, alone[4].scale) and np.isnan(results[4].support_height)


def test_host_top_footprint_and_slide_by_hand():
    """A table turned 90 deg about +Y (CAD x 1.2 m -> world z), scaled (1, 0.9, 1.1), centred at
    (1, 0.4, -4): top 0.4 + 0.9 · 0.75 / 2, footprint 0.8 · 1.1 m along world x by 1.2 m along z."""
    o = ObjectCorrespondences(np.zeros((0, 2)), np.zeros((0, 3)), np.zeros(0, np.int64), np.array([K, K]),
                              np.array([np.eye(3)] * 2), np.array([[0.0, -1.5, 0.0], [-1.0, -1.5, 0.0]]),
                              extent=np.array([1.2, 0.75, 0.8]), rests=True)
    r = PoseResult("ok", "", np.array([1.0, 0.4, -4.0]), matrix_to_quaternion(rotation_y(90.0)), np.array([1.0, 0.9, 1.1]))
    b, h = bottoms([o], [r])
    assert b[0] + h[0] == pytest.approx(0.4 + 0.9 * 0.375, abs=1e-12) and b[0] == pytest.approx(0.4 - 0.9 * 0.375, abs=1e-12)
    for dx, dz, inside in ((0.43, 0.59, True), (0.45, 0.0, False), (0.0, 0.61, False), (-0.43, -0.59, True)):
        assert over_footprint(o, r, np.array([1.0 + dx, 7.0, -4.0 + dz])) is inside
    # Cameras centred at (0.5, 1.5, 0): the bottom at 0.4 - 0.3375 slides to 0 with k = 1.5 / (1.5 - 0.0625).
    k = 1.5 / (1.5 - b[0])
    assert np.allclose(slid_centre(o, r, b[0], 0.0), np.array([0.5, 1.5, 0.0]) + k * (r.translation - [0.5, 1.5, 0.0]))
    assert np.allclose(slid_centre(o, r, b[0], 2.0), r.translation)  # across the cameras' height: no slide


def test_nearest_support_prefers_the_nearer_height_and_respects_the_gap():
    objects, _ = table_clip(22, noise=0.0)
    first = solve_poses(objects)
    b, h = bottoms(objects, first)
    tops = b + h
    pick = lambda gap, hosts: nearest_support(4, 0.0, hosts, objects, first, first[4], b[4], h[4], tops, gap)  # noqa: E731
    assert pick(0.5, [0, 1, 2, 3, 4]) == (3, pytest.approx(tops[3]))
    assert pick(0.5, [0, 1, 2]) is None  # the floor is 0.75 m (about two heights) below
    assert pick(10.0, [0, 1, 2]) == (FLOOR, 0.0)
    # Below the floor any distance is within reach (nothing of a room is below its floor); above, the gap applies.
    below = lambda bottom: nearest_support(4, 0.0, [], objects, first, first[4], bottom, 0.4, tops, 0.5)  # noqa: E731
    assert below(-1.0) == (FLOOR, 0.0) and below(0.19) == (FLOOR, 0.0) and below(0.21) is None


def test_support_prior_is_deterministic():
    objects, _ = table_clip(23)
    a, b = solve_with_support(objects, ["c"] * 5), solve_with_support(objects, ["c"] * 5)
    for x, y in zip(a, b):
        assert np.array_equal(x.translation, y.translation) and np.array_equal(x.rotation, y.rotation)
        assert np.array_equal(x.scale, y.scale) and (x.floor_prior, x.support) == (y.floor_prior, y.support)


def test_support_lifts_low_parallax_only_when_it_observes_the_depth():
    """Cameras at (0, 1.5, 0), the object 4 m away horizontally: resting at height 0 its bottom is
    seen atan(1.5 / 4) = 20.6 deg below the cameras, so the support fixes its depth; resting at the
    cameras' height it does not."""
    o = ObjectCorrespondences(np.zeros((0, 2)), np.zeros((0, 3)), np.zeros(0, np.int64), np.array([K, K]),
                              np.array([np.eye(3)] * 2), np.array([[0.1, -1.5, 0.0], [-0.1, -1.5, 0.0]]), rests=True)
    r = PoseResult("low_parallax", "key-frames see the object under 0.50 deg < 1.0 deg", np.array([0.0, 0.3, -4.0]),
                   np.array([1.0, 0, 0, 0]), np.ones(3))
    lifted = supported_status(o, r, 0.0, 1.0)
    assert lifted.status == "ok" and "20.6 deg" in lifted.message and "0.50 deg" in lifted.message
    assert supported_status(o, r, 1.5, 1.0).status == "low_parallax"
    assert supported_status(o, dataclasses.replace(r, status="high_residual"), 0.0, 1.0).status == "high_residual"


def test_allowed_loss_growth_has_a_one_pixel_floor():
    huber, l1 = SolverOptions(huber_px=5.0, floor_max_growth=0.5), SolverOptions(huber_px=0.0, floor_max_growth=0.5)
    assert allowed_loss(4.0, huber) == pytest.approx(6.0) and allowed_loss(4.0, l1) == pytest.approx(6.0)
    assert allowed_loss(0.0, huber) == pytest.approx(0.5 * 2 * 1 / 10)  # Huber(1 px; 5 px) = 1 / 10 per coordinate
    assert allowed_loss(0.0, l1) == pytest.approx(0.5 * 2)


def test_poses_table_names_the_host_track():
    """``PoseResult.support`` indexes the solved tracks; the ``poses`` row names the host by its
    track id (a track without a problem before them does not shift it)."""
    from tasks.pose.pose import TrackInput, poses_table, solve_tracks

    objects, _ = table_clip(21)
    base = dict(cad_id="m", cls="x", symmetry=1, upright=True, on_floor=False, mirrored=False, timestamps=(0, 1, 2, 3))
    tracks = [TrackInput(track_id="0", num_points=3, problem=None, status="too_few_points", **base)]
    tracks += [TrackInput(track_id=str(10 + i), num_points=len(o.xy), problem=o, **base) for i, o in enumerate(objects)]
    rows = {r["track_id"]: r for r in poses_table("c", tracks, solve_tracks(tracks, SolverOptions()), "h").to_pylist()}
    assert rows["14"]["floor_prior"] == "host" and rows["14"]["support_track"] == "13"
    assert rows["14"]["support_height"] == pytest.approx(0.75, abs=0.05)
    assert rows["13"]["floor_prior"] == "used" and rows["13"]["support_track"] is None
    assert rows["0"]["support_track"] is None and rows["0"]["support_height"] is None


def test_bottom_sd_shrinks_with_parallax():
    """The same object and clicks seen over 0.3 m or 2 m of camera travel: the wider baseline holds
    its bottom (its depth) tighter."""
    narrow, wide = (solve_poses(clip_objects(8, [0.0], noise=2.0, baseline=b)[0])[0] for b in (0.3, 2.0))
    assert 0 < wide.bottom_sd < narrow.bottom_sd / 2, (wide.bottom_sd, narrow.bottom_sd)
