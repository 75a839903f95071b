"""Stage ``frames``: extract the video frame at every camera timestamp.

Reads: the clip's ``clips`` row (its time offset and up rotation) and its video and camera file
in ``inputs/<clip>/`` (and, for SfM cameras, which lines were interpolated). Writes: one image per
camera line under ``media/frames/<clip>/<digest of the images>/`` and the clip's ``frames`` partition (camera in
pixels, world->camera and camera->world in the aligned world, +Y up: the camera file's extrinsics
turned by ``clips.up_rotation``, :mod:`tasks.video.world_up`; see :mod:`cadestate.geometry`). The frame
of camera timestamp ``t`` is the video's at ``t - clips.time_offset_us``. Fails, writing nothing,
when the video is corrupt or truncated or a decoded frame is further than
``max_timestamp_error_us`` from that time.
"""

from __future__ import annotations

import json
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pyarrow as pa
from PIL import Image

from cadestate.config import FramesConfig
from cadestate.geometry import camera_to_world, intrinsics_matrix
from cadestate.lineage import digest, file_sha256, table_digest
from cadestate.progress import progress
from tasks.stage import StageContext, StageDef, StageOutput
from tasks.video.camera_file import CameraTrack, parse_camera_file
from tasks.video.decode import VideoError, decode_at
from tasks.video.ingest import SFM_REPORT_FILE, clip_inputs
from tasks.video.world_up import align_extrinsics, stored_rotation
from warehouse import Warehouse

MEDIA_KIND = "frames"


def image_name(timestamp_us: int, image_format: str) -> str:
    """File name of the frame at ``timestamp_us`` (zero-padded so names sort by time)."""
    return f"{timestamp_us:013d}.{image_format}"


def frames_table(clip: str, cameras: CameraTrack, image_paths: list[str], width: int, height: int,
                 video_times_us: np.ndarray, time_offset_us: int = 0, up_rotation: np.ndarray | None = None,
                 interpolated: np.ndarray | None = None) -> pa.Table:
    """Rows of ``frames`` for one clip: float64 matrices flattened row-major. ``up_rotation``
    float[3, 3] (default identity) turns the camera file's world into the aligned world;
    ``interpolated`` bool[N] flags SfM cameras interpolated between registered ones."""
    n = len(cameras)
    K = intrinsics_matrix(cameras.intrinsics, width, height)
    R, t = align_extrinsics(cameras.R, cameras.t, np.eye(3) if up_rotation is None else up_rotation)
    R_cw, centre = camera_to_world(R, t)
    ts = cameras.timestamps_us
    return pa.table({
        "clip": [clip] * n,
        "timestamp_us": ts,
        "frame_index": np.arange(n, dtype=np.int32),
        "image_path": image_paths,
        "width": np.full(n, width, dtype=np.int32),
        "height": np.full(n, height, dtype=np.int32),
        "video_time_us": video_times_us,
        "timestamp_error_us": video_times_us - (ts - time_offset_us),
        "intrinsics": list(cameras.intrinsics),
        "K": list(K.reshape(n, 9)),
        "world_to_camera_R": list(R.reshape(n, 9)),
        "world_to_camera_t": list(t),
        "camera_to_world_R": list(R_cw.reshape(n, 9)),
        "camera_center": list(centre),
        "camera_interpolated": np.zeros(n, dtype=bool) if interpolated is None else np.asarray(interpolated, dtype=bool),
    })


def interpolated_cameras(cameras_path: Path, n: int, sfm: bool) -> np.ndarray:
    """bool[n]: which camera lines the ``cameras`` stage interpolated (its report beside the SfM
    camera file); all false for a given camera file (``sfm`` false: a report an earlier SfM ingest
    of the clip left is not this file's)."""
    report = cameras_path.with_name(SFM_REPORT_FILE)
    if sfm and cameras_path.name == "cameras.txt" and report.is_file():
        flags = json.loads(report.read_text()).get("interpolated")
        if isinstance(flags, list) and len(flags) == n:
            return np.asarray(flags, dtype=bool)
    return np.zeros(n, dtype=bool)


def _save(rgb: np.ndarray, path: Path, cfg: FramesConfig) -> None:
    image = Image.fromarray(rgb)
    if cfg.image_format == "jpg":
        image.save(path, quality=cfg.jpeg_quality)
    else:
        image.save(path, compress_level=1)


SAVES_IN_FLIGHT = 8
"""Decoded frames waiting for the two savers at most: the stage's memory is a few frames, not the
clip (240 frames of 1280 x 720 saved as PNG held 210 of them, 580 MB)."""


def extract_frames(wh: Warehouse, cfg: FramesConfig, clip: str, run_id: str, show_progress: bool = True) -> StageOutput:
    """Extract the clip's frames and write its ``frames`` partition (see module docstring)."""
    video, cameras_path, row = clip_inputs(wh, clip)
    cameras = parse_camera_file(cameras_path)
    offset = int(row.get("time_offset_us") or 0)
    name = f"clip {clip} ({row['source_video']})"  # errors name the user's file, not the warehouse copy
    times = np.empty(len(cameras), dtype=np.int64)
    names = [image_name(int(t), cfg.image_format) for t in cameras.timestamps_us]
    video_targets = cameras.timestamps_us - offset
    shifted = f" (video time {{}} µs after the offset of {offset} µs)" if offset else ""
    with wh.staging() as staged, ThreadPoolExecutor(max_workers=2) as pool:
        saving: deque = deque()
        decoded = decode_at(video, video_targets, cfg.seek_threshold_us)
        for i, frame in enumerate(progress(decoded, total=len(cameras), description=f"frames {clip}", enabled=show_progress)):
            err = frame.time_us - int(video_targets[i])
            if abs(err) > cfg.max_timestamp_error_us:
                raise VideoError(
                    f"{row['source_cameras']}:{i + 2}: {name}: camera line {i + 2} asks for {cameras.timestamps_us[i]} µs{shifted.format(video_targets[i])} "
                    f"but the nearest video frame "
                    f"is at {frame.time_us} µs ({err:+d} µs; [frames] max_timestamp_error_us = {cfg.max_timestamp_error_us}). "
                    "Wrong camera file for this video, or a truncated video?"
                )
            if frame.rgb.shape[:2] != (row["height"], row["width"]):
                raise VideoError(f"{name}: frame at {frame.time_us} µs is {frame.rgb.shape[1]}x{frame.rgb.shape[0]}, "
                                 f"expected {row['width']}x{row['height']}")
            times[i] = frame.time_us
            saving.append(pool.submit(_save, frame.rgb, staged / names[i], cfg))
            while len(saving) > SAVES_IN_FLIGHT:  # decoding outran PNG's saving: every frame was held at once
                saving.popleft().result()
        for job in saving:
            job.result()
        images_digest = digest(*(file_sha256(staged / name) for name in names))
        version = digest(images_digest, *names)[:16]  # by content: a rerun that decodes the same images keeps their paths
        final = wh.publish_media(MEDIA_KIND, clip, staged, version, content=True)
    image_paths = [wh.relative(final / name) for name in names]
    interpolated = interpolated_cameras(cameras_path, len(cameras), row.get("cameras_source") == "sfm")
    table = frames_table(clip, cameras, image_paths, row["width"], row["height"], times, offset,
                         stored_rotation(row.get("up_rotation")), interpolated)
    rows = wh.write("frames", clip, table)
    wh.prune_media(MEDIA_KIND, clip, keep=version)
    # The output digest covers the cameras, decoded times and image bytes, not the run-specific image folder.
    return StageOutput(rows, digest(table_digest(table.drop_columns(["image_path"])), images_digest))


def _run(ctx: StageContext) -> StageOutput:
    return extract_frames(ctx.wh, ctx.cfg, ctx.unit, ctx.run_id, ctx.show_progress)


STAGE = StageDef(
    name="frames", section="frames", scope="clip", upstream=("ingest",), tables=("frames",),
    description="extract the frame at every camera timestamp",
    run=_run,
)
