"""Accuracy of SfM cameras against true ones: a similarity alignment, rotation and trajectory errors.

Both inputs are world->camera rotations float[N, 3, 3] and camera centres float[N, 3] of the same
N frames (OpenCV axes), each in its own world. The SfM world is mapped onto the true one by a
similarity ``X_true = s A X_sfm + b``: ``A`` the rotation that best maps the SfM camera rotations
onto the true ones (chordal mean of ``R_sfm^T R_true``, transposed: walkthrough paths are nearly
straight, so the centres alone leave the rotation about the path free), then ``s, b`` by least
squares on the centres (:func:`umeyama` aligns centres alone). Then
- rotation error: the angle of ``R_true^T R_sfm A^T`` per frame (degrees);
- trajectory error: distance between the aligned SfM centre and the true one, as a percentage of
  the true path length (sum of the distances between consecutive true centres).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Similarity:
    """``X_true = scale * rotation @ X_sfm + translation`` (rotation float[3, 3], translation float[3])."""

    scale: float
    rotation: np.ndarray
    translation: np.ndarray

    def apply(self, X: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(X) @ self.rotation.T + self.translation


def umeyama(src: np.ndarray, dst: np.ndarray) -> Similarity:
    """The similarity minimising sum |dst - (s A src + b)|^2 over points float[N, 3] (N >= 3, not collinear)."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(xd.T @ xs / len(src))
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    A = U @ D @ Vt
    var = (xs ** 2).sum() / len(src)
    s = float(np.trace(np.diag(S) @ D) / var) if var > 0 else 1.0
    return Similarity(s, A, mu_d - s * A @ mu_s)


@dataclass(frozen=True)
class CameraErrors:
    """Per-frame rotation errors (degrees) and centre errors (% of the true path length)."""

    rotation_deg: np.ndarray
    trajectory_pct: np.ndarray
    path_length: float

    def summary(self) -> dict:
        return {"median_rotation_error_deg": round(float(np.median(self.rotation_deg)), 3),
                "max_rotation_error_deg": round(float(self.rotation_deg.max()), 3),
                "median_trajectory_error_pct": round(float(np.median(self.trajectory_pct)), 3),
                "rms_trajectory_error_pct": round(float(np.sqrt((self.trajectory_pct ** 2).mean())), 3)}


def _project_rotation(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def align(R_true: np.ndarray, c_true: np.ndarray, R_sfm: np.ndarray, c_sfm: np.ndarray) -> Similarity:
    """The similarity of the module docstring: rotation from the cameras' rotations, scale and
    translation from their centres."""
    A = _project_rotation(np.einsum("nji,njk->ik", R_true, R_sfm))  # R_true ~ R_sfm A^T, so A ~ mean R_true^T R_sfm
    src = np.asarray(c_sfm) @ A.T
    xs, xd = src - src.mean(0), np.asarray(c_true) - np.mean(c_true, 0)
    s = float((xs * xd).sum() / max((xs ** 2).sum(), 1e-12))
    return Similarity(s, A, np.mean(c_true, 0) - s * src.mean(0))


def camera_errors(R_true: np.ndarray, c_true: np.ndarray, R_sfm: np.ndarray, c_sfm: np.ndarray) -> CameraErrors:
    """Errors of SfM cameras against true ones after the similarity alignment (module docstring)."""
    sim = align(R_true, c_true, R_sfm, c_sfm)
    aligned = sim.apply(c_sfm)
    path = float(np.linalg.norm(np.diff(c_true, axis=0), axis=1).sum())
    rel = np.einsum("nji,njk->nik", R_true, R_sfm @ sim.rotation.T)  # R_true^T (R_sfm A^T)
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)
    return CameraErrors(np.degrees(np.arccos(cos)), 100 * np.linalg.norm(aligned - c_true, axis=1) / max(path, 1e-12), path)
