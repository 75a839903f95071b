"""bench.scoring: the three scoring modes of `bench report` on hand-made poses."""

from __future__ import annotations

import math

import pytest

from bench.eval_pose import PosedObject
from bench.scoring import score_all, score_pose, score_scan2cad

ID = (1.0, 0.0, 0.0, 0.0)
YAW90 = (math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0)  # 90 degrees about +Y


def obj(track, cls="chair", cad="c1", t=(0.0, 0.0, 0.0), q=ID, s=(1.0, 1.0, 1.0), mirrored=False, clip="a_0"):
    return PosedObject(track, cls, t, q, s, mirrored, cad, clip)


def test_any_track_credits_its_object_and_the_rest_are_duplicates():
    gt = [obj("0"), obj("1", t=(3.0, 0, 0))]
    wrong, right = obj("5", t=(1.0, 0, 0)), obj("9")
    truth = {("a_0", "5"): "0", ("a_0", "9"): "0", ("a_0", "7"): "1"}
    r = score_pose([wrong, right, obj("8", t=(9, 9, 9))], gt, truth, {})
    assert (r.num_correct, r.duplicates, r.false_positives) == (1, 1, 1)  # track 9 credits object 0; 5 duplicates it
    assert r.instance_accuracy == 0.5 and r.per_class == {"chair": (2, 1)}


def test_scan2cad_class_needs_the_class_and_no_scale_swap():
    gt = [obj("0", s=(3.0, 1.0, 1.0))]
    sym = {"c1": 4}
    turned = obj("3", q=YAW90, s=(1.0, 1.0, 3.0))  # the same shape turned by 90 degrees, x/z scales traded
    assert score_pose([turned], gt, {("a_0", "3"): "0"}, sym).num_correct == 1  # pose mode swaps the scales back
    assert score_scan2cad([turned], gt, sym, exact=False).num_correct == 0  # Scan2CAD compares scales as they are
    assert score_scan2cad([obj("3", q=YAW90, s=(3.0, 1.0, 1.0))], gt, sym, exact=False).num_correct == 1
    table = obj("4", cls="table", s=(3.0, 1.0, 1.0))
    assert score_pose([table], gt, {("a_0", "4"): "0"}, sym).num_correct == 1  # pose mode ignores the class
    r = score_scan2cad([table], gt, sym, exact=False)
    assert r.num_correct == 0 and r.false_positives == 1


def test_scan2cad_exact_needs_a_ground_truth_model_at_most_as_often():
    gt = [obj("0"), obj("1", t=(0.1, 0, 0)), obj("2", cad="c2", t=(5.0, 0, 0))]
    other_model = obj("3", cad="c9")
    assert score_scan2cad([other_model], gt, {}, exact=False).num_correct == 1
    assert score_scan2cad([other_model], gt, {}, exact=True).num_correct == 0
    # c2 appears once in the ground truth: the second c2 prediction is dropped before matching.
    twice = [obj("4", cad="c2"), obj("5", cad="c2", t=(0.1, 0, 0))]
    assert score_scan2cad(twice, gt, {}, exact=False).num_correct == 2
    assert score_scan2cad(twice, gt, {}, exact=True).num_correct == 1
    mirrored = obj("6", mirrored=True)  # a mirrored model is a CAD model of its own
    assert score_scan2cad([mirrored], gt, {}, exact=True).num_correct == 0
    assert score_scan2cad([mirrored], gt, {}, exact=False).num_correct == 1


def test_a_model_scan2cad_exact_drops_is_a_false_positive_not_a_correct_duplicate():
    """A pose of a model the clip's ground truth lacks is dropped by scan2cad-exact; it went on to
    the duplicates' test (which looked at neither model) and came back a correct duplicate."""
    gt = [obj("0", cad="a")]
    exact = score_scan2cad([obj("1", cad="a"), obj("2", cad="zzz")], gt, {}, exact=True)
    assert (exact.num_correct, exact.duplicates, exact.false_positives) == (1, 0, 1)
    assert [(o.on_object, o.correct) for o in exact.outcomes] == [(("a_0", "0"), True), (None, False)]
    twice = score_scan2cad([obj("1", cad="a"), obj("3", cad="a", t=(0.05, 0, 0))], gt, {}, exact=True)
    assert (twice.num_correct, twice.duplicates, twice.false_positives) == (1, 1, 0)  # its own model twice
    wide = score_scan2cad([obj("1", cad="a"), obj("2", cad="zzz")], gt, {}, exact=False)
    assert (wide.num_correct, wide.duplicates, wide.false_positives) == (1, 1, 0)  # the class mode takes any model


def test_duplicates_in_scan2cad_modes_and_all_modes():
    gt = [obj("0")]
    preds = [obj("1"), obj("2", t=(0.05, 0, 0)), obj("3", t=(4.0, 0, 0))]
    modes = score_all(preds, gt, {("a_0", "1"): "0", ("a_0", "2"): "0"}, {})
    assert list(modes) == ["pose", "scan2cad-class", "scan2cad-exact"]
    for m in modes.values():
        assert (m.num_correct, m.duplicates, m.false_positives) == (1, 1, 1), m
        assert m.as_dict()["instance_accuracy_pct"] == pytest.approx(100.0)


def test_a_wrong_second_pose_on_an_object_is_on_that_object_in_every_mode():
    """Two accepted poses on one chair, one right and one turned 90 degrees: the object is not
    yielded (two poses on it), the wrong one is a duplicate of the dataset, not a false annotation."""
    from bench.dataset_yield import pose_yield

    gt = [obj("0")]
    preds = [obj("1"), obj("2", q=YAW90)]
    truth = {("a_0", "1"): "0", ("a_0", "2"): "0"}
    for mode, result in score_all(preds, gt, truth, {}).items():
        y = pose_yield(result.outcomes, {("a_0", "0")})
        assert (y.yielded, y.duplicates, y.wrong_poses, y.false_annotations) == (0, 1, 1, 0), mode
        lone = pose_yield(score_all([obj("2", q=YAW90)], gt, truth, {})[mode].outcomes, {("a_0", "0")})
        assert (lone.yielded, lone.duplicates, lone.wrong_poses, lone.false_annotations) == (0, 0, 1, 0), mode
    off = score_all([obj("3", t=(5.0, 0, 0))], gt, {}, {})  # a track on no object: a false annotation
    assert all(pose_yield(r.outcomes, {("a_0", "0")}).false_annotations == 1 for r in off.values())


def test_scales_of_another_model_are_compared_as_sizes():
    """A library model's scale multiplies its size in metres: a washer (0.6 x 0.85 x 0.6 m) at scale 1
    where a refrigerator (0.7 x 1.8 x 0.7 m) stands at scale 1 is 27 % (and more) off, not 0 %."""
    extents = {"fridge": (0.7, 1.8, 0.7), "washer": (0.6, 0.85, 0.6), "big_washer": (0.7, 1.8, 0.7)}
    gt = [obj("0", cls="refrigerator", cad="fridge")]
    truth = {("a_0", "1"): "0"}
    washer = obj("1", cls="refrigerator", cad="washer")
    assert score_pose([washer], gt, truth, {}).num_correct == 1  # without sizes: scale multipliers only
    assert score_pose([washer], gt, truth, {}, extents).num_correct == 0
    assert score_scan2cad([washer], gt, {}, False, truth, extents).num_correct == 0
    grown = obj("1", cls="refrigerator", cad="washer", s=(0.7 / 0.6, 1.8 / 0.85, 0.7 / 0.6))  # the fridge's size
    assert score_pose([grown], gt, truth, {}, extents).num_correct == 1
    assert score_pose([obj("1", cls="refrigerator", cad="big_washer")], gt, truth, {}, extents).num_correct == 1


def test_box_matching_takes_the_most_pairs_that_pass():
    """Two pairs of IoU 0.51 beat the larger IoU sum of a pair of 0.95 and one of 0.45 (under 0.5)."""
    import numpy as np

    from bench.eval_detection import _match
    from bench.ignore import match_pairs

    iou = np.array([[0.95, 0.51], [0.51, 0.45]])
    assert _match(iou) == 2
    rows, cols = match_pairs(iou)
    assert sorted(zip(rows.tolist(), cols.tolist())) == [(0, 1), (1, 0)]
    assert _match(np.array([[0.4, 0.3]])) == 0 and _match(np.zeros((0, 3))) == 0
