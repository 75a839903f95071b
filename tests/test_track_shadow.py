"""Shadow tracks (tasks/tracking/shadow.py): a second track on an object a stronger track follows is
dropped; objects that only overlap, and tracks that overlap only a dropped shadow, are kept."""

from __future__ import annotations

import numpy as np
import pytest

from cadestate.config import ConfigError, TrackingConfig, config_from_dict
from tasks.tracking.affinity import Cameras
from tasks.tracking.shadow import same_frame_overlaps, shadow_groups
from tasks.tracking.track3d import box_rays
from tasks.tracking.tracking import Geometry, track_detections


def moving(box: tuple, frames: range, step: float = 0.002) -> np.ndarray:
    """float[F,4] (ymin, xmin, ymax, xmax): ``box`` drifting right by ``step`` a frame."""
    return np.array([[box[0], box[1] + step * f, box[2], box[3] + step * f] for f in frames])


def test_same_frame_overlaps_lists_each_overlapping_pair_of_a_frame_both_ways():
    frames = np.array([0, 0, 0, 1, 1])
    boxes = np.array([[0, 0, 1, 1], [0, 0, 1, 0.9], [0, 0, 0.2, 0.2], [0, 0, 1, 1], [0.5, 0.5, 1, 1]], float)
    a, b = same_frame_overlaps(frames, boxes, 0.5)
    assert sorted(zip(a.tolist(), b.tolist())) == [(0, 1), (1, 0)]  # frame 1's pair has IoU 0.25
    a, b = same_frame_overlaps(frames, boxes, 0.2)
    assert sorted(zip(a.tolist(), b.tolist())) == [(0, 1), (1, 0), (3, 4), (4, 3)]
    assert [len(x) for x in same_frame_overlaps(np.array([3]), boxes[:1], 0.0)] == [0, 0]


def test_a_second_track_on_a_tracked_object_is_a_shadow_and_overlapping_objects_are_not():
    table = moving((0.5, 0.1, 0.9, 0.6), range(20))
    table_again = moving((0.52, 0.1, 0.9, 0.62), range(4, 16))  # IoU ~0.9 with the table on frames 4-15
    chair = moving((0.6, 0.45, 0.95, 0.75), range(20))  # in front of the table: IoU < 0.3
    part = moving((0.5, 0.1, 0.9, 0.6), range(20))[::2]  # boxed again on every other frame only
    frames = np.r_[np.arange(20), np.arange(4, 16), np.arange(20), np.arange(0, 20, 2)]
    boxes = np.r_[table, table_again, chair, part]
    groups = [np.arange(20), np.arange(20, 32), np.arange(32, 52), np.arange(52, 62)]
    scores = np.r_[np.full(20, 0.8), np.full(12, 0.6), np.full(20, 0.7), np.full(10, 0.6)]
    assert shadow_groups(groups, frames, boxes, scores, 0.5, 0.5).tolist() == [False, True, False, True]
    assert shadow_groups(groups, frames, boxes, scores, 1.0, 0.5).tolist() == [False] * 4  # 1 keeps them all
    # too low a threshold takes the chair in front of the table (the table scores better) for the table again
    assert shadow_groups(groups, frames, boxes, scores, 0.15, 0.5).tolist() == [False, True, True, True]
    # the stronger track is the longer one; at equal length the better-scored one
    assert shadow_groups(groups[:2][::-1], frames, boxes, scores, 0.5, 0.5).tolist() == [True, False]
    twins = [np.arange(20), np.arange(52, 62)]
    even = np.r_[np.arange(20), np.arange(52, 62)]
    assert shadow_groups([even[:10], even[20:]], frames, boxes, scores, 0.5, 0.5).tolist() == [False, True]
    flipped = np.r_[np.full(20, 0.5), scores[20:]]
    assert shadow_groups([even[:10], even[20:]], frames, boxes, flipped, 0.5, 0.5).tolist() == [True, False]
    assert shadow_groups(twins, frames, boxes, scores, 0.5, 1.0).tolist() == [False, True]


def test_a_confident_track_is_no_shadow_of_a_less_confident_one():
    """A long track that the partition ran from a bed onto the table beside it (less sure of itself)
    covers the bed's own, confident track on its frames: that track is the bed's, and stays; a weak
    track trailing the long one on the same frames is a shadow."""
    bed = moving((0.4, 0.1, 0.8, 0.5), range(15))
    table = moving((0.5, 0.55, 0.8, 0.9), range(15, 30))
    bed_again = moving((0.41, 0.1, 0.8, 0.51), range(15))  # IoU ~0.95 with the long track's bed boxes
    frames = np.r_[np.arange(30), np.arange(15)]
    boxes = np.r_[bed, table, bed_again]
    groups = [np.arange(30), np.arange(30, 45)]
    for clean, shadow in ((0.8, False), (0.55, False), (0.5, True), (0.4, True)):  # as sure as the long one: a shadow
        scores = np.r_[np.full(30, 0.5), np.full(15, clean)]
        assert shadow_groups(groups, frames, boxes, scores, 0.5, 0.5).tolist() == [False, shadow], clean


def test_a_track_overlapping_only_a_dropped_shadow_is_kept():
    a = moving((0.1, 0.1, 0.5, 0.5), range(10))
    b = moving((0.1, 0.2, 0.5, 0.6), range(10))  # IoU 0.6 with a
    c = moving((0.1, 0.3, 0.5, 0.7), range(10))  # IoU 0.6 with b, 0.33 with a
    frames = np.tile(np.arange(10), 3)
    groups = [np.arange(10), np.arange(10, 20), np.arange(20, 30)]
    scores = np.r_[np.full(10, 0.9), np.full(10, 0.8), np.full(10, 0.7)]
    assert shadow_groups(groups, frames, np.r_[a, b, c], scores, 0.5, 0.5).tolist() == [False, True, False]


def test_tracking_drops_the_shadow_and_says_so():
    """One object boxed twice under two names on every frame, another alone: two tracks, one shadow."""
    frames_n = 30
    K = np.array([[500.0, 0, 320], [0, 500, 180], [0, 0, 1]])
    R = np.repeat(np.eye(3)[None], frames_n, 0)
    t = np.zeros((frames_n, 3))
    sofa = moving((0.4, 0.1, 0.8, 0.5), range(frames_n))
    sofa_as_bed = moving((0.42, 0.1, 0.82, 0.52), range(frames_n))  # IoU 0.83: kept by class-aware NMS
    lamp = moving((0.1, 0.6, 0.3, 0.7), range(frames_n))
    frame = np.tile(np.arange(frames_n), 3)
    boxes = np.r_[sofa, sofa_as_bed, lamp]
    labels = np.array(["sofa"] * frames_n + ["bed"] * frames_n + ["lamp"] * frames_n, dtype=object)
    rng = np.random.default_rng(0)
    looks = rng.normal(0, 1, (3, 32))
    vectors = np.repeat(looks, frames_n, 0) + rng.normal(0, 0.1, (3 * frames_n, 32))
    scores = np.r_[np.full(frames_n, 0.8), np.full(frames_n, 0.5), np.full(frames_n, 0.7)]
    cams = Cameras(np.repeat(K[None], frames_n, 0), R, 640, 360)
    geometry = Geometry(box_rays(boxes, cams.K[frame], R[frame], t[frame], 640, 360), np.array([0, 15, 29]))
    det_id = np.arange(len(frame))
    res = track_detections(det_id, frame, boxes, labels, vectors.astype(np.float32), cams, TrackingConfig(), scores=scores,
                           geometry=geometry)
    assert res.shadows == 1 and np.all(res.track[frames_n:2 * frames_n] == -1)
    assert len(set(res.track[:frames_n])) == 1 and len(set(res.track[2 * frames_n:])) == 1 and res.track.max() == 1
    kept = track_detections(det_id, frame, boxes, labels, vectors.astype(np.float32), cams, TrackingConfig(shadow_iou=1.0),
                            scores=scores, geometry=geometry)
    assert kept.shadows == 0 and kept.track.max() == 2



def test_a_shadow_needs_boxes_that_overlap():
    """IoU 0 would take every track on a frame another track holds for a shadow: the config refuses it."""
    with pytest.raises(ConfigError, match=r"shadow_iou"):
        config_from_dict({"tracking": {"shadow_iou": 0.0}})
    assert config_from_dict({"tracking": {"shadow_iou": 0.01}}).tracking.shadow_iou == 0.01
