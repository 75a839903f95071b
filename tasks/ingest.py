"""Stage ``ingest``: validate a clip's video and camera file, keep them in the warehouse, register the clip.

Reads: a video file and a RealEstate10K camera file. Writes: ``inputs/<clip>/video<ext>``,
``inputs/<clip>/cameras.txt`` and the clip's row of ``clips``. Fails (writing nothing) on a
malformed camera file, an unreadable video, cameras that ask for times past the video's end, or
intrinsics made for another frame shape (:func:`check_clip_inputs`, which ``cadestate ingest``
also runs before it starts anything).
"""

from __future__ import annotations

import datetime as dt
import math
import os
import shutil
import uuid
from dataclasses import dataclass
from pathlib import Path

import pyarrow as pa

from cadestate.config import IngestConfig
from cadestate.lineage import digest
from schemas.core import DEFAULT_SPLIT
from tasks.cameras import CameraFileError, CameraTrack, parse_camera_file
from tasks.clip_names import ClipNameError, check_clip_name, derive_clip_name, shared_video_ids
from tasks.stage import StageOutput
from tasks.video import VideoInfo, probe_video
from warehouse import Warehouse, WarehouseError, check_name

VIDEO_SUFFIXES = (".mp4", ".mkv", ".webm", ".mov", ".avi")
CAMERAS_FILE = "cameras.txt"
END_TOLERANCE_US = 100_000
"""Camera timestamps may exceed the stream's declared duration by this much (last frame's length)."""
ASPECT_ERROR = 0.10
"""Normalised intrinsics imply the frame's width/height: fy/fx = pixel aspect * W/H. A camera line
whose implied aspect differs from the video's by more than this fraction was made for another
video (a 16:9 camera file on a 4:3 video differs by 33 %): refused."""
ASPECT_WARNING = 0.02
"""A difference above this fraction (but within ASPECT_ERROR) is reported as suspicious."""


@dataclass(frozen=True)
class ClipSource:
    """A clip to ingest: its name, its video file, its RealEstate10K camera file and its dataset
    split (``train``, ``val``, ``test``: the val/test clips get the manual-track task)."""

    clip: str
    video: Path
    cameras: Path
    split: str = DEFAULT_SPLIT

    def __post_init__(self) -> None:
        check_name(self.clip)
        check_name(self.split, "split")


def discover_clips(folder: str | os.PathLike, split: str = DEFAULT_SPLIT) -> list[ClipSource]:
    """Clips of a folder (all of dataset split ``split``): each ``<name>.<video suffix>`` paired with ``<name>.txt``.

    A video without a camera file is an error (naming it), since SfM cameras come later.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: not a folder")
    videos = sorted(p for p in folder.iterdir() if p.suffix.lower() in VIDEO_SUFFIXES)
    if not videos:
        raise FileNotFoundError(f"{folder}: no video files ({', '.join(VIDEO_SUFFIXES)})")
    sources = []
    for video in videos:
        cameras = video.with_suffix(".txt")
        if not cameras.is_file():
            raise FileNotFoundError(f"{video}: no camera file {cameras.name} beside it")
        sources.append(ClipSource(video.stem, video, cameras, split))
    return sources


def ingest_inputs_hash(clip: str, video_sha256: str, cameras_sha256: str, split: str = DEFAULT_SPLIT) -> str:
    """Lineage digest of a clip's inputs and split (also the ingest stage's output hash, so a new
    split reruns what follows ingest: frames, which writes the same frames, and manual_tracks)."""
    return digest("ingest", clip, video_sha256, cameras_sha256, split)


def _place(src: Path, dst: Path, link: bool) -> None:
    """Put a copy of ``src`` at ``dst`` atomically (hard link when allowed and possible)."""
    if dst.exists() and os.path.samefile(src, dst):
        return
    tmp = dst.with_name(f".{dst.name}.{uuid.uuid4().hex}.tmp")
    try:
        try:
            if not link:
                raise OSError
            os.link(src, tmp)
        except OSError:
            shutil.copyfile(src, tmp)
        os.replace(tmp, dst)
    finally:
        tmp.unlink(missing_ok=True)


@dataclass(frozen=True)
class CheckedInputs:
    """A clip's parsed camera file and probed video, found to belong together; ``warnings``: what
    is legal but suspicious, one line each, naming the camera file and line."""

    cameras: CameraTrack
    video: VideoInfo
    warnings: tuple[str, ...] = ()


def _aspect_errors(cameras: CameraTrack, video: VideoInfo) -> list[float]:
    """Per camera, the relative difference between the frame aspect its intrinsics imply and the video's."""
    fx, fy = cameras.intrinsics[:, 0], cameras.intrinsics[:, 1]
    ratio = (fy / fx) / (video.pixel_aspect * video.width / video.height)
    return [math.expm1(abs(math.log(r))) for r in ratio.tolist()]


def _aspect_message(cameras: CameraTrack, index: int, video: VideoInfo, path: Path) -> str:
    """Why camera ``index`` does not fit ``video`` (the implied and the real frame aspect)."""
    fx, fy = cameras.intrinsics[index, :2].tolist()
    implied = fy / fx / video.pixel_aspect
    pixels = f", pixel aspect {video.pixel_aspect:.4g}" if video.pixel_aspect != 1.0 else ""
    return (f"fy/fx = {fy / fx:.4g} fits frames of aspect {implied:.4g} (width/height) but {path} is "
            f"{video.width}x{video.height} ({video.width / video.height:.4g}{pixels})")


def check_clip_inputs(video: Path, cameras: Path) -> CheckedInputs:
    """Parse ``cameras``, probe ``video`` and check that they belong together: no camera past the
    video's end (give or take END_TOLERANCE_US), intrinsics for the video's frame aspect
    (ASPECT_ERROR; ASPECT_WARNING gives a warning).

    Raises:
      CameraFileError: a malformed camera file, or a camera line that does not fit the video
        (naming the camera file and line).
      VideoError: an unreadable video.
    """
    track = parse_camera_file(cameras)
    info = probe_video(video)
    if info.duration_us:
        past = [i for i, t in enumerate(track.timestamps_us.tolist()) if t > info.duration_us + END_TOLERANCE_US]
        if past:
            raise CameraFileError(str(cameras), past[0] + 2, (
                f"timestamp {int(track.timestamps_us[past[0]])} µs is past the end of {video}, which lasts "
                f"{info.duration_us} µs ({len(past)} of the {len(track)} cameras are past it)"))
    errors = _aspect_errors(track, info)
    bad = [i for i, e in enumerate(errors) if e > ASPECT_ERROR]
    if bad:
        raise CameraFileError(str(cameras), bad[0] + 2, (
            f"{_aspect_message(track, bad[0], info, video)}: the intrinsics are another video's "
            f"(differ by {errors[bad[0]]:.0%}, more than {ASPECT_ERROR:.0%})"))
    worst = max(range(len(errors)), key=errors.__getitem__)
    warnings = ()
    if errors[worst] > ASPECT_WARNING:
        warnings = (f"{cameras}:{worst + 2}: {_aspect_message(track, worst, info, video)} "
                    f"(differ by {errors[worst]:.1%}: non-square pixels or a cropped video?)",)
    return CheckedInputs(track, info, warnings)


def ingest_clip(
    wh: Warehouse, cfg: IngestConfig, source: ClipSource, video_sha256: str, cameras_sha256: str, run_id: str
) -> StageOutput:
    """Validate ``source`` (:func:`check_clip_inputs`; its warnings become the stage's message) and
    register it (see module docstring). ``run_id`` is unused by ingest."""
    checked = check_clip_inputs(source.video, source.cameras)
    cameras, info = checked.cameras, checked.video
    last = int(cameras.timestamps_us[-1])
    inputs = wh.inputs_dir(source.clip)
    inputs.mkdir(parents=True, exist_ok=True)
    for old in inputs.glob("video.*"):  # a re-ingest with another container format
        if old.suffix.lower() != source.video.suffix.lower():
            old.unlink()
    video_dst = inputs / f"video{source.video.suffix.lower()}"
    cameras_dst = inputs / CAMERAS_FILE
    _place(source.video, video_dst, cfg.link_inputs)
    _place(source.cameras, cameras_dst, cfg.link_inputs)
    row = {
        "clip": source.clip,
        "url": cameras.url,
        "source_video": str(source.video),
        "source_cameras": str(source.cameras),
        "video_path": wh.relative(video_dst),
        "cameras_path": wh.relative(cameras_dst),
        "video_sha256": video_sha256,
        "cameras_sha256": cameras_sha256,
        "num_cameras": len(cameras),
        "first_timestamp_us": int(cameras.timestamps_us[0]),
        "last_timestamp_us": last,
        "width": info.width,
        "height": info.height,
        "fps": info.fps,
        "duration_us": info.duration_us,
        "codec": info.codec,
        "ingested_at": dt.datetime.now(dt.timezone.utc),
        "split": source.split,
    }
    rows = wh.write("clips", source.clip, pa.Table.from_pylist([row]))
    return StageOutput(rows, ingest_inputs_hash(source.clip, video_sha256, cameras_sha256, source.split),
                       message="; ".join(checked.warnings))


def clip_inputs(wh: Warehouse, clip: str) -> tuple[Path, Path, dict]:
    """The warehouse's copies of a registered clip's video and camera file, and its ``clips`` row."""
    rows = wh.read("clips", partitions=[clip]).to_pylist()
    if not rows:
        raise WarehouseError(f"clip {clip!r} is not ingested (see `cadestate status`)")
    row = rows[0]
    return wh.root / row["video_path"], wh.root / row["cameras_path"], row


def clip_split(row: dict) -> str:
    """The split of a ``clips`` row (``train`` for clips ingested before splits existed)."""
    return row.get("split") or DEFAULT_SPLIT


def registered_splits(wh: Warehouse) -> dict[str, str]:
    """clip -> split of every registered clip (what a re-ingest keeps unless told otherwise)."""
    return {r["clip"]: clip_split(r) for r in wh.read("clips").to_pylist()}


def registered_source(wh: Warehouse, clip: str) -> ClipSource:
    """A registered clip as a :class:`ClipSource` of the warehouse's copies, with its split (what
    ``cadestate run`` and label ingest rerun: the same clip, so cached)."""
    video, cameras, row = clip_inputs(wh, clip)
    return ClipSource(clip, video, cameras, clip_split(row))


def official_clip_name(track: CameraTrack, cameras: Path, given: str | None = None) -> str:
    """The clip's name in the official convention, ``<video_id>_<first timestamp µs>``
    (:mod:`tasks.clip_names`): derived from the camera file (its URL line and first timestamp), or
    ``given`` once checked against them. Raises :class:`ClipNameError` naming the file."""
    first = int(track.timestamps_us[0])
    if given:
        check_clip_name(given, track.url, first, str(cameras))
        return given
    return derive_clip_name(track.url, first, str(cameras))


def check_video_ids(wh: Warehouse, new: dict[str, str]) -> None:
    """Refuse clips ``new`` (name -> URL line) whose video id another clip of the warehouse (or of
    ``new``) has with a different URL: the official layout keeps a video's frames under its id."""
    known = {r["clip"]: r["url"] for r in wh.read("clips", columns=["clip", "url"]).to_pylist()}
    clash = shared_video_ids({**known, **new}.items())
    if clash:
        vid, names = next(iter(clash.items()))
        raise ClipNameError(f"clips {', '.join(names)} come from different videos (line 1 of their camera files) but "
                            f"share the video id {vid!r}: give one of them its own name with --clip")
