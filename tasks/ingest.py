"""Stage ``ingest``: validate a clip's video and camera file, keep them in the warehouse, register the clip.

Reads: a video file and a RealEstate10K camera file. Writes: ``inputs/<clip>/video<ext>``,
``inputs/<clip>/cameras.txt`` and the clip's row of ``clips``. Fails (writing nothing) on a
malformed camera file, an unreadable video, or cameras that ask for times past the video's end.
"""

from __future__ import annotations

import datetime as dt
import os
import shutil
import uuid
from dataclasses import dataclass
from pathlib import Path

import pyarrow as pa

from cadestate.config import IngestConfig
from cadestate.lineage import digest
from schemas.core import DEFAULT_SPLIT
from tasks.cameras import parse_camera_file
from tasks.stage import StageOutput
from tasks.video import VideoError, probe_video
from warehouse import Warehouse, WarehouseError, check_name

VIDEO_SUFFIXES = (".mp4", ".mkv", ".webm", ".mov", ".avi")
CAMERAS_FILE = "cameras.txt"
END_TOLERANCE_US = 100_000
"""Camera timestamps may exceed the stream's declared duration by this much (last frame's length)."""


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


def ingest_clip(
    wh: Warehouse, cfg: IngestConfig, source: ClipSource, video_sha256: str, cameras_sha256: str, run_id: str
) -> StageOutput:
    """Validate ``source`` and register it (see module docstring). ``run_id`` is unused by ingest."""
    cameras = parse_camera_file(source.cameras)
    info = probe_video(source.video)
    last = int(cameras.timestamps_us[-1])
    if info.duration_us and last > info.duration_us + END_TOLERANCE_US:
        raise VideoError(
            f"{source.video}: the video lasts {info.duration_us} µs but {source.cameras} asks for a frame "
            f"at {last} µs (line {len(cameras) + 1})"
        )
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
    return StageOutput(rows, ingest_inputs_hash(source.clip, video_sha256, cameras_sha256, source.split))


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
