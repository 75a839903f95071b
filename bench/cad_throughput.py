"""CAD library throughput over the whole Sweet Home 3D library, and renderer speed.

- ingest: ``cad_ingest`` (load, canonicalise, symmetry, samples, GLB) then ``cad_views`` (10
  renders at 224x224, 2x supersampled) of every library, run as the stage functions (no Prefect);
- render: a 640x360 frame of 10 library models standing in a room-sized grid, median of 20 frames,
  without and with 2x supersampling.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from itertools import groupby
from pathlib import Path

import trimesh

from cadestate.config import CadIngestConfig, CadViewsConfig
from cadestate.geometry import intrinsics_matrix, look_at
from cadestate.render import Camera, Instance, Renderer, RenderMesh, object_to_world
from tasks.cad.ingest import ingest_library
from tasks.cad.sources import default_source, sweethome3d_items
from tasks.cad.views import render_library
from warehouse import Warehouse

SCENE_CLASSES = ("chair", "sofa", "table", "bed", "cabinet", "lamp", "plant", "bookshelf", "display", "toilet")


def _scene_meshes(wh: Warehouse) -> list[RenderMesh]:
    rows = wh.read("cad_models", columns=["class", "mesh_path", "num_faces"]).to_pylist()
    picks = [next(r for r in rows if r["class"] == c) for c in SCENE_CLASSES]
    return [RenderMesh.from_trimesh(trimesh.load(wh.root / r["mesh_path"], force="scene")) for r in picks]


def _render_ms(meshes: list[RenderMesh], supersample: int, frames: int = 20) -> float:
    K = intrinsics_matrix([0.7, 1.25, 0.5, 0.5], 640, 360)
    R, t = look_at([0.0, 1.5, 4.5], [0.0, 0.6, 0.0])
    camera = Camera(K=K, R=R, t=t, width=640, height=360)
    instances = [Instance(m, object_to_world([(i % 5 - 2) * 1.2, -m.bounds[0][1], (i // 5) * -1.5],
                                             [1, 0, 0, 0], [1, 1, 1], False), i) for i, m in enumerate(meshes)]
    times = []
    with Renderer(640, 360, supersample=supersample) as renderer:
        renderer.render(instances, camera)  # upload and shader compilation
        for _ in range(frames):
            t0 = time.perf_counter()
            renderer.render(instances, camera)
            times.append(time.perf_counter() - t0)
    return 1000 * statistics.median(times)


def run() -> dict:
    items = list(sweethome3d_items(default_source()))
    with tempfile.TemporaryDirectory() as tmp:
        wh = Warehouse(tmp)
        t0 = time.perf_counter()
        for library, group in groupby(sorted(items, key=lambda i: i.library), key=lambda i: i.library):
            ingest_library(wh, CadIngestConfig(), library, list(group), "bench", show_progress=False)
        ingest_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        for library in wh.partitions("cad_models"):
            render_library(wh, CadViewsConfig(), library, "bench", show_progress=False)
        views_s = time.perf_counter() - t0
        meshes = _scene_meshes(wh)
        faces = sum(len(m.faces) for m in meshes)
        return {
            "models": len(items),
            "ingest_models_per_s": round(len(items) / ingest_s, 2),
            "views_models_per_s": round(len(items) / views_s, 2),
            "ingest_plus_views_models_per_s": round(len(items) / (ingest_s + views_s), 2),
            "total_s": round(ingest_s + views_s, 1),
            "render_scene": f"640x360, {len(meshes)} library models, {faces} triangles",
            "render_ms_per_frame": round(_render_ms(meshes, 1), 1),
            "render_ms_per_frame_supersample2": round(_render_ms(meshes, 2), 1),
        }
