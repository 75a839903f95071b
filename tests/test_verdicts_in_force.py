"""How far an overlay moves between two poses (tasks/human/verdicts_in_force.py), on known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cadestate.geometry import quaternion_to_matrix
from tasks.human.verdicts_in_force import CORNERS, FrameCamera, box_corners, overlay_shift_px

F = 500.0
K = np.array([[F, 0, 320], [0, F, 180], [0, 0, 1]])
AHEAD = FrameCamera(K, np.eye(3), np.zeros(3))
"""A camera at the origin looking along +Z (OpenCV: x right, y down)."""
UNIT = (1.0, 1.0, 1.0)


def _pose(translation=(0.0, 0.0, 5.0), rotation=(1.0, 0.0, 0.0, 0.0), scale=(1.0, 1.0, 1.0), mirrored=False) -> dict:
    return {"translation": list(translation), "rotation": list(rotation), "scale": list(scale), "is_mirrored": mirrored}


def test_box_corners_are_the_posed_box_corners():
    yaw = math.radians(30)
    pose = _pose((1.0, 2.0, 3.0), (math.cos(yaw / 2), 0.0, math.sin(yaw / 2), 0.0), (2.0, 1.0, 0.5))
    extent = (0.4, 1.0, 2.0)
    rotation = quaternion_to_matrix(np.array(pose["rotation"]))
    expected = np.array(pose["translation"]) + (CORNERS * extent * pose["scale"]) @ rotation.T
    np.testing.assert_allclose(box_corners(extent, pose), expected, atol=1e-12)


def test_a_sideways_move_shifts_the_nearest_corners_most():
    # 1 cm to the right: a corner at depth z moves F * 0.01 / z px; the near face is at z = 4.5
    shift = overlay_shift_px(UNIT, _pose(), _pose((0.01, 0.0, 5.0)), [AHEAD])
    assert shift == pytest.approx(F * 0.01 / 4.5, rel=1e-9)


def test_a_move_along_one_cameras_view_ray_shows_on_another_camera():
    # twice as far and twice as large, about the first camera's centre: every corner stays on its
    # ray, so that camera sees the same overlay (the depth/scale ambiguity); a camera 1 m to the
    # left sees the box centre move from x = 1 / 5 to 1 / 10 of the focal length, and its corners further
    far = _pose((0.0, 0.0, 10.0), scale=(2.0, 2.0, 2.0))
    assert overlay_shift_px(UNIT, _pose(), far, [AHEAD]) == pytest.approx(0.0, abs=1e-9)
    left = FrameCamera(K, np.eye(3), np.array([1.0, 0.0, 0.0]))
    assert overlay_shift_px(UNIT, _pose(), far, [left]) > F * (1 / 5 - 1 / 10)


def test_the_largest_shift_over_the_cameras_counts():
    # a camera 4 m nearer: the near face is 0.5 m away, the same 1 cm move shifts it F * 0.01 / 0.5 px there
    near = FrameCamera(K, np.eye(3), np.array([0.0, 0.0, -4.0]))
    assert overlay_shift_px(UNIT, _pose(), _pose((0.01, 0.0, 5.0)), [AHEAD, near]) == pytest.approx(F * 0.01 / 0.5, rel=1e-9)


def test_no_move_no_shift_and_a_corner_crossing_the_near_plane_is_not_a_shift():
    assert overlay_shift_px(UNIT, _pose(), _pose(), [AHEAD]) == 0.0
    assert overlay_shift_px(UNIT, _pose(), _pose((0.01, 0.0, 5.0)), []) == 0.0
    assert overlay_shift_px(UNIT, _pose(), _pose((0.0, 0.0, 0.3)), [AHEAD]) == math.inf


def test_corners_behind_the_camera_under_both_poses_are_left_out():
    # a box 4 m deep from z = -1 to 3 (a sofa passed close by): its near face is behind the camera,
    # not drawn; 1 cm to the right moves the far face (z = 3) by F * 0.01 / 3 px
    deep = (1.0, 1.0, 4.0)
    shift = overlay_shift_px(deep, _pose((0.0, 0.0, 1.0)), _pose((0.01, 0.0, 1.0)), [AHEAD])
    assert shift == pytest.approx(F * 0.01 / 3, rel=1e-9)
    assert overlay_shift_px(deep, _pose((0.0, 0.0, 1.0)), _pose((0.0, 0.0, 3.0)), [AHEAD]) == math.inf, "now all in front"


def test_corners_are_compared_one_to_one():
    # mirroring flips the CAD x axis: a box's corner set is the same, but each corner takes its
    # twin's place 1 m away (F * 1 / 4.5 px on the near face); the shift is of corners, not of the silhouette
    assert overlay_shift_px(UNIT, _pose(), _pose(mirrored=True), [AHEAD]) == pytest.approx(F / 4.5, rel=1e-9)


def test_a_verdict_goes_to_the_one_pose_it_matches_best():
    import datetime as dt
    import json

    import pyarrow as pa

    from tasks.human.verdicts_in_force import held_verdicts

    at = dt.datetime(2026, 12, 1, tzinfo=dt.timezone.utc)
    item = {"track_id": 0, "cad_id": "lib.a", "pose": _pose(), "keyframes": [{"timestamp_us": 10}]}
    tasks = pa.Table.from_pylist([{"task_id": "old", "kind": "verification", "created_at": at, "document": json.dumps({"items": [item]})}])
    answers = pa.Table.from_pylist([{"task_id": "old", "track_id": 0, "accepted": True, "comment": "", "same_as_track": None,
                                     "ingested_at": at + dt.timedelta(hours=1)}])
    pose = lambda t, x=0.0: {"track_id": t, "cad_id": "lib.a", **_pose((x, 0.0, 5.0)), "keyframe_timestamps_us": [10]}  # noqa: E731
    held = lambda poses: set(held_verdicts("new", poses, answers, tasks, {"lib.a": UNIT}, {10: AHEAD}, 2.0))  # noqa: E731
    assert held([pose(4), pose(5)]) == {4}, "a pose and its duplicate: one takes the verdict"
    assert held([pose(4, 0.001), pose(5)]) == {5}, "the identical overlay, not the one moved by 0.1 px"
    assert held([pose(4, 0.001)]) == {4}
    assert held([pose(4, 0.001), pose(0, 0.002)]) == {4}, "the smaller shift before the same id"
    assert held([pose(4, 0.05)]) == set(), "moved by 5.6 px"


def test_a_half_turn_with_the_other_quaternion_sign_is_the_same_pose():
    """q and -q are one rotation: a pose solved again with a half turn's other sign (w = 0) is the
    identical overlay, which counts where overlays are not compared (no model size, or
    [verification] carry_max_px 0): its verdict was asked again."""
    import datetime as dt
    import json

    import pyarrow as pa

    from tasks.human.verdicts_in_force import held_verdicts

    at = dt.datetime(2026, 12, 1, tzinfo=dt.timezone.utc)
    turn = (0.0, 0.0, 1.0, 0.0)  # half a turn about +Y
    item = {"track_id": 0, "cad_id": "lib.a", "pose": _pose(rotation=turn), "keyframes": [{"timestamp_us": 10}]}
    tasks = pa.Table.from_pylist([{"task_id": "old", "kind": "verification", "created_at": at, "document": json.dumps({"items": [item]})}])
    answers = pa.Table.from_pylist([{"task_id": "old", "track_id": 0, "accepted": True, "comment": "", "same_as_track": None,
                                     "ingested_at": at + dt.timedelta(hours=1)}])
    for q, kept in ((turn, {0}), ((0.0, 0.0, -1.0, 0.0), {0}), ((0.0, 1.0, 0.0, 0.0), set())):
        pose = {"track_id": 0, "cad_id": "lib.a", **_pose(rotation=q), "keyframe_timestamps_us": [10]}
        for extents, max_px in (({}, 2.0), ({"lib.a": UNIT}, 0.0)):
            assert set(held_verdicts("new", [pose], answers, tasks, extents, {10: AHEAD}, max_px)) == kept, (q, extents, max_px)
