"""Tables of the foundation: ``clips`` (ingest), ``frames`` (frame extraction), ``runs`` (every stage run).

Frames follow :mod:`cadestate.geometry`: world->camera ``R, t`` with ``X_cam = R @ X_world + t``,
OpenCV camera axes (x right, y down, z forward), metres (RealEstate10K worlds have an arbitrary
per-clip scale), matrices flattened row-major. The world of ``frames`` (and of every table after
it) is the **aligned world**, +Y up: the camera file's world turned by ``clips.up_rotation``
(``X_aligned = Q X_input``, :mod:`tasks.video.world_up`). Timestamps are the camera file's; with
``clips.time_offset_us`` the video is read at ``timestamp_us - time_offset_us``.
"""

from __future__ import annotations

import pyarrow as pa

from schemas.base import CLIP, TableSpec, column, vector

UTC_TS = pa.timestamp("us", tz="UTC")

CLIPS = TableSpec(
    name="clips",
    mode="replace",
    key=("clip",),
    description="One row per ingested clip: its inputs (kept in the warehouse), their hashes and the video's properties.",
    schema=pa.schema(
        [
            CLIP,
            column("url", pa.string(), "Line 1 of the camera file (the source video's URL)."),
            column("source_video", pa.string(), "Path of the video as given at ingest."),
            column("source_cameras", pa.string(), "Path of the camera file as given at ingest."),
            column("video_path", pa.string(), "The warehouse's copy of the video, relative to the warehouse root."),
            column("cameras_path", pa.string(), "The warehouse's copy of the camera file, relative to the warehouse root."),
            column("video_sha256", pa.string(), "SHA-256 of the video file."),
            column("cameras_sha256", pa.string(), "SHA-256 of the camera file."),
            column("num_cameras", pa.int32(), "Camera lines in the camera file (= frames to extract)."),
            column("first_timestamp_us", pa.int64(), "First camera timestamp.", unit="µs"),
            column("last_timestamp_us", pa.int64(), "Last camera timestamp.", unit="µs"),
            column("width", pa.int32(), "Video frame width.", unit="px"),
            column("height", pa.int32(), "Video frame height.", unit="px"),
            column("fps", pa.float64(), "Average frame rate of the video stream.", unit="1/s"),
            column("duration_us", pa.int64(), "Duration of the video stream.", unit="µs"),
            column("codec", pa.string(), "Video codec name."),
            column("ingested_at", UTC_TS, "When the clip was ingested."),
            column("split", pa.string(), "Dataset split (`cadestate ingest --split`): 'train', 'val', 'test', ...; "
                   "null (clips ingested before splits existed) reads as 'train'. [manual_tracks] splits get the "
                   "manual-track task.", nullable=True),
            column("time_offset_us", pa.int64(), "Subtracted from every camera timestamp to get the video time "
                   "(`cadestate ingest --time-offset-us / --align-start`: RealEstate10K counts from the start of the full "
                   "video, a clip cut from it starts at 0); null (older clips) reads as 0.", unit="µs", nullable=True),
            column("cameras_source", pa.string(), "'file' (a camera file was given) or 'sfm' (the `cameras` stage derived "
                   "it by structure from motion; kept as cameras_path); null reads as 'file'.", nullable=True),
            column("up_rotation", vector(9), "Q, row-major: X_aligned = Q X_input takes the camera file's world to the "
                   "aligned world (+Y up) in which frames and every later table are; null (older clips) reads as identity.",
                   frame="camera file's world -> aligned world (+Y up)", nullable=True),
            column("up_source", pa.string(), "How the up direction was found: 'auto' (from the cameras) or the axis "
                   "[ingest] up forced ('+y', ...).", nullable=True),
            column("up_note", pa.string(), "Why the automatic up estimate is unreliable ('' when it is not).", nullable=True),
            column("up_line_segments", pa.int32(), "With up 'auto': the video's vertical line segments that refined the "
                   "cameras' up estimate ([ingest] up_line_frames); 0 when they did not fix it (too few, one line seen one "
                   "way, or lines off) and the cameras' estimate stands; null when up was forced, or for older clips.", nullable=True),
        ]
    ),
)
DEFAULT_SPLIT = "train"
"""The split of a clip ingested without one."""

FRAMES = TableSpec(
    name="frames",
    mode="replace",
    key=("clip", "timestamp_us"),
    description="One row per camera line: the extracted image and its camera (intrinsics normalised, K in pixels, world->camera pose).",
    schema=pa.schema(
        [
            CLIP,
            column("timestamp_us", pa.int64(), "Camera timestamp from the camera file (as written there: with an "
                   "offset, the video time is timestamp_us - clips.time_offset_us).", unit="µs"),
            column("frame_index", pa.int32(), "0-based position of the camera line within the clip."),
            column("image_path", pa.string(), "Extracted image, relative to the warehouse root."),
            column("width", pa.int32(), "Image width.", unit="px"),
            column("height", pa.int32(), "Image height.", unit="px"),
            column("video_time_us", pa.int64(), "Presentation time of the decoded video frame used (video time).", unit="µs"),
            column("timestamp_error_us", pa.int64(), "video_time_us - (timestamp_us - clips.time_offset_us).", unit="µs"),
            column("intrinsics", vector(4), "(fx, fy, cx, cy) normalised: fx, cx by width; fy, cy by height.", frame="image, normalised [0,1], origin top-left"),
            column("K", vector(9), "Intrinsic matrix, row-major.", unit="px", frame="image, origin top-left corner, x right, y down"),
            column("world_to_camera_R", vector(9), "Rotation R of X_cam = R X_world + t, row-major (the camera file's R "
                   "times clips.up_rotation^T).", frame="aligned world (+Y up) -> camera (OpenCV: x right, y down, z forward)"),
            column("world_to_camera_t", vector(3), "Translation t of X_cam = R X_world + t.", unit="m", frame="world -> camera"),
            column("camera_to_world_R", vector(9), "R^T: camera axes as world vectors, row-major.", frame="camera -> world"),
            column("camera_center", vector(3), "Camera centre -R^T t.", unit="m", frame="aligned world (+Y up)"),
            column("camera_interpolated", pa.bool_(), "True when the camera is not SfM's own but interpolated between "
                   "its registered neighbours (the `cameras` stage); false for given camera files; null for older rows.",
                   nullable=True),
        ]
    ),
)

RUNS = TableSpec(
    name="runs",
    mode="append",
    key=("clip", "run_id"),
    description="Every stage run (completed, failed, paused or interrupted) with its lineage; CAD-library stages use the library as clip.",
    schema=pa.schema(
        [
            CLIP,
            column("run_id", pa.string(), "Unique id of this stage run: UTC start time, then 8 random hex digits (sorts by time)."),
            column("stage", pa.string(), "Stage name (= its config section)."),
            column("status", pa.string(), "completed | failed | paused | interrupted (its process ended mid-run; recorded by the clip's next run)."),
            column("config_hash", pa.string(), "Digest of the stage's config section."),
            column("inputs_hash", pa.string(), "Digest of everything the stage read (input files, upstream outputs)."),
            column("output_hash", pa.string(), "Digest of what the stage wrote; empty unless completed."),
            column("code_hash", pa.string(), "Digest of the stage's source code."),
            column("started_at", UTC_TS, "Start of the run."),
            column("duration_s", pa.float64(), "Wall time of the run.", unit="s"),
            column("rows_written", pa.int64(), "Rows the run wrote to its tables."),
            column("message", pa.string(), "Error message when failed; what it waits for when paused."),
        ]
    ),
)
