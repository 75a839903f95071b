"""Duplicate candidates after pose (tasks/pose/duplicates.py): overlaps of posed CAD boxes with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tasks.pose.duplicates import duplicate_candidates, overlap, posed_box

IDENTITY = (1.0, 0.0, 0.0, 0.0)


def about_up(degrees: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) rotation by ``degrees`` about +Y."""
    h = math.radians(degrees) / 2
    return (math.cos(h), 0.0, math.sin(h), 0.0)


def box(t=(0.0, 0.0, 0.0), q=IDENTITY, s=(1.0, 1.0, 1.0), mirrored=False, extent=(0.5, 0.9, 0.5)):
    return posed_box(extent, t, q, s, mirrored)


def test_identical_boxes_overlap_fully():
    assert overlap(box((1, 0, 2)), box((1, 0, 2))) == 1.0


def test_a_flat_model_overlaps_its_twin():
    """A model of one flat face (a rug: a side of 0) had a box of no volume: no overlap, not even
    with its own twin, so two poses of one rug were never flagged."""
    rug = (2.0, 0.0, 1.4)
    assert overlap(box(extent=rug), box(extent=rug)) == 1.0
    assert overlap(box(extent=rug), box((0.0, 0.5, 0.0), extent=rug)) == 0.0  # one above the other: apart
    # Two solves of one rug or picture differ in depth by centimetres: its box was 1 % of 2 m thick,
    # and 2 cm apart overlapped 0.05 (not flagged at 0.3).
    for depth in (0.02, 0.05):
        assert overlap(box(extent=rug), box((0.0, depth, 0.0), extent=rug)) >= 0.5
    table = box((0.0, 0.2, 0.0), extent=(1.2, 0.4, 0.6))  # a coffee table 0.4 m high on the floor the rug lies on
    assert overlap(box(extent=rug), table) < 0.3


def test_disjoint_boxes_do_not_overlap():
    assert overlap(box(), box((0.6, 0, 0))) == 0.0  # 0.1 m apart along x
    assert overlap(box(), box((0.0, 0, 0.52))) == 0.0  # near enough for the sphere test: the grid decides


def test_half_shifted_box_overlaps_half():
    assert overlap(box(), box((0.25, 0, 0))) == pytest.approx(0.5)
    assert overlap(box(), box((0, 0.45, 0), q=about_up(0))) == pytest.approx(0.5)


def test_quarter_turn_about_up_of_a_square_footprint_overlaps_fully():
    assert overlap(box(), box(q=about_up(90))) == pytest.approx(1.0)


def test_quarter_turn_of_an_oblong_footprint_overlaps_the_square_in_the_middle():
    # 1.0 x 0.5 footprint turned 90 degrees: the 0.5 x 0.5 middle is shared, half of each box
    assert overlap(box(extent=(1.0, 0.9, 0.5)), box(q=about_up(90), extent=(1.0, 0.9, 0.5))) == pytest.approx(0.5)


def test_mirrored_pose_is_the_same_box():
    assert overlap(box(mirrored=True), box()) == pytest.approx(1.0)
    assert overlap(box((0.25, 0, 0), mirrored=True), box()) == pytest.approx(0.5)


def test_small_box_inside_a_big_one_overlaps_fully_from_either_side():
    small, big = box((0.1, 0.1, 0.1), s=(0.2, 0.2, 0.2)), box(s=(2, 2, 2))
    assert overlap(small, big) == overlap(big, small) == 1.0


def test_scale_and_rotation_place_the_box():
    # a 1 m cube scaled 2x along CAD x, turned 90 degrees about up: it spans z in [-1, 1], x in [-0.5, 0.5]
    long = box(q=about_up(90), s=(2, 1, 1), extent=(1, 1, 1))
    assert overlap(long, box((0, 0, 0.75), extent=(1, 1, 1))) == pytest.approx(0.75)
    assert overlap(long, box((0.75, 0, 0), extent=(1, 1, 1))) == pytest.approx(0.25)


def test_candidates_are_the_pairs_at_or_above_the_threshold():
    boxes = {3: box(), 5: box((0.02, 0, 0.03)), 7: box((0.25, 0, 0)), 9: box((5, 0, 0))}
    assert duplicate_candidates(boxes, 0.5) == {3: (5, 7), 5: (3, 7), 7: (3, 5)}
    assert duplicate_candidates(boxes, 0.9) == {3: (5,), 5: (3,)}
    assert duplicate_candidates({3: box(), 9: box((5, 0, 0))}, 0.5) == {}


def test_overlap_is_deterministic_and_symmetric():
    rng = np.random.default_rng(0)
    for _ in range(5):
        q = rng.normal(size=4)
        a, b = box(rng.normal(size=3) * 0.2, tuple(q / np.linalg.norm(q))), box(rng.normal(size=3) * 0.2)
        assert overlap(a, b) == overlap(a, b)
        if a.volume != b.volume:
            assert overlap(a, b) == overlap(b, a)
