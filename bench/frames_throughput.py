"""Frame extraction throughput on the paper's average clip: 138 camera lines, 640x360, 30 fps.

Measures the ``frames`` stage as the pipeline runs it (decode at every camera timestamp, save
JPEGs, write the table) and decoding alone, each as the median of ``repeats`` runs.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

from bench.demo_clip import DemoClipSpec, make_demo_clip
from cadestate.config import FramesConfig, IngestConfig
from cadestate.lineage import file_sha256
from tasks.video.camera_file import parse_camera_file
from tasks.video.decode import decode_at
from tasks.video.frames import extract_frames
from tasks.video.ingest import ClipSource, ingest_clip
from warehouse import Warehouse

SPEC = DemoClipSpec(name="bench_138", width=640, height=360, fps=30, num_video_frames=276, sample_every=2, seed=7)


def run(cache_dir: Path, repeats: int = 5) -> dict:
    """Generate the clip once into ``cache_dir`` and time extraction on it."""
    video, cameras = cache_dir / f"{SPEC.name}.mp4", cache_dir / f"{SPEC.name}.txt"
    if not (video.exists() and cameras.exists()):
        make_demo_clip(cache_dir, SPEC)
    timestamps = parse_camera_file(cameras).timestamps_us
    decode_s, stage_s = [], []
    for i in range(repeats):
        t0 = time.perf_counter()
        for _ in decode_at(video, timestamps):
            pass
        decode_s.append(time.perf_counter() - t0)
        with tempfile.TemporaryDirectory() as tmp:
            wh = Warehouse(tmp)
            source = ClipSource(SPEC.name, video, cameras)
            ingest_clip(wh, IngestConfig(), source, file_sha256(video), file_sha256(cameras), "r")
            t0 = time.perf_counter()
            extract_frames(wh, FramesConfig(), SPEC.name, f"run{i}", show_progress=False)
            stage_s.append(time.perf_counter() - t0)
    n = len(timestamps)
    return {
        "clip": f"{n} camera lines, {SPEC.width}x{SPEC.height}, {SPEC.num_video_frames} H.264 frames at {SPEC.fps} fps",
        "frames_stage_fps": round(n / statistics.median(stage_s), 1),
        "frames_stage_s": round(statistics.median(stage_s), 3),
        "decode_only_fps": round(n / statistics.median(decode_s), 1),
        "repeats": repeats,
    }
