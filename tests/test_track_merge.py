"""Fragments joined in 3D (tasks/tracking/track3d.py, tasks/tracking/merge.py) on synthetic cameras and boxes."""

from __future__ import annotations

import numpy as np

from cadestate.config import TrackingConfig
from cadestate.geometry import look_at, project
from tasks.tracking.affinity import Cameras
from tasks.tracking.merge import CUES, MergeModel, is_thin, make_fragment, merge_step, pair_cues
from tasks.tracking.merge_calibration import MERGE_CALIBRATION
from tasks.tracking.track3d import box_rays, triangulate
from tasks.tracking.tracking import Geometry, track_detections

W, H = 640, 360
K = np.array([[500.0, 0, 320], [0, 500, 180], [0, 0, 1]])
OBJECTS = np.array([[0.0, 0.5, 3.0], [1.5, 0.4, 3.5]])
"""Two objects (aligned world, m), 0.5 m across, in front of a camera walking along +X at 1.5 m."""


def walk(frames: int, baseline: float = 2.0, look: np.ndarray = np.array([0.7, 0.5, 3.2])):
    """World->camera (R float[F,3,3], t float[F,3]) of a camera walking ``baseline`` m along +X."""
    poses = [look_at(np.array([x, 1.5, 0.0]), look) for x in np.linspace(-baseline / 2, baseline / 2, frames)]
    return np.stack([p[0] for p in poses]), np.stack([p[1] for p in poses])


def boxes_of(X: np.ndarray, R: np.ndarray, t: np.ndarray, size: float = 0.5) -> np.ndarray:
    """Normalised boxes float[F,4] of a ``size`` m object centred at ``X`` seen by each camera."""
    out = []
    for Rf, tf in zip(R, t):
        (u, v), = project(K, Rf, tf, X[None])[0]
        depth = (Rf @ X + tf)[2]
        half = 500 * size / 2 / depth
        out.append(((v - half) / H, (u - half) / W, (v + half) / H, (u + half) / W))
    return np.asarray(out)


def test_rays_through_box_centres_meet_at_the_object():
    R, t = walk(20)
    X = OBJECTS[0]
    rays = box_rays(boxes_of(X, R, t), np.repeat(K[None], 20, 0), R, t, W, H)
    p = triangulate(rays)
    assert np.allclose(p.X, X, atol=1e-3) and p.cost < 1e-4
    assert np.allclose(p.depth, [np.linalg.norm(X - c) for c in rays.origin], atol=1e-3)
    # seen from one spot (no baseline) the point is free along the ray: far larger variance there
    R0, t0 = walk(20, baseline=0.0)
    narrow = triangulate(box_rays(boxes_of(X, R0, t0), np.repeat(K[None], 20, 0), R0, t0, W, H))
    along = rays.direction.mean(0)
    assert along @ narrow.cov @ along > 100 * (along @ p.cov @ along)


def clip_arrays(gap: tuple[int, int] = (10, 30), frames: int = 40):
    """Object 0 seen on frames outside ``gap`` (two fragments), object 1 on every frame; one
    descriptor per object (+ noise); the clip's arrays as the tracking stage sees them."""
    rng = np.random.default_rng(0)
    R, t = walk(frames)
    looks = rng.normal(0, 1, (2, 64))
    rows = []
    for o in (0, 1):
        b = boxes_of(OBJECTS[o], R, t)
        for f in range(frames):
            if o == 0 and gap[0] <= f < gap[1]:
                continue
            rows.append((f, b[f], "chair", looks[o] + rng.normal(0, 0.2, 64), o))
    frame = np.array([r[0] for r in rows])
    boxes = np.array([r[1] for r in rows])
    cams = Cameras(np.repeat(K[None], frames, 0), R, W, H)
    geometry = Geometry(box_rays(boxes, cams.K[frame], R[frame], t[frame], W, H), np.array([0, 20, 39]))
    return (np.arange(len(rows)) + 100, frame, boxes, np.array([r[2] for r in rows], dtype=object),
            np.array([r[3] for r in rows], np.float32), np.array([r[4] for r in rows]), cams, geometry)


def test_fragments_of_one_object_cost_little_to_join_two_objects_much():
    _, frame, boxes, labels, vec, truth, _, g = clip_arrays()
    frag = lambda m: make_fragment(m, frame, labels, np.ones(len(frame)), vec.astype(float), g.rays)  # noqa: E731
    first = frag(np.flatnonzero((truth == 0) & (frame < 10)))
    second = frag(np.flatnonzero((truth == 0) & (frame >= 30)))
    other = frag(np.flatnonzero((truth == 1) & (frame >= 10) & (frame < 30)))
    same, different = pair_cues(first, second), pair_cues(first, other)
    misfit, app, gap = CUES.index("ray_misfit"), CUES.index("appearance"), CUES.index("log_gap")
    assert same[misfit] < 0.1 < 2 < different[misfit]
    assert same[app] > 0.9 and abs(different[app]) < 0.5
    assert np.isclose(same[gap], np.log1p(21)) and np.isclose(different[gap], np.log1p(1))


def test_stored_model_joins_a_split_object_and_nothing_else():
    det_id, frame, boxes, labels, vec, truth, cams, g = clip_arrays()
    cfg = TrackingConfig(thin_detections=1)
    before = track_detections(det_id, frame, boxes, labels, vec, cams, cfg).track  # no geometry: the partition alone
    assert len(np.unique(before[truth == 0])) == 2
    after = track_detections(det_id, frame, boxes, labels, vec, cams, cfg, geometry=g)
    assert after.joined == 1 and after.thin == 0
    for o in (0, 1):  # one track per object, and it is that object's alone
        assert len(np.unique(after.track[truth == o])) == 1 and np.all(after.track[truth == o] >= 0)
    assert after.track[truth == 0][0] != after.track[truth == 1][0]
    off = track_detections(det_id, frame, boxes, labels, vec, cams, TrackingConfig(merge=False, thin_detections=1), geometry=g)
    assert off.joined == 0 and len(np.unique(off.track[truth == 0])) == 2


def test_fragments_sharing_a_frame_are_never_joined():
    _, frame, boxes, labels, vec, truth, _, g = clip_arrays()
    always = MergeModel(np.zeros(6), np.ones(6), np.zeros(6), 50.0)  # probability 1 for any pair
    groups = [np.flatnonzero(truth == 0), np.flatnonzero(truth == 1)]  # overlap in time
    res = merge_step(groups, frame, labels, np.ones(len(frame)), None, g.rays, g.keyframes, always, 0.5, 1, 1)
    assert res.joins == 0 and len(res.groups) == 2


def test_thin_tracks_are_dropped_and_counted():
    _, frame, boxes, labels, vec, truth, _, g = clip_arrays(gap=(3, 40))
    short = make_fragment(np.flatnonzero(truth == 0), frame, labels, np.ones(len(frame)), None, g.rays)  # frames 0-2
    assert is_thin(short, np.array([20, 39]), 6) and not is_thin(short, np.array([2, 20]), 6)
    assert not is_thin(short, np.array([20, 39]), 3)
    never = MergeModel(np.zeros(6), np.ones(6), np.zeros(6), -50.0)
    groups = [np.flatnonzero(truth == 0), np.flatnonzero(truth == 1)]
    res = merge_step(groups, frame, labels, np.ones(len(frame)), None, g.rays, np.array([20, 39]), never, 0.5, 1, 6)
    assert res.thin == 1 and len(res.groups) == 1 and set(res.groups[0]) == set(np.flatnonzero(truth == 1))
    res = merge_step(groups, frame, labels, np.ones(len(frame)), None, g.rays, np.array([20, 39]), never, 0.5, 4, 6)
    assert res.thin == 0 and len(res.groups) == 1  # below min_detections: dropped as before, not counted thin


def test_weak_tracks_are_dropped_and_counted():
    """A track whose detections score below ``min_track_score`` on average is dropped after joining
    (its strongest box does not save it); at the threshold it stays; 0, the default, keeps every track."""
    det_id, frame, boxes, labels, vec, truth, cams, g = clip_arrays()
    scores = np.where(truth == 0, 0.6, 0.36)
    scores[np.flatnonzero(truth == 1)[0]] = 0.9  # one sure box among the weak ones: mean 0.374
    cfg = TrackingConfig(thin_detections=1, min_track_score=0.4)
    res = track_detections(det_id, frame, boxes, labels, vec, cams, cfg, scores=scores, geometry=g)
    assert res.weak == 1 and res.joined == 1 and np.all(res.track[truth == 1] == -1)
    assert len(np.unique(res.track[truth == 0])) == 1 and res.track.max() == 0
    mean = float(scores[truth == 1].mean())
    assert TrackingConfig().min_track_score == 0.0
    for threshold, weak in ((mean, 0), (0.0, 0), (0.6 + 1e-9, 2)):
        res = track_detections(det_id, frame, boxes, labels, vec, cams, TrackingConfig(thin_detections=1, min_track_score=threshold),
                               scores=scores, geometry=g)
        assert res.weak == weak and res.track.max() == 1 - weak, threshold


def test_stored_model_is_generated_with_its_training_seeds():
    assert MERGE_CALIBRATION is not None and tuple(MERGE_CALIBRATION["cues"]) == CUES
    assert MERGE_CALIBRATION["training_seeds"] and MERGE_CALIBRATION["pairs"]["one_object"] > 0
    model = MergeModel.from_dict(MERGE_CALIBRATION)
    coef = dict(zip(CUES, model.coef))
    assert coef["ray_misfit"] < 0 and coef["appearance"] > 0  # far apart in 3D: two objects; alike: one


def tracking_row(clip: str, tracks: int, detections: int, joined: int, thin: int, shadows: int, weak: int):
    """The status row of a completed tracking stage whose message counts these."""
    from tasks.status import StageStatus

    return StageStatus(clip, "tracking", "completed", "", tracks, (), f"{tracks} tracks from {detections} detections "
                       f"({joined} fragments joined in 3D, {thin} thin tracks dropped, {shadows} shadow tracks dropped, "
                       f"{weak} weak tracks dropped)")


def test_status_counts_the_thin_shadow_and_weak_tracks_dropped():
    from tasks.status import clip_notes

    rows = [tracking_row("a_0", 4, 90, 1, 3, 2, 4), tracking_row("b_0", 4, 90, 0, 0, 0, 0)]
    assert clip_notes(rows) == ["a_0: 3 tracks too thin to annotate were dropped (fewer than [tracking] thin_detections "
                                "detections, none on a manual-track key-frame)",
                                "a_0: 2 shadow tracks were dropped (their boxes on a stronger track's boxes: one object "
                                "tracked twice; [tracking] shadow_iou)",
                                "a_0: 4 weak tracks were dropped (their detections' mean score below [tracking] "
                                "min_track_score)"]
    nothing = [tracking_row("c_0", 0, 9, 0, 0, 0, 0), tracking_row("d_0", 0, 0, 0, 0, 0, 0)]
    assert clip_notes(nothing) == ["c_0: tracking kept no track of its 9 detections (no object boxed on [tracking] "
                                   "min_detections frames, or every track dropped as counted here), so every later "
                                   "stage ran on nothing"]  # no detection at all: the detect stage's note says it


def test_stored_cue_calibration_was_fitted_on_seeds_the_default_benchmark_does_not_use():
    from bench.benchmark import DEFAULT_SEED
    from tasks.tracking.calibration import CALIBRATION

    seeds = CALIBRATION["training_seeds"]
    assert seeds and DEFAULT_SEED not in seeds and set(seeds) == set(MERGE_CALIBRATION["training_seeds"])
    assert CALIBRATION["pairs"]["true"] > 0 and CALIBRATION["label"]["same"] > 0 > CALIBRATION["label"]["different"]


def test_the_greedy_join_is_the_plain_one_most_probable_pair_first():
    """merge_fragments (pairs in a heap, those that no 3D cue could lift to the threshold never
    triangulated) joins what the plain greedy loop joins: rescore every pair after each join,
    join the most probable compatible pair (ties: smaller indices) while it reaches the threshold."""
    from tasks.tracking.merge import compatible, join, merge_fragments

    rng = np.random.default_rng(3)
    R, t = walk(60)
    frame = np.tile(np.arange(60), 6)
    objects = np.repeat(np.arange(6), 60)
    centres = np.array([[x, 0.5, 3.0 + 0.3 * (x % 2)] for x in np.linspace(-1.5, 1.5, 6)])
    boxes = np.concatenate([boxes_of(c, R, t) for c in centres]) + rng.normal(0, 0.004, (360, 4))
    looks = rng.normal(0, 1, (6, 32))[objects] + rng.normal(0, 0.8, (360, 32))
    labels = np.array(["chair", "table"], dtype=object)[objects % 2]
    scores = rng.uniform(0.4, 0.9, 360)
    rays = box_rays(boxes, np.repeat(K[None], 360, 0), R[frame], t[frame], W, H)
    cut = rng.integers(0, 60, (6, 3))  # each object in 4 runs of frames, some of them mixed up
    groups = []
    for o in range(6):
        members = np.flatnonzero(objects == o)
        groups += [g for g in np.split(members, np.sort(cut[o])) if len(g)]
    groups[0], groups[5] = np.sort(np.concatenate([groups[0][:5], groups[5][5:]])), np.concatenate([groups[5][:5], groups[0][5:]])
    groups = [g for g in groups if len(g) and len(np.unique(frame[g])) == len(g)]
    model = MergeModel.from_dict(MERGE_CALIBRATION)
    frags = [make_fragment(g, frame, labels, scores, looks, rays) for g in groups]
    for threshold in (0.3, 0.5, 0.8):
        got, joins = merge_fragments(frags, model, threshold, labels, scores, rays)
        plain, alive, n = list(frags), set(range(len(frags))), 0
        while True:
            best = max(((float(model.probability(pair_cues(plain[i], plain[j]))[0]), -i, -j)
                        for i in sorted(alive) for j in sorted(alive) if i < j and compatible(plain[i], plain[j])),
                       default=None)
            if best is None or best[0] < threshold:
                break
            i, j = -best[1], -best[2]
            plain[i], n = join(plain[i], plain[j], labels, scores, rays), n + 1
            alive.discard(j)
        assert joins == n > 0
        assert [f.members.tolist() for f in got] == [plain[k].members.tolist() for k in sorted(alive)]
