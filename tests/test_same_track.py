"""The overlap rule of tasks.human.same_track on boxes and task versions (the warehouse case: tests/test_resume.py)."""

import datetime as dt

import pytest

from tasks.human.same_track import box_iou, seen_then


def test_box_iou_of_ymin_xmin_ymax_xmax_boxes():
    assert box_iou((0, 0, 1, 1), (0, 0, 1, 1)) == 1.0
    assert box_iou((0, 0, 0.5, 1), (0.25, 0, 0.75, 1)) == pytest.approx(1 / 3)  # half of each overlaps
    assert box_iou((0, 0, 0.2, 0.2), (0.5, 0.5, 0.7, 0.7)) == 0.0
    assert box_iou((0.3, 0.3, 0.3, 0.3), (0.3, 0.3, 0.3, 0.3)) == 0.0  # empty boxes overlap nothing


def test_an_answer_is_checked_against_the_task_version_it_saw():
    t = [dt.datetime(2026, 12, 1, h, tzinfo=dt.timezone.utc) for h in range(4)]
    versions = [(t[0], {1: (0, 0, 1, 1)}), (t[2], {1: (0, 0, 0.5, 0.5)})]
    assert seen_then(versions, t[1]) == {1: (0, 0, 1, 1)}  # written before the second version
    assert seen_then(versions, t[3]) == {1: (0, 0, 0.5, 0.5)}
    assert seen_then(versions, t[0] - dt.timedelta(hours=1)) == {1: (0, 0, 1, 1)}  # none before: the oldest
