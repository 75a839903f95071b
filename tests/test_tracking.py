"""Tracking stage logic (tasks/tracking/tracking.py, tasks/tracking/affinity.py) on synthetic detections."""

from __future__ import annotations

import numpy as np
import pytest

from cadestate.config import TrackingConfig
from tasks.tracking.affinity import candidate_pairs, rotation_warp, Cameras
from tasks.tracking.tracking import track_detections, vote


def synthetic_clip(seed: int = 0, frames: int = 40, objects: int = 4):
    """Objects drifting slowly, each with its own descriptor (+ noise) and label; one clutter box per 7 frames."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(0.2, 0.8, (objects, 2))
    vel = rng.normal(0, 0.003, (objects, 2))
    looks = rng.normal(0, 1, (objects, 64))
    rows = []
    for f in range(frames):
        for o in range(objects):
            cy, cx = centres[o] + f * vel[o]
            rows.append((f, (cy - 0.1, cx - 0.08, cy + 0.1, cx + 0.08), f"c{o % 2}", looks[o] + rng.normal(0, 0.3, 64), o))
        if f % 7 == 3:
            y, x = rng.uniform(0, 0.9, 2)
            rows.append((f, (y, x, y + 0.05, x + 0.05), f"c{f}", rng.normal(0, 1, 64), -1))
    perm = rng.permutation(len(rows))
    rows = [rows[k] for k in perm]
    frame = np.array([r[0] for r in rows])
    det_id = frame * 10000 + np.array([k for k in range(len(rows))])  # unique, not in frame order
    return (det_id, frame, np.array([r[1] for r in rows]), np.array([r[2] for r in rows], dtype=object),
            np.array([r[3] for r in rows], dtype=np.float32), np.array([r[4] for r in rows]))


def test_tracks_follow_objects_one_detection_per_frame():
    det_id, frame, boxes, labels, vec, truth = synthetic_clip()
    res = track_detections(det_id, frame, boxes, labels, vec, None, TrackingConfig())
    t = res.track
    kept = t >= 0
    assert len(np.unique(t[kept])) == 4
    for k in np.unique(t[kept]):  # each track is one object, all its frames
        assert len(np.unique(truth[t == k])) == 1 and np.sum(t == k) == 40
        assert len(np.unique(frame[t == k])) == np.sum(t == k)  # no two detections of one frame
    assert np.all(t[truth == -1] == -1)  # clutter singletons are below min_detections


def test_track_ids_are_stable_and_independent_of_input_order():
    det_id, frame, boxes, labels, vec, _ = synthetic_clip(1)
    cfg = TrackingConfig(min_detections=1)
    ref = track_detections(det_id, frame, boxes, labels, vec, None, cfg).track
    assert np.array_equal(ref, track_detections(det_id, frame, boxes, labels, vec, None, cfg).track)
    perm = np.random.default_rng(5).permutation(len(det_id))
    again = track_detections(det_id[perm], frame[perm], boxes[perm], labels[perm], vec[perm], None, cfg).track
    assert np.array_equal(again, ref[perm])
    # ids are ranks by first det_id
    firsts = [det_id[ref == k].min() for k in range(ref.max() + 1)]
    assert firsts == sorted(firsts)


def test_min_detections_and_empty_input():
    det_id, frame, boxes, labels, vec, _ = synthetic_clip(2)
    everything = track_detections(det_id, frame, boxes, labels, vec, None, TrackingConfig(min_detections=1)).track
    assert np.all(everything >= 0)
    empty = track_detections(np.zeros(0, int), np.zeros(0, int), np.zeros((0, 4)), np.zeros(0, object), None, None, TrackingConfig())
    assert len(empty.track) == 0


def test_detections_all_below_min_score_make_no_track_and_no_warning():
    import warnings

    det_id, frame, boxes, labels, vec, _ = synthetic_clip(3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy's "Mean of empty slice" of the clip's mean descriptor was printed
        res = track_detections(det_id, frame, boxes, labels, vec, None, TrackingConfig(min_score=0.9),
                               scores=np.full(len(det_id), 0.5))
    assert np.all(res.track == -1) and len(res.pairs.a) == 0


def test_candidate_pairs_window_and_rotation_warp_identity():
    a, b = candidate_pairs(np.array([2, 0, 1, 1, 5]), 2)
    pairs = sorted(zip(a.tolist(), b.tolist()))
    assert pairs == [(1, 0), (1, 2), (1, 3), (2, 0), (3, 0)]
    K = np.array([[500.0, 0, 320], [0, 500, 180], [0, 0, 1]])
    cams = Cameras(np.stack([K, K]), np.stack([np.eye(3), np.eye(3)]), 640, 360)
    box = np.array([[0.2, 0.3, 0.5, 0.6]])
    assert np.allclose(rotation_warp(box, np.array([0]), np.array([1]), cams), box)


def test_vote_weights_by_score_and_breaks_ties_by_name():
    assert vote(["chair", "couch", "chair"], [0.2, 0.9, 0.3]) == ("couch", 0.9 / 1.4)
    assert vote(["b", "a"], [0.5, 0.5])[0] == "a"


def test_tracking_accuracy_of_warehouse_tracks(tmp_path):
    """bench.track_bench.tracking_accuracy (the `tracking` section of `cadestate bench report`): the
    pipeline's tracks joined to their detections, scored against ground truth with the ignore rule."""
    import json

    import pyarrow as pa
    import pytest

    pytest.importorskip("trackeval")
    from bench.track_bench import tracking_accuracy, tracking_markdown
    from schemas.detection import DETECTIONS
    from schemas.official import ObjectAnnotation, ObjectsFile, TrackEntry, objects_to_json, write_json
    from schemas.tracking import TRACK_DETECTIONS, TRACKS
    from warehouse import Warehouse

    bench, clip = tmp_path / "bench", "c0"
    (bench / clip).mkdir(parents=True)
    (bench / "manifest.json").write_text(json.dumps({"seed": 1, "clips": [clip, "not_tracked"], "library": "x"}))
    boxes = {"a": (0.1, 0.1, 0.4, 0.3), "b": (0.5, 0.5, 0.9, 0.8), "c": (0.1, 0.6, 0.3, 0.9)}  # c: mostly hidden
    write_json(bench / clip / "objects.json", objects_to_json(ObjectsFile(clip, tuple(
        ObjectAnnotation(k, "03001627", False, False, tuple(TrackEntry(1000 * f, boxes[k]) for f in range(3)), None)
        for k in boxes))))
    (bench / clip / "visibility.json").write_text(json.dumps({"frames": [
        {"timestamp": 1000 * f, "objects": [{"track_id": k, "visible_fraction": 0.1 if k == "c" else 1.0, "truncated_fraction": 0.0}
                                            for k in boxes]} for f in range(3)]}))
    wh = Warehouse(tmp_path / "wh")
    assert tracking_accuracy(bench, wh) is None and tracking_markdown(None) == []
    # track 0 follows a; b is followed by track 1 then track 2 (one ID switch); track 3 lies on c (dropped)
    track_of = {"a": [0, 0, 0], "b": [1, 1, 2], "c": [3, 3, 3]}
    dets, members = [], []
    for f in range(3):
        for r, k in enumerate(boxes):
            det_id = f * 10000 + r
            dets.append({"clip": clip, "det_id": det_id, "timestamp_us": 1000 * f, "frame_index": f, "box": list(boxes[k]),
                         "label": "chair", "label_id": 56, "score": 0.9, "model_sha256": "x"})
            members.append({"clip": clip, "track_id": track_of[k][f], "det_id": det_id, "frame_index": f, "timestamp_us": 1000 * f})
    wh.write("detections", clip, pa.Table.from_pylist(dets, schema=DETECTIONS.schema))
    wh.write("track_detections", clip, pa.Table.from_pylist(members, schema=TRACK_DETECTIONS.schema))
    wh.write("tracks", clip, pa.Table.from_pylist(
        [{"clip": clip, "track_id": t, "label": "chair", "label_votes": 1.0, "first_timestamp_us": 0, "last_timestamp_us": 2000,
          "first_frame_index": 0, "last_frame_index": 2, "num_detections": 3, "mean_score": 0.9, "cohesion": 1.0}
         for t in range(4)], schema=TRACKS.schema))
    r = tracking_accuracy(bench, wh)
    assert r["clips"] == 1 and r["tracks"] == 4
    assert (r["true_positives"], r["false_positives"], r["misses"], r["id_switches"]) == (6, 0, 0, 1)
    assert r["ignored_gt_boxes"] == 3 and r["dropped_pred_boxes"] == 3
    assert r["mota"] == pytest.approx(5 / 6, abs=1e-4)
    assert any("| HOTA |" in line for line in tracking_markdown(r))


def _reference_cues(frame, boxes, labels, vectors, cams, window):
    """The cues as computed before issue 21 (every pair's descriptors and homography materialised at once):
    the chunked computation must reproduce them to the bit (track ids depend on them)."""
    from tasks.tracking.affinity import box_iou_pairs, centred

    a, b = candidate_pairs(frame, window)
    fa, fb = frame[a], frame[b]
    W, H = cams.width, cams.height
    Hm = cams.K[fb] @ cams.R[fb] @ np.swapaxes(cams.R[fa], 1, 2) @ np.linalg.inv(cams.K[fa])
    ys, xs = boxes[a][:, [0, 0, 2, 2]] * H, boxes[a][:, [1, 3, 1, 3]] * W
    q = np.einsum("pij,pkj->pki", Hm, np.stack([xs, ys, np.ones_like(xs)], axis=2))
    ok = np.all(q[:, :, 2] > 1e-9, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = q[:, :, 0] / q[:, :, 2] / W, q[:, :, 1] / q[:, :, 2] / H
    warped = np.where(ok[:, None], np.stack([v.min(1), u.min(1), v.max(1), u.max(1)], axis=1), boxes[a])
    c = centred(vectors)
    return a, b, np.einsum("pd,pd->p", c[a], c[b]).astype(np.float64), labels[a] == labels[b], box_iou_pairs(warped, boxes[b])


def test_chunked_cues_equal_the_materialised_ones_to_the_bit():
    from scipy.spatial.transform import Rotation

    from tasks.tracking.affinity import box_iou_pairs, centred, pair_cosines, pair_features, pair_ious

    rng = np.random.default_rng(7)
    n, frames = 700, 60
    frame = rng.integers(0, frames, n)
    y, x = rng.uniform(0, 0.7, n), rng.uniform(0, 0.7, n)
    boxes = np.stack([y, x, y + rng.uniform(0.05, 0.3, n), x + rng.uniform(0.05, 0.3, n)], axis=1)
    labels = rng.choice(np.array(["chair", "couch", "table"], dtype=object), n)
    vectors = rng.normal(0, 1, (n, 768)).astype(np.float32)
    K = np.tile(np.array([[500.0, 0, 320], [0, 500, 180], [0, 0, 1]]), (frames, 1, 1))
    K[:, 0, 0] += rng.uniform(-20, 20, frames)  # a zoom: intrinsics differ per frame
    R = Rotation.from_rotvec(np.cumsum(rng.normal(0, 0.05, (frames, 3)), axis=0)).as_matrix()
    cams = Cameras(K, R, 640, 360)
    a, b, cos, same, iou = _reference_cues(frame, boxes, labels, vectors, cams, 6)
    p = pair_features(frame, boxes, labels, vectors, cams, 6)
    assert len(a) > 3 * 8192  # several chunks of PAIR_CHUNK
    assert np.array_equal(p.a, a) and np.array_equal(p.b, b) and np.array_equal(p.same_label, same)
    assert np.array_equal(p.cosine, cos) and np.array_equal(p.iou, iou)
    assert not np.array_equal(iou, box_iou_pairs(boxes[a], boxes[b]))  # the warp does move boxes here
    for chunk in (1, 7, 1000, len(a) + 5):  # any chunk size, partial last chunk included
        assert np.array_equal(pair_cosines(centred(vectors), a, b, chunk=chunk), cos)
    for chunk in (7, 1000, len(a) + 5):
        assert np.array_equal(pair_ious(boxes, frame, a, b, cams, chunk=chunk), iou)


def test_detection_vectors_read_from_arrow_as_the_row_by_row_read():
    import pyarrow as pa
    import pytest

    from schemas.detection import EMBEDDINGS
    from tasks.tracking.tracking import TrackingError, detection_vectors

    rng = np.random.default_rng(3)
    det_id = np.array([5, 11, 12, 40])
    rows = [{"clip": "c", "owner": "detection", "owner_id": int(d), "vector": rng.normal(0, 1, 8).astype(np.float32).tolist(),
             "model_sha256": "m"} for d in det_id[::-1]]  # stored out of order
    rows.insert(2, {"clip": "c", "owner": "manual", "owner_id": 11, "vector": [9.0] * 8, "model_sha256": "x"})
    table = pa.Table.from_pylist(rows, schema=EMBEDDINGS.schema)
    table = pa.concat_tables([table.slice(0, 2), table.slice(2)])  # several chunks
    by_id = {r["owner_id"]: r["vector"] for r in rows if r["owner"] == "detection"}
    vectors, sha = detection_vectors(table.select(["owner", "owner_id", "vector", "model_sha256"]), det_id, "c")
    assert vectors.dtype == np.float32 and sha == "m"
    assert np.array_equal(vectors, np.asarray([by_id[d] for d in det_id.tolist()], dtype=np.float32))
    with pytest.raises(TrackingError, match="det_id 13"):
        detection_vectors(table, np.array([5, 13]), "c")
    nan = pa.Table.from_pylist([{**r, "vector": [float("nan")] + r["vector"][1:]} if r["owner_id"] == 12 else r for r in rows],
                               schema=EMBEDDINGS.schema)
    with pytest.raises(TrackingError, match=r"clip c: 1 descriptors hold a value that is not a finite number \(e\.g\. det_id 12\)"):
        detection_vectors(nan, det_id, "c")  # one NaN would make every cosine of the clip NaN, binned as 'identical'
    empty = pa.Table.from_pylist([{**r, "vector": []} for r in rows], schema=EMBEDDINGS.schema)
    with pytest.raises(TrackingError, match="descriptors of length 0"):
        detection_vectors(empty, det_id, "c")


def test_bins_no_fitted_pair_fell_in_take_the_nearest_fitted_value_not_zero():
    """An empty bin's ratio was 0, "no evidence": cosines under -0.8 (two objects of opposite
    look, a clip's two main ones once centred) weighed 0 where -0.8 to -0.3 weighed -10, so two
    chairs side by side were joined; gaps past the fitting window took no prior at all."""
    from tasks.tracking.affinity import PairFeatures, affinities, fit_calibration
    from tasks.tracking.calibration import CALIBRATION

    rng = np.random.default_rng(0)
    n = 4000
    same = rng.random(n) < 0.3
    gap = rng.integers(1, 5, n)  # fitted on gaps 1 to 4 only
    cos = np.where(same, rng.uniform(0.5, 1.0, n), rng.uniform(-0.6, 0.4, n))  # no cosine under -0.6
    iou = np.where(same, rng.uniform(0.4, 1.0, n), rng.uniform(0.0, 0.3, n))
    pairs = PairFeatures(np.zeros(n, np.int64), np.ones(n, np.int64), gap, cos, np.ones(n, bool), iou)
    cal = fit_calibration([pairs], [same])
    assert cal["appearance"][0] == cal["appearance"][1] == cal["appearance"][4] < -5  # -1 .. -0.6: as -0.6 .. -0.5
    assert cal["prior"][-2:] == [cal["prior"][3]] * 2 and cal["motion"][-1] == cal["motion"][3]  # gaps 5+: as 3-4
    far = PairFeatures(np.zeros(2, np.int64), np.ones(2, np.int64), np.array([4, 30]), np.array([-0.95, -0.95]),
                       np.ones(2, bool), np.array([0.5, 0.5]))
    w = affinities(far, cal)
    assert w[1] == w[0] < 0
    w = affinities(far, CALIBRATION)  # the shipped tables: opposite looks keep apart, within the window or past it
    assert w[0] < -5 and w[1] < -5


def test_a_nan_cue_is_refused_not_the_strongest_attraction():
    """A NaN cosine or IoU was binned past the last edge: the top bin, a pair with a NaN descriptor
    and different labels weighed +15 (and one NaN descriptor, through the clip's mean, made every
    cosine NaN). ``pair_features`` and ``affinities`` are public (the benchmark calls them)."""
    from tasks.tracking.affinity import PairFeatures, affinities, pair_features
    from tasks.tracking.calibration import CALIBRATION

    one = np.zeros(1, np.int64)
    nan_cos = PairFeatures(one, one + 1, one + 1, np.array([np.nan]), np.zeros(1, bool), np.array([0.5]))
    with pytest.raises(ValueError, match=r"^1 pair cue\(s\) are NaN \(a NaN box or descriptor\)"):
        affinities(nan_cos, CALIBRATION)
    vectors = np.eye(3, 8, dtype=np.float32)
    vectors[1, 0] = np.nan
    boxes = np.array([[0.1, 0.1, 0.5, 0.5]] * 3)
    with pytest.raises(ValueError, match="are NaN"):
        affinities(pair_features(np.arange(3), boxes, np.array(["chair"] * 3), vectors, None, 5), CALIBRATION)
    assert np.isfinite(affinities(pair_features(np.arange(3), boxes, np.array(["chair"] * 3), np.eye(3, 8), None, 5),
                                  CALIBRATION)).all()
