"""The world's up from the vertical lines a video shows: wall corners, door and window frames,
furniture legs. It refines the estimate from the cameras (:mod:`tasks.video.world_up`).

Why: the cameras' estimate rests on how people hold phones and walk; on the benchmark's clips it
is 0.1-3.1 degrees off, and every upright object is then solved that far from upright. Straight
vertical edges are everywhere indoors, and each one says where up is.

Frames: OpenCV gives a segment's endpoints with pixel centres at integer coordinates; they are
moved by +0.5 to the intrinsics' convention (pixels, x right, y down, from the top-left corner of
the top-left pixel, as a camera file's principal point at 0.5 of the width is the image centre).
Rotations are world->camera (OpenCV axes) of the **input world** (the camera file's), so the
normals and the up found are in the input world too.

Method: a straight 3D segment and the camera centre span its *interpretation plane*, whose unit
normal ``n`` (camera frame: ``K^-1 p1 x K^-1 p2``, world: ``R^T n``) is orthogonal to the segment's
direction. For a vertical segment ``n . up = 0``. Up is the direction the most segment length
agrees with: the score ``sum_s length_s * max(0, 1 - (r_s / tol)^2)``, ``r_s = asin |n_s . u|``, is
searched over directions within :data:`SEARCH_DEG` of the cameras' estimate (coarse to fine,
:data:`SEARCH_LEVELS`), then polished by least squares with Cauchy weights (the smallest
eigenvector of ``sum_s w_s n_s n_s^T``). Other straight lines (horizontal edges, slanted chair
backs) agree with no single direction near up and barely move the peak. Too few agreeing
segments (fewer than :data:`MIN_SEGMENTS` on :data:`MIN_FRAMES` frames): no estimate, and the
cameras' stands.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

SEARCH_DEG = 10.0
"""Directions up to this far from the cameras' estimate are searched."""
SEARCH_LEVELS = ((0.5, SEARCH_DEG), (0.1, 1.0), (0.02, 0.2))
"""(grid step, radius) in degrees of each search level, each centred on the last one's best."""
MIN_SEGMENT_FRACTION = 0.05
"""Segments shorter than this fraction of the frame's longer side are not used (short ones point poorly)."""
MIN_SEGMENTS = 20
"""An estimate needs at least this many segments within the tolerance of it ..."""
MIN_FRAMES = 3
"""... on at least this many frames."""
POLISH_STEPS = 5
"""Reweighted least-squares steps after the search."""


@dataclass(frozen=True)
class SegmentNormals:
    """Line segments of a clip's sampled frames as interpretation-plane normals.

    Attributes:
      normals: float64[S, 3] unit normals, input world.
      lengths: float64[S] segment lengths, px.
      frames: int64[S] index of the sampled frame each segment is on.
    """

    normals: np.ndarray
    lengths: np.ndarray
    frames: np.ndarray


@dataclass(frozen=True)
class LineUp:
    """Up from vertical lines. ``up``: float64[3] unit, input world; ``segments``: segments within
    the tolerance of it; ``frames``: sampled frames they lie on; ``moved_deg``: its angle from the
    cameras' estimate it started from."""

    up: np.ndarray
    segments: int
    frames: int
    moved_deg: float


def frame_segment_normals(gray: np.ndarray, intrinsics_px: np.ndarray, world_to_camera_R: np.ndarray,
                          detector=None) -> tuple[np.ndarray, np.ndarray]:
    """(unit interpretation-plane normals float64[S, 3] in the world, lengths float64[S] px) of the
    line segments of one frame ``gray`` uint8[H, W]; ``intrinsics_px`` (fx, fy, cx, cy);
    ``world_to_camera_R`` float[3, 3]; ``detector``: an OpenCV line segment detector (made when None)."""
    import cv2

    detector = detector if detector is not None else cv2.createLineSegmentDetector()
    found = detector.detect(gray)[0]
    if found is None:
        return np.zeros((0, 3)), np.zeros(0)
    seg = found.reshape(-1, 4).astype(np.float64)
    lengths = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1])
    keep = lengths >= MIN_SEGMENT_FRACTION * max(gray.shape)
    seg, lengths = seg[keep], lengths[keep]
    fx, fy, cx, cy = (float(v) for v in intrinsics_px)

    def rays(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.stack([(x + 0.5 - cx) / fx, (y + 0.5 - cy) / fy, np.ones_like(x)], axis=1)

    n = np.cross(rays(seg[:, 0], seg[:, 1]), rays(seg[:, 2], seg[:, 3]))
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 0
    n = n[ok] / norm[ok, None]
    return n @ np.asarray(world_to_camera_R, dtype=np.float64), lengths[ok]  # rows: R^T n


def video_segment_normals(video: str | os.PathLike, times_us: np.ndarray, intrinsics: np.ndarray,
                          world_to_camera_R: np.ndarray) -> SegmentNormals:
    """:func:`frame_segment_normals` of the video's frames nearest ``times_us`` int[F] (video time,
    increasing); ``intrinsics`` float[F, 4] normalised (fx/W, fy/H, cx/W, cy/H, as in a camera file);
    ``world_to_camera_R`` float[F, 3, 3]."""
    import cv2

    from tasks.video.decode import decode_at

    detector = cv2.createLineSegmentDetector()
    normals, lengths, frames = [], [], []
    for i, frame in enumerate(decode_at(video, np.asarray(times_us, dtype=np.int64))):
        H, W = frame.rgb.shape[:2]
        gray = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2GRAY)
        n, length = frame_segment_normals(gray, np.asarray(intrinsics[i]) * [W, H, W, H], world_to_camera_R[i], detector)
        normals.append(n)
        lengths.append(length)
        frames.append(np.full(len(n), i, dtype=np.int64))
    if not normals:
        return SegmentNormals(np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64))
    return SegmentNormals(np.concatenate(normals), np.concatenate(lengths), np.concatenate(frames))


def _residual_deg(normals: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """float64[S, D] angles (degrees) between each direction and each segment's interpretation plane."""
    return np.degrees(np.arcsin(np.clip(np.abs(normals @ directions.T), 0.0, 1.0)))


def _directions(centre: np.ndarray, step_deg: float, radius_deg: float) -> np.ndarray:
    """float64[D, 3] unit directions on a square grid of ``step_deg`` (tangent plane of ``centre``)
    within ``radius_deg`` of it; ``centre`` first."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(centre[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    a = np.cross(centre, helper)
    a /= np.linalg.norm(a)
    b = np.cross(centre, a)
    k = int(math.floor(radius_deg / step_deg))
    g = np.radians(np.arange(-k, k + 1) * step_deg)
    X, Y = (m.ravel() for m in np.meshgrid(g, g))
    order = np.argsort(np.hypot(X, Y), kind="stable")
    X, Y = X[order], Y[order]
    inside = np.hypot(X, Y) <= math.radians(radius_deg) + 1e-12
    d = centre[None] + np.tan(X[inside])[:, None] * a + np.tan(Y[inside])[:, None] * b
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _score(seg: SegmentNormals, directions: np.ndarray, tol_deg: float, chunk: int = 512) -> np.ndarray:
    """float64[D] agreement of the segments with each direction (module docstring)."""
    out = np.empty(len(directions))
    for s in range(0, len(directions), chunk):
        r = _residual_deg(seg.normals, directions[s:s + chunk])
        out[s:s + chunk] = seg.lengths @ np.clip(1.0 - (r / tol_deg) ** 2, 0.0, None)
    return out


def _polish(seg: SegmentNormals, up: np.ndarray, tol_deg: float) -> np.ndarray:
    """``up`` after :data:`POLISH_STEPS` Cauchy-weighted least-squares steps (segments beyond 3
    tolerances out)."""
    for _ in range(POLISH_STEPS):
        r = _residual_deg(seg.normals, up[None])[:, 0]
        w = seg.lengths / (1.0 + (r / tol_deg) ** 2) * (r < 3 * tol_deg)
        if not w.any():
            break
        v = np.linalg.eigh((seg.normals * w[:, None]).T @ seg.normals)[1][:, 0]
        up = v if v @ up > 0 else -v
    return up


def refine_up(seg: SegmentNormals, start: np.ndarray, tol_deg: float) -> LineUp | None:
    """Up from the segments ``seg``, searched near ``start`` float[3] (the cameras' estimate, unit,
    input world) with tolerance ``tol_deg`` (module docstring); None when too few segments agree."""
    start = np.asarray(start, dtype=np.float64) / np.linalg.norm(start)
    if len(seg.normals) < MIN_SEGMENTS:
        return None
    best = start
    for step, radius in SEARCH_LEVELS:
        candidates = _directions(best, step, radius)
        best = candidates[int(np.argmax(_score(seg, candidates, max(tol_deg, step))))]
    up = _polish(seg, best, tol_deg)
    agree = _residual_deg(seg.normals, up[None])[:, 0] <= tol_deg
    frames = len(np.unique(seg.frames[agree]))
    if agree.sum() < MIN_SEGMENTS or frames < MIN_FRAMES:
        return None
    moved = math.degrees(math.acos(float(np.clip(up @ start, -1.0, 1.0))))
    return LineUp(up, int(agree.sum()), frames, moved)
