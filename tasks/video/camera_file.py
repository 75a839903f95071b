"""Read and write RealEstate10K camera files.

File format (one text file per clip, UTF-8, ``\\n``, ``\\r\\n`` or ``\\r`` line endings, mixed too; a
leading UTF-8 byte-order mark, as Windows editors write, is dropped: it is an encoding artefact, not
part of the URL):

- line 1: the source video URL: any text that is not itself numbers only (a camera line, or a
  broken one), which would mean that the URL line is missing;
- every further line: one camera, 19 whitespace-separated columns
  ``timestamp fx fy cx cy 0 0 r11 r12 r13 t1 r21 r22 r23 t2 r31 r32 r33 t3``;
- blank lines only at the end of the file.

Frames (see :mod:`cadestate.geometry`):

- ``timestamp``: integer microseconds since the start of the video, strictly increasing.
- ``fx fy cx cy``: intrinsics **normalised** by the image width (fx, cx) and height (fy, cy);
  fx and fy within FOCAL_RANGE (a field of view of 1 to 179 degrees), the principal point
  (cx, cy) inside the image give or take PRINCIPAL_POINT_MARGIN.
- columns 6-7: unused (conventionally 0); any finite value is accepted and dropped.
- ``[R|t]`` (row-major 3x4): **world->camera**, ``X_cam = R @ X_world + t``, OpenCV camera axes
  (x right, y down, z forward); every |t| component at most TRANSLATION_MAX.
"""

from __future__ import annotations

import math
import os
import re
import secrets
from dataclasses import dataclass

import numpy as np

from cadestate.geometry import rotation_error

ROTATION_TOLERANCE = 1e-3
"""Largest ``rotation_error`` (max |R R^T - I|, |det R - 1|) accepted for the R of [R|t]."""
FOV_RANGE_DEG = (1.0, 179.0)
"""Fields of view (degrees, per image axis) that a camera line may describe."""
FOCAL_RANGE = (0.5 / math.tan(math.radians(FOV_RANGE_DEG[1] / 2)), 0.5 / math.tan(math.radians(FOV_RANGE_DEG[0] / 2)))
"""(lowest, highest) normalised focal length fx or fy: those of FOV_RANGE_DEG (fov = 2 atan(1 / 2f))."""
PRINCIPAL_POINT_MARGIN = 0.1
"""How far outside [0, 1] (the image, normalised) the principal point cx, cy may lie."""
TRANSLATION_MAX = 1e6
"""Largest |t| component of [R|t] (scene units; RealEstate10K scenes span tens of units)."""
BOM = "\ufeff"

COLUMNS = ("timestamp", "fx", "fy", "cx", "cy", "unused1", "unused2",
           "r11", "r12", "r13", "t1", "r21", "r22", "r23", "t2", "r31", "r32", "r33", "t3")
"""Names of the 19 columns of a camera line, in file order."""

_INT64_MAX = int(np.iinfo(np.int64).max)
_TIMESTAMP = re.compile(r"[0-9]+")
_FLOAT = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")


@dataclass(frozen=True, eq=False)
class CameraTrack:
    """Cameras of one clip, as in a RealEstate10K camera file.

    Every instance can be written with :func:`format_camera_track` and read back unchanged:
    ``__post_init__`` applies the rules of the parser (ValueError naming the camera index).
    Two tracks are equal when their URLs and arrays are equal.

    Attributes:
      url: str, line 1 of the file (the source video URL; may be any non-empty text without
        "\n" or surrounding whitespace).
      timestamps_us: int64[N], N >= 1, non-negative and strictly increasing, microseconds since
        the start of the video.
      intrinsics: float64[N, 4] normalised (fx, fy, cx, cy): fx, cx divided by image width, fy, cy
        by height; finite, fx and fy within FOCAL_RANGE, cx and cy within PRINCIPAL_POINT_MARGIN
        of [0, 1].
      world_to_camera: float64[N, 3, 4] [R|t], X_cam = R @ X_world + t, OpenCV camera axes;
        finite, R a rotation within ROTATION_TOLERANCE, |t| components at most TRANSLATION_MAX.
    """

    url: str
    timestamps_us: np.ndarray
    intrinsics: np.ndarray
    world_to_camera: np.ndarray

    def __post_init__(self) -> None:
        url = self.url
        if not isinstance(url, str) or not url or url != url.strip() or "\n" in url or "\r" in url:
            raise ValueError(f"url must be non-empty one-line text without surrounding whitespace: {url!r}")
        n = len(self.timestamps_us) if isinstance(self.timestamps_us, np.ndarray) else 0
        for name, dtype, shape in (("timestamps_us", np.int64, (n,)), ("intrinsics", np.float64, (n, 4)),
                                   ("world_to_camera", np.float64, (n, 3, 4))):
            a = getattr(self, name)
            if n == 0 or not isinstance(a, np.ndarray) or a.dtype != dtype or a.shape != shape:
                got = f"{a.dtype}{list(a.shape)}" if isinstance(a, np.ndarray) else type(a).__name__
                want = ", ".join(["N", *map(str, shape[1:])])
                raise ValueError(f"{name} must be {np.dtype(dtype)}[{want}] (same N >= 1 in all arrays), "
                                 f"got {got}")
        ts = self.timestamps_us
        if np.any(ts < 0) or np.any(ts[1:] <= ts[:-1]):
            raise ValueError("timestamps_us must be non-negative and strictly increasing")
        for i in range(n):
            problem = _camera_problem(self.intrinsics[i], self.world_to_camera[i])
            if problem:
                raise ValueError(f"camera {i}: {problem}")

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CameraTrack):
            return NotImplemented
        return self.url == other.url and all(
            np.array_equal(getattr(self, f), getattr(other, f))
            for f in ("timestamps_us", "intrinsics", "world_to_camera"))

    __hash__ = None  # type: ignore[assignment]  # mutable arrays: not hashable

    def __len__(self) -> int:
        return len(self.timestamps_us)

    @property
    def R(self) -> np.ndarray:
        """float64[N, 3, 3] world->camera rotations (a view of ``world_to_camera``)."""
        return self.world_to_camera[:, :, :3]

    @property
    def t(self) -> np.ndarray:
        """float64[N, 3] world->camera translations (a view of ``world_to_camera``)."""
        return self.world_to_camera[:, :, 3]


LINE_END = re.compile(r"\r*\n|\r")
"""Unix, Windows (also \r\r\n) and classic Mac line ends, mixed too."""


class CameraFileError(ValueError):
    """A malformed camera file. str(e) == f"{path}:{line}: {message}", or f"{path}: {message}"
    when the problem is the whole file (``line`` 0; else 1-based).
    """

    def __init__(self, path: str, line: int, message: str):
        super().__init__(path, line, message)  # args kept whole so that the error pickles
        self.path, self.line, self.message = path, line, message

    def __str__(self) -> str:
        return f"{self.path}:{self.line}: {self.message}" if self.line else f"{self.path}: {self.message}"


def _column(name: str) -> str:
    """How errors name a column: ``column 2 (fx)``."""
    return f"column {COLUMNS.index(name) + 1} ({name})"


def _camera_problem(intrinsics: np.ndarray, world_to_camera: np.ndarray) -> str | None:
    """What is wrong with one camera (float[4] intrinsics, float[3, 4] [R|t]), or None; the
    message names the column."""
    if not (np.all(np.isfinite(intrinsics)) and np.all(np.isfinite(world_to_camera))):
        return "intrinsics and [R|t] must be finite"
    lo, hi = FOCAL_RANGE
    for name, value in zip(("fx", "fy"), intrinsics[:2].tolist()):
        if not value > 0:
            return f"{_column(name)} must be > 0, found {value!r}"
        if not lo <= value <= hi:
            return (f"{_column(name)} = {value!r} is not a field of view of {FOV_RANGE_DEG[0]:g} to "
                    f"{FOV_RANGE_DEG[1]:g} degrees (normalised focal length in [{lo:.4g}, {hi:.4g}])")
    margin = PRINCIPAL_POINT_MARGIN
    for name, value in zip(("cx", "cy"), intrinsics[2:].tolist()):
        if not -margin <= value <= 1 + margin:
            return (f"{_column(name)} = {value!r} puts the principal point outside the image "
                    f"(normalised, must be in [{-margin:g}, {1 + margin:g}])")
    R = world_to_camera[:, :3]
    error = rotation_error(R)
    if error > ROTATION_TOLERANCE:
        return (f"R is not a rotation: rotation error {error:.3g} > {ROTATION_TOLERANCE:g} "
                f"(det {np.linalg.det(R):.3g})")
    for name, value in zip(("t1", "t2", "t3"), world_to_camera[:, 3].tolist()):
        if abs(value) > TRANSLATION_MAX:
            return f"{_column(name)} = {value!r} is too far from the origin (|t| must be <= {TRANSLATION_MAX:g})"
    return None


def _quote(text: str, limit: int = 40) -> str:
    """``repr(text)``, cut to about ``limit`` characters (errors show what the file holds, on one line)."""
    shown = repr(text)
    return shown if len(shown) <= limit else shown[:limit] + "..."


def _is_number(text: str) -> bool:
    """Whether Python reads ``text`` as a float (nan and inf included)."""
    try:
        float(text)
    except ValueError:
        return False
    return True


def is_camera_line(line: str) -> bool:
    """Whether ``line`` is 19 numbers: a camera line, which a URL line never is."""
    fields = line.split()
    return len(fields) == len(COLUMNS) and all(map(_is_number, fields))


def _parse_camera_line(fields: list[str]) -> tuple[int, np.ndarray]:
    """Timestamp and float64[18] values (fx fy cx cy unused1 unused2 [R|t]) of one camera line.

    Raises ValueError naming the first bad column.
    """
    if len(fields) != len(COLUMNS):
        raise ValueError(f"expected {len(COLUMNS)} columns, found {len(fields)}")
    if not _TIMESTAMP.fullmatch(fields[0]):
        raise ValueError(f"column 1 (timestamp) is not a non-negative integer: {_quote(fields[0])}")
    timestamp = int(fields[0])
    if timestamp > _INT64_MAX:
        raise ValueError(f"column 1 (timestamp) does not fit in int64: {_quote(fields[0])}")
    values = np.empty(len(COLUMNS) - 1)
    for col, (name, text) in enumerate(zip(COLUMNS[1:], fields[1:]), start=2):
        value = float(text) if _FLOAT.fullmatch(text) else math.nan
        if not math.isfinite(value):
            raise ValueError(f"column {col} ({name}) is not a finite number: {_quote(text)}")
        values[col - 2] = value
    return timestamp, values


def parse_camera_text(text: str, source: str = "<string>") -> CameraTrack:
    """Parse the contents of a camera file; ``source`` names it in errors.

    A leading byte-order mark is dropped (see the module docstring).

    Raises:
      CameraFileError: ``f"{source}:{line}: {what is wrong}"`` at the first problem found.
    """
    text = text.removeprefix(BOM)
    lines = LINE_END.split(text)
    if not text.strip():
        raise CameraFileError(source, 0, "empty file")
    if not lines[0].strip():
        raise CameraFileError(source, 1, "line 1 (the URL) is empty")
    if is_camera_line(lines[0]):
        raise CameraFileError(source, 1, "line 1 is a camera line (19 numbers), not the video URL: "
                                         "the URL line is missing")
    first = lines[0].split()
    if len(first) > 1 and all(map(_is_number, first)):
        raise CameraFileError(source, 1, f"line 1 holds {len(first)} numbers, not the video URL: the URL line is "
                                         f"missing (and a camera line has {len(COLUMNS)} numbers)")
    last = max(i for i, line in enumerate(lines) if line.strip())
    if last == 0:
        raise CameraFileError(source, 2, "no camera lines after the URL (line 1)")
    timestamps: list[int] = []
    rows: list[np.ndarray] = []
    line_of: dict[int, int] = {}
    for lineno, line in enumerate(lines[1:last + 1], start=2):
        if not line.strip():
            raise CameraFileError(source, lineno, "blank line before more camera lines")
        try:
            timestamp, values = _parse_camera_line(line.split())
            problem = _camera_problem(values[:4], values[6:].reshape(3, 4))
            if problem:
                raise ValueError(problem)
            if timestamp in line_of:
                raise ValueError(f"duplicate timestamp {timestamp} (also on line {line_of[timestamp]})")
            if timestamps and timestamp < timestamps[-1]:
                raise ValueError(f"timestamp {timestamp} is not after {timestamps[-1]} "
                                 f"on line {line_of[timestamps[-1]]}")
        except ValueError as e:
            raise CameraFileError(source, lineno, str(e)) from None
        line_of[timestamp] = lineno
        timestamps.append(timestamp)
        rows.append(values)
    table = np.stack(rows)
    return CameraTrack(url=lines[0].strip(), timestamps_us=np.array(timestamps, dtype=np.int64),
                       intrinsics=table[:, :4], world_to_camera=table[:, 6:].reshape(-1, 3, 4))


def parse_camera_file(path: str | os.PathLike[str]) -> CameraTrack:
    """Read and parse a camera file (UTF-8).

    Raises:
      CameraFileError: malformed contents, a non-UTF-8 byte (naming its line), or (line 0) an
        unreadable file.
    """
    source = os.fspath(path)
    try:
        with open(source, "rb") as f:
            data = f.read()
    except OSError as e:
        raise CameraFileError(source, 0, f"cannot read file: {e.strerror or e}") from e
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        line = len(LINE_END.split(data[:e.start].decode("utf-8", "replace")))  # as the parser counts lines
        raise CameraFileError(source, line, f"not valid UTF-8 (byte 0x{data[e.start]:02x} at "
                                            f"offset {e.start})") from None
    return parse_camera_text(text, source)


def format_camera_track(track: CameraTrack) -> str:
    """Camera file text of ``track``; ``parse_camera_text`` gives back the same bits.

    Floats are written with ``repr`` (shortest exact round trip), the unused columns as 0,
    each line ends with ``\\n``.
    """
    lines = [track.url]
    for timestamp, intrinsics, rt in zip(track.timestamps_us, track.intrinsics, track.world_to_camera):
        values = [*intrinsics.tolist(), 0.0, 0.0, *rt.ravel().tolist()]
        lines.append(" ".join([str(int(timestamp)), *map(repr, values)]))
    return "\n".join(lines) + "\n"


def write_camera_file(path: str | os.PathLike[str], track: CameraTrack) -> None:
    """Write ``track`` to ``path`` atomically: readers see the old file or the whole new one.

    The text goes to a temporary file in the same directory, is fsynced and then renamed over
    ``path``; on any failure the temporary file is removed and ``path`` is left untouched.
    """
    path = os.fspath(path)
    text = format_camera_track(track)
    directory, name = os.path.split(os.path.abspath(path))
    tmp = os.path.join(directory, f".{name}.{secrets.token_hex(8)}.tmp")
    try:
        with open(tmp, "x", encoding="utf-8", newline="\n") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
