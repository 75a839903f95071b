"""bench.scene / bench.walkthrough: seeded furnished rooms, camera walks and CAD-Estate ground truth.

Needs the Sweet Home 3D furniture (``make cad-library``): the session's small library of 15 of its
models (``small_cad_library`` in conftest.py).
"""

from __future__ import annotations

import json
import shutil
from fractions import Fraction

import av
import numpy as np
import pytest
import trimesh

from bench.scene import EXCLUDED_CLASSES, FOOTPRINT_MARGIN_M, generate_scene
from bench.walkthrough import (
    CAMERA_CLEARANCE_M, ROOM_INSTANCE_ID, WalkthroughSpec, camera_path, generate_clip,
)
from cadestate.geometry import camera_to_world, pixel_intrinsics_matrix, project, quaternion_to_matrix
from cadestate.render import Camera, Instance, Renderer, object_to_world
from schemas.official import read_frames, read_objects
from tasks.video.camera_file import parse_camera_file
from tasks.video.decode import frame_timestamp_us, write_video

SPEC = WalkthroughSpec(width=320, height=180, num_video_frames=40, sample_every=2, alone_scale=1.0)
SEED = 7


@pytest.fixture(scope="module")
def library(small_cad_library):
    """(warehouse, cad_models rows): the session's small Sweet Home 3D library (tests/conftest.py)."""
    assert len(small_cad_library[1]) >= 12
    return small_cad_library


@pytest.fixture(scope="module")
def clip(library, tmp_path_factory):
    wh, rows = library
    return generate_clip(tmp_path_factory.mktemp("walk_a"), "walk", SEED, rows, wh.root, SPEC)


_VERTS: dict[str, np.ndarray] = {}


def vertices(wh, mesh_path: str) -> np.ndarray:
    """float64[V, 3] canonical vertices of a library mesh (scene graph baked in)."""
    if mesh_path not in _VERTS:
        scene = trimesh.load(wh.root / mesh_path, force="scene")
        _VERTS[mesh_path] = np.asarray(scene.to_geometry().vertices, np.float64)
    return _VERTS[mesh_path]


def posed(wh, mesh_path, translation, rotation, scale, mirrored) -> np.ndarray:
    M = object_to_world(translation, rotation, scale, mirrored)
    return vertices(wh, mesh_path) @ M[:3, :3].T + M[:3, 3]


def test_same_seed_same_clip(library, clip, tmp_path):
    wh, rows = library
    again = generate_clip(tmp_path, "walk", SEED, list(reversed(rows)), wh.root, SPEC)
    for a, b in ((clip.objects_path, again.objects_path), (clip.frames_path, again.frames_path),
                 (clip.cameras_path, again.cameras_path), (clip.visibility_path, again.visibility_path),
                 (clip.video_path, again.video_path)):
        assert a.read_bytes() == b.read_bytes(), a.name
    other = generate_scene(SEED + 1, rows)
    assert [o.translation for o in other.objects] != [o.translation for o in clip.scene.objects]


def test_the_same_frames_encode_to_the_same_bytes(clip, tmp_path):
    """write_video is a function of its frames (libx264 without macroblock-tree rate control): a
    rendered walkthrough's frames encoded eight times give one file. With x264's default rate
    control the first GOP came out differently in about half the encodes of such frames (never
    with the demo clip's flat boxes), so a benchmark clip was another video each session."""
    with av.open(str(clip.video_path)) as container:
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    options = {"crf": str(SPEC.crf), "preset": "veryfast"}
    digests = set()
    for k in range(8):
        write_video(tmp_path / f"{k}.mp4", iter(frames), SPEC.width, SPEC.height, SPEC.fps, options=options)
        digests.add((tmp_path / f"{k}.mp4").read_bytes())
    assert len(digests) == 1


def test_placement_constraints(library):
    wh, rows = library
    spec = WalkthroughSpec(num_video_frames=60)
    for seed in range(12):
        scene = generate_scene(seed, rows)
        room = scene.room
        assert 3.5 <= room.width <= 7 and 3.5 <= room.depth <= 7 and 2.5 <= room.height <= 2.9
        assert 4 <= len(scene.objects) <= 12, seed
        for o in scene.objects:
            assert o.cls not in EXCLUDED_CLASSES
            w, x, y, z = o.rotation
            assert x == 0 and z == 0 and abs(w * w + y * y - 1) < 1e-9  # rotation about +Y only
            assert all(0.85 - 1e-9 <= s <= 1.15 + 1e-9 for s in o.scale)
            v = posed(wh, o.mesh_path, o.translation, o.rotation, o.scale, o.mirrored)
            floor = 0.0 if o.support < 0 else posed(wh, *(lambda s: (s.mesh_path, s.translation, s.rotation, s.scale,
                                                                     s.mirrored))(scene.objects[o.support]))[:, 1].max()
            assert abs(v[:, 1].min() - floor) < 2e-3, (seed, o.cad_id)
            assert np.all(np.abs(v[:, 0]) <= room.width / 2 + 1e-6) and np.all(np.abs(v[:, 2]) <= room.depth / 2 + 1e-6)
            assert v[:, 1].max() < room.height
        feet = scene.footprints()
        for i in range(len(feet)):
            for j in range(i + 1, len(feet)):
                if scene.objects[i].support < 0 and scene.objects[j].support < 0:
                    assert not feet[i].overlaps(feet[j], FOOTPRINT_MARGIN_M - 1e-6), (seed, i, j)
        for o in scene.objects:  # supported objects stand within their support's footprint
            if o.support >= 0:
                assert feet[o.support].contains(o.footprint(), 1e-6)
        poses = camera_path(scene, spec, np.random.default_rng(seed))
        _, centres = camera_to_world(poses[:, :, :3], poses[:, :, 3])
        assert np.all((centres[:, 1] >= 1.2 - 1e-9) & (centres[:, 1] <= 1.7 + 1e-9))
        assert scene.clearance(centres[:, [0, 2]]).min() > 0.3 and CAMERA_CLEARANCE_M > 0.3
        forward = poses[:, 2, :3]  # camera z axis in world
        assert np.all(np.abs(forward[:, 1]) < np.sin(np.radians(20)))  # looking mostly horizontally
    mirrored = [o.mirrored for s in range(12) for o in generate_scene(s, rows).objects]
    assert 0.1 < np.mean(mirrored) < 0.45


def test_table_group_faces_the_table(library):
    wh, rows = library
    for seed in range(20):
        scene = generate_scene(seed, rows)
        tables = [o for o in scene.objects if o.cls == "table"]
        if not tables:
            continue
        t = tables[0]
        chairs = [o for o in scene.objects[scene.objects.index(t) + 1:] if o.cls == "chair"]
        assert 2 <= len(chairs) <= 4
        for c in chairs[:2]:
            front = np.array([np.sin(c.yaw), np.cos(c.yaw)])
            to_table = np.array([t.translation[0] - c.translation[0], t.translation[2] - c.translation[2]])
            assert front @ to_table / np.linalg.norm(to_table) > 0.8
        return
    pytest.fail("no table group in 20 scenes")


def test_boxes_are_projections_of_fully_visible_objects(library, clip):
    wh, _ = library
    frames = read_frames(clip.frames_path)
    objects = read_objects(clip.objects_path)
    visibility = json.loads(clip.visibility_path.read_text())
    H, W = frames.image_size
    checked = 0
    for fr, vis in zip(frames.frames, visibility["frames"]):
        assert vis["timestamp"] == fr.timestamp
        K = pixel_intrinsics_matrix(np.array(fr.intrinsics))
        R, t = quaternion_to_matrix(np.array(fr.rotation)), np.array(fr.translation)
        for obj, v in zip(objects.objects, vis["objects"]):
            assert 0 <= v["visible_fraction"] <= 1 and 0 <= v["truncated_fraction"] <= 1
            if v["visible_fraction"] < 0.999 or v["truncated_fraction"] > 0 or v["visible_pixels"] < 100:
                continue
            mesh_path = clip.scene.objects[int(obj.track_id)].mesh_path
            uv, depth = project(K, R, t, posed(wh, mesh_path, obj.translation, obj.rotation, obj.scale, obj.is_mirrored))
            assert np.all(depth > 0)
            entry = next(e for e in obj.track if e.timestamp == fr.timestamp)
            box_px = np.array(entry.box) * [H, W, H, W]
            projected = np.array([uv[:, 1].min(), uv[:, 0].min(), uv[:, 1].max(), uv[:, 0].max()])
            if projected[0] < 1 or projected[1] < 1 or projected[2] > H - 1 or projected[3] > W - 1:
                continue
            np.testing.assert_allclose(box_px, projected, atol=1.5, err_msg=f"{obj.track_id} at {fr.timestamp}")
            checked += 1
    assert checked >= 3
    assert any(v["truncated_fraction"] > 0.05 and v["visible_pixels"] > 0 for f in visibility["frames"] for v in f["objects"])


def test_official_round_trip(library, clip):
    """The JSON poses and cameras, read back, put the CAD meshes onto their boxes' pixels."""
    wh, rows = library
    frames = read_frames(clip.frames_path)
    objects = read_objects(clip.objects_path)
    track = parse_camera_file(clip.cameras_path)
    assert frames.clip_name == objects.clip_name == "walk" and frames.image_size == (SPEC.height, SPEC.width)
    assert [f.timestamp for f in frames.frames] == track.timestamps_us.tolist()
    assert not any(f.key_frame for f in frames.frames)
    by_id = {r["cad_id"]: r for r in rows}
    assert len(objects.objects) == len(clip.scene.objects)
    H, W = frames.image_size
    with Renderer(W, H) as renderer:
        for n, (fr, R_file) in enumerate(zip(frames.frames, track.R)):
            R, t = quaternion_to_matrix(np.array(fr.rotation)), np.array(fr.translation)
            np.testing.assert_allclose(R, R_file, atol=1e-9)
            np.testing.assert_allclose(t, track.t[n], atol=1e-12)
            K = pixel_intrinsics_matrix(np.array(fr.intrinsics))
            if n % 5:
                continue
            # Re-render from the JSON alone: instance-mask boxes equal the exported boxes.
            from bench.walkthrough import load_mesh
            instances = [Instance(m, np.eye(4), ROOM_INSTANCE_ID) for m in clip.scene.room.meshes]
            for k, o in enumerate(objects.objects):
                row = by_id[o.cad_id]
                assert o.cls == row["class_id"] and not o.is_track_automatic
                instances.append(Instance(load_mesh(wh.root / row["mesh_path"]),
                                          object_to_world(o.translation, o.rotation, o.scale, o.is_mirrored), k + 1))
            ids = renderer.render(instances, Camera(K, R, t, W, H)).instance_id
            for k, o in enumerate(objects.objects):
                entry = [e for e in o.track if e.timestamp == fr.timestamp]
                mask = ids == k + 1
                assert bool(entry) == bool(mask.any())
                if not entry:
                    continue
                rr, cc = np.nonzero(mask)
                assert entry[0].box == (rr.min() / H, cc.min() / W, (rr.max() + 1) / H, (cc.max() + 1) / W)
                # The posed vertices in front of the camera project around the box.
                uv, depth = project(K, R, t, posed(wh, by_id[o.cad_id]["mesh_path"], o.translation, o.rotation,
                                                   o.scale, o.is_mirrored))
                if np.all(depth > 0):
                    y0, x0, y1, x1 = np.array(entry[0].box) * [H, W, H, W]
                    assert uv[:, 0].min() <= x0 + 1 and uv[:, 0].max() >= x1 - 1
                    assert uv[:, 1].min() <= y0 + 1 and uv[:, 1].max() >= y1 - 1


def test_video_decodes_to_camera_timestamps(clip):
    track = parse_camera_file(clip.cameras_path)
    with av.open(str(clip.video_path)) as container:
        stream = container.streams.video[0]
        times = [round(Fraction(f.pts) * stream.time_base * 1_000_000) for f in container.decode(stream)]
        assert (stream.codec_context.width, stream.codec_context.height) == (SPEC.width, SPEC.height)
    assert len(times) == SPEC.num_video_frames
    assert times == [frame_timestamp_us(i, SPEC.fps) for i in range(SPEC.num_video_frames)]
    assert track.timestamps_us.tolist() == times[::SPEC.sample_every]
    assert len(track) == len(clip.frame_indices) == SPEC.num_video_frames // SPEC.sample_every


def test_files_replace_atomically(library, clip, tmp_path):
    wh, rows = library
    shutil.copytree(clip.frames_path.parent, tmp_path / "walk")
    (tmp_path / "walk.txt").write_text("stale")
    spec = WalkthroughSpec(width=160, height=96, num_video_frames=4, sample_every=2, alone_scale=1.0)
    gt = generate_clip(tmp_path, "walk", SEED, rows, wh.root, spec)
    assert parse_camera_file(gt.cameras_path).timestamps_us.tolist() == [0, frame_timestamp_us(2, 30)]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["walk", "walk.mp4", "walk.txt"]
    assert sorted(p.name for p in (tmp_path / "walk").iterdir()) == ["frames.json", "objects.json", "visibility.json"]
