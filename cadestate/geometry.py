"""Coordinate frames and camera conventions used everywhere in the pipeline.

Units are metres. Every function names the frame it maps from and to.

World frame
    Whatever frame the clip's camera file uses (RealEstate10K: the SfM frame of the clip, with an
    arbitrary scale per clip). The CAD canonical frame is +Y up; the synthetic benchmark builds
    worlds with +Y up, so "world up" defaults to +Y (see ``WORLD_UP``).

Camera frame (OpenCV)
    x right, y down, z forward (the viewing direction). A point with z > 0 is in front of the camera.

Image frame
    Pixels, origin at the top-left corner of the top-left pixel, x right, y down. A pixel's
    centre is at (i + 0.5, j + 0.5). Normalised image coordinates divide x by the width and y by
    the height, so (0, 0) is the top-left corner and (1, 1) the bottom-right one.

Extrinsics
    ``R, t`` are **world->camera**: ``X_cam = R @ X_world + t`` (RealEstate10K's [R|t]).
    The camera->world transform is ``R.T, c`` with the camera centre ``c = -R.T @ t``.

Quaternions
    ``(w, x, y, z)`` (the CAD-Estate JSON order), unit norm, Hamilton convention.
"""

from __future__ import annotations

import numpy as np

WORLD_UP = np.array([0.0, 1.0, 0.0])
"""World up axis: +Y, as in ShapeNet / Scan2CAD / CAD-Estate."""


def intrinsics_matrix(normalised: np.ndarray, width: int, height: int) -> np.ndarray:
    """Pixel intrinsics from RealEstate10K normalised intrinsics.

    Args:
        normalised: float[..., 4] ``(fx, fy, cx, cy)``, fx and cx divided by the image width,
            fy and cy divided by the image height.
        width, height: image size in pixels.
    Returns:
        float64[..., 3, 3] ``K = [[W*fx, 0, W*cx], [0, H*fy, H*cy], [0, 0, 1]]``.
    """
    n = np.asarray(normalised, dtype=np.float64)
    K = np.zeros(n.shape[:-1] + (3, 3))
    K[..., 0, 0] = n[..., 0] * width
    K[..., 1, 1] = n[..., 1] * height
    K[..., 0, 2] = n[..., 2] * width
    K[..., 1, 2] = n[..., 3] * height
    K[..., 2, 2] = 1.0
    return K


def pixel_intrinsics_matrix(pixels: np.ndarray) -> np.ndarray:
    """Pixel intrinsics ``(fx, fy, cx, cy)`` float[..., 4] (as the official CAD-Estate ``frames.json``
    stores them) to ``K`` float64[..., 3, 3] = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]."""
    return intrinsics_matrix(pixels, 1, 1)


def pixel_intrinsics(K: np.ndarray) -> np.ndarray:
    """Inverse of :func:`pixel_intrinsics_matrix`: float[..., 3, 3] -> float64[..., 4] (fx, fy, cx, cy) in pixels."""
    return normalised_intrinsics(K, 1, 1)


def normalised_intrinsics(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """Inverse of :func:`intrinsics_matrix`: float[..., 3, 3] -> float[..., 4] (fx, fy, cx, cy)."""
    K = np.asarray(K, dtype=np.float64)
    return np.stack(
        [K[..., 0, 0] / width, K[..., 1, 1] / height, K[..., 0, 2] / width, K[..., 1, 2] / height],
        axis=-1,
    )


def hfov_intrinsics(hfov_deg: float, width: int, height: int) -> np.ndarray:
    """float64[4] normalised (fx, fy, cx, cy) of a camera with horizontal field of view ``hfov_deg``,
    square pixels and the principal point at the image centre."""
    fx = 0.5 / np.tan(np.radians(hfov_deg) / 2)
    return np.array([fx, fx * width / height, 0.5, 0.5])


def camera_to_world(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World->camera ``(R, t)`` to camera->world ``(R_cw, c)``.

    Args:
        R: float[..., 3, 3] world->camera rotation.
        t: float[..., 3] world->camera translation.
    Returns:
        ``R_cw`` float[..., 3, 3] (= R^T) and the camera centre ``c`` float[..., 3] in world
        coordinates, so that ``X_world = R_cw @ X_cam + c``.
    """
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    R_cw = np.swapaxes(R, -1, -2)
    c = -np.einsum("...ij,...j->...i", R_cw, t)
    return R_cw, c


def world_to_camera(R_cw: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera->world ``(R_cw, c)`` back to world->camera ``(R, t)``; inverse of :func:`camera_to_world`."""
    R = np.swapaxes(np.asarray(R_cw, dtype=np.float64), -1, -2)
    t = -np.einsum("...ij,...j->...i", R, np.asarray(c, dtype=np.float64))
    return R, t


def project(K: np.ndarray, R: np.ndarray, t: np.ndarray, X_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project world points into an image.

    Args:
        K: float[3, 3] pixel intrinsics.
        R, t: world->camera rotation float[3, 3] and translation float[3].
        X_world: float[N, 3] points in world coordinates.
    Returns:
        ``uv`` float[N, 2] pixel coordinates (image frame above) and ``depth`` float[N], the
        camera-frame z (positive in front of the camera).
    """
    X_cam = np.asarray(X_world, dtype=np.float64) @ np.asarray(R).T + np.asarray(t)
    depth = X_cam[:, 2]
    uvw = X_cam @ np.asarray(K).T
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = uvw[:, :2] / uvw[:, 2:3]
    return uv, depth


def rotation_error(R: np.ndarray) -> float:
    """How far float[3, 3] is from a proper rotation: max(|R R^T - I|, |det R - 1|)."""
    R = np.asarray(R, dtype=np.float64)
    return float(max(np.abs(R @ R.T - np.eye(3)).max(), abs(np.linalg.det(R) - 1.0)))


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """Unit quaternion float[..., 4] (w, x, y, z) to rotation matrix float[..., 3, 3]."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def matrix_to_quaternion(R: np.ndarray) -> np.ndarray:
    """Rotation matrix float[3, 3] to unit quaternion float[4] (w, x, y, z) with w >= 0."""
    R = np.asarray(R, dtype=np.float64)
    # Largest-pivot method (Shepperd): numerically stable for every rotation.
    m = np.array([np.trace(R), R[0, 0], R[1, 1], R[2, 2]])
    i = int(np.argmax(m))
    if i == 0:
        s = 2.0 * np.sqrt(1.0 + m[0])
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif i == 1:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif i == 2:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = WORLD_UP) -> tuple[np.ndarray, np.ndarray]:
    """World->camera ``(R, t)`` of an OpenCV camera at ``eye`` looking at ``target``.

    The camera's image "up" (-y_cam) is as close to the world ``up`` as the viewing direction allows;
    looking straight along ``up`` (or against it), it is the first world axis (x, y, z) least along
    the view instead (+X for +Y up), not NaN.
    """
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(-np.asarray(up, dtype=np.float64), z)  # right = down x forward
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(-np.eye(3)[np.argmin(np.abs(z))], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # down
    R = np.stack([x, y, z])  # rows: camera axes in world coordinates
    return R, -R @ eye
