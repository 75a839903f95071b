"""The benchmark's ground truth, read the official way (pixel intrinsics, OpenGL projection,
object->world T·R·S·mirror; tests/official_loader.py), lands on the pixels our renderer draws.

Needs the Sweet Home 3D furniture (the session's small library, tests/conftest.py).
"""

from __future__ import annotations

import json

import numpy as np

from bench.walkthrough import WalkthroughSpec, generate_clip, load_mesh
from cadestate.geometry import intrinsics_matrix
from cadestate.render import Camera, Instance, Renderer, object_to_world
from official_loader import load_frames, silhouette, to_pixels
from schemas.official import read_objects
from tasks.cad.export import triangle_soup
from tasks.video.camera_file import parse_camera_file

SPEC = WalkthroughSpec(width=320, height=180, num_video_frames=24, sample_every=4, alone_scale=0.5)


def test_official_projection_matches_our_renderer(small_cad_library, tmp_path):
    wh, rows = small_cad_library
    clip = generate_clip(tmp_path, "walk_0", 11, rows, wh.root, SPEC)
    frames = load_frames(clip.frames_path)
    raw = json.loads(clip.frames_path.read_text())
    assert raw["image_size"] == [SPEC.height, SPEC.width]
    assert raw["frames"][0]["intrinsics"][2] == SPEC.width / 2  # pixels, not normalised
    objects = read_objects(clip.objects_path)
    cameras = parse_camera_file(clip.cameras_path)  # the RealEstate10K file: normalised intrinsics
    mesh_of = {r["cad_id"]: r["mesh_path"] for r in rows}
    visibility = json.loads(clip.visibility_path.read_text())
    H, W = frames.image_size
    ious = []
    with Renderer(W, H) as renderer:
        for i, vis in enumerate(visibility["frames"]):
            K = intrinsics_matrix(cameras.intrinsics[i], W, H)
            camera = Camera(K, cameras.R[i], cameras.t[i], W, H)
            for obj, v in zip(objects.objects, vis["objects"]):
                if v["truncated_fraction"] > 0 or v["visible_pixels"] < 400:
                    continue
                M = object_to_world(obj.translation, obj.rotation, obj.scale, obj.is_mirrored)
                ours = renderer.render([Instance(load_mesh(wh.root / mesh_of[obj.cad_id]), M, 1)], camera).instance_id == 1
                soup = triangle_soup(wh.root / mesh_of[obj.cad_id]).astype(np.float64)
                official_M = _official_object_to_world(obj)
                world = soup.reshape(-1, 3) @ official_M[:3, :3].T + official_M[:3, 3]
                px, depth = to_pixels(frames, i, world)
                assert np.all(depth > 0)
                theirs = silhouette(px.reshape(-1, 3, 2), H, W)
                ious.append((ours & theirs).sum() / (ours | theirs).sum())
    assert len(ious) >= 5
    assert min(ious) > 0.99, ious


def _official_object_to_world(obj) -> np.ndarray:
    """T · R · S · diag(-1, 1, 1) from the loader's own matrices (not cadestate.render's)."""
    from official_loader import rotate, scale, translate

    M = translate(obj.translation) @ rotate(obj.rotation) @ scale(obj.scale)
    return M @ scale([-1, 1, 1]) if obj.is_mirrored else M
