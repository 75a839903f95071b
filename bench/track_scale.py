"""Tracking at clip scale (issue 21): time and peak memory of the whole ``tracking`` computation
(:func:`tasks.tracking.tracking.track_detections`: pair cues, affinities, solver) on synthetic clips
of 5k to 35k detections, each measured in a fresh subprocess so its peak RSS is its own.

    python -m bench.track_scale [N ...]     # default 5000 20000 35000; prints one JSON row per size

The synthetic clip (:func:`synthetic_clip`) is a camera panning slowly across a room of static
objects: each object is seen over an interval of frames, its box carried from frame to frame by
the camera rotation (plus jitter), its 768-d descriptor its own look plus noise, its label one of
a few classes (sometimes flipped, as a detector's are); a few clutter boxes a frame. It is built
so the cues and the calibrated weights look like a real clip's, not to be a faithful video.
"""

from __future__ import annotations

import gc
import json
import subprocess
import sys
import time
from dataclasses import dataclass

import numpy as np

from tasks.tracking.affinity import Cameras, rotation_warp

DESCRIPTOR_DIM = 768
"""Length of the embedder's descriptors (the memory of the appearance cue scales with it)."""
SIZES = (5000, 20000, 35000)
"""Detections per synthetic clip in the benchmark (35k: a 10-minute clip at the demo's frame rate)."""


@dataclass(frozen=True)
class SyntheticClip:
    """N detections: ids int64[N], frame int64[N], boxes float64[N,4] (normalised ymin, xmin,
    ymax, xmax), labels object[N], descriptors float32[N,D], cameras, true object int64[N] (-1: clutter)."""

    det_id: np.ndarray
    frame_index: np.ndarray
    boxes: np.ndarray
    labels: np.ndarray
    vectors: np.ndarray
    cameras: Cameras
    truth: np.ndarray


def _cameras(frames: int, yaw_per_frame: float) -> Cameras:
    """A 640x360 camera (fx = fy = 500) turning about its vertical axis by ``yaw_per_frame`` radians a frame."""
    K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 180.0], [0.0, 0.0, 1.0]])
    t = yaw_per_frame * np.arange(frames)
    c, s = np.cos(t), np.sin(t)
    R = np.zeros((frames, 3, 3))
    R[:, 0, 0], R[:, 0, 2], R[:, 1, 1], R[:, 2, 0], R[:, 2, 2] = c, -s, 1.0, s, c
    return Cameras(np.repeat(K[None], frames, axis=0), R, 640, 360)


def synthetic_clip(n: int, seed: int = 0, per_frame: int = 8, life: int = 40, dim: int = DESCRIPTOR_DIM,
                   clutter: float = 0.1, miss: float = 0.1, label_flip: float = 0.05) -> SyntheticClip:
    """Exactly ``n`` detections, about ``per_frame`` a frame: objects seen over ``life`` frames each
    (missed in ``miss`` of them), ``clutter`` of the boxes false positives, ``label_flip`` of the
    labels wrong."""
    rng = np.random.default_rng(seed)
    frames = max(2, int(np.ceil(n / per_frame)))
    cams = _cameras(frames, 0.004)
    n_obj = max(1, int(np.ceil(frames * per_frame * (1 - clutter) / (life * (1 - miss)))))
    first = rng.integers(-life // 2, frames - life // 2, n_obj)
    obj = np.repeat(np.arange(n_obj), life)
    f = np.repeat(first, life) + np.tile(np.arange(life), n_obj)
    keep = (f >= 0) & (f < frames) & (rng.random(len(f)) >= miss)
    obj, f = obj[keep], f[keep]
    n_clutter = max(0, n - len(f)) if len(f) < n else int(clutter * n)
    obj = np.concatenate([obj, np.full(n_clutter, -1)])
    f = np.concatenate([f, rng.integers(0, frames, n_clutter)])
    pick = np.sort(rng.permutation(len(f))[:n])  # exactly n, a uniform subset
    obj, f = obj[pick], f[pick]
    looks = rng.normal(0, 1, (n_obj, dim)).astype(np.float32)
    cls = rng.integers(0, 6, n_obj)
    size = rng.uniform(0.1, 0.3, (n_obj, 2))
    centre = rng.uniform(0.25, 0.75, (n_obj, 2))
    is_clutter = obj < 0
    o = np.maximum(obj, 0)
    box0 = np.concatenate([centre[o] - size[o] / 2, centre[o] + size[o] / 2], axis=1)
    boxes = rotation_warp(box0, np.clip(first[o], 0, frames - 1), f, cams) + rng.normal(0, 0.01, (n, 4))
    small = rng.uniform(0, 0.9, (n, 2))
    boxes[is_clutter] = np.concatenate([small, small + 0.08], axis=1)[is_clutter]
    vectors = looks[o] + rng.normal(0, 0.8, (n, dim)).astype(np.float32)
    vectors[is_clutter] = rng.normal(0, 1, (int(is_clutter.sum()), dim)).astype(np.float32)
    label_id = np.where(rng.random(n) < label_flip, rng.integers(0, 6, n), cls[o])
    labels = np.array([f"class{k}" for k in label_id], dtype=object)
    order = np.lexsort((rng.random(n), f))
    det_id = np.arange(n, dtype=np.int64)  # in frame order, as the detect stage numbers them
    return SyntheticClip(det_id, f[order], boxes[order], labels[order], vectors[order], cams, obj[order])


def _rss_mb(field: str) -> float:
    """``VmRSS`` (now) or ``VmHWM`` (peak since the last reset) of this process in MB, from /proc."""
    with open("/proc/self/status") as f:
        line = next(x for x in f if x.startswith(field + ":"))
    return int(line.split()[1]) / 1024


def measure(n: int, seed: int = 0) -> dict:
    """Track a synthetic clip of ``n`` detections in this process: wall and CPU seconds of
    :func:`track_detections` (the clip is built before the clock starts), the number of pairs, the
    process's RSS before tracking (interpreter, libraries, the clip) and its peak while tracking, in
    MB (the peak is reset after building the clip by writing 5 to /proc/self/clear_refs; Linux)."""
    from cadestate.config import TrackingConfig
    from tasks.tracking.tracking import track_detections

    clip = synthetic_clip(n, seed)
    gc.collect()
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")  # resets VmHWM to the current RSS
    before = _rss_mb("VmRSS")
    t0, c0 = time.perf_counter(), time.process_time()
    res = track_detections(clip.det_id, clip.frame_index, clip.boxes, clip.labels, clip.vectors, clip.cameras,
                           TrackingConfig())
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {"detections": n, "pairs": int(len(res.pairs.a)), "tracks": int(res.track.max()) + 1,
            "seconds": round(wall, 2), "cpu_seconds": round(cpu, 2), "rss_before_mb": round(before, 1),
            "peak_rss_mb": round(_rss_mb("VmHWM"), 1)}


def measure_in_subprocess(n: int, seed: int = 0) -> dict:
    """:func:`measure` in a fresh Python process (so the peak RSS is that clip's alone)."""
    out = subprocess.run([sys.executable, "-m", "bench.track_scale", "--one", str(n), str(seed)],
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def run(sizes=SIZES) -> list[dict]:
    """:func:`measure_in_subprocess` per size."""
    return [measure_in_subprocess(n) for n in sizes]


def main(argv: list[str]) -> None:
    if argv[:1] == ["--one"]:
        print(json.dumps(measure(int(argv[1]), int(argv[2]))))
        return
    for n in [int(x) for x in argv] or SIZES:
        print(json.dumps(measure_in_subprocess(n)), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
