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


def test_duplicates_in_scan2cad_modes_and_all_modes():
    gt = [obj("0")]
    preds = [obj("1"), obj("2", t=(0.05, 0, 0)), obj("3", t=(4.0, 0, 0))]
    modes = score_all(preds, gt, {("a_0", "1"): "0", ("a_0", "2"): "0"}, {})
    assert list(modes) == ["pose", "scan2cad-class", "scan2cad-exact"]
    for m in modes.values():
        assert (m.num_correct, m.duplicates, m.false_positives) == (1, 1, 1), m
        assert m.as_dict()["instance_accuracy_pct"] == pytest.approx(100.0)
