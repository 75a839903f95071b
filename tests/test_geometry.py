"""Coordinate-frame conventions of cadestate.geometry, checked by round trips and known answers."""

import numpy as np
import pytest

from cadestate.geometry import (
    camera_to_world, hfov_intrinsics, intrinsics_matrix, look_at, matrix_to_quaternion, normalised_intrinsics,
    project, quaternion_to_matrix, rotation_error, world_to_camera,
)

rng = np.random.default_rng(0)


def random_rotations(n):
    q = rng.normal(size=(n, 4))
    return quaternion_to_matrix(q / np.linalg.norm(q, axis=1, keepdims=True))


def test_intrinsics_round_trip_and_known_values():
    n = np.array([0.8, 1.4, 0.5, 0.45])
    K = intrinsics_matrix(n, 640, 360)
    assert K[0, 0] == 0.8 * 640 and K[1, 1] == 1.4 * 360 and K[0, 2] == 320 and K[1, 2] == 0.45 * 360
    np.testing.assert_allclose(normalised_intrinsics(K, 640, 360), n)


def test_hfov_intrinsics():
    # 90° horizontal field of view: the image half-width equals the focal length.
    np.testing.assert_allclose(hfov_intrinsics(90.0, 640, 360), [0.5, 0.5 * 640 / 360, 0.5, 0.5])
    K = intrinsics_matrix(hfov_intrinsics(65.0, 640, 360), 640, 360)
    assert K[0, 0] == pytest.approx(K[1, 1])  # square pixels
    assert np.degrees(2 * np.arctan(320 / K[0, 0])) == pytest.approx(65.0)


def test_camera_to_world_round_trip_and_centre_projects_behind():
    R = random_rotations(5)
    t = rng.normal(size=(5, 3))
    R_cw, c = camera_to_world(R, t)
    R2, t2 = world_to_camera(R_cw, c)
    np.testing.assert_allclose(R2, R)
    np.testing.assert_allclose(t2, t)
    # The camera centre maps to the camera-frame origin.
    np.testing.assert_allclose(np.einsum("nij,nj->ni", R, c) + t, 0, atol=1e-12)


def test_quaternion_round_trip_and_convention():
    for R in random_rotations(50):
        q = matrix_to_quaternion(R)
        assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        np.testing.assert_allclose(quaternion_to_matrix(q), R, atol=1e-12)
    # (w, x, y, z) order: 90° about +Y maps +Z to +X (right-handed).
    q = np.array([np.cos(np.pi / 4), 0, np.sin(np.pi / 4), 0])
    np.testing.assert_allclose(quaternion_to_matrix(q) @ [0, 0, 1], [1, 0, 0], atol=1e-12)
    # 180° rotations (w = 0) are handled by the pivoting branch.
    for axis in np.eye(3):
        R = quaternion_to_matrix(np.r_[0.0, axis])
        np.testing.assert_allclose(quaternion_to_matrix(matrix_to_quaternion(R)), R, atol=1e-12)


def test_look_at_is_opencv_with_world_up():
    R, t = look_at([0, 1.5, 0], [0, 1.5, -4])  # looking down -Z, +Y up
    assert rotation_error(R) < 1e-12
    K = intrinsics_matrix([0.8, 1.4, 0.5, 0.5], 640, 360)
    uv, depth = project(K, R, t, np.array([[0, 1.5, -4], [1, 1.5, -4], [0, 2.5, -4], [0, 1.5, 4]]))
    np.testing.assert_allclose(uv[0], [320, 180])  # target at the principal point
    assert uv[1, 0] > 320  # world +X is image right
    assert uv[2, 1] < 180  # world up is image up (y down)
    assert depth[0] == pytest.approx(4) and depth[3] < 0  # behind the camera: negative depth


def test_project_matches_formula():
    R = random_rotations(1)[0]
    t = np.array([0.1, -0.2, 3.0])
    K = np.array([[500.0, 0, 300], [0, 480, 200], [0, 0, 1]])
    X = rng.normal(size=(10, 3)) * 0.5
    uv, depth = project(K, R, t, X)
    Xc = X @ R.T + t
    np.testing.assert_allclose(uv[:, 0], 500 * Xc[:, 0] / Xc[:, 2] + 300)
    np.testing.assert_allclose(uv[:, 1], 480 * Xc[:, 1] / Xc[:, 2] + 200)
    np.testing.assert_allclose(depth, Xc[:, 2])


def test_rotation_error_flags_reflections_and_scaling():
    assert rotation_error(np.eye(3)) == 0
    assert rotation_error(np.diag([1.0, 1, -1])) == pytest.approx(2)
    assert rotation_error(1.01 * np.eye(3)) > 0.02


@pytest.mark.parametrize("target", [(0.0, -3.0, 0.0), (0.0, 3.0, 0.0)])
def test_look_at_straight_down_or_up_is_a_rotation_facing_the_target(target):
    """Looking along the world's up (a camera over a table) gives a proper rotation whose image up
    is +X, where the cross product with up vanished and gave NaN."""
    eye = np.array([1.0, 1.0, 1.0])
    R, t = look_at(eye, eye + np.array(target))
    assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
    assert np.allclose(R[2], np.sign(target[1]) * np.array([0.0, 1.0, 0.0]))  # forward: along the view
    assert np.allclose(-R[1], [1.0, 0.0, 0.0]) and np.allclose(R @ eye + t, 0.0)
