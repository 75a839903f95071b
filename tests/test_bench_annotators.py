"""Simulated human annotators (bench.annotators, bench.noise): programmatic meshes posed in front of
a synthetic 320x180 camera orbiting them."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import trimesh

from bench.annotators import (KeyframeCorrespondences, Pose, SurfaceSamples, annotate_correspondences, choose_keyframes,
                              draw_manual_track, frame_camera, mesh_shape_distance, pose_mask_ious, select_cad,
                              shape_distance, track_to_json, verify_pose, visible_mask)
from bench.noise import AnnotatorNoise
from cadestate.geometry import look_at, matrix_to_quaternion, project, quaternion_to_matrix
from cadestate.render import Instance, Renderer, RenderMesh, object_to_world
from schemas.official import Frame, FramesFile, ObjectAnnotation, TrackEntry
from tasks.cad.symmetry import rotation_y

W, H = 320, 180
F_PX = 250.0
CENTRE = np.array([0.3, 0.45, -0.2])  # where the objects stand (world)


def make_frames(n: int = 24, radius: float = 3.2, sweep: float = 70.0, height: float = 1.4) -> FramesFile:
    """A camera orbiting CENTRE over +-sweep/2 degrees, looking at it."""
    frames = []
    for i, a in enumerate(np.radians(np.linspace(-sweep / 2, sweep / 2, n))):
        eye = CENTRE + np.array([radius * np.sin(a), height - CENTRE[1], radius * np.cos(a)])
        R, t = look_at(eye, CENTRE)
        frames.append(Frame(i * 100_000, False, (F_PX, F_PX, W / 2, H / 2), tuple(t.tolist()),
                            tuple(matrix_to_quaternion(R).tolist())))
    return FramesFile("synthetic", (H, W), tuple(frames))


def chair() -> trimesh.Trimesh:
    """An asymmetric chair-like mesh of boxes (seat, backrest at -Z, four legs, one armrest at +X),
    bbox centred."""
    parts = [trimesh.creation.box((0.5, 0.05, 0.5)),
             trimesh.creation.box((0.5, 0.5, 0.05)).apply_translation((0, 0.275, -0.225)),
             trimesh.creation.box((0.05, 0.2, 0.4)).apply_translation((0.225, 0.125, 0.0))]
    parts += [trimesh.creation.box((0.04, 0.45, 0.04)).apply_translation((x, -0.25, z))
              for x in (-0.22, 0.22) for z in (-0.22, 0.22)]
    m = trimesh.util.concatenate(parts)
    return m.apply_translation(-m.bounds.mean(axis=0))


def gt_track(frames: FramesFile, mesh: trimesh.Trimesh, pose: Pose) -> tuple[TrackEntry, ...]:
    """Boxes of the projected mesh vertices, clipped to the image."""
    X = np.asarray(mesh.vertices) @ pose.matrix()[:3, :3].T + pose.matrix()[:3, 3]
    out = []
    for f in frames.frames:
        cam = frame_camera(f, W, H)
        uv, _ = project(cam.K, cam.R, cam.t, X)
        lo, hi = np.clip(uv.min(0) / [W, H], 0, 1), np.clip(uv.max(0) / [W, H], 0, 1)
        out.append(TrackEntry(f.timestamp, (lo[1], lo[0], hi[1], hi[0])))
    return tuple(out)


def make_object(frames: FramesFile, mesh: trimesh.Trimesh, yaw: float = 25.0, scale=(1.0, 1.0, 1.0),
                mirrored: bool = False, track_id: str = "obj") -> ObjectAnnotation:
    q = tuple(matrix_to_quaternion(rotation_y(yaw)).tolist())
    pose = Pose(tuple(CENTRE.tolist()), q, tuple(scale), mirrored)
    return ObjectAnnotation(track_id, "chair", False, mirrored, gt_track(frames, mesh, pose), "cad",
                            pose.translation, pose.rotation, pose.scale)


def closest_faces(mesh: trimesh.Trimesh, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Brute-force distance from each point to the mesh surface, and the nearest face (no rtree)."""
    tri = np.asarray(mesh.triangles)[None]  # [1, T, 3, 3]
    p = np.asarray(points, np.float64)[:, None]  # [P, 1, 3]
    a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    q = p - np.sum((p - a) * n, axis=-1, keepdims=True) * n  # projection on the plane
    inside = np.ones(q.shape[:2], bool)
    for u, v in ((a, b), (b, c), (c, a)):
        inside &= np.sum(np.cross(v - u, q - u) * n, axis=-1) >= -1e-12
    d = np.where(inside, np.linalg.norm(p - q, axis=-1), np.inf)
    for u, v in ((a, b), (b, c), (c, a)):  # outside: nearest point on an edge
        s = np.clip(np.sum((p - u) * (v - u), -1) / np.sum((v - u) ** 2, -1), 0, 1)[..., None]
        d = np.minimum(d, np.linalg.norm(p - (u + s * (v - u)), axis=-1))
    return d.min(axis=1), d.argmin(axis=1)


def project_normalised(frames: FramesFile, obj: ObjectAnnotation, kc: KeyframeCorrespondences,
                       xyz: np.ndarray | None = None, mirrored: bool | None = None) -> np.ndarray:
    """GT-pose projection (normalised) of a record's 3D points (CAD frame: mirror applied first)."""
    M = object_to_world(obj.translation, obj.rotation, obj.scale, obj.is_mirrored if mirrored is None else mirrored)
    X = np.asarray(kc.xyz if xyz is None else xyz) @ M[:3, :3].T + M[:3, 3]
    cam = frame_camera(frames.frames[kc.frame_index], W, H)
    uv, depth = project(cam.K, cam.R, cam.t, X)
    assert (depth > 0).all()
    return uv / [W, H]


def facing_camera(frames: FramesFile, obj: ObjectAnnotation, mesh: trimesh.Trimesh,
                  kc: KeyframeCorrespondences) -> np.ndarray:
    """bool per point: its face's outward normal (posed, mirror included) faces the camera."""
    M = object_to_world(obj.translation, obj.rotation, obj.scale, obj.is_mirrored)
    pts = np.asarray(kc.xyz)
    dist, tri = closest_faces(mesh, pts)
    assert (dist < 1e-9).all()
    n = mesh.face_normals[tri] @ np.linalg.inv(M[:3, :3])
    X = pts @ M[:3, :3].T + M[:3, 3]
    cam = frame_camera(frames.frames[kc.frame_index], W, H)
    return np.sum(n * (-cam.R.T @ cam.t - X), axis=1) > 0


@pytest.fixture(scope="module")
def renderer():
    with Renderer(W, H) as r:
        yield r


EXACT = AnnotatorNoise().exact()


def test_zero_noise_clicks_are_exact_projections_of_visible_points(renderer):
    frames, box = make_frames(), trimesh.creation.box((1.0, 0.8, 0.6))
    obj = make_object(frames, box, yaw=30.0, scale=(1.2, 0.9, 1.1))
    kcs = annotate_correspondences(frames, obj, box, noise=EXACT, rng=np.random.default_rng(0), renderer=renderer)
    assert 3 <= len(kcs) <= 5
    stamps = [kc.timestamp for kc in kcs]
    assert stamps == sorted(set(stamps)) and stamps[-1] - stamps[0] >= 1_000_000  # spread over the track
    seen = set()
    for kc in kcs:
        assert 4 <= len(kc.xy) <= 6 and not kc.is_mirrored and kc.symmetry_deg == 0.0
        xy = np.asarray(kc.xy)
        np.testing.assert_allclose(xy, project_normalised(frames, obj, kc), atol=1e-6)
        assert ((xy > 0) & (xy < 1)).all()
        assert facing_camera(frames, obj, box, kc).all()  # convex box: visible == front-facing
        points = set(kc.xyz)
        assert not points & seen  # different points on every key-frame
        seen |= points
    json.dumps([kc.to_json() for kc in kcs])
    assert [KeyframeCorrespondences.from_json(kc.to_json()) for kc in kcs] == kcs
    assert kcs[0].correspondences()[0].xy == kcs[0].xy[0]


def test_depth_test_removes_hidden_back_face(renderer):
    frames, box = make_frames(), trimesh.creation.box((1.0, 0.8, 0.6))
    obj = make_object(frames, box, yaw=0.0)
    M = Pose.of(obj).matrix()
    # two-sided samples (normals not trusted): only the depth test can reject the -Z face
    samples = replace(SurfaceSamples.from_mesh(box, 3000, seed=0), two_sided=True)
    back = samples.points[:, 2] < -0.3 + 1e-9
    R, t = look_at(CENTRE + [0.0, 0.0, 3.0], CENTRE)  # straight at the +Z face
    cam = frame_camera(Frame(0, True, (F_PX, F_PX, W / 2, H / 2), tuple(t), tuple(matrix_to_quaternion(R))), W, H)
    ok, _ = visible_mask(samples, M, cam, EXACT)
    assert ok[back].sum() > 50  # without a render, the back face projects inside the image
    view = renderer.render([Instance(RenderMesh.from_trimesh(box), M, 0)], cam)
    ok, _ = visible_mask(samples, M, cam, EXACT, view.depth, view.instance_id)
    assert ok[back].sum() == 0 and ok[~back].sum() > 200
    # outward normals of a closed mesh: back faces are never clickable
    for kc in annotate_correspondences(frames, obj, box, noise=replace(EXACT, points_per_keyframe=(6, 6)),
                                       rng=np.random.default_rng(1), renderer=renderer, keyframes=range(24)):
        assert (np.asarray(kc.xyz)[:, 2] > -0.3 + 1e-9).all()
    kcs = annotate_correspondences(frames, obj, box, noise=EXACT, rng=np.random.default_rng(1), renderer=renderer,
                                   samples=replace(SurfaceSamples.from_mesh(box, 3000, seed=0), two_sided=True))
    assert kcs and all(((np.asarray(kc.xy) > 0) & (np.asarray(kc.xy) < 1)).all() for kc in kcs)


def test_chair_self_occlusion_and_occluders(renderer):
    """Cameras face the chair's front (+Z): the backrest's rear side is never clicked; a wall
    between camera and chair hides it completely."""
    frames, mesh = make_frames(), chair()
    obj = make_object(frames, mesh, yaw=0.0)
    zmin = mesh.bounds[0, 2]
    kcs = annotate_correspondences(frames, obj, mesh, noise=EXACT, rng=np.random.default_rng(2), renderer=renderer,
                                   keyframes=range(0, 24, 2))
    assert len(kcs) == 12
    for kc in kcs:
        assert (np.asarray(kc.xyz)[:, 2] > zmin + 1e-6).all()
        np.testing.assert_allclose(kc.xy, project_normalised(frames, obj, kc), atol=1e-6)
    cam0 = frame_camera(frames.frames[0], W, H)
    eye = -cam0.R.T @ cam0.t
    wall = np.eye(4)
    wall[:3, :3], wall[:3, 3] = cam0.R.T, eye + 0.5 * (CENTRE - eye)  # a screen half-way, facing camera 0
    occluder = Instance(RenderMesh.from_trimesh(trimesh.creation.box((3.0, 3.0, 0.01))), wall, 7)
    kcs = annotate_correspondences(frames, obj, mesh, noise=EXACT, rng=np.random.default_rng(2), renderer=renderer,
                                   keyframes=[0, 23], occluders=[occluder])
    assert [kc.frame_index for kc in kcs] == [23]


def test_click_noise_has_the_model_spread(renderer):
    frames, mesh = make_frames(n=36), chair()
    noise = replace(AnnotatorNoise(), coplanar_prob=0.0)
    residuals = []
    for seed, yaw in enumerate((0.0, 40.0, -35.0)):
        obj = make_object(frames, mesh, yaw=yaw)
        for kc in annotate_correspondences(frames, obj, mesh, noise=noise, rng=np.random.default_rng(seed),
                                           renderer=renderer, keyframes=range(36)):
            residuals.append((np.asarray(kc.xy) - project_normalised(frames, obj, kc)) * [W, H])
    r = np.concatenate(residuals)
    assert len(r) > 400
    assert np.all(np.abs(r.std(axis=0) - 3.0) < 0.2 * 3.0), r.std(axis=0)
    assert np.all(np.abs(r.mean(axis=0)) < 0.5)


def test_mirrored_object_points_are_in_the_cad_frame(renderer):
    frames, mesh = make_frames(), chair()
    obj = make_object(frames, mesh, yaw=20.0, scale=(1.1, 1.0, 0.9), mirrored=True)
    kcs = annotate_correspondences(frames, obj, mesh, noise=EXACT, rng=np.random.default_rng(3), renderer=renderer)
    assert kcs and all(kc.is_mirrored for kc in kcs)
    off = 0.0
    for kc in kcs:
        np.testing.assert_allclose(kc.xy, project_normalised(frames, obj, kc), atol=1e-6)
        off = max(off, np.abs(np.asarray(kc.xy) - project_normalised(frames, obj, kc, mirrored=False)).max())
    assert off > 0.01  # ignoring the mirror does not fit
    box = trimesh.creation.box((1.0, 0.8, 0.6))
    obj = make_object(frames, box, yaw=30.0, scale=(1.3, 1.0, 0.8), mirrored=True)
    for kc in annotate_correspondences(frames, obj, box, noise=EXACT, rng=np.random.default_rng(4),
                                       renderer=renderer, keyframes=range(0, 24, 3)):
        assert facing_camera(frames, obj, box, kc).all()
        np.testing.assert_allclose(kc.xy, project_normalised(frames, obj, kc), atol=1e-6)


@pytest.mark.parametrize("order", [2, 4, 36])
def test_symmetric_swap_gives_symmetric_equivalents(renderer, order):
    if order == 36:
        mesh = trimesh.creation.cylinder(radius=0.4, height=0.7, sections=128)
        mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))  # axis -> +Y
    else:
        mesh = trimesh.creation.box((0.8, 0.7, 0.8 if order == 4 else 0.5))
    frames = make_frames()
    obj = make_object(frames, mesh, yaw=15.0)
    noise = replace(EXACT, symmetric_swap_prob=1.0)
    kcs = annotate_correspondences(frames, obj, mesh, noise=noise, rng=np.random.default_rng(5), renderer=renderer,
                                   symmetry_order=order, keyframes=range(0, 24, 3))
    assert len(kcs) == 8
    for kc in kcs:
        deg = kc.symmetry_deg
        assert deg != 0.0
        if order < 36:
            assert np.isclose(deg * order / 360.0, round(deg * order / 360.0))
        xyz = np.asarray(kc.xyz)
        dist, _ = closest_faces(mesh, xyz)  # still on the surface
        assert dist.max() < 1e-3
        original = xyz @ rotation_y(-deg).T
        np.testing.assert_allclose(kc.xy, project_normalised(frames, obj, kc, original), atol=1e-6)
    assert len({kc.symmetry_deg for kc in kcs}) > (order > 2)
    plain = annotate_correspondences(frames, obj, mesh, noise=noise, rng=np.random.default_rng(5), renderer=renderer,
                                     symmetry_order=1, keyframes=range(0, 24, 3))
    assert all(kc.symmetry_deg == 0.0 for kc in plain)


def test_coplanar_sets_are_coplanar(renderer):
    frames, mesh = make_frames(), chair()
    for seed, yaw in enumerate((0.0, 30.0)):
        obj = make_object(frames, mesh, yaw=yaw)
        kcs = annotate_correspondences(frames, obj, mesh, noise=replace(EXACT, coplanar_prob=1.0),
                                       rng=np.random.default_rng(seed), renderer=renderer)
        assert kcs and all(kc.coplanar for kc in kcs)
        xyz = np.concatenate([kc.xyz for kc in kcs])  # one plane for the whole object
        assert np.linalg.svd(xyz - xyz.mean(axis=0), compute_uv=False)[-1] < 1e-9
        for kc in kcs:
            np.testing.assert_allclose(kc.xy, project_normalised(frames, obj, kc), atol=1e-6)
    kcs = annotate_correspondences(frames, obj, mesh, noise=EXACT, rng=np.random.default_rng(0), renderer=renderer)
    assert not any(kc.coplanar for kc in kcs)


def test_select_cad():
    box = trimesh.creation.box((1.0, 0.8, 0.6))
    meshes = {"box": box, "box_long": trimesh.creation.box((1.05, 0.8, 0.62)),
              "box_double": trimesh.creation.box((2.0, 0.8, 0.6)), "sphere": trimesh.creation.icosphere(3),
              "chair": chair()}
    dist = lambda a, b: mesh_shape_distance(meshes[a], meshes[b])  # noqa: E731
    assert select_cad("box", ["chair", "box_long", "box", "sphere"], dist) == "box"
    assert select_cad("box", ["chair", "box_long", "sphere"], dist) == "box_long"
    assert select_cad("box", ["chair", "sphere", "box_double"], dist) is None
    assert select_cad("box", [], dist) is None
    table = {c: dist("box", c) for c in meshes}
    assert select_cad("box", ["sphere", "box_long"], table) == "box_long"
    assert select_cad("box", ["sphere", "box_long"], {("box", "sphere"): 0.5, ("box", "box_long"): 0.3}) is None
    never = replace(AnnotatorNoise(), cad_pick_true_prob=0.0)
    assert select_cad("box", ["box", "box_long"], dist, never) == "box_long"
    # the helper: invariant to size and translation, grows with shape difference
    p = trimesh.sample.sample_surface(box, 2000, seed=0)[0]
    assert shape_distance(p, 2.5 * p + 1.0) < 1e-12
    assert shape_distance(p, trimesh.sample.sample_surface(box, 2000, seed=1)[0]) < 0.02
    assert table["box_long"] < table["sphere"] < table["box_double"] < table["chair"]


def test_verify_pose(renderer):
    frames, mesh = make_frames(), chair()
    obj = make_object(frames, mesh, yaw=20.0, mirrored=True)
    keyframes = [0, 8, 16, 23]
    assert verify_pose(frames, obj, obj, mesh, keyframes, renderer=renderer)
    pose = Pose.of(obj)
    shifted = replace(pose, translation=tuple(np.add(pose.translation, (0.3, 0.0, 0.0))))
    assert not verify_pose(frames, obj, shifted, mesh, keyframes, renderer=renderer)
    assert min(pose_mask_ious(frames, obj, shifted, mesh, keyframes, renderer=renderer)) < 0.7
    assert 0.7 < min(pose_mask_ious(frames, obj, replace(pose, mirrored=False), mesh, keyframes, renderer=renderer)) < 1
    as_tuple = (pose.translation, pose.rotation, pose.scale, True)
    assert verify_pose(frames, obj, as_tuple, mesh, keyframes)  # makes its own renderer
    assert not verify_pose(frames, obj, None, mesh, keyframes, renderer=renderer)
    kcs = annotate_correspondences(frames, obj, mesh, rng=np.random.default_rng(0), renderer=renderer)
    assert verify_pose(frames, obj, obj, mesh, kcs, renderer=renderer)



def test_a_look_alike_is_verified_on_its_alignment_not_its_shape(renderer):
    """bench.simulated_labels._verify: the chosen model against itself at the object's true pose (where
    the simulated clicks put it). A look-alike 40 % wider and 20 % shallower than the true chair,
    posed where the chair is, passes; against the chair's own silhouette it fails for its shape
    alone; moved by 30 cm it fails."""
    frames, mesh = make_frames(), chair()
    look_alike = mesh.copy().apply_scale((1.4, 1.0, 0.8))
    obj = make_object(frames, mesh, yaw=20.0, mirrored=False)
    keyframes = [0, 8, 16, 23]
    assert verify_pose(frames, obj, obj, look_alike, keyframes, renderer=renderer)
    assert not verify_pose(frames, obj, obj, look_alike, keyframes, renderer=renderer, gt_mesh=mesh)
    pose = Pose.of(obj)
    shifted = replace(pose, translation=tuple(np.add(pose.translation, (0.3, 0.0, 0.0))))
    assert not verify_pose(frames, obj, shifted, look_alike, keyframes, renderer=renderer)


def test_the_verifier_does_not_see_a_misalignment_finer_than_its_clicks(renderer):
    """verify_tolerance_px (3 px, the clicks' sigma): a chair 6 m away, 5 cm off (about 2 px) fails
    on its bare silhouettes (its thin legs) and passes with the masks grown; 10 cm off (4 px) fails."""
    frames, mesh = make_frames(radius=6.0), chair()
    obj = make_object(frames, mesh, yaw=20.0)
    pose, keyframes = Pose.of(obj), [0, 8, 16, 23]

    def moved(d: float) -> Pose:
        return replace(pose, translation=tuple(np.add(pose.translation, (d, 0.0, 0.0))))

    bare = replace(AnnotatorNoise(), verify_tolerance_px=0.0)
    assert not verify_pose(frames, obj, moved(0.05), mesh, keyframes, noise=bare, renderer=renderer)
    assert verify_pose(frames, obj, moved(0.05), mesh, keyframes, renderer=renderer)
    assert not verify_pose(frames, obj, moved(0.10), mesh, keyframes, renderer=renderer)
    with pytest.raises(ValueError, match="noise levels"):
        AnnotatorNoise(verify_tolerance_px=-1.0)

def test_verify_pose_sees_the_pose_through_the_cameras_of_its_own_world(renderer):
    """An SfM clip: its cameras and the solved pose live in a world that is the true one moved by a
    similarity (X' = s W X + b); the verifier renders the pose through those cameras, frame for
    frame, and the true object through the true ones."""
    from scipy.spatial.transform import Rotation

    frames, mesh = make_frames(), chair()
    obj = make_object(frames, mesh, yaw=20.0, mirrored=True)
    s, W, b = 0.37, Rotation.from_euler("xyz", (40, -70, 15), degrees=True).as_matrix(), np.array([2.0, -1.0, 0.5])
    moved = []
    for f in frames.frames:
        R = quaternion_to_matrix(np.asarray(f.rotation))
        t = s * np.asarray(f.translation) - R @ W.T @ b  # X_cam' = s X_cam: the same pixels
        moved.append(replace(f, translation=tuple(t.tolist()), rotation=tuple(matrix_to_quaternion(R @ W.T).tolist())))
    sfm_frames = replace(frames, frames=tuple(moved))
    pose = Pose.of(obj)
    in_sfm_world = Pose(tuple((s * W @ np.asarray(pose.translation) + b).tolist()),
                        tuple(matrix_to_quaternion(W @ quaternion_to_matrix(np.asarray(pose.rotation))).tolist()),
                        tuple(s * np.asarray(pose.scale)), pose.mirrored)
    keyframes = [0, 8, 16, 23]
    ious = pose_mask_ious(frames, obj, in_sfm_world, mesh, keyframes, renderer=renderer, pose_frames=sfm_frames)
    assert min(ious) > 0.98
    assert verify_pose(frames, obj, in_sfm_world, mesh, keyframes, renderer=renderer, pose_frames=sfm_frames)
    assert not verify_pose(frames, obj, in_sfm_world, mesh, keyframes, renderer=renderer)  # through the true cameras


def test_manual_track():
    frames, mesh = make_frames(n=31), chair()
    obj = make_object(frames, mesh)
    obj = replace(obj, track=obj.track[3:29])  # visible on 26 frames
    track = draw_manual_track(frames, obj, AnnotatorNoise(), np.random.default_rng(0))
    assert len(track) == 6
    t = np.array([e.timestamp for e in track])
    assert t[0] == obj.track[0].timestamp and t[-1] == obj.track[-1].timestamp
    assert np.ptp(np.diff(t)) <= 100_000  # regular up to one frame
    for e, gt in zip(track, (g for g in obj.track if g.timestamp in set(t))):
        b, g = np.asarray(e.box), np.asarray(gt.box)
        assert ((b >= 0) & (b <= 1)).all() and b[0] < b[2] and b[1] < b[3] and e.correspondences is None
        size = np.array([g[2] - g[0], g[3] - g[1]] * 2)
        assert (np.abs(b - g) <= 5 * 0.02 * size).all() and not np.allclose(b, g)
    exact = draw_manual_track(frames, obj, EXACT, np.random.default_rng(0))
    gt = {g.timestamp: g.box for g in obj.track}
    assert all(np.allclose(e.box, gt[e.timestamp]) for e in exact)
    edge = replace(obj, track=(TrackEntry(0, (0.0, 0.0, 0.5, 0.4)), TrackEntry(100_000, (0.5, 0.7, 1.0, 1.0))))
    boxes = np.array([e.box for e in draw_manual_track(frames, edge, replace(AnnotatorNoise(), box_noise=0.3),
                                                       np.random.default_rng(1))])
    assert len(boxes) == 2 and ((boxes >= 0) & (boxes <= 1)).all()
    json.dumps(track_to_json(track))


def test_deterministic_with_a_fixed_seed(renderer):
    frames, mesh = make_frames(), chair()
    obj = make_object(frames, mesh, yaw=10.0)
    noise = AnnotatorNoise(seed=7)

    def run(noise):
        return annotate_correspondences(frames, obj, mesh, noise=noise, renderer=renderer, symmetry_order=2)

    first = run(noise)
    assert first == run(noise) == run(AnnotatorNoise(seed=7))
    assert first != run(AnnotatorNoise(seed=8))
    assert draw_manual_track(frames, obj, noise) == draw_manual_track(frames, obj, noise)
    assert noise.rng("a", 1).random() == noise.rng("a", 1).random() != noise.rng("b", 1).random()


def test_noise_model_defaults():
    n = AnnotatorNoise()
    assert n.click_sigma_px == 3.0 and n.points_per_keyframe == (4, 6) and n.keyframes_per_object == (3, 5)
    assert n.track_keyframes == 6 and n.verify_iou == 0.7 and n.box_noise == 0.02
    assert n.exact().click_sigma_px == 0.0 and n.exact().symmetric_swap_prob == 0.0
    with pytest.raises(ValueError):
        AnnotatorNoise(points_per_keyframe=(5, 4))
    with pytest.raises(ValueError):
        AnnotatorNoise(coplanar_prob=1.5)


def test_keyframes_follow_the_track_and_other_inputs(renderer):
    frames, box = make_frames(), trimesh.creation.box((1.0, 0.8, 0.6))
    obj = make_object(frames, box, yaw=30.0)
    obj = replace(obj, track=obj.track[5:16])  # the object is tracked on frames 5-15 only
    kcs = annotate_correspondences(frames, obj, trimesh.Scene([box]), noise=EXACT, rng=np.random.default_rng(0),
                                   renderer=renderer)  # a scene, as GLB files load
    assert 3 <= len(kcs) and all(5 <= kc.frame_index <= 15 for kc in kcs)
    assert kcs[0].frame_index == 5 and kcs[-1].frame_index == 15  # spread over the track
    # surface samples alone (no mesh): no depth test, outward normals still hide back faces
    samples = SurfaceSamples.from_mesh(box, 2000, seed=3)
    kcs = annotate_correspondences(frames, obj, None, noise=EXACT, rng=np.random.default_rng(0), samples=samples)
    assert kcs
    for kc in kcs:
        assert facing_camera(frames, obj, box, kc).all()
        np.testing.assert_allclose(kc.xy, project_normalised(frames, obj, kc), atol=1e-6)


def _aimed_frames(aside: list[float]) -> FramesFile:
    """:func:`make_frames` with camera i looking ``aside[i]`` metres to the right of CENTRE (the
    object then shows on the image's left, cut off by its edge, or out of view)."""
    out = []
    for f, shift in zip(make_frames().frames, aside):
        R0, t0 = quaternion_to_matrix(np.asarray(f.rotation)), np.asarray(f.translation)
        R, t = look_at(-R0.T @ t0, CENTRE + shift * R0[0])
        out.append(Frame(f.timestamp, False, f.intrinsics, tuple(t.tolist()), tuple(matrix_to_quaternion(R).tolist())))
    return FramesFile("synthetic", (H, W), tuple(out))


def test_keyframes_are_evenly_spaced_over_the_whole_visible_track():
    """Paper 3.2-3.3: key-frames evenly spaced over the track, not clustered where the object is
    best seen. Out of view on frames 0-3, mostly cut off by the image edge on 4-15, whole on 16-23
    (so well visible only there): the key-frames still span 4-23."""
    frames = _aimed_frames([8.0] * 4 + [2.7] * 12 + [0.0] * 8)
    box = trimesh.creation.box((1.0, 0.8, 0.6))
    obj = make_object(frames, box)
    samples = SurfaceSamples.from_mesh(box, 2000, seed=0)
    M = Pose.of(obj).matrix()
    share = [visible_mask(samples, M, frame_camera(f, W, H), EXACT)[0].mean() for f in frames.frames]
    assert max(share[:4]) == 0 and 0 < max(share[4:16]) < EXACT.well_visible_fraction * max(share) <= min(share[16:])
    noise = replace(EXACT, keyframes_per_object=(4, 4))
    assert choose_keyframes(frames, obj, samples, noise, np.random.default_rng(0)) == [4, 10, 17, 23]


def test_merge_rounds_keeps_the_last_work_and_sums_the_time():
    from bench.simulated_labels import merge_rounds
    from tasks.stage_chain import StageReport

    runs = [StageReport("c", "detect", "completed", 5, 2.0, "5 boxes"), StageReport("c", "cad_selection", "paused", 0, 0.5, "waits"),
            StageReport("c", "detect", "cached", 0, 0.1), StageReport("c", "cad_selection", "completed", 3, 0.25, "3 chosen"),
            StageReport("c", "cad_selection", "cached", 0, 0.0)]
    assert merge_rounds(runs) == [StageReport("c", "detect", "completed", 5, 2.1, "5 boxes"),
                                  StageReport("c", "cad_selection", "completed", 3, 0.75, "3 chosen")]
    assert merge_rounds([StageReport("c", "ingest", "cached", 0, 0.0)]) == [StageReport("c", "ingest", "cached", 0, 0.0)]


def test_stage_seconds_sums_the_runs_of_the_current_output(tmp_path):
    import datetime as dt

    import pyarrow as pa

    from bench.stage_times import stage_seconds
    from schemas import TABLES
    from warehouse import Warehouse

    wh = Warehouse(tmp_path / "w")
    when = dt.datetime(2026, 1, 1, tzinfo=dt.timezone.utc)
    runs = [("detect", "completed", 9.0), ("detect", "completed", 2.0), ("cad_selection", "completed", 4.0),
            ("cad_selection", "paused", 0.5), ("cad_selection", "completed", 0.25), ("pose", "paused", 1.0)]
    rows = [{"clip": "a", "run_id": f"r{i}", "stage": stage, "status": status, "duration_s": s,
             "started_at": when + dt.timedelta(seconds=i), "config_hash": "c", "inputs_hash": "i", "output_hash": "o",
             "code_hash": "k", "rows_written": 0, "message": ""} for i, (stage, status, s) in enumerate(runs)]
    schema = TABLES["runs"].schema
    wh.write("runs", "a", pa.Table.from_pylist([{f.name: r.get(f.name) for f in schema} for r in rows], schema=schema))
    # the last completed run and the pauses it resumed; older history left out; a stage never completed: all
    assert stage_seconds(wh, ["a", "b"]) == {"a": {"detect": 2.0, "cad_selection": 0.75, "pose": 1.0}}


def test_simulated_verifier_names_the_flagged_duplicates_of_one_object():
    from types import SimpleNamespace as NS

    from bench.simulated_labels import same_as_answers

    items = [NS(track_id=1, maybe_same_as=(3, 5)), NS(track_id=3, maybe_same_as=(1,)), NS(track_id=5, maybe_same_as=(1,)),
             NS(track_id=7, maybe_same_as=(8,)), NS(track_id=8, maybe_same_as=(7,)), NS(track_id=9, maybe_same_as=()),
             NS(track_id=10, maybe_same_as=(11,)), NS(track_id=11, maybe_same_as=(10,))]
    truth = {1: "a", 3: "a", 5: "b", 7: "c", 8: "c", 9: "a"}.get  # 10 and 11 follow no object
    # 1 and 3 on object a (5 is flagged but another object; 9 is on a but not flagged): the accepted 3 keeps its pose;
    # 7 and 8 both accepted: the lower id keeps it
    verdicts = {1: "reject", 3: "accept", 7: "accept", 8: "accept", 10: "accept", 11: "accept"}
    assert same_as_answers(NS(items=items), truth, verdicts) == {1: 3, 8: 7}
    assert same_as_answers(NS(items=items), truth, {}) == {3: 1, 8: 7}  # nothing answered: the lowest id


def test_a_simulated_persons_dice_follow_the_object_not_the_track_number():
    """bench.simulated_labels._Clip.dice: renumbering the tracks (another detector, another tracking)
    keeps the draws of each object's main track (most boxes); two tracks on one object, and tracks
    on no object, draw apart."""
    from bench.simulated_labels import _Clip

    def clip(truth: dict[int, str], sizes: dict[int, int]) -> _Clip:
        c = object.__new__(_Clip)
        c.truth, c.sizes = truth, sizes
        return c

    # object 10: a 16-box fragment and its 77-box main track, then one 115-box track; object 8 renumbered
    before = clip({2: "10", 6: "10", 3: "8"}, {2: 16, 6: 77, 3: 138})
    after = clip({3: "10", 2: "8"}, {3: 115, 2: 138})
    assert before.dice(6) == after.dice(3) and before.dice(3) == after.dice(2)
    assert before.dice(2) != before.dice(6) and before.dice(2) != before.dice(3)
    assert before.dice(4) == ("track", "4") != before.dice(5)
    noise = AnnotatorNoise()
    assert (noise.rng("c", "select_cad", *before.dice(3)).random() == noise.rng("c", "select_cad", *after.dice(2)).random()
            != noise.rng("c", "select_cad", *before.dice(2)).random())


def test_a_simulated_person_never_clicks_one_model_point_twice():
    """Visible samples that lie closer than the label rule's SAME_POINT_M (a sliver of the model in
    view) are one point to click: the key-frame gets the distinct ones, or is skipped when fewer
    than points_per_keyframe[0] are distinct, so every label written passes validation."""
    from bench.annotators import _farthest_points
    from tasks.human.label_format import SAME_POINT_M

    rng = np.random.default_rng(0)
    cluster = rng.uniform(-1e-4, 1e-4, (40, 3))  # 40 samples within 0.2 mm of the model's centre
    spread = np.vstack([cluster, [[0.2, 0.0, 0.0], [0.0, 0.2, 0.0]]])
    pick = _farthest_points(spread, 6, np.random.default_rng(1))
    assert len(pick) == 3 and all(np.linalg.norm(spread[a] - spread[b]) >= SAME_POINT_M
                                  for i, a in enumerate(pick) for b in pick[:i])
    frames = make_frames()
    obj = make_object(frames, chair())
    tiny = SurfaceSamples(cluster, np.tile([0.0, 0.0, 1.0], (40, 1)))
    assert annotate_correspondences(frames, obj, None, noise=EXACT, rng=np.random.default_rng(2), samples=tiny,
                                    keyframes=[0, 12]) == []
    wide = SurfaceSamples(spread[[0, 40, 41]], np.tile([0.0, 0.0, 1.0], (3, 1)))  # three distinct points
    assert annotate_correspondences(frames, obj, None, noise=replace(EXACT, points_per_keyframe=(3, 3)),
                                    rng=np.random.default_rng(2), samples=wide, keyframes=[12]) != []
