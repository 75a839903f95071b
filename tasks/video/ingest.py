"""Stage ``ingest``: validate a clip's video and camera file, keep them in the warehouse, register the clip.

Reads: a video file and a RealEstate10K camera file (given, or written by the ``cameras`` stage
from the video: ``inputs/<clip>/cameras.sfm.txt``). Writes: ``inputs/<clip>/video<ext>``,
``inputs/<clip>/cameras.txt`` and the clip's row of ``clips``, with the clip's time offset (camera
timestamp - video time, µs) and the rotation that turns the camera file's world to +Y up
(:mod:`tasks.video.world_up`; ``[ingest] up``). Fails (writing nothing) on a malformed camera file, an
unreadable video, cameras that ask for times outside the video (after the offset), or intrinsics
made for another frame shape (:func:`check_clip_inputs`, which ``cadestate ingest`` also runs
before it starts anything).
"""

from __future__ import annotations

import datetime as dt
import json
import math
import os
import shutil
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
import pyarrow as pa

from cadestate.atomic import TMP_SUFFIX, fsync_dir
from cadestate.config import FramesConfig, IngestConfig
from cadestate.geometry import camera_to_world
from cadestate.lineage import digest, file_sha256, known_file_sha256
from schemas.core import DEFAULT_SPLIT
from tasks.stage import StageContext, StageDef, StageOutput
from tasks.video.camera_file import (FOCAL_RANGE, FOV_RANGE_DEG, CameraFileError, CameraTrack, is_camera_line,
                                     parse_camera_file)
from tasks.video.clip_names import ClipNameError, check_clip_name, derive_clip_name, shared_video_ids, video_id_of
from tasks.video.decode import VideoInfo, decode_at, frame_times_us, probe_video
from tasks.video.inputs import clip_split, ingest_source_digest, registered_inputs
from tasks.video.placed import record_placed
from tasks.video.vertical_lines import video_segment_normals
from tasks.video.world_up import UpEstimate, estimate_up
from warehouse import Warehouse, WarehouseError, check_name

VIDEO_SUFFIXES = (".mp4", ".mkv", ".webm", ".mov", ".avi")
CAMERAS_FILE = "cameras.txt"
SFM_CAMERAS_FILE = "cameras.sfm.txt"
"""The ``cameras`` stage's camera file of a clip ingested without one, in ``inputs/<clip>/``."""
SFM_REPORT_FILE = "cameras.sfm.json"
"""Beside it: what SfM registered (per camera line: registered or interpolated), in ``inputs/<clip>/``."""
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
    """A clip to ingest: its name, its video file, its RealEstate10K camera file (None: none was
    given, the ``cameras`` stage derives one by SfM), its dataset split (``train``, ``val``,
    ``test``: the val/test clips get the manual-track task), ``time_offset_us`` (camera timestamp -
    video time, µs; RealEstate10K counts from the start of the full YouTube video) and, for SfM,
    ``intrinsics`` (fx, fy, cx, cy in pixels, fixed; None: estimated)."""

    clip: str
    video: Path
    cameras: Path | None
    split: str = DEFAULT_SPLIT
    time_offset_us: int = 0
    intrinsics: tuple[float, float, float, float] | None = None

    def __post_init__(self) -> None:
        check_name(self.clip)
        check_name(self.split, "split")

    @cached_property
    def video_sha256(self) -> str:
        """SHA-256 of the video file, read once per source (and per process while the file stays the same)."""
        return known_file_sha256(self.video)


def sfm_cameras_path(wh: Warehouse, clip: str) -> Path:
    """Where the ``cameras`` stage writes the SfM camera file of ``clip``."""
    return wh.inputs_dir(clip) / SFM_CAMERAS_FILE


def cameras_file(wh: Warehouse, source: ClipSource) -> Path:
    """The camera file ingest reads: the given one, else the ``cameras`` stage's."""
    return source.cameras if source.cameras is not None else sfm_cameras_path(wh, source.clip)


def discover_clips(folder: str | os.PathLike) -> list[tuple[Path, Path]]:
    """The clip inputs of a folder: (video, camera file) pairs, each ``<name>.<video suffix>`` with
    ``<name>.txt``. The clips are named from their camera files (:func:`official_clip_name`), not
    from the file names, which may hold any character (``living room.mp4``).

    A video without a camera file is an error (naming it), since SfM cameras come later; so is a
    camera file (a ``.txt`` whose second line is a camera line) without a video of a suffix read
    (a ``.m4v`` beside it): its clip was left out of the batch without a word.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: not a folder")
    videos = sorted(p for p in folder.iterdir() if p.suffix.lower() in VIDEO_SUFFIXES)
    if not videos:
        raise FileNotFoundError(f"{folder}: no video files ({', '.join(VIDEO_SUFFIXES)})")
    pairs = []
    for video in videos:
        cameras = video.with_suffix(".txt")
        if not cameras.is_file():
            raise FileNotFoundError(f"{video}: no camera file {cameras.name} beside it")
        pairs.append((video, cameras))
    paired = {c for _, c in pairs}
    for text in sorted(p for p in folder.iterdir() if p.suffix == ".txt" and p not in paired and _is_camera_file(p)):
        raise FileNotFoundError(f"{text}: a camera file with no video beside it ({', '.join(text.stem + s for s in VIDEO_SUFFIXES)}): "
                                "its clip would be left out")
    return pairs


def _is_camera_file(path: Path) -> bool:
    """Whether ``path``'s second line is a camera line (its first is the video's URL)."""
    try:
        with path.open("rb") as f:
            lines = [f.readline(4096) for _ in range(2)]
    except OSError:
        return False
    return is_camera_line(lines[1].decode("utf-8", "replace"))


def ingest_inputs_hash(clip: str, video_sha256: str, cameras_sha256: str, split: str = DEFAULT_SPLIT,
                       time_offset_us: int = 0) -> str:
    """Lineage digest of a clip's inputs, split and time offset (also the ingest stage's output
    hash, so a new split reruns what follows ingest: frames, which writes the same frames, and
    manual_tracks). An offset of 0 leaves the digest of clips ingested before offsets existed."""
    if time_offset_us:
        return digest("ingest", clip, video_sha256, cameras_sha256, split, f"offset={int(time_offset_us)}")
    return digest("ingest", clip, video_sha256, cameras_sha256, split)
def _place(src: Path, dst: Path, link: bool) -> None:
    """Put a copy of ``src`` at ``dst`` atomically and durably (a hard link when allowed and
    possible; a copy is on disk before it is renamed, and the rename before this returns: the
    ``clips`` row written next, durable, names it)."""
    if dst.exists() and os.path.samefile(src, dst):
        return
    tmp = dst.with_name(f".{dst.name}.{uuid.uuid4().hex}{TMP_SUFFIX}")
    try:
        try:
            if not link:
                raise OSError
            os.link(src, tmp)
        except OSError:
            shutil.copyfile(src, tmp)
            with open(tmp, "rb") as copied:
                os.fsync(copied.fileno())
        os.replace(tmp, dst)
        fsync_dir(dst.parent)
    finally:
        tmp.unlink(missing_ok=True)


@dataclass(frozen=True)
class CheckedInputs:
    """A clip's parsed camera file and probed video, found to belong together; ``warnings``: what
    is legal but suspicious, one line each, naming the camera file and line."""

    cameras: CameraTrack
    video: VideoInfo
    warnings: tuple[str, ...] = ()
    time_offset_us: int = 0


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


def align_start_offset(track: CameraTrack, info: VideoInfo, cameras: Path, video: Path) -> int:
    """``--align-start``: the offset that maps the first camera timestamp to the video's first
    frame (time 0), allowed only when every timestamp lies past the video's end (a clip cut from
    the video its camera file counts from). Raises :class:`CameraFileError` otherwise."""
    first = int(track.timestamps_us[0])
    if not info.duration_us or first <= info.duration_us + END_TOLERANCE_US:
        raise CameraFileError(str(cameras), 2, (
            f"--align-start: the first timestamp ({first} µs) lies within {video}, which lasts {info.duration_us} µs, "
            "so the camera file may well count from this video's start; give --time-offset-us explicitly"))
    return first


def _check_times(track: CameraTrack, info: VideoInfo, video: Path, cameras: Path, offset: int) -> None:
    """Every camera's video time (timestamp - offset) within the video (give or take END_TOLERANCE_US)."""
    times = track.timestamps_us - offset
    before = np.flatnonzero(times < -END_TOLERANCE_US)
    if before.size:
        i = int(before[0])
        raise CameraFileError(str(cameras), i + 2, (
            f"timestamp {int(track.timestamps_us[i])} µs minus the time offset {offset} µs is before the start of {video}"))
    if not info.duration_us:
        return
    past = np.flatnonzero(times > info.duration_us + END_TOLERANCE_US)
    if past.size:
        i = int(past[0])
        hint = ""
        if past.size == len(track) and not offset:
            hint = (": all cameras lie past its end, so the camera file counts from the start of a longer video; "
                    "give --time-offset-us N, or --align-start to map its first timestamp to the video's first frame")
        shifted = f" minus the time offset {offset} µs" if offset else ""
        raise CameraFileError(str(cameras), i + 2, (
            f"timestamp {int(track.timestamps_us[i])} µs{shifted} is past the end of {video}, which lasts "
            f"{info.duration_us} µs ({past.size} of the {len(track)} cameras are past it){hint}"))


def _check_frame_times(track: CameraTrack, video: Path, cameras: Path, offset: int, tolerance_us: int) -> None:
    """Every camera has a video frame within ``tolerance_us`` of its time: the first and the last
    decoded (a truncated file, or one whose stream states no duration), every one against the
    frame times the video's packets state (:func:`frame_times_us`: a 60 fps camera file on a 30 fps
    video has every other camera between two frames). Caught before anything starts, not by the
    frames stage, and before a re-ingest replaces a clip's camera file."""
    shifted = f" minus the time offset {offset} µs" if offset else ""

    def refuse(line: int, nearest: int, target: int) -> None:
        raise CameraFileError(str(cameras), line + 2, (
            f"timestamp {int(track.timestamps_us[line])} µs{shifted} has no frame in {video}: the nearest is at "
            f"{nearest} µs ({nearest - target:+d} µs; [frames] max_timestamp_error_us = {tolerance_us}): "
            "a truncated video, or one of another frame rate than the camera file's?"))

    lines = sorted({0, len(track) - 1})
    targets = track.timestamps_us[lines] - offset
    for line, target, frame in zip(lines, targets.tolist(), decode_at(video, np.maximum(targets, 0))):
        if abs(frame.time_us - target) > tolerance_us:
            refuse(line, frame.time_us, target)
    times = frame_times_us(video)
    if times is None or not times.size:
        return
    targets = np.asarray(track.timestamps_us, np.int64) - offset
    after = np.clip(np.searchsorted(times, targets), 1, len(times) - 1) if len(times) > 1 else np.zeros(len(targets), int)
    before = np.maximum(after - 1, 0)
    nearest = np.where(np.abs(times[before] - targets) <= np.abs(times[after] - targets), times[before], times[after])
    bad = np.flatnonzero(np.abs(nearest - targets) > tolerance_us)
    if bad.size:
        refuse(int(bad[0]), int(nearest[bad[0]]), int(targets[bad[0]]))
    shared = np.flatnonzero(np.diff(nearest) == 0)  # cameras a few ms apart: a file in milliseconds passed whole
    if shared.size:
        i = int(shared[0])
        raise CameraFileError(str(cameras), i + 3, (
            f"timestamp {int(track.timestamps_us[i + 1])} µs falls on the same frame of {video} as line {i + 2}'s "
            f"({int(nearest[i])} µs): each camera needs a frame of its own (timestamps in milliseconds, not µs?)"))


def check_clip_inputs(video: Path, cameras: Path, time_offset_us: int = 0, align_start: bool = False,
                      tolerance_us: int = FramesConfig().max_timestamp_error_us) -> CheckedInputs:
    """Parse ``cameras``, probe ``video`` and check that they belong together: every camera within
    the video once ``time_offset_us`` is subtracted (give or take END_TOLERANCE_US), a frame within
    ``tolerance_us`` of every camera's time (:func:`_check_frame_times`),
    intrinsics for the video's frame aspect (ASPECT_ERROR; ASPECT_WARNING gives a warning).
    ``align_start``: the offset is :func:`align_start_offset`'s (``time_offset_us`` must then be 0);
    the result's ``time_offset_us`` is the offset in force.

    Raises:
      CameraFileError: a malformed camera file, or a camera line that does not fit the video
        (naming the camera file and line).
      VideoError: an unreadable video.
    """
    track = parse_camera_file(cameras)
    info = probe_video(video)
    if align_start:
        if time_offset_us:
            raise ValueError("--align-start and --time-offset-us exclude each other")
        time_offset_us = align_start_offset(track, info, cameras, video)
    _check_times(track, info, video, cameras, time_offset_us)
    _check_frame_times(track, video, cameras, time_offset_us, tolerance_us)
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
    return CheckedInputs(track, info, warnings, time_offset_us)


def ingest_clip(
    wh: Warehouse, cfg: IngestConfig, source: ClipSource, video_sha256: str, cameras_sha256: str, run_id: str,
    tolerance_us: int = FramesConfig().max_timestamp_error_us,
) -> StageOutput:
    """Validate ``source`` (:func:`check_clip_inputs`, with the frames stage's ``tolerance_us``; its
    warnings become the stage's message),
    find its world's up (:func:`find_up`, ``cfg.up``; an unreliable estimate is
    noted in the message and ``clips.up_note``) and register it (see module docstring).
    ``cameras_sha256`` is that of :func:`cameras_file`. ``run_id`` is unused by ingest."""
    cameras_path = cameras_file(wh, source)
    checked = check_clip_inputs(source.video, cameras_path, source.time_offset_us, tolerance_us=tolerance_us)
    cameras, info = checked.cameras, checked.video
    up = find_up(source.video, cameras, source.time_offset_us, cfg)
    last = int(cameras.timestamps_us[-1])
    inputs = wh.inputs_dir(source.clip)
    inputs.mkdir(parents=True, exist_ok=True)
    # a killed ingest's part copy of the video (Ctrl-C ends a run at once, SIGKILL): no live copy is under
    # way, as the clip's stages run under its lock (tasks.stage_chain.run_unit)
    for left in inputs.glob(f".*{TMP_SUFFIX}"):
        left.unlink(missing_ok=True)
    video_dst = inputs / f"video{source.video.suffix.lower()}"
    cameras_dst = inputs / CAMERAS_FILE
    _place(source.video, video_dst, cfg.link_inputs)
    _place(cameras_path, cameras_dst, cfg.link_inputs)
    row = {
        "clip": source.clip,
        "url": cameras.url,
        "source_video": str(source.video),
        "source_cameras": str(source.cameras if source.cameras is not None else cameras_dst),
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
        "time_offset_us": int(source.time_offset_us),
        "cameras_source": "file" if source.cameras is not None else "sfm",
        "up_rotation": up.rotation.ravel().tolist(),
        "up_source": up.source,
        "up_note": up.note,
        "up_line_segments": up.line_segments if up.source == "auto" else None,
    }
    rows = wh.write("clips", source.clip, pa.Table.from_pylist([row], schema=wh.spec("clips").schema))
    record_placed(inputs, {video_dst: video_sha256, cameras_dst: cameras_sha256})  # the files the row now names
    for old in inputs.glob("video.*"):  # a re-ingest's from another container: only once the row names the new one
        if old != video_dst:
            old.unlink()
    notes = [*checked.warnings, *([f"world up: {up.note}"] if up.note else [])]
    # The output is the registered inputs and the world they are turned into: a new up reruns frames.
    output = digest(ingest_inputs_hash(source.clip, video_sha256, cameras_sha256, source.split, source.time_offset_us),
                    up.rotation.tobytes().hex())
    return StageOutput(rows, output, message="; ".join(notes))


def find_up(video: Path, cameras: CameraTrack, time_offset_us: int, cfg: IngestConfig) -> UpEstimate:
    """The up of the camera file's world as ingest finds it: from the cameras, refined by the
    vertical lines of ``cfg.up_line_frames`` frames evenly over the clip (camera timestamp -
    ``time_offset_us`` = video time), or the axis ``cfg.up`` forces (:mod:`tasks.video.world_up`)."""
    lines = None
    if cfg.up == "auto" and cfg.up_line_frames > 0:
        index = np.unique(np.linspace(0, len(cameras) - 1, min(cfg.up_line_frames, len(cameras))).round().astype(int))
        lines = video_segment_normals(video, cameras.timestamps_us[index] - time_offset_us, cameras.intrinsics[index],
                                      cameras.R[index])
    return estimate_up(cameras.R, cfg.up, camera_to_world(cameras.R, cameras.t)[1], lines, cfg.up_line_tolerance_deg)


def clip_inputs(wh: Warehouse, clip: str) -> tuple[Path, Path, dict]:
    """The warehouse's copies of a registered clip's video and camera file, and its ``clips`` row."""
    rows = wh.read("clips", partitions=[clip]).to_pylist()
    if not rows:
        raise WarehouseError(f"clip {clip!r} is not ingested (see `cadestate status`)")
    row = rows[0]
    return wh.root / row["video_path"], wh.root / row["cameras_path"], row

def registered_splits(wh: Warehouse) -> dict[str, str]:
    """clip -> split of every registered clip (what a re-ingest keeps unless told otherwise)."""
    return {r["clip"]: clip_split(r) for r in wh.read("clips").to_pylist()}


def registered_source(wh: Warehouse, clip: str) -> ClipSource:
    """A registered clip as a :class:`ClipSource` of the warehouse's copies, with its split and, for
    an SfM clip, the intrinsics it was given (what ``cadestate run`` and label ingest rerun: the
    same clip, so cached)."""
    video, cameras, row = clip_inputs(wh, clip)
    sfm = row.get("cameras_source") == "sfm"
    return ClipSource(clip, video, None if sfm else cameras, clip_split(row), int(row.get("time_offset_us") or 0),
                      intrinsics=given_intrinsics(wh, clip) if sfm else None)


def given_intrinsics(wh: Warehouse, clip: str) -> tuple[float, float, float, float] | None:
    """The ``--intrinsics`` an SfM clip was ingested with, as its SfM report keeps them (None: none given)."""
    try:
        given = json.loads(sfm_cameras_path(wh, clip).with_name(SFM_REPORT_FILE).read_text()).get("given_intrinsics")
    except (OSError, ValueError, AttributeError):
        return None
    if not isinstance(given, list) or len(given) != 4 or not all(isinstance(v, (int, float)) for v in given):
        return None
    return tuple(float(v) for v in given)


def sfm_source(video: Path, given: str | None = None,
               intrinsics: tuple[float, float, float, float] | None = None) -> ClipSource:
    """A video to ingest without a camera file (the ``cameras`` stage derives one by SfM): named
    ``<video file stem>_0`` (:func:`tasks.video.clip_names.derive_clip_name` of its ``file://`` URL, the
    SfM camera file's line 1; its first frame is at 0 µs), or ``given`` once checked. Raises
    VideoError (unreadable video), ClipNameError, or CameraFileError (intrinsics outside the image)."""
    if video.suffix.lower() not in VIDEO_SUFFIXES:
        raise FileNotFoundError(f"{video}: not a video ({', '.join(VIDEO_SUFFIXES)}); give VIDEO [CAMERAS.txt]")
    info = probe_video(video)
    url = video.resolve().as_uri()
    if given:
        check_clip_name(given, url, 0, str(video))
    name = given or derive_clip_name(url, 0, str(video))
    if intrinsics is not None:
        fx, fy, cx, cy = intrinsics
        if not (0 <= cx <= info.width and 0 <= cy <= info.height):
            raise CameraFileError(str(video), 0, f"--intrinsics: principal point ({cx:g}, {cy:g}) px is outside the "
                                                 f"{info.width}x{info.height} frame")
        low, high = FOCAL_RANGE  # checked here, not by the SfM camera file made after all of SfM's work
        for axis, f, size in (("fx", fx, info.width), ("fy", fy, info.height)):
            if not low <= f / size <= high:
                raise CameraFileError(str(video), 0, (
                    f"--intrinsics: {axis} = {f:g} px is not a field of view of {FOV_RANGE_DEG[0]:g} to "
                    f"{FOV_RANGE_DEG[1]:g} degrees on the {info.width}x{info.height} frame ({low * size:.4g} to "
                    f"{high * size:.4g} px)"))
    return ClipSource(name, video, None, intrinsics=intrinsics)


def official_clip_name(track: CameraTrack, cameras: Path, given: str | None = None) -> str:
    """The clip's name in the official convention, ``<video_id>_<first timestamp µs>``
    (:mod:`tasks.video.clip_names`): derived from the camera file (its URL line and first timestamp), or
    ``given`` once checked against them. Raises :class:`ClipNameError` naming the file."""
    first = int(track.timestamps_us[0])
    if given:
        check_clip_name(given, track.url, first, str(cameras))
        return given
    return derive_clip_name(track.url, first, str(cameras))


def check_video_ids(wh: Warehouse, new: Sequence[tuple[str, str]]) -> None:
    """Refuse clips ``new`` (clip name, URL line) whose video id another clip of the warehouse (or of
    ``new``, or a registered clip of the same name) has with a different URL: the official layout
    keeps a video's frames under its id, so two videos under one id would mix."""
    known = [(r["clip"], r["url"]) for r in wh.read("clips", columns=["clip", "url"]).to_pylist()]
    clash = shared_video_ids([*known, *new])
    if clash:
        vid = next(iter(clash))
        pairs = sorted({(n, u.strip()) for n, u in [*known, *new] if video_id_of(n) == vid})
        listed = ", ".join(f"{n} ({u or 'no URL'})" for n, u in pairs)
        raise ClipNameError(f"clips {listed} come from different videos (line 1 of their camera files) but share the "
                            f"video id {vid!r}: give one of them its own name with --clip")


def _run(ctx: StageContext) -> StageOutput:
    source = ctx.source
    return ingest_clip(ctx.wh, ctx.cfg, source, source.video_sha256, file_sha256(cameras_file(ctx.wh, source)), ctx.run_id,
                       ctx.config.frames.max_timestamp_error_us)


def _source_inputs(source: ClipSource) -> list[str]:
    return [ingest_source_digest(source.video_sha256, source.split, source.time_offset_us)]


STAGE = StageDef(
    name="ingest", section="ingest", scope="clip", upstream=("cameras",), tables=("clips",),
    description="validate the video and camera file, find the world's up, keep them, register the clip",
    extra_sections=("frames.max_timestamp_error_us",), run=_run, source_inputs=_source_inputs, clip_inputs=registered_inputs,
)
