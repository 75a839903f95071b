"""tasks.dataset.symmetry_turn: a symmetric model's pose turned to the turn its clicks were made
on reprojects them exactly, and stays the same model in the same place (known answers)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cadestate.geometry import intrinsics_matrix, look_at, matrix_to_quaternion, project
from tasks.dataset.objects import DatasetFrame, DatasetObject, Pose
from tasks.dataset.symmetry_turn import turn_to_clicks, turned, y_rotation

SIZE = (240, 320)  # height, width


def frames() -> dict[int, DatasetFrame]:
    K = intrinsics_matrix(np.array([0.8, 0.8 * 320 / 240, 0.5, 0.5]), 320, 240)
    out = {}
    for ts, eye in ((0, [3.0, 1.6, 4.0]), (100, [-2.5, 1.5, 4.5]), (200, [0.5, 2.0, 5.0])):
        R, t = look_at(np.array(eye), np.array([0.0, 0.5, 0.0]))
        out[ts] = DatasetFrame(ts, K, R, t, "", False)
    return out


def posed(symmetry: int, mirrored: bool, scale=(1.3, 0.8, 0.6), clicked_turn: float = 0.0) -> DatasetObject:
    """An object whose clicks were made on the model turned by ``clicked_turn`` (what the solver may keep)."""
    rng = np.random.default_rng(symmetry + 10 * mirrored)
    q = matrix_to_quaternion(y_rotation(0.7) @ np.array([[1, 0, 0], [0, np.cos(0.05), -np.sin(0.05)], [0, np.sin(0.05), np.cos(0.05)]]))
    pose = Pose((0.2, 0.4, -0.3), tuple(q), scale, mirrored)
    M = pose.matrix() @ np.block([[y_rotation(clicked_turn), np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]])
    clicks = {}
    for ts, f in frames().items():
        xyz = rng.uniform(-0.5, 0.5, (6, 3))
        uv, _ = project(f.K, f.R, f.t, xyz @ M[:3, :3].T + M[:3, 3])
        clicks[ts] = tuple((tuple(p / [SIZE[1], SIZE[0]]), tuple(x)) for p, x in zip(uv, xyz))
    return DatasetObject(1, True, "table", "04379243", {}, mirrored, "m", pose, clicks, symmetry=symmetry)


def reprojection_px(o: DatasetObject) -> float:
    M = o.pose.matrix()
    worst = 0.0
    for ts, f in frames().items():
        xy = np.array([p for p, _ in o.correspondences[ts]]) * [SIZE[1], SIZE[0]]
        uv, _ = project(f.K, f.R, f.t, np.array([x for _, x in o.correspondences[ts]]) @ M[:3, :3].T + M[:3, 3])
        worst = max(worst, float(np.abs(uv - xy).max()))
    return worst


@pytest.mark.parametrize("symmetry, turn", [(2, np.pi), (4, np.pi / 2), (4, 3 * np.pi / 2), (4, np.pi)])
@pytest.mark.parametrize("mirrored", [False, True])
def test_the_clicked_turn_is_found_and_reprojects_exactly(symmetry, turn, mirrored):
    o = posed(symmetry, mirrored, clicked_turn=turn)
    assert reprojection_px(o) > 5
    folded = turn_to_clicks(o, frames(), SIZE)
    assert reprojection_px(folded) < 1e-6
    expected = o.pose.matrix() @ np.block([[y_rotation(turn), np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]])
    np.testing.assert_allclose(folded.pose.matrix(), expected, atol=1e-9)  # the same shape in the same place
    assert folded.pose.translation == o.pose.translation and folded.pose.is_mirrored == mirrored


def test_a_round_model_turns_by_any_degree_when_its_x_and_z_scales_agree():
    o = posed(36, False, scale=(0.9, 0.7, 0.9), clicked_turn=np.radians(37))
    assert reprojection_px(turn_to_clicks(o, frames(), SIZE)) < 1e-6
    uneven = posed(36, False, scale=(0.9, 0.7, 0.5), clicked_turn=np.radians(37))
    assert turn_to_clicks(uneven, frames(), SIZE).pose.rotation in (uneven.pose.rotation, turned(uneven.pose, np.pi).rotation)


def test_a_round_model_posed_exactly_is_not_turned_by_its_clicks_noise():
    """A round model posed exactly, clicked with 1.5 px of noise: the degree whose reprojection the
    noise favoured was taken, and every key-frame's 3D points turned 8.7 mm off what was clicked."""
    o = posed(36, False, scale=(0.9, 0.7, 0.9))
    rng = np.random.default_rng(5)
    noisy = {ts: tuple(((x + rng.normal(0, 1.5) / SIZE[1], y + rng.normal(0, 1.5) / SIZE[0]), xyz) for (x, y), xyz in pairs)
             for ts, pairs in o.correspondences.items()}
    o = dataclasses.replace(o, correspondences=noisy)
    assert turn_to_clicks(o, frames(), SIZE) is o


def test_clicks_that_fit_already_and_unsymmetric_models_keep_their_pose():
    o = posed(2, True)
    assert turn_to_clicks(o, frames(), SIZE) is o
    one = posed(1, False, clicked_turn=np.pi)
    assert turn_to_clicks(one, frames(), SIZE) is one


@pytest.mark.parametrize("mirrored", [False, True])
def test_key_frames_clicked_on_different_turns_all_reproject_through_the_one_pose(mirrored):
    """The solver matches each key-frame to its own turn: a 4-way table clicked on turn 0 in one
    key-frame and on 90 and 270 degrees in the others. The exported pose is one turn; the other
    key-frames' 3D points are turned to the same points of the symmetric model, so every click
    reprojects, and the points stay where they were up to a symmetric turn."""
    o = posed(4, mirrored)
    per_frame = {0: 0.0, 100: np.pi / 2, 200: 3 * np.pi / 2}
    M = o.pose.matrix()
    clicks = {}
    for ts, f in frames().items():
        turn = M @ np.block([[y_rotation(per_frame[ts]), np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]])
        xyz = np.array([x for _, x in o.correspondences[ts]])
        uv, _ = project(f.K, f.R, f.t, xyz @ turn[:3, :3].T + turn[:3, 3])
        clicks[ts] = tuple((tuple(p / [SIZE[1], SIZE[0]]), tuple(x)) for p, x in zip(uv, xyz))
    o = dataclasses.replace(o, correspondences=clicks)
    assert reprojection_px(o) > 5
    folded = turn_to_clicks(o, frames(), SIZE)
    assert reprojection_px(folded) < 1e-6
    for ts in clicks:  # each point moved by a quarter turn about +Y at most: the same point of the model
        before = np.array([x for _, x in clicks[ts]])
        after = np.array([x for _, x in folded.correspondences[ts]])
        assert any(np.allclose(after, before @ y_rotation(k * np.pi / 2).T, atol=1e-12) for k in range(4)), ts
        assert [xy for xy, _ in folded.correspondences[ts]] == [xy for xy, _ in clicks[ts]]  # the clicks themselves kept
