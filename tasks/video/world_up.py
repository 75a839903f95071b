"""The world's up direction of a clip, found from its cameras, and the rotation that makes it +Y.

Two world frames (see :mod:`cadestate.geometry`):

- the **input world**: the frame of the clip's camera file (RealEstate10K: ORB-SLAM's, whose up is
  arbitrary, roughly the first camera's -y; SfM: COLMAP's, arbitrary too; our renderer: +Y up);
- the **aligned world**: the input world turned by the rotation ``Q`` (float64[3, 3]) found at
  ingest, ``X_aligned = Q @ X_input``, so that gravity points along -Y. Every stage after ingest
  (``frames`` and everything that reads it) works in the aligned world; ``clips.up_rotation`` keeps
  ``Q`` and the exports map results back to the input world with ``Q.T``.

Estimating gravity. People hold phones upright and level: a camera's x axis (right) is nearly
horizontal (little roll) and its y axis (down) nearly along gravity, tilted by the pitch, which
is often biased (phones point a little down). People also walk on level floors: the camera's
centre moves nearly horizontally, whatever the pitch. So the down direction ``g`` (unit, input
world) minimises ``sum_i (x_i . g)^2 + w n sum_j (d_j . g)^2 / sum_j |d_j|^2 + MU * sum_i (1 - (y_i . g)^2)``
over the n cameras, with ``d_j`` the moves between cameras :data:`MOTION_SPAN` of the clip apart
(long enough that a walker's bob of a few cm is small against the step) and ``w`` the walk's
coherence (net move / path length, 0 for a camera that stands and shakes). The x axes decide
``g`` when the camera pans (they span the horizontal plane); a walk that is not sideways decides
it with them when the camera does not pan; the y axes break the tie only when neither does. On
14 benchmark clips (+Y up, pitched 2-14 degrees down, panning little) the y axes alone had put up
2-13 degrees off; with the walk, 0.1-3.1. Vertical lines in the video then refine it when enough
agree (:mod:`tasks.video.vertical_lines`; ``[ingest] up_line_frames``). ``Q`` is the smallest
rotation taking ``-g`` to +Y (an input world that is +Y up already is left almost unchanged).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from tasks.video.vertical_lines import SegmentNormals

MU = 0.01
"""Weight of the y axes (down) against the x axes (level) in the gravity objective."""
MAX_ROLL_RMS_DEG = 10.0
"""An estimate whose cameras lean further than this from level (RMS roll) is unreliable."""
MIN_PAN_DEG = 10.0
"""Below this spread of the cameras' right axes (RMS, degrees), and without a walk across them
(:data:`MIN_WALK_DEG`), only the down axes fix the tilt about the viewing direction, and the
pitch of the phone biases it: the estimate is unreliable."""
MOTION_SPAN = 0.25
"""The walk's moves are taken between cameras this fraction of the clip apart (at least 1)."""
MIN_WALK_DEG = 30.0
"""A coherent walk (:data:`MIN_WALK_COHERENCE`) at least this far from the cameras' right axis
fixes the tilt about the viewing direction together with it."""
MIN_WALK_COHERENCE = 0.5
"""A walk whose net move is at least this fraction of its path length has a main direction."""
MAX_CLIMB_DEG = 20.0
"""An estimate the walk moved further than this from the cameras' axes' own (x level, y down) is
unreliable: the walk holds up level with the path, so stairs, a ramp or a rising camera tilt it by
their slope (a 35° stair: 35° off); the axes alone err by the phone's pitch (2-13° on the benchmark)."""
AXES = {"+x": (1.0, 0.0, 0.0), "-x": (-1.0, 0.0, 0.0), "+y": (0.0, 1.0, 0.0), "-y": (0.0, -1.0, 0.0),
        "+z": (0.0, 0.0, 1.0), "-z": (0.0, 0.0, -1.0)}
"""``[ingest] up`` values that force the input world's up axis (``auto`` estimates it)."""


@dataclass(frozen=True)
class UpEstimate:
    """The input world's up direction and the rotation to the aligned world.

    Attributes:
      up: float64[3] unit up direction (against gravity), input world.
      rotation: float64[3, 3] ``Q``, ``X_aligned = Q @ X_input``, ``Q @ up = (0, 1, 0)``.
      source: ``auto`` (estimated from the cameras) or the forced axis (``+y``, ...).
      roll_rms_deg: RMS angle of the cameras' x axes from the horizontal plane of ``up``.
      pan_deg: RMS spread of the cameras' x axes about their mean, degrees (how much the camera pans).
      walk_deg: angle between the walk's main direction and the cameras' mean x axis, degrees (90:
        forward or backward, 0: sideways; 0 without camera centres or a coherent walk).
      tilt_deg: angle between ``up`` and the input world's +Y, degrees.
      note: why the estimate is unreliable ("" when it is not, or when it was forced).
      line_segments: vertical line segments that refined the cameras' estimate (0: too few agreed,
        or no lines were given; :mod:`tasks.video.vertical_lines`).
    """

    up: np.ndarray
    rotation: np.ndarray
    source: str
    roll_rms_deg: float
    pan_deg: float
    tilt_deg: float
    note: str = ""
    walk_deg: float = 0.0
    line_segments: int = 0

    @property
    def reliable(self) -> bool:
        return not self.note


def rotation_to_y(up: np.ndarray) -> np.ndarray:
    """The smallest rotation float64[3, 3] taking the unit vector ``up`` (float[3]) to +Y
    (about the x axis when ``up`` is -Y)."""
    u = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    y = np.array([0.0, 1.0, 0.0])
    axis = np.cross(u, y)
    s, c = np.linalg.norm(axis), float(u @ y)
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = axis / s
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * K + (1 - c) * (K @ K)


def _deg(radians: float) -> float:
    return math.degrees(radians)


def walk_term(centres: np.ndarray | None) -> tuple[np.ndarray, float]:
    """(sum_j d_j d_j^T / sum_j |d_j|^2 float64[3, 3], the walk's coherence in [0, 1]) of camera
    centres float[N, 3] in time order (module docstring); zeros and 0 for None or a camera that
    does not move."""
    if centres is None or len(centres) < 2:
        return np.zeros((3, 3)), 0.0
    c = np.asarray(centres, dtype=np.float64)
    k = max(1, int(len(c) * MOTION_SPAN))
    d = c[k:] - c[:-k]
    total, path = float((d ** 2).sum()), float(np.linalg.norm(np.diff(c, axis=0), axis=1).sum())
    if total <= 0 or path <= 0:
        return np.zeros((3, 3)), 0.0
    return d.T @ d / total, min(1.0, float(np.linalg.norm(c[-1] - c[0])) / path)


def _up_of_axes(x: np.ndarray, y: np.ndarray, walk: np.ndarray | None = None) -> np.ndarray:
    """Up float64[3] minimising the module docstring's objective over the cameras' x and y axes
    float[N, 3] and the walk's term float64[3, 3] (weighted; None: left out)."""
    n = len(x)
    A = x.T @ x + MU * (n * np.eye(3) - y.T @ y) + (0 if walk is None else walk)
    v = np.linalg.eigh(A)[1][:, 0]  # down or up: up is the one against the cameras' y axes (down)
    return v if float((y @ v).sum()) < 0 else -v


def estimate_up(world_to_camera_R: np.ndarray, forced: str = "auto", centres: np.ndarray | None = None,
                lines: "SegmentNormals | None" = None, line_tolerance_deg: float = 0.5) -> UpEstimate:
    """Up of the input world from the cameras' world->camera rotations float[N, 3, 3] (OpenCV
    axes: row 0 of R is the camera's x (right), row 1 its y (down), in input-world coordinates)
    and their centres float[N, 3] in time order (None: the rotations alone), refined by the line
    segments ``lines`` of the video when enough of them agree (None: the cameras alone;
    :func:`tasks.video.vertical_lines.refine_up` with ``line_tolerance_deg``); ``forced``:
    ``auto`` or a key of :data:`AXES`."""
    R = np.asarray(world_to_camera_R, dtype=np.float64)
    x, y = R[:, 0, :], R[:, 1, :]
    walk, coherence = walk_term(centres)
    if forced != "auto":
        if forced not in AXES:
            raise ValueError(f"up must be 'auto' or one of {', '.join(AXES)}, got {forced!r}")
        up = np.array(AXES[forced])
    else:
        up = _up_of_axes(x, y, coherence * len(R) * walk)
    from_lines = None
    if forced == "auto" and lines is not None:
        from tasks.video.vertical_lines import refine_up

        from_lines = refine_up(lines, up, line_tolerance_deg)
        if from_lines is not None:
            up = from_lines.up
    roll = np.arcsin(np.clip(np.abs(x @ up), 0, 1))
    mean_x = x.mean(axis=0)
    mean_x /= max(np.linalg.norm(mean_x), 1e-12)
    pan = np.arccos(np.clip(x @ mean_x, -1, 1))
    roll_rms, pan_rms = _deg(float(np.sqrt((roll ** 2).mean()))), _deg(float(np.sqrt((pan ** 2).mean())))
    tilt = _deg(float(np.arccos(np.clip(up[1], -1, 1))))
    walk_deg = 0.0
    if coherence >= MIN_WALK_COHERENCE:
        main = np.linalg.eigh(walk)[1][:, -1]
        walk_deg = _deg(float(np.arccos(np.clip(abs(main @ mean_x), 0, 1))))
    note = ""
    if forced == "auto" and from_lines is None:  # vertical lines fix up however the camera was held and moved
        if roll_rms > MAX_ROLL_RMS_DEG:
            note = (f"the cameras lean {roll_rms:.1f}° from level (RMS roll, more than {MAX_ROLL_RMS_DEG:g}°): "
                    "the world's up may be wrong; set [ingest] up to force it")
        elif pan_rms < MIN_PAN_DEG and walk_deg < MIN_WALK_DEG:
            note = (f"the camera barely pans ({pan_rms:.1f}° RMS, less than {MIN_PAN_DEG:g}°) and does not walk "
                    f"forward or back (its walk is {walk_deg:.0f}° from sideways, less than {MIN_WALK_DEG:g}°): the up "
                    "direction rests on the phone being held level in pitch; set [ingest] up to force it")
        elif coherence > 0 and (climb := _deg(float(np.arccos(np.clip(up @ _up_of_axes(x, y), -1, 1))))) > MAX_CLIMB_DEG:
            note = (f"the walk puts up {climb:.0f}° from where the cameras' axes put it (more than {MAX_CLIMB_DEG:g}°): "
                    "the path climbs (stairs, a ramp) or the phone points far down; set [ingest] up to force it")
    return UpEstimate(up, rotation_to_y(up), forced, roll_rms, pan_rms, tilt, note, walk_deg,
                      from_lines.segments if from_lines else 0)


def align_extrinsics(R: np.ndarray, t: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World->camera ``(R, t)`` (float[..., 3, 3], float[..., 3]) of the input world to the aligned
    world ``X_aligned = Q @ X_input``: ``(R @ Q.T, t)``; :func:`unalign_extrinsics` undoes it."""
    return np.asarray(R, dtype=np.float64) @ np.asarray(Q).T, np.asarray(t, dtype=np.float64)


def unalign_extrinsics(R: np.ndarray, t: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World->camera of the aligned world back to the input world: ``(R @ Q, t)``."""
    return np.asarray(R, dtype=np.float64) @ np.asarray(Q), np.asarray(t, dtype=np.float64)


def unalign_pose(translation: np.ndarray, rotation: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An object-to-world pose's translation float[3] and rotation matrix float[3, 3] in the aligned
    world to the input world (scale and mirror are unchanged): ``(Q.T @ T, Q.T @ R)``."""
    Qt = np.asarray(Q, dtype=np.float64).T
    return Qt @ np.asarray(translation, dtype=np.float64), Qt @ np.asarray(rotation, dtype=np.float64)


def stored_rotation(values: object) -> np.ndarray:
    """``clips.up_rotation`` (9 floats, row-major; null for clips ingested before it existed:
    identity) as float64[3, 3]."""
    if values is None:
        return np.eye(3)
    return np.asarray(values, dtype=np.float64).reshape(3, 3)


def pose_to_input_world(translation: Sequence[float], rotation_wxyz: Sequence[float],
                        Q: np.ndarray) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """An object-to-world pose (translation float[3], quaternion (w, x, y, z)) of the aligned world
    in the camera file's world, as tuples (scale and mirror are unchanged)."""
    from cadestate.geometry import matrix_to_quaternion, quaternion_to_matrix

    T, R = unalign_pose(np.asarray(translation), quaternion_to_matrix(np.asarray(rotation_wxyz)), Q)
    return tuple(float(v) for v in T), tuple(float(v) for v in matrix_to_quaternion(R))
