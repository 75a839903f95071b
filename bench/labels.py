"""Simulated annotators on a benchmark: their clicks and tracks from the ground truth, and what they contain.

For every clip, ``<bench>/simulated_clicks/<clip>.json`` holds, per ground-truth object, the 3D<->2D
correspondences of :func:`bench.annotators.annotate_correspondences` (other objects of the
scene occlude) and a manual track of :func:`bench.annotators.draw_manual_track`, made with the
noise model :class:`bench.noise.AnnotatorNoise`: the benchmark's own file, not a label file (the
label files the simulated people answer tasks with go to ``<bench>/labels/<clip>/``,
:mod:`bench.simulated_labels`; it sat in ``labels/``, where ``cadestate labels validate`` of that
folder took it for a bad label file). :mod:`bench.pose_bench` and :mod:`bench.sfm_bench` read it.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import trimesh

from bench.annotators import (KeyframeCorrespondences, annotate_correspondences, draw_manual_track, frame_camera,
                              track_to_json)
from bench.noise import DEFAULT_NOISE, AnnotatorNoise
from cadestate.geometry import project
from cadestate.progress import progress
from cadestate.render import Instance, Renderer, RenderMesh, object_to_world
from schemas.official import read_frames, read_objects
from tasks.cad.symmetry import rotation_y
from warehouse import Warehouse, atomic_write_bytes

CLICKS = "simulated_clicks"


def clicks_path(bench_dir: Path | str, clip: str) -> Path:
    """``<bench>/simulated_clicks/<clip>.json``: the clip's file of simulated clicks (module docstring)."""
    return Path(bench_dir) / CLICKS / f"{clip}.json"


def simulate_clip_labels(bench_dir: Path, clip: str, wh: Warehouse, noise: AnnotatorNoise = DEFAULT_NOISE) -> dict:
    """The label file of one clip (also written to ``<bench>/simulated_clicks/<clip>.json``)."""
    frames = read_frames(Path(bench_dir) / clip / "frames.json")
    objects = read_objects(Path(bench_dir) / clip / "objects.json")
    models = {m["cad_id"]: m for m in wh.read("cad_models", columns=["cad_id", "symmetry", "mesh_path"]).to_pylist()}
    meshes = {o.cad_id: trimesh.load(wh.root / models[o.cad_id]["mesh_path"], force="scene") for o in objects.objects}
    posed = [Instance(RenderMesh.from_trimesh(meshes[o.cad_id]), object_to_world(o.translation, o.rotation, o.scale, o.is_mirrored), k + 1)
             for k, o in enumerate(objects.objects)]
    H, W = frames.image_size
    result = {"clip_name": clip, "noise": dataclasses.asdict(noise), "objects": []}
    with Renderer(W, H) as renderer:
        for k, obj in enumerate(objects.objects):
            keyframes = annotate_correspondences(
                frames, obj, meshes[obj.cad_id], noise=noise, renderer=renderer,
                symmetry_order=int(models[obj.cad_id]["symmetry"]), occluders=[p for j, p in enumerate(posed) if j != k])
            result["objects"].append({
                "track_id": obj.track_id, "cad_id": obj.cad_id,
                "correspondences": [kf.to_json() for kf in keyframes],
                "manual_track": track_to_json(draw_manual_track(frames, obj, noise, noise.rng(clip, obj.track_id, "track"))),
            })
    out = clicks_path(bench_dir, clip)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out, json.dumps(result, indent=1).encode())
    return result


def simulate_labels(bench_dir: Path, clips: list[str], wh: Warehouse, show_progress: bool = True) -> int:
    """Label files for ``clips`` that do not have one yet; returns how many were written."""
    todo = [c for c in clips if not clicks_path(bench_dir, c).is_file()]
    for clip in progress(todo, total=len(todo), description="simulated labels", enabled=show_progress):
        simulate_clip_labels(bench_dir, clip, wh)
    return len(todo)


def label_statistics(bench_dir: Path, clips: list[str]) -> dict:
    """What the label files hold, and the measured click error against the ground-truth projection."""
    keyframes = points = coplanar = swapped = annotated = objects_n = 0
    residuals: list[float] = []
    for clip in clips:
        path = clicks_path(bench_dir, clip)
        if not path.is_file():
            continue
        labels = json.loads(path.read_text())
        frames = read_frames(Path(bench_dir) / clip / "frames.json")
        gt = {o.track_id: o for o in read_objects(Path(bench_dir) / clip / "objects.json").objects}
        by_ts = {f.timestamp: f for f in frames.frames}
        H, W = frames.image_size
        for obj in labels["objects"]:
            objects_n += 1
            kfs = obj["correspondences"]
            annotated += bool(kfs)
            o = gt[obj["track_id"]]
            M = object_to_world(o.translation, o.rotation, o.scale, o.is_mirrored)
            for kf in map(KeyframeCorrespondences.from_json, kfs):
                keyframes += 1
                points += len(kf.xy)
                coplanar += kf.coplanar
                swapped += kf.symmetry_deg != 0
                camera = frame_camera(by_ts[kf.timestamp], W, H)
                true_xyz = np.asarray(kf.xyz, float) @ rotation_y(kf.symmetry_deg)  # undo the symmetric swap
                uv, _ = project(camera.K, camera.R, camera.t, true_xyz @ M[:3, :3].T + M[:3, 3])
                residuals += np.linalg.norm(np.asarray(kf.xy) * [W, H] - uv, axis=1).tolist()
    return {
        "objects": objects_n, "objects_with_correspondences": annotated, "keyframes": keyframes,
        "points_per_keyframe": round(points / max(keyframes, 1), 2),
        "keyframes_per_annotated_object": round(keyframes / max(annotated, 1), 2),
        "coplanar_keyframe_share": round(coplanar / max(keyframes, 1), 3),
        "symmetric_swap_keyframe_share": round(swapped / max(keyframes, 1), 3),
        "click_error_px_mean": round(float(np.mean(residuals)), 2) if residuals else None,
    }


def correspondence_rows(labels: dict) -> list[dict]:
    """Rows of the ``correspondences`` table (:data:`schemas.pose.CORRESPONDENCES`) from one clip's
    label file (:func:`simulate_clip_labels`): one per click, point_index in click order."""
    rows = []
    for obj in labels["objects"]:
        for kf in map(KeyframeCorrespondences.from_json, obj["correspondences"]):
            for i, (xy, xyz) in enumerate(zip(kf.xy, kf.xyz)):
                rows.append({"clip": labels["clip_name"], "track_id": str(obj["track_id"]), "timestamp_us": kf.timestamp,
                             "point_index": i, "cad_id": obj["cad_id"], "point_2d": list(xy), "point_3d": list(xyz),
                             "is_mirrored": kf.is_mirrored})
    return rows
