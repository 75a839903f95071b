"""Temporal rescoring of detections (tasks/detection/temporal.py): links, chains, scores."""

from __future__ import annotations

import numpy as np
import pytest

from tasks.detection.temporal import FrameDetections, chain_ids, mutual_links, pairwise_iou, temporal_scores


def frame(boxes, scores, labels) -> FrameDetections:
    return FrameDetections(np.array(boxes, np.float64).reshape(-1, 4), np.array(scores, np.float64), np.array(labels, np.int64))


def test_pairwise_iou_of_known_boxes():
    a = np.array([[0, 0, 10, 10], [0, 0, 2, 2]], np.float64)
    b = np.array([[5, 0, 15, 10], [20, 20, 30, 30], [0, 0, 10, 10]], np.float64)
    iou = pairwise_iou(a, b)
    assert iou.shape == (2, 3)
    assert iou[0, 0] == pytest.approx(50 / 150)
    assert iou[0, 1] == 0 and iou[0, 2] == 1
    assert iou[1, 2] == pytest.approx(4 / 100)
    # the same under a per-axis scale: normalised boxes and pixel boxes link alike
    scale = np.array([1 / 640, 1 / 360, 1 / 640, 1 / 360])
    assert np.allclose(pairwise_iou(a * scale, b * scale), iou)


def test_links_are_mutual_best_overlaps_of_one_label_above_the_threshold():
    a = frame([[0, 0, 10, 10], [0, 0, 10, 9], [50, 50, 60, 60]], [0.9, 0.5, 0.8], [1, 1, 2])
    b = frame([[1, 0, 11, 10], [50, 50, 60, 60], [100, 100, 110, 110]], [0.8, 0.7, 0.4], [1, 3, 1])
    # box 0 of a and box 0 of b are each other's best; a's box 1 also overlaps b's 0 but is not its best;
    # a's box 2 overlaps b's box 1 exactly, but under another label
    assert mutual_links(a, b, 0.4) == [(0, 0)]
    assert mutual_links(a, b, 0.9) == []  # IoU 9/11 is under 0.9
    assert mutual_links(a, frame([], [], []), 0.4) == []


def test_chains_follow_consecutive_frames_and_break_where_the_box_jumps():
    box = [0, 0, 10, 10]
    frames = [frame([box], [0.5], [1]), frame([box], [0.5], [1]), frame([[30, 30, 40, 40]], [0.5], [1]),
              frame([[30, 30, 40, 40], box], [0.5, 0.5], [1, 1])]
    ids = chain_ids(frames, 0.4)
    assert ids[0] == ids[1] != ids[2]
    assert ids[2] == ids[3] and ids[4] not in (ids[0], ids[2])  # the box comes back: a new chain, frame 2 held none there


def test_a_weak_box_on_a_long_chain_rises_a_sure_one_keeps_its_score_and_a_lone_sure_box_falls():
    box, lone = [0, 0, 10, 10], [200, 200, 220, 220]
    own = [0.6] * 12
    own[5], own[8] = 0.2, 0.9
    frames = [frame([box] + ([lone] if t == 3 else []), [own[t]] + ([0.9] if t == 3 else []), [1] + ([1] if t == 3 else []))
              for t in range(12)]
    new = temporal_scores(frames, weight=0.7, link_iou=0.4, chain_frames=10)
    mean = float(np.mean(own))  # one chain of 12 >= 10 boxes: counted whole
    assert new[5][0] == pytest.approx(0.7 * mean + 0.3 * 0.2)
    assert new[5][0] > 0.35 > 0.2
    assert new[8][0] == pytest.approx(0.9)  # above its chain's mean: the chain does not pull it down
    assert new[3][1] == pytest.approx(0.7 * 0.9 / 10 + 0.3 * 0.9)  # a chain of one box counts for 1/10
    assert new[3][1] < 0.35 < 0.9


def test_weight_zero_keeps_the_network_scores():
    frames = [frame([[0, 0, 10, 10]], [0.42], [1]), frame([], [], [])]
    new = temporal_scores(frames, weight=0.0, link_iou=0.4, chain_frames=10)
    assert [list(s) for s in new] == [[0.42], []]
    assert temporal_scores([], 0.7, 0.4, 10) == []
