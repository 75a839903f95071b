"""Evaluators of the synthetic benchmark (bench/evaluate.py and its modules): hand-made cases with
known answers. Tracking tests need TrackEval (``trackeval==1.3.0``) and are skipped without it."""

from __future__ import annotations

import importlib.util
import math

import numpy as np
import pytest

from bench.eval_pose import (PosedObject, is_correct, match_and_score, rotation_error_deg, scale_error_pct,
                             symmetry_order, translation_error)
from bench.eval_retrieval import retrieval_recall
from bench.ignore import DETECTABLE_CLASSES, box_iou, is_ignored, predictions_to_drop
from bench.stats import dataset_statistics, statistics_markdown
from schemas.official import Frame, FramesFile, ObjectAnnotation, ObjectsFile, TrackEntry

needs_trackeval = pytest.mark.skipif(importlib.util.find_spec("trackeval") is None, reason="trackeval not installed")

ID = (1.0, 0.0, 0.0, 0.0)


def qaxis(axis, deg: float) -> np.ndarray:
    """Quaternion (w, x, y, z) of a rotation by deg about axis."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    h = math.radians(deg) / 2
    return np.array([math.cos(h), *(math.sin(h) * a)])


def qmul(a, b) -> np.ndarray:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw])


def obj(track_id="t1", cls="chair", t=(0.0, 0.0, 3.0), q=ID, s=(1.0, 1.0, 1.0), **kw) -> PosedObject:
    return PosedObject(track_id, cls, tuple(t), tuple(q), tuple(s), **kw)


# ---------------------------------------------------------------- pose

def test_perfect_prediction_scores_100():
    gts = [obj("a", t=(0, 0, 2)), obj("b", "sofa", t=(1, 0, 3), q=qaxis([0, 1, 0], 33))]
    for match in ("track", "greedy"):
        r = match_and_score(gts, gts, match=match)
        assert r.instance_accuracy == 1.0 and r.class_accuracy == 1.0 and r.num_correct == 2
        assert not r.unmatched_predictions


def test_translation_threshold():
    gt = obj()
    assert translation_error((0.25, 0, 3), gt.translation) == pytest.approx(0.25)
    assert match_and_score([obj(t=(0.25, 0, 3))], [gt]).instance_accuracy == 0.0
    assert match_and_score([obj(t=(0, 0.19, 3))], [gt]).instance_accuracy == 1.0


def test_two_fold_symmetry_about_object_up():
    base = qaxis([1, 0, 0], 90)  # the object lies on its back: its up axis is not world +Y
    flipped = qmul(base, qaxis([0, 1, 0], 180))  # 180 degrees about the object's own up axis
    assert rotation_error_deg(flipped, base, 2) == pytest.approx(0.0, abs=1e-6)
    assert rotation_error_deg(flipped, base, 1) == pytest.approx(180.0)
    assert rotation_error_deg(flipped, base, "__SYM_ROTATE_UP_2") == pytest.approx(0.0, abs=1e-6)
    assert is_correct((0, 0, 0), flipped, (1, 1, 1), (0, 0, 0), base, (1, 1, 1), symmetry=2)
    assert not is_correct((0, 0, 0), flipped, (1, 1, 1), (0, 0, 0), base, (1, 1, 1), symmetry=1)
    world_flip = qmul(qaxis([0, 1, 0], 180), base)  # about WORLD +Y: not a symmetry of this object
    assert rotation_error_deg(world_flip, base, 2) > 20
    # symmetries are looked up by the ground truth's cad_id
    gt, pred = obj(q=base, cad_id="table1"), obj(q=flipped, cad_id="table1")
    assert match_and_score([pred], [gt], {"table1": 2}).instance_accuracy == 1.0
    assert match_and_score([pred], [gt], {"table1": 1}).instance_accuracy == 0.0
    assert match_and_score([pred], [gt]).instance_accuracy == 0.0  # default: no symmetry


def test_four_fold_and_36_way_symmetry():
    assert rotation_error_deg(qaxis([0, 1, 0], 90), ID, 4) == pytest.approx(0.0, abs=1e-6)
    assert rotation_error_deg(qaxis([0, 1, 0], 90), ID, 2) == pytest.approx(90.0)
    for deg in (7.0, 45.0, 123.4, 181.0, 275.5, 359.0):
        assert rotation_error_deg(qaxis([0, 1, 0], deg), ID, 36) <= 5.0 + 1e-9
        assert rotation_error_deg(qaxis([0, 1, 0], deg), ID, "__SYM_ROTATE_UP_INF") <= 5.0 + 1e-9
    assert rotation_error_deg(qaxis([1, 0, 0], 30), ID, 36) == pytest.approx(30.0)  # tilt is not symmetric
    assert symmetry_order("__SYM_NONE") == 1 and symmetry_order(None) == 1
    with pytest.raises(ValueError):
        symmetry_order("__SYM_BOGUS")


def test_rotation_threshold_and_quaternion_sign():
    assert rotation_error_deg(-qaxis([0, 0, 1], 10), ID) == pytest.approx(10.0)  # q and -q are the same rotation
    assert match_and_score([obj(q=qaxis([0, 0, 1], 19))], [obj()]).instance_accuracy == 1.0
    assert match_and_score([obj(q=qaxis([0, 0, 1], 21))], [obj()]).instance_accuracy == 0.0


def test_scale_threshold():
    assert scale_error_pct((1.21, 1.21, 1.21), (1, 1, 1)) == pytest.approx(21.0)
    assert match_and_score([obj(s=(1.21, 1.21, 1.21))], [obj()]).instance_accuracy == 0.0
    assert match_and_score([obj(s=(0.81, 0.81, 0.81))], [obj()]).instance_accuracy == 1.0
    # Scan2CAD averages the per-axis ratios: (1.3 + 1.0 + 0.8) / 3 = 1.0333 -> 3.3 %
    assert scale_error_pct((1.3, 1.0, 0.8), (1, 1, 1)) == pytest.approx(100 / 30)
    assert scale_error_pct((2, 4, 6), (2, 4, 6)) == 0.0


def test_wrong_mirror_flag_is_incorrect():
    gt = obj(is_mirrored=True)
    r = match_and_score([obj(is_mirrored=False)], [gt])
    assert r.instance_accuracy == 0.0 and not r.matches[0].mirror_ok and r.matches[0].translation_error == 0
    assert match_and_score([obj(is_mirrored=True)], [gt]).instance_accuracy == 1.0


def test_class_mean_vs_instance_mean():
    gts = [obj(f"c{i}", "chair", t=(i, 0, 3)) for i in range(3)] + [obj("b", "bed", t=(5, 0, 3))]
    preds = [obj(f"c{i}", "chair", t=(i, 0, 3)) for i in range(3)] + [obj("b", "bed", t=(6, 0, 3))]
    r = match_and_score(preds, gts)
    assert r.instance_accuracy == pytest.approx(0.75)
    assert r.class_accuracy == pytest.approx(0.5)
    assert {row.cls: (row.num_gt, row.num_correct) for row in r.per_class} == {"bed": (1, 0), "chair": (3, 3)}
    assert "class mean" in r.markdown() and r.as_dict()["per_class"]["chair"]["accuracy"] == 1.0


def test_greedy_matching_takes_each_gt_once():
    gts = [obj("g1", t=(0, 0, 3)), obj("g2", t=(0.1, 0, 3))]
    # three predictions on g1's spot: the best two take g1 (nearest) and g2 (within 0.2 m), the third is a FP
    preds = [obj("p1", t=(0, 0, 3), score=0.9), obj("p2", t=(0, 0, 3), score=0.8), obj("p3", t=(0, 0, 3), score=0.7)]
    r = match_and_score(preds, gts, match="greedy")
    assert r.instance_accuracy == 1.0
    assert {(m.pred.track_id, m.gt.track_id) for m in r.matches} == {("p1", "g1"), ("p2", "g2")}
    assert [p.track_id for p in r.unmatched_predictions] == ["p3"]
    # g2 far away: duplicates of g1 cannot be counted twice
    far = [obj("g1", t=(0, 0, 3)), obj("g2", t=(1.0, 0, 3))]
    r = match_and_score(preds, far, match="greedy")
    assert r.instance_accuracy == 0.5 and len(r.unmatched_predictions) == 2
    # greedy matches only within a class and within a clip
    assert match_and_score([obj("p", "bed")], [obj("g")], match="greedy").instance_accuracy == 0.0
    assert match_and_score([obj("p", clip="A")], [obj("g", clip="B")], match="greedy").instance_accuracy == 0.0


def test_track_matching():
    gts = [obj("a", t=(0, 0, 3)), obj("b", t=(0.1, 0, 3)), obj("c", t=(3, 0, 3))]
    # track ids decide, not proximity: "a" predicted on b's spot is still correct (0.1 m off);
    # "b" predicted 1 m away is wrong; "c" has no prediction (a miss); "z" is not a GT track (FP)
    preds = [obj("a", t=(0.1, 0, 3)), obj("b", t=(1.1, 0, 3)), obj("z", t=(3, 0, 3))]
    r = match_and_score(preds, gts, match="track")
    assert r.num_correct == 1 and r.instance_accuracy == pytest.approx(1 / 3)
    assert [p.track_id for p in r.unmatched_predictions] == ["z"]
    assert match_and_score([obj("a", "bed")], [obj("a")]).instance_accuracy == 0.0  # wrong class
    with pytest.raises(ValueError):
        match_and_score([obj("a"), obj("a")], gts)
    with pytest.raises(ValueError):
        match_and_score(preds, gts, match="hungarian")


# ---------------------------------------------------------------- ignore rule

def test_ignore_rule():
    assert not is_ignored("chair", 0.3, 0.5)
    assert is_ignored("chair", 0.29, 0.0)
    assert is_ignored("chair", 1.0, 0.51)
    assert not is_ignored("lamp", 1.0, 0.0)
    assert is_ignored("lamp", 1.0, 0.0, detectable={"chair"})
    assert is_ignored("door", 1.0, 0.0)
    assert box_iou([[0, 0, 1, 1]], [[0, 0, 1, 0.5], [2, 2, 3, 3]]) == pytest.approx(np.array([[0.5, 0.0]]))
    # prediction 0 is on the ignore box; prediction 1 covers a real object also overlapping the ignore box
    gt = np.array([[0, 0, 0.2, 0.2], [0.5, 0.5, 0.7, 0.7], [0.5, 0.5, 0.69, 0.69]])
    ignore = np.array([False, True, False])
    pred = np.array([[0.5, 0.5, 0.7, 0.7], [0.5, 0.5, 0.69, 0.69], [0.8, 0.8, 0.9, 0.9]])
    assert predictions_to_drop(pred, gt, ignore).tolist() == [True, False, False]



def test_detection_drops_within_each_class_on_ignore_regions():
    """A table in view and a chair mostly hidden under it (ignored). Matched to the table
    class-agnostically, a chair box on the hidden chair beside a table box took the table's match:
    the table box was dropped (a miss and a false positive). Alone, a box of another class on the
    table is a false positive, as it was."""
    from bench.eval_detection import FrameBoxes, evaluate_detections

    table, chair, table_box = [0.4, 0.2, 0.8, 0.8], [0.45, 0.2, 0.8, 0.7], [0.42, 0.2, 0.8, 0.66]

    def frame(pred, labels):
        return FrameBoxes(np.array([table, chair]), ["table", "chair"], np.array([False, True]), np.array(pred), labels)

    for label in ("chair", "sofa"):
        alone = evaluate_detections([frame([chair], [label])])
        assert (alone["predictions"], alone["recall"], alone["precision"]) == (1, 0.0, 0.0)
    both = evaluate_detections([frame([chair, table_box], ["chair", "table"])])
    assert (both["predictions"], both["recall"], both["precision"]) == (1, 1.0, 1.0)


def test_detectable_classes_are_every_class_the_rooms_hold():
    from bench.scene import EXCLUDED_CLASSES
    from tasks.cad.classes import BY_NAME

    assert DETECTABLE_CLASSES == set(BY_NAME) - EXCLUDED_CLASSES


# ---------------------------------------------------------------- tracking

A, B = (0.1, 0.1, 0.3, 0.3), (0.5, 0.5, 0.8, 0.8)


def tb(frame, track, box, ignore=False):
    from bench.eval_tracking import TrackBox

    return TrackBox(frame, track, box, ignore)


@needs_trackeval
def test_identical_tracks_are_perfect():
    from bench.eval_tracking import evaluate_tracking

    gt = [tb(f, "A", A) for f in range(5)] + [tb(f, "B", B) for f in range(1, 4)]
    r = evaluate_tracking(gt, [tb(b.frame, "p" + b.track_id, b.box) for b in gt])
    assert r.mota == 1.0 and r.idf1 == 1.0 and r.hota == pytest.approx(1.0)
    assert r.precision == 1.0 and r.recall == 1.0 and r.id_switches == 0 and r.true_positives == 8


def _switching():
    gt = [tb(f, "A", A) for f in range(4)] + [tb(f, "B", B) for f in range(4)]
    # track x follows A on frames 0-1, then jumps to B; y covers B then z covers A
    pred = [tb(0, "x", A), tb(1, "x", A), tb(2, "x", B), tb(3, "x", B),
            tb(0, "y", B), tb(1, "y", B), tb(2, "z", A), tb(3, "z", A)]
    return gt, pred


@needs_trackeval
def test_id_switch_is_counted():
    from bench.eval_tracking import evaluate_tracking

    r = evaluate_tracking(*_switching())
    assert r.id_switches == 2  # A: x -> z, B: y -> x
    assert r.mota == pytest.approx((8 - 2) / 8)
    assert r.precision == 1.0 and r.recall == 1.0
    assert r.idf1 == pytest.approx(0.5)  # best one-to-one ids: A-x (2 frames), B-y (2 frames): 4 of 8
    assert r.hota < 1.0


@pytest.mark.skipif(importlib.util.find_spec("motmetrics") is None or importlib.util.find_spec("trackeval") is None,
                    reason="motmetrics/trackeval not installed")
def test_trackeval_agrees_with_motmetrics():
    import motmetrics as mm

    from bench.eval_tracking import evaluate_tracking

    gt, pred = _switching()
    acc = mm.MOTAccumulator(auto_id=True)
    num = {"A": 1, "B": 2, "x": 1, "y": 2, "z": 3}  # motmetrics 1.4.0 + pandas 3 fails on string ids
    for f in range(4):
        g = [b for b in gt if b.frame == f]
        p = [b for b in pred if b.frame == f]
        d = 1 - box_iou(np.array([b.box for b in g]), np.array([b.box for b in p]))
        acc.update([num[b.track_id] for b in g], [num[b.track_id] for b in p], np.where(d <= 0.5, d, np.nan))
    m = mm.metrics.create().compute(acc, metrics=["mota", "idf1", "num_switches"], name="x")
    r = evaluate_tracking(gt, pred)
    assert r.mota == pytest.approx(m["mota"].iloc[0]) and r.idf1 == pytest.approx(m["idf1"].iloc[0])
    assert r.id_switches == m["num_switches"].iloc[0]


@needs_trackeval
def test_ignore_region_is_neither_miss_nor_false_positive():
    from bench.eval_tracking import evaluate_tracking

    gt = [tb(f, "A", A) for f in range(3)] + [tb(f, "B", B, ignore=True) for f in range(3)]
    pred = [tb(f, "a", A) for f in range(3)] + [tb(f, "b", B) for f in range(2)]  # b covers the ignore box
    r = evaluate_tracking(gt, pred)
    assert r.misses == 0 and r.false_positives == 0 and r.precision == 1.0 and r.recall == 1.0
    assert r.ignored_gt_boxes == 3 and r.dropped_pred_boxes == 2 and r.mota == 1.0
    # the same boxes not flagged as ignore: b's frames match, frame 2 of B is a miss
    r = evaluate_tracking([tb(b.frame, b.track_id, b.box) for b in gt], pred)
    assert r.misses == 1 and r.false_positives == 0 and r.recall == pytest.approx(5 / 6)


@needs_trackeval
def test_multi_clip_and_official_files():
    from bench.evaluate import evaluate_clips
    from bench.eval_tracking import evaluate_tracking_clips

    r = evaluate_tracking_clips([_switching(), ([tb(0, "A", A)], [tb(0, "a", A)])])
    assert r.true_positives == 9 and r.id_switches == 2 and r.mota == pytest.approx(7 / 9)
    with pytest.raises(ValueError):
        evaluate_tracking_clips([([tb(0, "A", A), tb(0, "A", B)], [])])
    gt, _ = _two_clips()
    out = evaluate_clips([(o, o) for _, o in gt], symmetries={"c1": 2})
    assert out["pose"]["instance_accuracy"] == 1.0 and out["tracking"]["mota"] == 1.0
    ignore_sofa = lambda o, t: is_ignored({"03001627": "chair"}.get(o.cls, "?"))  # noqa: E731
    out = evaluate_clips([(o, o) for _, o in gt], gt_ignore=ignore_sofa)
    assert out["tracking"]["ignored_gt_boxes"] == 2 and out["tracking"]["dropped_pred_boxes"] == 2


# ---------------------------------------------------------------- retrieval

def test_retrieval_recall():
    truth = {"t1": ("c1", "chair"), "t2": ("c2", "sofa"), "t3": ("c3", "bed")}
    ranked = {
        "t1": [("c1", "chair"), ("c9", "chair")],
        "t2": [("c8", "sofa"), ("c7", "chair"), ("c6", "chair"), ("c5", "chair"), ("c2", "sofa")],
        "t3": [("c4", "chair"), ("c5", "table")] + [(f"x{i}", "table") for i in range(8)] + [("c3", "bed")],
    }
    r = retrieval_recall(ranked, truth)
    assert r.cad_recall == {1: pytest.approx(1 / 3), 10: pytest.approx(2 / 3)}
    assert r.class_recall == {1: pytest.approx(2 / 3), 10: pytest.approx(2 / 3)}  # t3's bed is 11th
    assert retrieval_recall({}, truth).cad_recall[10] == 0.0  # missing lists are misses
    assert r.as_dict()["cad_recall@1"] == pytest.approx(1 / 3)


# ---------------------------------------------------------------- statistics

def _frames(name, n):
    return FramesFile(name, (192, 320), tuple(Frame(1000 * i, i == 0, (300, 300, 160, 96), (0, 0, 0), ID)
                                             for i in range(n)))


def _two_clips():
    box = (0.1, 0.1, 0.3, 0.3)
    pose = dict(translation=(0.0, 0.0, 3.0), rotation=ID, scale=(1.0, 1.0, 1.0))
    a = ObjectsFile("A", (
        ObjectAnnotation("o1", "03001627", True, False, (TrackEntry(0, box), TrackEntry(1000, box)), "c1", **pose),
        ObjectAnnotation("o2", "04256520", True, False, (TrackEntry(0, (0.5, 0.5, 0.9, 0.9)),), "c2", **pose),
        ObjectAnnotation("o3", "04256520", False, False, (TrackEntry(2000, box),), None),  # not posed
    ))
    b = ObjectsFile("B", (
        ObjectAnnotation("o1", "03001627", True, False, (TrackEntry(0, box), TrackEntry(1000, box)), "c1", **pose),))
    return [(_frames("A", 3), a), (_frames("B", 2), b)], None


def test_stats_on_two_clips():
    clips, _ = _two_clips()
    s = dataset_statistics(clips)
    assert s == {"clips": 2, "frames": 5, "objects": 4, "posed_objects": 3, "cad_models": 2, "classes": 2,
                 "classes_over_1000": 0, "classes_over_100": 0, "objects_per_clip": 1.5,
                 "objects_per_frame": pytest.approx(1.0), "frames_per_clip": 2.5}
    md = statistics_markdown({"Train": s, "Total": s})
    assert "| #Posed objects | 3 | 3 |" in md and "| #Frames per scene | 2.5 | 2.5 |" in md
    assert "| Dataset | Total |" in statistics_markdown(s)
    with pytest.raises(ValueError):
        dataset_statistics([(_frames("A", 1), clips[1][1])])


# ---- detection -------------------------------------------------------------------------------------
def test_detector_labels_stand_for_classes():
    from tasks.cad.classes import class_of_label
    from tasks.detection.models.furniture_files import FURNITURE_CLASSES, FURNITURE_LABELS
    from tasks.detection.models.nanodet import COCO_LABELS

    assert {class_of_label(label) for label in FURNITURE_LABELS} - {None} == set(FURNITURE_CLASSES) | {"laptop", "clock", "vehicle"}
    assert [class_of_label(label) for label in ("couch", "dining table", "tv", "laptop", "vase", "oven", "cat", "other")] == [
        "sofa", "table", "display", "laptop", "jar", "stove", None, None]
    coco_found = {class_of_label(label) for label in COCO_LABELS} - {None}
    assert coco_found < DETECTABLE_CLASSES | {"laptop", "clock", "vehicle"} and "cabinet" not in coco_found


def test_detection_recall_precision_by_hand():
    from bench.eval_detection import OTHER, FrameBoxes, evaluate_detections

    chair, sofa, hidden = [0.1, 0.1, 0.5, 0.3], [0.5, 0.5, 0.9, 0.9], [0.1, 0.6, 0.3, 0.8]
    frames = [
        # chair found; sofa called "chair" (a sofa miss, a chair false positive); a prediction on the
        # ignored (hidden) box is dropped; a "book" elsewhere is a false positive of no class
        FrameBoxes(np.array([chair, sofa, hidden]), ["chair", "sofa", "table"], np.array([False, False, True]),
                   np.array([chair, sofa, hidden, [0.0, 0.0, 0.05, 0.05]]), ["chair", "chair", "dining table", "book"]),
        # sofa found as couch, chair missed
        FrameBoxes(np.array([chair, sofa]), ["chair", "sofa"], np.array([False, False]),
                   np.array([[0.51, 0.5, 0.9, 0.9]]), ["couch"]),
    ]
    r = evaluate_detections(frames)
    assert r["ground_truth"] == 4 and r["predictions"] == 4
    assert r["per_class"]["chair"] == {"ground_truth": 2, "predictions": 2, "true_positives": 1, "recall": 0.5, "precision": 0.5}
    assert r["per_class"]["sofa"]["recall"] == 0.5 and r["per_class"]["sofa"]["precision"] == 1.0
    assert r["per_class"][OTHER] == {"ground_truth": 0, "predictions": 1, "true_positives": 0, "recall": None, "precision": 0.0}
    assert "table" not in r["per_class"]  # only an ignore box and a dropped prediction
    assert r["recall"] == 0.5 and r["precision"] == 0.5 and r["class_agnostic_recall"] == 0.75


# ---- pose: 4-way symmetric models turned by 90 degrees ---------------------------------------------
def test_four_way_symmetric_pose_turned_by_90_degrees_swaps_sx_and_sz():
    """A 4-way model posed R_gt·R_y(90) with (sz, sy, sx) is the same object as R_gt with (sx, sy, sz)."""
    from bench.eval_pose import symmetric_rotation_error, symmetric_scale
    from cadestate.geometry import matrix_to_quaternion
    from tasks.cad.symmetry import rotation_y

    q_gt = matrix_to_quaternion(rotation_y(30.0))
    s_gt = (0.5, 0.7, 1.5)
    q_turned = matrix_to_quaternion(rotation_y(120.0))  # R_gt · R_y(90)
    err, i = symmetric_rotation_error(q_turned, q_gt, 4)
    assert err < 1e-6 and i % 2 == 1
    assert symmetric_scale(s_gt, 4, i).tolist() == [1.5, 0.7, 0.5]
    assert is_correct((0, 0, 0), q_turned, (1.5, 0.7, 0.5), (0, 0, 0), q_gt, s_gt, 4)
    assert not is_correct((0, 0, 0), q_turned, s_gt, (0, 0, 0), q_gt, s_gt, 4)  # the unswapped sizes are 44 % off
    assert is_correct((0, 0, 0), q_gt, s_gt, (0, 0, 0), q_gt, s_gt, 4)
    # 180 degrees keeps the axes; a 2-way model never swaps
    assert is_correct((0, 0, 0), matrix_to_quaternion(rotation_y(210.0)), s_gt, (0, 0, 0), q_gt, s_gt, 4)
    assert symmetric_scale(s_gt, 2, 1).tolist() == list(s_gt)
    gt = PosedObject("1", "table", (0, 0, 0), tuple(q_gt), s_gt, cad_id="m", clip="c")
    pred = PosedObject("1", "table", (0, 0, 0), tuple(q_turned), (1.5, 0.7, 0.5), cad_id="m", clip="c")
    assert match_and_score([pred], [gt], {"m": 4}).num_correct == 1


def test_pose_ground_truth_is_the_objects_the_clip_shows(tmp_path):
    """A room's object the camera never sees (no box on any frame) is no object anyone could pose:
    it left the pose section's denominator at 10 where the yield's was the 7 in view."""
    import json

    from bench.pose_bench import _gt
    from schemas.official import objects_to_json

    box, pose = (0.1, 0.1, 0.3, 0.3), dict(translation=(0.0, 0.0, 3.0), rotation=ID, scale=(1.0, 1.0, 1.0))
    objects = ObjectsFile("A", (
        ObjectAnnotation("0", "03001627", False, False, (TrackEntry(0, box),), "c1", **pose),
        ObjectAnnotation("1", "04256520", False, False, (), "c2", **pose),  # behind the camera all along
    ))
    (tmp_path / "A").mkdir()
    (tmp_path / "A" / "objects.json").write_text(json.dumps(objects_to_json(objects)))
    assert [g.track_id for g in _gt(tmp_path, ["A"])] == ["0"]
