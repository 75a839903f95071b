"""The posed CAD model as image layers over a key-frame, for the verification page (paper 3.5).

The verification stage's overlays are flat JPEGs blended at a fixed opacity. The page wants
layers it can fade, outline and hide, so :func:`verification_layers` renders (once, cached under
``media/verification/<clip>/<task_id>/layers/``) per key-frame of a track two RGBA PNGs of the
frame's size, pixel-aligned with the frame image: ``model`` (the shaded posed model, alpha = its
mask) and ``outline`` (the mask's boundary and depth edges, 2 px, alpha = 1 on them). The pose is
the task item's (official order: mirror, scale, rotation, translation;
:func:`cadestate.render.object_to_world`); cameras are the ``frames`` rows' K and world->camera.
"""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np

from warehouse import Warehouse

LAYERS = "layers"
OUTLINE_RGB = (40, 255, 120)
_RENDER_LOCK = threading.Lock()  # one GL context at a time in this process


def _outline(instance: np.ndarray, depth: np.ndarray, width: int = 2) -> np.ndarray:
    """bool[H, W]: the model's silhouette and depth discontinuities (> 5 % of the depth), ``width`` px."""
    from scipy.ndimage import binary_dilation

    mask = instance == 1
    z = np.where(mask, depth, np.inf)
    edges = np.zeros_like(mask)
    for axis in (0, 1):
        a, b = np.take(z, range(z.shape[axis] - 1), axis), np.take(z, range(1, z.shape[axis]), axis)
        both = np.isfinite(a) & np.isfinite(b)
        gap = np.abs(np.where(both, a, 0.0) - np.where(both, b, 0.0))
        jump = (np.isfinite(a) != np.isfinite(b)) | (both & (gap > 0.05 * np.where(both, np.minimum(a, b), 0.0)))
        pad = [(0, 0), (0, 0)]
        pad[axis] = (0, 1)
        edges |= np.pad(jump, pad)
    return binary_dilation(edges, iterations=max(1, width - 1)) if width > 1 else edges


def verification_layers(wh: Warehouse, clip: str, task_id: str, item: dict) -> list[dict]:
    """Per key-frame of one verification task item (a JSON item of the task file): its timestamp
    and the ``model`` and ``outline`` layer paths (relative to the warehouse root), rendered if missing."""
    folder = wh.root / "media" / "verification" / clip / task_id / LAYERS
    layers = []
    for kf in item["keyframes"]:
        base = folder / f"{item['track_id']}_{kf['timestamp_us']}"
        layers.append((kf["timestamp_us"], {"model": base.with_suffix(".model.png"), "outline": base.with_suffix(".outline.png")}))
    todo = [(stamp, paths) for stamp, paths in layers if not all(p.is_file() for p in paths.values())]
    if todo:
        _render(wh, clip, item, todo)
    return [{"timestamp_us": stamp, **{k: wh.relative(p) for k, p in paths.items()}} for stamp, paths in layers]


def _render(wh: Warehouse, clip: str, item: dict, todo: list[tuple[int, dict[str, Path]]]) -> None:
    import io

    import trimesh
    from PIL import Image

    from cadestate.render import Camera, Instance, Renderer, RenderMesh, object_to_world
    from warehouse import atomic_write_bytes

    frames = {r["timestamp_us"]: r for r in wh.read("frames", [clip], columns=[
        "timestamp_us", "width", "height", "K", "world_to_camera_R", "world_to_camera_t"]).to_pylist()}
    p = item["pose"]
    M = object_to_world(p["translation"], p["rotation"], p["scale"], p["is_mirrored"])
    first = frames[todo[0][0]]
    W, H = int(first["width"]), int(first["height"])
    mesh = RenderMesh.from_trimesh(trimesh.load(wh.root / item["mesh_path"], force="scene"))
    with _RENDER_LOCK, Renderer(W, H) as renderer:
        for stamp, paths in todo:
            f = frames[stamp]
            camera = Camera(np.array(f["K"]).reshape(3, 3), np.array(f["world_to_camera_R"]).reshape(3, 3),
                            np.array(f["world_to_camera_t"]), W, H, 0.01, 1000.0)
            result = renderer.render([Instance(mesh, M, 1)], camera)
            mask = result.instance_id == 1
            model = np.dstack([result.rgb, (mask * 255).astype(np.uint8)])
            edges = _outline(result.instance_id, result.depth)
            outline = np.zeros((H, W, 4), np.uint8)
            outline[edges] = (*OUTLINE_RGB, 255)
            for key, rgba in (("model", model), ("outline", outline)):
                buf = io.BytesIO()
                Image.fromarray(rgba, "RGBA").save(buf, format="PNG", optimize=False)
                atomic_write_bytes(paths[key], buf.getvalue())
