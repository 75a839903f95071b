"""Synthetic RealEstate10K-like walkthrough clips of furnished rooms, with CAD-Estate ground truth.

:func:`generate_clip` builds a room with library CAD models (:func:`bench.scene.generate_scene`),
flies a phone-like camera through it (slow dolly + pan at 1.2-1.7 m, small pitch, 30 fps), renders
every video frame with :class:`cadestate.render.Renderer` (Lambert + ambient, textures,
supersampled RGB) and writes, each file atomically:

- ``<out>/<name>.mp4``: H.264, frame ``i`` at pts ``i`` in time base ``1/fps`` (exact times);
- ``<out>/<name>.txt``: RealEstate10K camera file of every ``sample_every``-th video frame (line 1:
  ``synthetic://walkthrough/<video id>``, the video id of ``name``, :func:`tasks.video.clip_names.video_id_of`);
- ``<out>/<name>/frames.json``, ``<out>/<name>/objects.json``: the official CAD-Estate format
  (:mod:`schemas.official`; intrinsics in pixels, the camera file's normalised), one frame per camera line, one object per placed model, track boxes
  = bounding boxes of the object's visible pixels in the instance-id mask;
- ``<out>/<name>/visibility.json``: per camera line and object, visible pixels, visible fraction
  (visible / rendered alone) and truncated fraction (share of the object, rendered alone in a
  camera with twice the field of view in x and y, that falls outside the image).

Frames: see :mod:`cadestate.geometry` (world metres, +Y up; OpenCV cameras; world->camera R, t).
Deterministic in ``(seed, models, spec)``.
"""

from __future__ import annotations

import functools
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from bench.scene import Scene, generate_scene
from cadestate.geometry import hfov_intrinsics, intrinsics_matrix, look_at, matrix_to_quaternion, pixel_intrinsics, project
from cadestate.render import Camera, Instance, Lighting, Renderer, RenderMesh
from schemas.official import Frame, FramesFile, ObjectAnnotation, ObjectsFile, TrackEntry, frames_to_json, \
    objects_to_json, write_json
from tasks.video.camera_file import CameraTrack, write_camera_file
from tasks.video.clip_names import video_id_of
from tasks.video.decode import frame_timestamp_us, write_video

ROOM_INSTANCE_ID = 0
"""Instance id of the room (walls, floor, ...); object ``k`` of the scene gets id ``k + 1``."""
CAMERA_CLEARANCE_M = 0.35
"""Closest the camera gets to a wall or to any object's footprint (> 0.3 m)."""


@dataclass(frozen=True)
class WalkthroughSpec:
    """What to generate. ``width``/``height`` even (yuv420p). ``alone_scale``: resolution of the
    per-object "alone" renders in the double-field-of-view camera relative to exact (1.0 = the
    same pixel grid as the image, exact fractions; 0.5 = a ``width`` x ``height`` render)."""

    width: int = 640
    height: int = 360
    fps: int = 30
    num_video_frames: int = 276
    sample_every: int = 2
    hfov_deg: float = 65.0
    supersample: int = 2
    codec: str = "libx264"
    alone_scale: float = 0.5
    crf: int = 20


@dataclass(frozen=True, eq=False)
class ClipGroundTruth:
    """A generated clip. ``frame_indices`` int64[N] video frame of each camera line;
    ``timestamps_us`` int64[N]; ``intrinsics`` float64[4] normalised (fx, fy, cx, cy);
    ``world_to_camera`` float64[N, 3, 4] [R|t] of the camera lines; ``K`` float64[3, 3] pixels;
    ``timings`` seconds spent per phase."""

    name: str
    scene: Scene
    spec: WalkthroughSpec
    lighting: Lighting
    video_path: Path
    cameras_path: Path
    frames_path: Path
    objects_path: Path
    visibility_path: Path
    frame_indices: np.ndarray
    timestamps_us: np.ndarray
    intrinsics: np.ndarray
    K: np.ndarray
    world_to_camera: np.ndarray
    timings: dict = field(default_factory=dict)


@functools.lru_cache(maxsize=256)
def _load_mesh(path: str, mtime_ns: int) -> RenderMesh:
    return RenderMesh.from_trimesh(trimesh.load(path, force="scene"))


def load_mesh(path: Path) -> RenderMesh:
    """The canonical GLB at ``path`` as a RenderMesh (cached per path and modification time)."""
    return _load_mesh(str(path), Path(path).stat().st_mtime_ns)


def random_lighting(rng: np.random.Generator) -> Lighting:
    """Light from above at a random azimuth; ambient 0.35-0.55, diffuse 0.5-0.75."""
    az, el = rng.uniform(0, 2 * math.pi), rng.uniform(math.radians(35), math.radians(75))
    direction = (math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az))
    return Lighting(tuple(float(v) for v in direction), float(rng.uniform(0.35, 0.55)), float(rng.uniform(0.5, 0.75)))


def _smooth(s: np.ndarray) -> np.ndarray:
    """Ease-in/ease-out blended with linear motion: the camera never stops dead."""
    return 0.5 * s + 0.5 * (0.5 - 0.5 * np.cos(np.pi * s))


def camera_path(scene: Scene, spec: WalkthroughSpec, rng: np.random.Generator,
                candidates: int = 48, max_tries: int = 2000) -> np.ndarray:
    """World->camera [R|t] float64[num_video_frames, 3, 4]: a dolly from A to B (0.6-2.5 m) with a
    slight sway and bob, eye at 1.2-1.7 m, a pan of up to +-45 degrees, pitch -2..-14 degrees. Of
    ``candidates`` collision-free paths (>= CAMERA_CLEARANCE_M from walls and footprints at every
    frame) the one that keeps most object centres in view wins. Raises RuntimeError if none."""
    n = spec.num_video_frames
    s = _smooth(np.linspace(0.0, 1.0, n))
    time_s = np.arange(n) / spec.fps
    K = intrinsics_matrix(hfov_intrinsics(spec.hfov_deg, spec.width, spec.height), spec.width, spec.height)
    room = scene.room
    centres = np.array([o.translation for o in scene.objects])
    best, best_score, found = None, -1.0, 0
    for _ in range(max_tries):
        if found >= candidates:
            break
        a = np.array([rng.uniform(-room.width / 2, room.width / 2), rng.uniform(-room.depth / 2, room.depth / 2)])
        if scene.clearance(a)[0] < CAMERA_CLEARANCE_M:
            continue
        target = centres[int(rng.integers(len(centres)))][[0, 2]] if rng.uniform() < 0.7 else np.zeros(2)
        view_yaw = math.atan2(*(target - a)) + rng.uniform(-0.4, 0.4)
        move_yaw = view_yaw + rng.choice([0.0, 0.0, math.pi / 2, -math.pi / 2, math.pi]) + rng.uniform(-0.5, 0.5)
        length = rng.uniform(0.6, 2.5)
        b = a + length * np.array([math.sin(move_yaw), math.cos(move_yaw)])
        perp = np.array([math.cos(move_yaw), -math.sin(move_yaw)])
        sway = 0.06 * np.sin(2 * np.pi * time_s / rng.uniform(5, 9) + rng.uniform(0, 2 * np.pi))
        xz = a + (b - a) * s[:, None] + perp * sway[:, None]
        clear = scene.clearance(xz[::3]).min()
        if clear < CAMERA_CLEARANCE_M:
            continue
        height = rng.uniform(1.2, 1.7) + 0.015 * np.sin(2 * np.pi * time_s / rng.uniform(1.5, 3) + rng.uniform(0, 6))
        height = np.clip(height, 1.2, 1.7)
        pan = rng.uniform(-math.radians(45), math.radians(45))
        yaw = view_yaw - pan / 2 + pan * s + 0.03 * np.sin(2 * np.pi * time_s / rng.uniform(4, 8))
        pitch = rng.uniform(-math.radians(14), -math.radians(2)) + 0.02 * np.sin(2 * np.pi * time_s / rng.uniform(5, 9))
        eyes = np.stack([xz[:, 0], height, xz[:, 1]], axis=1)
        dirs = np.stack([np.cos(pitch) * np.sin(yaw), np.sin(pitch) * np.ones(n), np.cos(pitch) * np.cos(yaw)], axis=1)
        found += 1
        score = 0.0
        for i in np.linspace(0, n - 1, 6).astype(int):  # only the scored frames' poses: the winner's come last
            R, t = look_at(eyes[i], eyes[i] + dirs[i])
            uv, depth = project(K, R, t, centres)
            inside = (depth > 0.3) & (uv[:, 0] > 0) & (uv[:, 0] < spec.width) & (uv[:, 1] > 0) & (uv[:, 1] < spec.height)
            score += np.count_nonzero(inside & (depth > 1.3)) - 1.5 * np.count_nonzero(inside & (depth <= 1.3))
        score += 3.0 * min(clear, 1.0)  # prefer walks that keep well away from furniture
        if score > best_score:
            best, best_score = (eyes, dirs), score
    if best is None:
        raise RuntimeError(f"no collision-free camera path in scene {scene.seed}")
    poses = np.empty((n, 3, 4))
    for i, (eye, direction) in enumerate(zip(*best)):
        R, t = look_at(eye, eye + direction)
        poses[i] = np.concatenate([R, t[:, None]], axis=1)
    return poses


def _box_of(mask: np.ndarray) -> tuple[int, int, int, int]:
    """(row min, col min, row max + 1, col max + 1) of a non-empty bool mask."""
    rows, cols = np.any(mask, axis=1), np.any(mask, axis=0)
    r = np.flatnonzero(rows)
    c = np.flatnonzero(cols)
    return int(r[0]), int(c[0]), int(r[-1]) + 1, int(c[-1]) + 1


def generate_clip(out_dir: str | os.PathLike, name: str, seed: int, models: list[dict],
                  wh_root: str | os.PathLike, spec: WalkthroughSpec = WalkthroughSpec()) -> ClipGroundTruth:
    """Generate clip ``name`` from ``seed`` and the library rows ``models`` (``cad_models`` rows;
    meshes read from ``wh_root / mesh_path``); see the module docstring for the files."""
    if spec.width % 2 or spec.height % 2 or spec.sample_every < 1 or spec.num_video_frames < 1:
        raise ValueError(f"invalid walkthrough spec: {spec}")
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    gt_dir = out_dir / name
    gt_dir.mkdir(parents=True, exist_ok=True)
    scene = generate_scene(seed, models)
    rng = np.random.default_rng([int(seed), 0xCA3E7A])
    lighting = random_lighting(rng)
    poses = camera_path(scene, spec, rng)
    normalised = hfov_intrinsics(spec.hfov_deg, spec.width, spec.height)
    W, H = spec.width, spec.height
    K = intrinsics_matrix(normalised, W, H)
    meshes = [load_mesh(Path(wh_root) / o.mesh_path) for o in scene.objects]
    obj_instances = [Instance(m, o.object_to_world(), k + 1) for k, (m, o) in enumerate(zip(meshes, scene.objects))]
    instances = [Instance(m, np.eye(4), ROOM_INSTANCE_ID) for m in scene.room.meshes] + obj_instances
    background = (0.9, 0.9, 0.9)
    frame_indices = np.arange(0, spec.num_video_frames, spec.sample_every, dtype=np.int64)
    sampled = set(frame_indices.tolist())
    timings["setup"] = time.perf_counter() - t0

    # Wide camera for the alone renders: twice the field of view, the image's pixel grid at
    # ``alone_scale`` (scale 1: the image is exactly its central W x H block).
    a = spec.alone_scale
    Ww, Hw = int(round(2 * W * a)) // 2 * 2, int(round(2 * H * a)) // 2 * 2
    K_wide = np.array([[K[0, 0] * a, 0, (K[0, 2] + W / 2) * a], [0, K[1, 1] * a, (K[1, 2] + H / 2) * a], [0, 0, 1]])
    c0, c1 = int(round(W / 2 * a)), int(round(W / 2 * a)) + int(round(W * a))
    r0, r1 = int(round(H / 2 * a)), int(round(H / 2 * a)) + int(round(H * a))
    masks: dict[int, np.ndarray] = {}
    stats: dict[int, list[tuple[int, float, float]]] = {}
    t_alone = 0.0

    renderer = Renderer(W, H, spec.supersample)
    alone_renderer = Renderer(Ww, Hw, 1)
    try:
        def frames():
            nonlocal t_alone
            for i in range(spec.num_video_frames):
                R, t = poses[i, :, :3], poses[i, :, 3]
                result = renderer.render(instances, Camera(K, R, t, W, H), lighting, background)
                if i in sampled:
                    ta = time.perf_counter()
                    ids = result.instance_id
                    masks[i] = ids.copy()
                    wide = Camera(K_wide, R, t, Ww, Hw)
                    per_object = []
                    for k, (inst, obj) in enumerate(zip(obj_instances, scene.objects)):
                        visible = int(np.count_nonzero(ids == k + 1))
                        uv, depth = project(K_wide, R, t, obj.corners())
                        in_wide = bool(np.all(depth > 0) and uv[:, 0].max() > 0 and uv[:, 0].min() < Ww
                                       and uv[:, 1].max() > 0 and uv[:, 1].min() < Hw) or bool(
                            np.any(depth > 0) and not np.all(depth > 0))
                        if not in_wide:
                            per_object.append((visible, 0.0, 1.0))
                            continue
                        alone = alone_renderer.render([inst], wide, lighting).instance_id == k + 1
                        total = int(np.count_nonzero(alone))
                        inside = int(np.count_nonzero(alone[r0:r1, c0:c1]))
                        if total == 0 or inside == 0:
                            per_object.append((visible, 0.0 if visible == 0 else 1.0, 1.0 if total == 0 else 1.0))
                            continue
                        alone_px = inside / (a * a)
                        per_object.append((visible, min(1.0, visible / alone_px), 1.0 - inside / total))
                    stats[i] = per_object
                    t_alone += time.perf_counter() - ta
                yield result.rgb

        video_path = out_dir / f"{name}.mp4"
        t1 = time.perf_counter()
        options = {"crf": str(spec.crf), "preset": "veryfast"} if spec.codec == "libx264" else None
        write_video(video_path, frames(), spec.width, spec.height, spec.fps, spec.codec, options)
        timings["render_encode"] = time.perf_counter() - t1 - t_alone
        timings["alone_renders"] = t_alone
    finally:
        renderer.release()
        alone_renderer.release()

    t2 = time.perf_counter()
    timestamps = np.array([frame_timestamp_us(int(i), spec.fps) for i in frame_indices], dtype=np.int64)
    track = CameraTrack(url=f"synthetic://walkthrough/{video_id_of(name)}", timestamps_us=timestamps,
                        intrinsics=np.tile(normalised, (len(frame_indices), 1)),
                        world_to_camera=np.ascontiguousarray(poses[frame_indices]))
    cameras_path = out_dir / f"{name}.txt"
    write_camera_file(cameras_path, track)

    frames_file = FramesFile(name, (H, W), tuple(
        Frame(int(ts), False, tuple(float(v) for v in pixel_intrinsics(K)), tuple(float(v) for v in poses[i, :, 3]),
              tuple(float(v) for v in matrix_to_quaternion(poses[i, :, :3])))
        for i, ts in zip(frame_indices.tolist(), timestamps.tolist())))
    objects = []
    for k, obj in enumerate(scene.objects):
        entries = []
        for i, ts in zip(frame_indices.tolist(), timestamps.tolist()):
            m = masks[i] == k + 1
            if not m.any():
                continue
            y0, x0, y1, x1 = _box_of(m)
            entries.append(TrackEntry(int(ts), (y0 / H, x0 / W, y1 / H, x1 / W)))
        objects.append(ObjectAnnotation(track_id=str(k), cls=obj.class_id, is_track_automatic=False,
                                        is_mirrored=obj.mirrored, track=tuple(entries), cad_id=obj.cad_id,
                                        translation=obj.translation, rotation=obj.rotation, scale=obj.scale))
    visibility = {
        "clip_name": name, "image_size": [H, W], "alone_scale": a,
        "frames": [{"timestamp": int(ts), "frame_index": int(i), "objects": [
            {"track_id": str(k), "visible_pixels": v, "visible_fraction": round(vf, 6), "truncated_fraction": round(tf, 6)}
            for k, (v, vf, tf) in enumerate(stats[i])]}
            for i, ts in zip(frame_indices.tolist(), timestamps.tolist())],
    }
    frames_path, objects_path, visibility_path = gt_dir / "frames.json", gt_dir / "objects.json", gt_dir / "visibility.json"
    write_json(frames_path, frames_to_json(frames_file))
    write_json(objects_path, objects_to_json(ObjectsFile(name, tuple(objects))))
    write_json(visibility_path, visibility)
    timings["ground_truth"] = time.perf_counter() - t2
    timings["total"] = time.perf_counter() - t0
    return ClipGroundTruth(name, scene, spec, lighting, video_path, cameras_path, frames_path, objects_path,
                           visibility_path, frame_indices, timestamps, normalised, K,
                           np.ascontiguousarray(poses[frame_indices]), timings)


def render_frame(scene: Scene, pose: np.ndarray, spec: WalkthroughSpec, wh_root: str | os.PathLike,
                 lighting: Lighting = Lighting()) -> np.ndarray:
    """uint8[H, W, 3] of ``scene`` seen from world->camera ``pose`` float[3, 4] (for previews)."""
    K = intrinsics_matrix(hfov_intrinsics(spec.hfov_deg, spec.width, spec.height), spec.width, spec.height)
    instances = [Instance(m, np.eye(4), ROOM_INSTANCE_ID) for m in scene.room.meshes] + [
        Instance(load_mesh(Path(wh_root) / o.mesh_path), o.object_to_world(), k + 1) for k, o in enumerate(scene.objects)]
    with Renderer(spec.width, spec.height, spec.supersample) as r:
        return r.render(instances, Camera(K, pose[:, :3], pose[:, 3], spec.width, spec.height), lighting,
                        (0.9, 0.9, 0.9)).rgb


__all__ = ["WalkthroughSpec", "ClipGroundTruth", "generate_clip", "camera_path", "render_frame", "load_mesh",
           "random_lighting", "ROOM_INSTANCE_ID"]
