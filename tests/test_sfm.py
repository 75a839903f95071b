"""SfM cameras (tasks/video/sfm.py) and the ``cameras`` stage: interpolation, clear failures, real runs.

The real runs need the Sweet Home 3D furniture (``make cad-library``): a benchmark walkthrough of
the session's small library (``small_cad_library`` in conftest.py).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bench.sfm_eval import align, camera_errors, umeyama
from bench.walkthrough import WalkthroughSpec, generate_clip
from cadestate.config import CamerasConfig
from cadestate.geometry import camera_to_world
from tasks.video.camera_file import parse_camera_file
from tasks.video.sfm import SfmError, _interpolate, check_registered, run_sfm, sample_frames
from tasks.video.sfm_focal import best_focal, focal_hypotheses


def test_interpolation_fills_gaps_and_holds_the_ends():
    times = np.arange(6) * 100
    registered = np.array([False, True, False, False, True, False])
    R = np.tile(np.eye(3), (6, 1, 1))
    R[4] = Rotation.from_euler("y", 30, degrees=True).as_matrix()
    c = np.zeros((6, 3))
    c[4] = [3.0, 0, 0]
    R_all, c_all = _interpolate(times, registered, R, c)
    np.testing.assert_allclose(c_all[:, 0], [0, 0, 1, 2, 3, 3])
    angles = Rotation.from_matrix(R_all).as_euler("xyz", degrees=True)[:, 1]
    np.testing.assert_allclose(angles, [0, 0, 10, 20, 30, 30], atol=1e-9)


def test_similarity_alignment_recovers_a_turned_scaled_world():
    rng = np.random.default_rng(0)
    R_true = Rotation.random(20, random_state=1).as_matrix()
    c_true = np.cumsum(rng.normal(size=(20, 3)) * 0.1, axis=0)
    A = Rotation.random(random_state=2).as_matrix()
    R_sfm, c_sfm = R_true @ A, 0.25 * (c_true - 1.0) @ A  # X_sfm = 0.25 A^T (X_true - 1)
    errors = camera_errors(R_true, c_true, R_sfm, c_sfm)
    assert errors.rotation_deg.max() < 1e-4 and errors.trajectory_pct.max() < 1e-6
    assert align(R_true, c_true, R_sfm, c_sfm).scale == pytest.approx(4.0)
    assert umeyama(c_sfm, c_true).scale == pytest.approx(4.0)


def test_too_few_registered_frames_and_dropped_models_are_named():
    registered = np.array([True] * 7 + [False] * 3)
    with pytest.raises(SfmError, match=r"v.mp4: SfM registered 7 of 10 sampled frames \(70%\), fewer than \[cameras\] "
                                       r"min_registered_fraction = 0.8; 2 other disconnected model\(s\) of 2, 1 frames dropped"):
        check_registered("v.mp4", registered, CamerasConfig(), [7, 2, 1])
    assert check_registered("v.mp4", registered, CamerasConfig(min_registered_fraction=0.7), [7]) == ""


def test_focal_hypotheses_span_the_field_of_view_range_evenly_in_log_focal():
    f = focal_hypotheses(640, CamerasConfig(fov_min_deg=40.0, fov_max_deg=100.0, fov_hypotheses=6))
    fov = np.degrees(2 * np.arctan(320 / f))
    np.testing.assert_allclose(fov[[0, -1]], [100.0, 40.0])
    np.testing.assert_allclose(np.diff(np.log(f)), np.log(f[1] / f[0]))


def test_best_focal_is_the_adjusted_focal_of_the_lowest_error_clipped_to_the_range():
    f = np.geomspace(300.0, 900.0, 6)
    adjusted = np.array([250.0, 480.0, 510.0, np.nan, 800.0, 1000.0])
    errors = np.array([0.9, 0.7, 0.6, np.inf, 0.8, 0.5])
    assert best_focal(f, adjusted, errors) == 900.0  # the lowest error's adjusted focal, clipped
    errors[5] = np.inf
    assert best_focal(f, adjusted, errors) == 510.0
    assert best_focal(f, adjusted, np.full(6, np.inf)) == pytest.approx(np.sqrt(300.0 * 900.0))  # none: the middle


def test_too_few_frames_is_a_clear_error(tmp_path, small_clip):
    with pytest.raises(SfmError, match=r"small.mp4: 1 frame\(s\) sampled at 0.1 fps; SfM needs at least 2"):
        sample_frames(small_clip.video_path, 0.1, tmp_path)


SPEC = WalkthroughSpec(width=320, height=180, num_video_frames=60, sample_every=2, alone_scale=0.5)
"""A 2-second benchmark walkthrough (textured room, real CAD furniture): 30 camera lines at 15 fps."""
SEED = 11


@pytest.fixture(scope="module")
def walkthrough(small_cad_library, tmp_path_factory):
    """A benchmark walkthrough of the session's small Sweet Home 3D library (tests/conftest.py)."""
    wh, rows = small_cad_library
    return generate_clip(tmp_path_factory.mktemp("sfm_walk"), "walk", SEED, rows, wh.root, SPEC)


@pytest.mark.slow
def test_sfm_on_a_rendered_walkthrough(walkthrough):
    """A real pycolmap run on a textured benchmark walkthrough, sampled at its camera lines'
    15 fps: every frame gets a camera, nearly all registered, cameras close to the true ones
    after a similarity alignment (issue 20: >= 95 %, median rotation error < 1 degree), and the
    same cameras on a second run (seeded RANSAC and mapper, single-threaded extraction)."""
    result = run_sfm(walkthrough.video_path, CamerasConfig(sample_fps=15.0))
    truth = parse_camera_file(walkthrough.cameras_path)
    assert result.track.timestamps_us.tolist() == truth.timestamps_us.tolist()  # the same sampled frames
    assert result.registered_fraction >= 0.95, result.models
    errors = camera_errors(truth.R, camera_to_world(truth.R, truth.t)[1], result.track.R,
                           camera_to_world(result.track.R, result.track.t)[1])
    summary = errors.summary()
    assert summary["median_rotation_error_deg"] < 1.0, summary
    assert summary["median_trajectory_error_pct"] < 5.0, summary  # measured 2.25 % (focal estimated, 320 x 180)
    again = run_sfm(walkthrough.video_path, CamerasConfig(sample_fps=15.0))
    np.testing.assert_array_equal(again.track.world_to_camera, result.track.world_to_camera)


@pytest.mark.slow
def test_sfm_on_a_textureless_clip_is_a_clear_error(small_clip):
    """The demo clip (flat-coloured boxes, almost blank walls: ~100 SIFT features a frame) is no
    input for SfM: a one-line SfmError naming the video and how many frames were registered."""
    with pytest.raises(SfmError, match=r"small.mp4: SfM (registered \d+ of 30 sampled frames \(\d+%\), fewer than "
                                       r"\[cameras\] min_registered_fraction|found no model in 30 sampled frames)"):
        run_sfm(small_clip.video_path, CamerasConfig(sample_fps=10.0))
