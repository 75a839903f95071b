"""Stage ``frames``: extract the video frame at every camera timestamp.

Reads: the clip's ``clips`` row and its video and camera file in ``inputs/<clip>/``.
Writes: one image per camera line under ``media/frames/<clip>/<run_id>/`` and the clip's
``frames`` partition (camera in pixels, world->camera and camera->world; see
:mod:`cadestate.geometry`). Fails, writing nothing, when the video is corrupt or truncated or a
decoded frame is further than ``max_timestamp_error_us`` from its camera timestamp.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pyarrow as pa
from PIL import Image

from cadestate.config import FramesConfig
from cadestate.geometry import camera_to_world, intrinsics_matrix
from cadestate.lineage import digest, file_sha256, table_digest
from cadestate.progress import progress
from tasks.cameras import CameraTrack, parse_camera_file
from tasks.ingest import clip_inputs
from tasks.stage import StageOutput
from tasks.video import VideoError, decode_at
from warehouse import Warehouse

MEDIA_KIND = "frames"


def image_name(timestamp_us: int, image_format: str) -> str:
    """File name of the frame at ``timestamp_us`` (zero-padded so names sort by time)."""
    return f"{timestamp_us:013d}.{image_format}"


def frames_table(clip: str, cameras: CameraTrack, image_paths: list[str], width: int, height: int,
                 video_times_us: np.ndarray) -> pa.Table:
    """Rows of ``frames`` for one clip: float64 matrices flattened row-major."""
    n = len(cameras)
    K = intrinsics_matrix(cameras.intrinsics, width, height)
    R_cw, centre = camera_to_world(cameras.R, cameras.t)
    ts = cameras.timestamps_us
    return pa.table({
        "clip": [clip] * n,
        "timestamp_us": ts,
        "frame_index": np.arange(n, dtype=np.int32),
        "image_path": image_paths,
        "width": np.full(n, width, dtype=np.int32),
        "height": np.full(n, height, dtype=np.int32),
        "video_time_us": video_times_us,
        "timestamp_error_us": video_times_us - ts,
        "intrinsics": list(cameras.intrinsics),
        "K": list(K.reshape(n, 9)),
        "world_to_camera_R": list(cameras.R.reshape(n, 9)),
        "world_to_camera_t": list(cameras.t),
        "camera_to_world_R": list(R_cw.reshape(n, 9)),
        "camera_center": list(centre),
    })


def _save(rgb: np.ndarray, path: Path, cfg: FramesConfig) -> None:
    image = Image.fromarray(rgb)
    if cfg.image_format == "jpg":
        image.save(path, quality=cfg.jpeg_quality)
    else:
        image.save(path, compress_level=1)


def extract_frames(wh: Warehouse, cfg: FramesConfig, clip: str, run_id: str, show_progress: bool = True) -> StageOutput:
    """Extract the clip's frames and write its ``frames`` partition (see module docstring)."""
    video, cameras_path, row = clip_inputs(wh, clip)
    cameras = parse_camera_file(cameras_path)
    name = f"clip {clip} ({row['source_video']})"  # errors name the user's file, not the warehouse copy
    times = np.empty(len(cameras), dtype=np.int64)
    names = [image_name(int(t), cfg.image_format) for t in cameras.timestamps_us]
    with wh.staging() as staged, ThreadPoolExecutor(max_workers=2) as pool:
        saving = []
        decoded = decode_at(video, cameras.timestamps_us, cfg.seek_threshold_us)
        for i, frame in enumerate(progress(decoded, total=len(cameras), description=f"frames {clip}", enabled=show_progress)):
            err = frame.time_us - int(cameras.timestamps_us[i])
            if abs(err) > cfg.max_timestamp_error_us:
                raise VideoError(
                    f"{name}: camera line {i + 2} asks for {cameras.timestamps_us[i]} µs but the nearest video frame "
                    f"is at {frame.time_us} µs ({err:+d} µs; [frames] max_timestamp_error_us = {cfg.max_timestamp_error_us}). "
                    "Wrong camera file for this video, or a truncated video?"
                )
            if frame.rgb.shape[:2] != (row["height"], row["width"]):
                raise VideoError(f"{name}: frame at {frame.time_us} µs is {frame.rgb.shape[1]}x{frame.rgb.shape[0]}, "
                                 f"expected {row['width']}x{row['height']}")
            times[i] = frame.time_us
            saving.append(pool.submit(_save, frame.rgb, staged / names[i], cfg))
        for job in saving:
            job.result()
        images_digest = digest(*(file_sha256(staged / name) for name in names))
        final = wh.publish_media(MEDIA_KIND, clip, staged, run_id)
    image_paths = [wh.relative(final / name) for name in names]
    table = frames_table(clip, cameras, image_paths, row["width"], row["height"], times)
    rows = wh.write("frames", clip, table)
    wh.prune_media(MEDIA_KIND, clip, keep=run_id)
    # The output digest covers the cameras, decoded times and image bytes, not the run-specific image folder.
    return StageOutput(rows, digest(table_digest(table.drop_columns(["image_path"])), images_digest))
