"""Stage ``cad_views``: render every model of a library from random viewpoints around it.

Reads: ``cad_models`` of one library and its canonical meshes. Writes: ``cad_views`` and the
renders under ``media/cad_views/<library>/<digest of the renders>/`` (the output digest covers
their pixels). The model sits at the origin of its
canonical frame (+Y up, front +Z), which is the "world" of these cameras: azimuth 0 looks at
its front from +Z, elevation is above the horizontal; the camera looks at the origin from a
distance at which the bounding sphere fills the frame. Viewpoints are a deterministic function
of (seed, cad_id), so a model renders identically whatever else is in the library.
"""

from __future__ import annotations

import hashlib
import math

import numpy as np
import pyarrow as pa
import trimesh
from PIL import Image

from cadestate.config import CadViewsConfig
from cadestate.geometry import look_at
from cadestate.lineage import digest, folder_digest, table_digest
from cadestate.progress import progress
from cadestate.render import Camera, Instance, Renderer, RenderMesh
from tasks.stage import StageContext, StageDef, StageOutput
from warehouse import Warehouse

MEDIA_KIND = "cad_views"
FOV_DEG = 40.0
ELEVATION_RANGE_DEG = (5.0, 40.0)
BACKGROUND = (1.0, 1.0, 1.0)


def viewpoints(cad_id: str, count: int, seed: int) -> np.ndarray:
    """float64[count, 2] (azimuth, elevation) in degrees, deterministic in (seed, cad_id)."""
    key = int.from_bytes(hashlib.sha256(cad_id.encode()).digest()[:8], "little")
    rng = np.random.default_rng([seed, key])
    azimuth = rng.uniform(0.0, 360.0, count)
    elevation = rng.uniform(*ELEVATION_RANGE_DEG, count)
    return np.stack([azimuth, elevation], axis=1)


def view_camera(extent: np.ndarray, azimuth_deg: float, elevation_deg: float, size: int) -> Camera:
    """A square camera looking at the canonical origin, framing a model of bounding-box size ``extent``."""
    f = size / 2 / math.tan(math.radians(FOV_DEG) / 2)
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]])
    radius = max(float(np.linalg.norm(extent)) / 2, 1e-3)
    distance = radius / math.sin(math.radians(FOV_DEG) / 2) * 1.05
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    eye = distance * np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
    R, t = look_at(eye, np.zeros(3))
    return Camera(K=K, R=R, t=t, width=size, height=size, near=max(distance - 2 * radius, 1e-3), far=distance + 2 * radius)


def render_library(wh: Warehouse, cfg: CadViewsConfig, library: str, run_id: str, show_progress: bool = True) -> StageOutput:
    """Render ``cfg.views`` views of every model of ``library`` (see module docstring)."""
    models = wh.read("cad_models", partitions=[library], columns=["library", "cad_id", "extent", "mesh_path"]).to_pylist()
    rows = []
    with wh.staging() as staged, Renderer(cfg.size, cfg.size, supersample=2) as renderer:
        for model in progress(models, total=len(models), description=f"views {library}", enabled=show_progress):
            mesh = RenderMesh.from_trimesh(trimesh.load(wh.root / model["mesh_path"], force="scene"))
            extent = np.asarray(model["extent"])
            for view, (az, el) in enumerate(viewpoints(model["cad_id"], cfg.views, cfg.seed)):
                camera = view_camera(extent, az, el, cfg.size)
                result = renderer.render([Instance(mesh, np.eye(4), 0)], camera, background=BACKGROUND)
                name = f"{model['cad_id']}_{view:02d}.png"
                Image.fromarray(result.rgb).save(staged / name, compress_level=1)
                rows.append({
                    "library": library, "cad_id": model["cad_id"], "view": view,
                    "image_path": name, "width": cfg.size, "height": cfg.size,
                    "azimuth_deg": float(az), "elevation_deg": float(el), "K": camera.K.ravel().tolist(),
                    "world_to_camera_R": camera.R.ravel().tolist(), "world_to_camera_t": camera.t.tolist(),
                })
        pixels = folder_digest(staged)
        version = pixels[:16]  # by content: a rerun that renders the same views keeps their paths
        rows = [{**r, "image_path": f"media/{MEDIA_KIND}/{library}/{version}/{r['image_path']}"} for r in rows]
        wh.publish_media(MEDIA_KIND, library, staged, version, content=True)
    table = pa.Table.from_pylist(rows, schema=wh.spec("cad_views").schema)
    written = wh.write("cad_views", library, table)
    wh.prune_media(MEDIA_KIND, library, keep=version)
    return StageOutput(written, digest(table_digest(table.drop_columns(["image_path"])), pixels))


def _run(ctx: StageContext) -> StageOutput:
    return render_library(ctx.wh, ctx.cfg, ctx.unit, ctx.run_id, ctx.show_progress)


STAGE = StageDef(
    name="cad_views", section="cad_views", scope="library", upstream=("cad_ingest",), tables=("cad_views",),
    description="render every CAD model from random viewpoints",
    run=_run,
)
