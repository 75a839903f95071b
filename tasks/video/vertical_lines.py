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
backs) agree with no single direction near up and barely move the peak.

What is not a line of the room is left out first: a segment found on the same line of the image
on at least :data:`STATIC_FRACTION` of the other frames (an overlay, a logo, a letterbox edge, or
a camera that does not move) says nothing about the world. No estimate (the cameras' stands) when
too few segments agree (fewer than :data:`MIN_SEGMENTS` on :data:`MIN_FRAMES` frames), when they
are one line seen the same way (their normals spread less than :data:`MIN_SPREAD_DEG` about up:
up is then any direction in one plane), or when the polish ends farther than :data:`SEARCH_DEG`
from the start.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

SEARCH_DEG = 20.0
"""Directions up to this far from the cameras' estimate are searched."""
SEARCH_LEVELS = ((0.5, SEARCH_DEG), (0.1, 1.0), (0.02, 0.2))
"""(grid step, radius) in degrees of each search level, each centred on the last one's best."""
MIN_SEGMENT_FRACTION = 0.05
"""Segments shorter than this fraction of the frame's longer side are not used (short ones point poorly)."""
MIN_SEGMENTS = 50
"""An estimate needs at least this many segments within the tolerance of it (a few vertical lines
per frame: with 32, a 320x192 test clip's few short edges put up 3.4 degrees off) ..."""
MIN_FRAMES = 3
"""... on at least this many frames."""
POLISH_STEPS = 5
"""Reweighted least-squares steps after the search."""
STATIC_PX = 2.0
"""Segments of two frames on image lines this close (px, their distances from the origin) ..."""
STATIC_DEG = 1.0
"""... and this parallel (degrees), that overlap, are at the same place of the image ..."""
STATIC_FRACTION = 0.25
"""... and one found so on at least this fraction of the other frames is left out."""
MIN_SPREAD_DEG = 5.0
"""The agreeing normals must spread at least this much (RMS angle, degrees) within the plane
orthogonal to up: otherwise they are one line seen one way, and up is not fixed."""


@dataclass(frozen=True)
class SegmentNormals:
    """Line segments of a clip's sampled frames as interpretation-plane normals.

    Attributes:
      normals: float64[S, 3] unit normals, input world.
      lengths: float64[S] segment lengths, px.
      frames: int64[S] index of the sampled frame each segment is on.
      endpoints: float64[S, 4] (x0, y0, x1, y1) px as OpenCV gives them (pixel centres at integers).
    """

    normals: np.ndarray
    lengths: np.ndarray
    frames: np.ndarray
    endpoints: np.ndarray


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
                          detector=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(unit interpretation-plane normals float64[S, 3] in the world, lengths float64[S] px,
    endpoints float64[S, 4] px) of the line segments of one frame ``gray`` uint8[H, W];
    ``intrinsics_px`` (fx, fy, cx, cy); ``world_to_camera_R`` float[3, 3]; ``detector``: an OpenCV
    line segment detector (made when None)."""
    import cv2

    detector = detector if detector is not None else cv2.createLineSegmentDetector()
    found = detector.detect(gray)[0]
    if found is None:
        return np.zeros((0, 3)), np.zeros(0), np.zeros((0, 4))
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
    return n @ np.asarray(world_to_camera_R, dtype=np.float64), lengths[ok], seg[ok]  # rows: R^T n


def video_segment_normals(video: str | os.PathLike, times_us: np.ndarray, intrinsics: np.ndarray,
                          world_to_camera_R: np.ndarray) -> SegmentNormals:
    """:func:`frame_segment_normals` of the video's frames nearest ``times_us`` int[F] (video time,
    increasing); ``intrinsics`` float[F, 4] normalised (fx/W, fy/H, cx/W, cy/H, as in a camera file);
    ``world_to_camera_R`` float[F, 3, 3]."""
    import cv2

    from tasks.video.decode import decode_at

    detector = cv2.createLineSegmentDetector()
    per_frame = []
    for i, frame in enumerate(decode_at(video, np.asarray(times_us, dtype=np.int64))):
        H, W = frame.rgb.shape[:2]
        gray = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2GRAY)
        per_frame.append(frame_segment_normals(gray, np.asarray(intrinsics[i]) * [W, H, W, H], world_to_camera_R[i],
                                               detector))
    return stack_frames(per_frame)


def stack_frames(per_frame: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> SegmentNormals:
    """One :class:`SegmentNormals` of :func:`frame_segment_normals`' results, frame ``i`` the ``i``-th."""
    if not per_frame:
        return SegmentNormals(np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros((0, 4)))
    return SegmentNormals(np.concatenate([f[0] for f in per_frame]), np.concatenate([f[1] for f in per_frame]),
                          np.concatenate([np.full(len(f[0]), i, dtype=np.int64) for i, f in enumerate(per_frame)]),
                          np.concatenate([f[2] for f in per_frame]))


def _image_lines(e: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Of segments ``e`` float[S, 4] px: unit directions float[S, 2] (pointing right or down), offsets
    float[S] (signed distance of their line from the origin) and extents float[S, 2] along the
    direction."""
    d = e[:, 2:] - e[:, :2]
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    d = np.where((d[:, :1] < 0) | ((d[:, :1] == 0) & (d[:, 1:] < 0)), -d, d)
    rho = e[:, 0] * -d[:, 1] + e[:, 1] * d[:, 0]
    a, b = (e[:, :2] * d).sum(1), (e[:, 2:] * d).sum(1)
    return d, rho, np.stack([np.minimum(a, b), np.maximum(a, b)], axis=1)


def moving_segments(seg: SegmentNormals) -> SegmentNormals:
    """``seg`` without the segments that lie on the same line of the image (within
    :data:`STATIC_PX` and :data:`STATIC_DEG`, overlapping) as a segment of at least
    :data:`STATIC_FRACTION` of the other frames: overlays, and everything a still camera sees."""
    frames = np.unique(seg.frames)
    if len(frames) < 2:
        return seg
    d, rho, ext = _image_lines(seg.endpoints)
    repeats = np.zeros(len(rho), dtype=np.int64)
    cos_tol = math.cos(math.radians(STATIC_DEG))
    members = [np.flatnonzero(seg.frames == f) for f in frames]
    for i, mine in enumerate(members):
        for theirs in members[i + 1:]:  # the relation is symmetric: each pair of frames once, counted both ways
            same = ((np.abs(d[mine] @ d[theirs].T) >= cos_tol) & (np.abs(rho[mine, None] - rho[None, theirs]) <= STATIC_PX)
                    & (ext[mine, None, 0] <= ext[None, theirs, 1]) & (ext[None, theirs, 0] <= ext[mine, None, 1]))
            repeats[mine] += same.any(axis=1)
            repeats[theirs] += same.any(axis=0)
    keep = repeats < STATIC_FRACTION * (len(frames) - 1)
    return SegmentNormals(seg.normals[keep], seg.lengths[keep], seg.frames[keep], seg.endpoints[keep])


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


def _scatter(normals: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """float64[3, 3] ``sum_s w_s n_s n_s^T`` of ``normals`` float[S, 3] and ``weights`` float[S]."""
    return (normals * weights[:, None]).T @ normals


def _spread_deg(normals: np.ndarray, weights: np.ndarray) -> float:
    """RMS angle (degrees) by which unit ``normals`` float[S, 3] (weights float[S]) spread about their
    main direction within their best-fitting plane: atan of sqrt(middle / largest eigenvalue) of
    :func:`_scatter`."""
    e = np.linalg.eigvalsh(_scatter(normals, weights))
    return math.degrees(math.atan(math.sqrt(max(e[1], 0.0) / e[2]))) if e[2] > 0 else 0.0


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
        v = np.linalg.eigh(_scatter(seg.normals, w))[1][:, 0]
        up = v if v @ up > 0 else -v
    return up


def refine_up(seg: SegmentNormals, start: np.ndarray, tol_deg: float) -> LineUp | None:
    """Up from the segments ``seg``, searched near ``start`` float[3] (the cameras' estimate, unit,
    input world) with tolerance ``tol_deg`` (module docstring); None when too few segments agree."""
    start = np.asarray(start, dtype=np.float64) / np.linalg.norm(start)
    seg = moving_segments(seg)
    if len(seg.normals) < MIN_SEGMENTS:
        return None
    best = start
    for step, radius in SEARCH_LEVELS:
        candidates = _directions(best, step, radius)
        best = candidates[int(np.argmax(_score(seg, candidates, max(tol_deg, step))))]
    up = _polish(seg, best, tol_deg)
    agree = _residual_deg(seg.normals, up[None])[:, 0] <= tol_deg
    frames = len(np.unique(seg.frames[agree]))
    moved = math.degrees(math.acos(float(np.clip(up @ start, -1.0, 1.0))))
    if (agree.sum() < MIN_SEGMENTS or frames < MIN_FRAMES or moved > SEARCH_DEG
            or _spread_deg(seg.normals[agree], seg.lengths[agree]) < MIN_SPREAD_DEG):
        return None
    return LineUp(up, int(agree.sum()), frames, moved)
