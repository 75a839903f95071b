"""Simulated human annotators of the synthetic benchmark (seed paper, sections 3.1-3.5).

Each function takes ground truth (official :mod:`schemas.official` records, CAD meshes in their
canonical frame: metres, +Y up, front +Z, bbox centred) and returns what a human would have
labelled, with the errors of :class:`bench.noise.AnnotatorNoise` (the one place for the noise
model). Frames: see :mod:`cadestate.geometry`; object-to-world = T·R·S·diag(-1, 1, 1) when
mirrored (:func:`cadestate.render.object_to_world`); 3D points are in the CAD's own frame.

- :func:`annotate_correspondences` (3.3): 4-6 visible surface points per key-frame -> 2D clicks.
- :func:`select_cad` (3.2): the true model when offered, else the nearest shape, else "none".
- :func:`verify_pose` (3.5): mask IoU of predicted vs true render on every key-frame.
- :func:`draw_manual_track` (3.1): boxes on 6 regularly spaced frames.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from bench.noise import DEFAULT_NOISE, AnnotatorNoise
from cadestate.geometry import pixel_intrinsics_matrix, project, quaternion_to_matrix
from cadestate.render import Camera, Instance, Renderer, RenderMesh, object_to_world
from schemas.official import Correspondence, Frame, FramesFile, ObjectAnnotation, TrackEntry
from tasks.cad.symmetry import rotation_y
from tasks.human.label_format import SAME_POINT_M

OWN_ID = 0  # instance id of the annotated object in visibility renders; occluders get 1, 2, ...


# ----------------------------------------------------------------------------------------- records

@dataclass(frozen=True)
class Pose:
    """A 9-DoF pose: translation (x, y, z), rotation (w, x, y, z), scale (sx, sy, sz), mirror flag."""

    translation: tuple[float, float, float]
    rotation: tuple[float, float, float, float]
    scale: tuple[float, float, float]
    mirrored: bool = False

    @staticmethod
    def of(obj: Pose | ObjectAnnotation | Sequence[Any]) -> Pose:
        """From a Pose, a posed ObjectAnnotation or a tuple (translation, rotation, scale, mirrored)."""
        if isinstance(obj, Pose):
            return obj
        if isinstance(obj, ObjectAnnotation):
            if obj.translation is None:
                raise ValueError(f"object {obj.track_id} has no pose")
            return Pose(obj.translation, obj.rotation, obj.scale, obj.is_mirrored)
        t, r, s, *m = obj
        return Pose(tuple(map(float, t)), tuple(map(float, r)), tuple(map(float, s)), bool(m[0]) if m else False)

    def matrix(self) -> np.ndarray:
        """float64[4, 4] object (CAD frame) -> world."""
        return object_to_world(self.translation, self.rotation, self.scale, self.mirrored)


@dataclass(frozen=True)
class KeyframeCorrespondences:
    """One key-frame's clicks. ``xy[i]`` (normalised to [0, 1]) pairs with ``xyz[i]`` (CAD frame).
    ``symmetry_deg``: the rotation about +Y the annotator's 3D points carry relative to the true
    correspondences (0 when none: rotating ``xyz`` by ``-symmetry_deg`` gives points that project
    to ``xy`` under the GT pose). ``coplanar``: the points were taken on one planar face."""

    frame_index: int
    timestamp: int
    xy: tuple[tuple[float, float], ...]
    xyz: tuple[tuple[float, float, float], ...]
    is_mirrored: bool
    coplanar: bool = False
    symmetry_deg: float = 0.0

    def correspondences(self) -> tuple[Correspondence, ...]:
        """As official ``Correspondence`` records (for ``TrackEntry.correspondences``)."""
        return tuple(Correspondence(a, b) for a, b in zip(self.xy, self.xyz))

    def to_json(self) -> dict:
        return {"frame_index": self.frame_index, "timestamp": self.timestamp, "is_mirrored": self.is_mirrored,
                "coplanar": self.coplanar, "symmetry_deg": self.symmetry_deg,
                "correspondences": [{"2d": list(a), "3d": list(b)} for a, b in zip(self.xy, self.xyz)]}

    @staticmethod
    def from_json(d: Mapping[str, Any]) -> KeyframeCorrespondences:
        cs = d["correspondences"]
        return KeyframeCorrespondences(
            int(d["frame_index"]), int(d["timestamp"]), tuple(tuple(map(float, c["2d"])) for c in cs),
            tuple(tuple(map(float, c["3d"])) for c in cs), bool(d["is_mirrored"]), bool(d.get("coplanar", False)),
            float(d.get("symmetry_deg", 0.0)))


def track_to_json(entries: Sequence[TrackEntry]) -> list[dict]:
    """Manual-track boxes as JSON (official ``track`` entries without correspondences)."""
    return [{"timestamp": e.timestamp, "box": list(e.box), "correspondences": None} for e in entries]


@dataclass(frozen=True)
class SurfaceSamples:
    """Points on a CAD surface (CAD frame): points float[N, 3], normals float[N, 3], face_ids int[N]
    (the mesh faces they lie on; None without a mesh: no co-planar sets). ``two_sided``: the
    normals may point either way (a surface is clickable from both sides); False when they point
    out of a closed volume, so back-facing points are never clickable (they are always hidden)."""

    points: np.ndarray
    normals: np.ndarray
    face_ids: np.ndarray | None = None
    two_sided: bool = True

    @staticmethod
    def from_mesh(mesh: trimesh.Trimesh, count: int, seed: int) -> SurfaceSamples:
        points, faces = trimesh.sample.sample_surface(mesh, count, seed=seed)
        return SurfaceSamples(np.asarray(points, np.float64), np.asarray(mesh.face_normals[faces], np.float64),
                              np.asarray(faces, np.int64), two_sided=not mesh.is_volume)


def as_trimesh(mesh: trimesh.Trimesh | trimesh.Scene) -> trimesh.Trimesh:
    """A single mesh, scene-graph transforms baked in (GLB files load as scenes)."""
    return mesh.to_mesh() if isinstance(mesh, trimesh.Scene) else mesh


def frame_camera(frame: Frame, width: int, height: int, near: float = 0.01, far: float = 1000.0) -> Camera:
    """The pixel camera of a frame (its pixel intrinsics -> K; world->camera R, t) of a
    ``width`` x ``height`` image."""
    return Camera(pixel_intrinsics_matrix(np.asarray(frame.intrinsics)),
                  quaternion_to_matrix(np.asarray(frame.rotation)), np.asarray(frame.translation, np.float64),
                  width, height, near, far)


def _size(frames: FramesFile, image_size: tuple[int, int] | None) -> tuple[int, int]:
    """(width, height) from ``image_size`` (height, width) or the frames file's."""
    size = image_size or frames.image_size
    if size is None:
        raise ValueError("image size unknown: pass image_size=(height, width)")
    return int(size[1]), int(size[0])


def _transform(points: np.ndarray, M: np.ndarray) -> np.ndarray:
    return points @ M[:3, :3].T + M[:3, 3]


# ----------------------------------------------------------------------------------------- visibility

def visible_mask(samples: SurfaceSamples, M: np.ndarray, camera: Camera, noise: AnnotatorNoise,
                 depth: np.ndarray | None = None, ids: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Which samples an annotator can click in this view, and their pixel positions float[N, 2].
    Visible: in front of the camera, ``edge_margin_px`` inside the image, facing the camera (either
    side when ``samples.two_sided``) at more than a grazing angle and, given a render (``depth``,
    ``ids``), on the annotated object's pixel and not behind the rendered surface (self-occlusion
    and occluders)."""
    X = _transform(samples.points, M)
    n = samples.normals @ np.linalg.inv(M[:3, :3])  # inverse-transpose (handles mirror, scale)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    uv, z = project(camera.K, camera.R, camera.t, X)
    centre = -camera.R.T @ camera.t
    ray = centre - X
    cos = np.sum(n * ray, axis=1) / np.maximum(np.linalg.norm(ray, axis=1), 1e-12)
    cos = np.abs(cos) if samples.two_sided else cos
    m = noise.edge_margin_px
    with np.errstate(invalid="ignore"):
        ok = ((z > camera.near) & (uv[:, 0] >= m) & (uv[:, 0] <= camera.width - m) & (uv[:, 1] >= m)
              & (uv[:, 1] <= camera.height - m) & (cos >= noise.min_view_cosine))
    if depth is not None:
        idx = np.flatnonzero(ok)
        px = np.clip(np.floor(uv[idx]).astype(np.int64), 0, [camera.width - 1, camera.height - 1])
        d, zi = depth[px[:, 1], px[:, 0]], z[idx]
        tol = noise.depth_tolerance * zi + 3.0 * zi / camera.K[0, 0]
        good = d >= zi - tol
        if ids is not None:
            good &= ids[px[:, 1], px[:, 0]] == OWN_ID
        ok[idx[~good]] = False
    return ok, uv


def _render_view(renderer: Renderer, rmesh: RenderMesh, M: np.ndarray, camera: Camera,
                 occluders: Sequence[Instance]):
    instances = [Instance(rmesh, M, OWN_ID)] + [Instance(o.mesh, o.object_to_world, i + 1)
                                                 for i, o in enumerate(occluders)]
    return renderer.render(instances, camera)


def choose_keyframes(frames: FramesFile, obj: ObjectAnnotation, samples: SurfaceSamples, noise: AnnotatorNoise,
                     rng: np.random.Generator, image_size: tuple[int, int] | None = None) -> list[int]:
    """Frame indices an annotator would annotate: ``keyframes_per_object`` key-frames evenly spaced
    in time over the object's whole visible track (paper 3.2-3.3: "a set of evenly spaced
    key-frames"), restricted to the object's track when it has one and to the ``key_frame`` frames
    when any are marked. Visible: some surface samples clickable. Each key-frame is the frame
    nearest its evenly spaced target time among those where the object is well visible (share of
    the surface samples in view at least ``well_visible_fraction`` of the best frame), taken only
    from the frames nearer that target than any other (the annotator navigates to a good view
    near each key-frame); when there is none, the visible frame nearest the target."""
    W, H = _size(frames, image_size)
    idx = list(range(len(frames.frames)))
    stamps = {e.timestamp for e in obj.track}
    if stamps and (on_track := [i for i in idx if frames.frames[i].timestamp in stamps]):
        idx = on_track
    if marked := [i for i in idx if frames.frames[i].key_frame]:
        idx = marked
    M = Pose.of(obj).matrix()
    score = np.array([visible_mask(samples, M, frame_camera(frames.frames[i], W, H), noise)[0].mean() for i in idx])
    if not len(idx) or score.max() <= 0:
        return []
    visible = [(frames.frames[i].timestamp, i, s) for i, s in zip(idx, score) if s > 0]
    t = np.array([v[0] for v in visible], np.float64)
    good = np.array([v[2] >= noise.well_visible_fraction * score.max() for v in visible])
    lo, hi = noise.keyframes_per_object
    n = min(int(rng.integers(lo, hi + 1)), int(good.sum()))
    targets = np.linspace(t.min(), t.max(), n) if n > 1 else np.array([t[good][np.argmax([v[2] for v, g in zip(visible, good) if g])]])
    segment = np.argmin(np.abs(t[:, None] - targets[None]), axis=1)  # the target each visible frame is nearest to
    out = []
    for k, target in enumerate(targets):
        mine = np.flatnonzero(segment == k)
        if not len(mine):
            continue
        pool = mine[good[mine]] if good[mine].any() else mine
        out.append(visible[int(pool[np.argmin(np.abs(t[pool] - target))])][1])
    return sorted(set(out))


# ----------------------------------------------------------------------------------------- 3.3 clicks

def _planar_groups(mesh: trimesh.Trimesh) -> np.ndarray:
    """int[F]: a planar-region id per face (trimesh facets; faces in no facet are their own region)."""
    group = len(mesh.facets) + np.arange(len(mesh.faces))
    for k, facet in enumerate(mesh.facets):
        group[facet] = k
    return group


def _farthest_points(points: np.ndarray, n: int, rng: np.random.Generator, apart: float = SAME_POINT_M) -> np.ndarray:
    """Indices of up to ``n`` well-spread points (greedy farthest-point sampling from a random
    start), each at least ``apart`` from the others: fewer when the rest lie closer (a sliver of
    the model in view), as a person does not click one model point twice (the label rule
    :data:`tasks.human.label_format.SAME_POINT_M`)."""
    chosen = [int(rng.integers(len(points)))]
    d = np.linalg.norm(points - points[chosen[0]], axis=1)
    for _ in range(1, n):
        if d.max() < apart:
            break
        chosen.append(int(np.argmax(d)))
        d = np.minimum(d, np.linalg.norm(points - points[chosen[-1]], axis=1))
    return np.array(chosen)


def annotate_correspondences(frames: FramesFile, obj: ObjectAnnotation, mesh: trimesh.Trimesh | trimesh.Scene | None,
                             image_size: tuple[int, int] | None = None, noise: AnnotatorNoise = DEFAULT_NOISE,
                             rng: np.random.Generator | None = None, renderer: Renderer | None = None, *,
                             samples: SurfaceSamples | None = None, symmetry_order: int = 1,
                             keyframes: Sequence[int] | None = None,
                             occluders: Sequence[Instance] = ()) -> list[KeyframeCorrespondences]:
    """3D<->2D clicks of one posed object (GT pose = ``obj``'s translation/rotation/scale/mirror).

    Args:
        mesh: the CAD model (canonical frame); None only with ``samples`` (then no depth test).
        image_size: (height, width); default ``frames.image_size``.
        rng: default ``noise.rng(frames.clip_name, obj.track_id)``.
        renderer: a :class:`Renderer` of the image size for the depth test (one is made if None).
        samples: candidate surface points (default: ``noise.surface_samples`` on ``mesh``).
        symmetry_order: the model's order about +Y (1, 2, 4, 36; :mod:`tasks.cad.symmetry`).
        keyframes: frame indices to annotate (default :func:`choose_keyframes`).
        occluders: other posed objects that may hide this one (their ids are ignored).
    Returns one record per key-frame with at least ``points_per_keyframe[0]`` clickable points (on
    the chosen planar face for a co-planar annotation); points are never reused across key-frames.
    """
    W, H = _size(frames, image_size)
    rng = rng if rng is not None else noise.rng(frames.clip_name, obj.track_id)
    tm = as_trimesh(mesh) if mesh is not None else None
    if samples is None:
        if tm is None:
            raise ValueError("need a mesh or surface samples")
        samples = SurfaceSamples.from_mesh(tm, noise.surface_samples, int(rng.integers(2**31)))
    group = _planar_groups(tm)[samples.face_ids] if tm is not None and samples.face_ids is not None else None
    M = Pose.of(obj).matrix()
    if keyframes is None:
        keyframes = choose_keyframes(frames, obj, samples, noise, rng, (H, W))
    own_renderer = renderer is None and tm is not None
    if own_renderer:
        renderer = Renderer(W, H)
    rmesh = RenderMesh.from_trimesh(tm) if tm is not None else None
    lo, hi = noise.points_per_keyframe
    views = []  # (frame index, visible mask, pixel positions)
    try:
        for fi in keyframes:
            camera = frame_camera(frames.frames[fi], W, H)
            view = _render_view(renderer, rmesh, M, camera, occluders) if rmesh is not None else None
            ok, uv = visible_mask(samples, M, camera, noise, None if view is None else view.depth,
                                  None if view is None else view.instance_id)
            views.append((int(fi), ok, uv))
    finally:
        if own_renderer:
            renderer.release()
    plane = None  # the planar region of a co-planar annotation: the one best seen on all key-frames
    if group is not None and rng.random() < noise.coplanar_prob and views:
        seen = np.stack([np.bincount(group[ok], minlength=group.max() + 1) for _, ok, _ in views])
        if (seen >= lo).any():  # most key-frames showing enough of it, then most points seen
            plane = int(np.argmax((seen >= lo).sum(axis=0) * (len(samples.points) * len(views) + 1)
                                  + seen.sum(axis=0)))
    used = np.zeros(len(samples.points), bool)
    out = []
    for fi, ok, uv in views:
        vis = np.flatnonzero(ok & ~used & (True if plane is None else group == plane))
        if len(vis) < lo:
            continue
        n = min(int(rng.integers(lo, hi + 1)), len(vis))
        pick = vis[_farthest_points(samples.points[vis], n, rng)]
        if len(pick) < lo:
            continue
        n = len(pick)
        used[pick] = True
        xyz = samples.points[pick]
        deg = 0.0
        if symmetry_order > 1 and rng.random() < noise.symmetric_swap_prob:
            deg = (float(rng.uniform(0.0, 360.0)) if symmetry_order >= 36
                   else 360.0 * int(rng.integers(1, symmetry_order)) / symmetry_order)
            xyz = xyz @ rotation_y(deg).T
        click = uv[pick] + rng.normal(0.0, noise.click_sigma_px, (n, 2)) if noise.click_sigma_px > 0 else uv[pick]
        xy = np.clip(click / [W, H], 0.0, 1.0)
        out.append(KeyframeCorrespondences(
            fi, frames.frames[fi].timestamp, tuple(map(tuple, xy.tolist())), tuple(map(tuple, xyz.tolist())),
            bool(obj.is_mirrored), plane is not None, deg))
    return out


# ----------------------------------------------------------------------------------------- 3.2 CAD

def shape_distance(points_a: np.ndarray, points_b: np.ndarray) -> float:
    """Symmetric chamfer distance (mean of the two mean nearest-neighbour distances) between two
    surface samplings (canonical frames), each centred on its bounding box and divided by its
    bounding-box diagonal: 0 for the same shape at any size, ~0.01 for resampling noise."""
    def norm(p: np.ndarray) -> np.ndarray:
        p = np.asarray(p, np.float64)
        lo, hi = p.min(axis=0), p.max(axis=0)
        return (p - (lo + hi) / 2) / max(float(np.linalg.norm(hi - lo)), 1e-12)
    a, b = norm(points_a), norm(points_b)
    return 0.5 * float(cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean())


def mesh_shape_distance(mesh_a: trimesh.Trimesh | trimesh.Scene, mesh_b: trimesh.Trimesh | trimesh.Scene,
                        count: int = 2048, seed: int = 0) -> float:
    """:func:`shape_distance` of area-uniform samples of two meshes."""
    sample = lambda m: trimesh.sample.sample_surface(as_trimesh(m), count, seed=seed)[0]  # noqa: E731
    return shape_distance(sample(mesh_a), sample(mesh_b))


def select_cad(true_cad_id: str, candidates: Sequence[str],
               shape_distance: Callable[[str, str], float] | Mapping[Any, float],
               noise: AnnotatorNoise = DEFAULT_NOISE, rng: np.random.Generator | None = None) -> str | None:
    """The annotator's choice among ``candidates``: the true model when offered (with probability
    ``cad_pick_true_prob``), else the candidate nearest in shape to the true model if within
    ``cad_max_distance``, else None ("none of these"). ``shape_distance``: f(true_id, candidate_id)
    or a dict keyed by candidate id or by (true_id, candidate_id)."""
    def dist(c: str) -> float:
        if callable(shape_distance):
            return float(shape_distance(true_cad_id, c))
        for key in ((true_cad_id, c), (c, true_cad_id), c):
            if key in shape_distance:
                return float(shape_distance[key])
        raise KeyError(f"no shape distance between {true_cad_id!r} and {c!r}")

    if true_cad_id in candidates:
        if noise.cad_pick_true_prob >= 1.0 or (rng if rng is not None else noise.rng("select_cad", true_cad_id)
                                               ).random() < noise.cad_pick_true_prob:
            return true_cad_id
    others = [c for c in candidates if c != true_cad_id]
    if not others:
        return None
    d = [dist(c) for c in others]
    best = int(np.argmin(d))
    return others[best] if d[best] <= noise.cad_max_distance else None


# ----------------------------------------------------------------------------------------- 3.5 verification

def grown(mask: np.ndarray, radius: float) -> np.ndarray:
    """bool[H, W] ``mask`` grown by a disc of ``radius`` pixels (unchanged for radius < 1)."""
    r = int(np.floor(radius))
    if r < 1 or not mask.any():
        return mask
    from scipy.ndimage import binary_dilation

    y, x = np.mgrid[-r:r + 1, -r:r + 1]
    return binary_dilation(mask, structure=x * x + y * y <= radius * radius)


def pose_mask_ious(frames: FramesFile, gt_obj: ObjectAnnotation, predicted: Pose | ObjectAnnotation | Sequence[Any],
                   mesh: trimesh.Trimesh | trimesh.Scene, keyframes: Sequence[int | KeyframeCorrespondences],
                   image_size: tuple[int, int] | None = None, gt_mesh: trimesh.Trimesh | trimesh.Scene | None = None,
                   renderer: Renderer | None = None, pose_frames: FramesFile | None = None,
                   tolerance_px: float = 0.0) -> list[float]:
    """Per key-frame (frame index or :class:`KeyframeCorrespondences`): IoU of the silhouettes of
    ``mesh`` under ``predicted``, seen through ``pose_frames`` (default ``frames``: the cameras of
    the predicted pose's world, frame for frame), and of ``gt_mesh`` (default ``mesh``) under the GT
    pose through ``frames`` (1 when both are empty), each silhouette first grown by a disc of
    radius ``tolerance_px``."""
    W, H = _size(frames, image_size)
    own = renderer is None
    renderer = renderer or Renderer(W, H)
    pred_mesh = RenderMesh.from_trimesh(as_trimesh(mesh))
    true_mesh = pred_mesh if gt_mesh is None else RenderMesh.from_trimesh(as_trimesh(gt_mesh))
    Mp, Mg = Pose.of(predicted).matrix(), Pose.of(gt_obj).matrix()
    ious = []
    try:
        for k in keyframes:
            fi = k.frame_index if isinstance(k, KeyframeCorrespondences) else int(k)
            seen_from = frame_camera((pose_frames or frames).frames[fi], W, H)
            a = grown(renderer.render([Instance(pred_mesh, Mp, 0)], seen_from).instance_id >= 0, tolerance_px)
            b = grown(renderer.render([Instance(true_mesh, Mg, 0)], frame_camera(frames.frames[fi], W, H)).instance_id >= 0,
                      tolerance_px)
            union = np.count_nonzero(a | b)
            ious.append(1.0 if union == 0 else np.count_nonzero(a & b) / union)
    finally:
        if own:
            renderer.release()
    return ious


def verify_pose(frames: FramesFile, gt_obj: ObjectAnnotation, predicted: Pose | ObjectAnnotation | Sequence[Any] | None,
                mesh: trimesh.Trimesh | trimesh.Scene, keyframes: Sequence[int | KeyframeCorrespondences],
                image_size: tuple[int, int] | None = None, noise: AnnotatorNoise = DEFAULT_NOISE,
                gt_mesh: trimesh.Trimesh | trimesh.Scene | None = None, renderer: Renderer | None = None,
                pose_frames: FramesFile | None = None) -> bool:
    """The verifier's verdict: True when the mask IoU, the masks grown by ``noise.verify_tolerance_px``,
    is >= ``noise.verify_iou`` on every key-frame (False with no key-frames or no predicted pose).
    See :func:`pose_mask_ious`."""
    if predicted is None or (isinstance(predicted, ObjectAnnotation) and predicted.translation is None):
        return False
    ious = pose_mask_ious(frames, gt_obj, predicted, mesh, keyframes, image_size, gt_mesh, renderer, pose_frames,
                          noise.verify_tolerance_px)
    return bool(ious) and min(ious) >= noise.verify_iou


# ----------------------------------------------------------------------------------------- 3.1 tracks

def draw_manual_track(frames: FramesFile | None, gt_obj: ObjectAnnotation, noise: AnnotatorNoise = DEFAULT_NOISE,
                      rng: np.random.Generator | None = None) -> list[TrackEntry]:
    """Boxes on ``noise.track_keyframes`` frames regularly spaced in time over the object's GT
    track (the frames where it is visible; restricted to ``frames``' timestamps when given), each
    side moved by N(0, ``box_noise`` x the box's size along it), clipped to [0, 1]. Fewer entries
    when the object is visible on fewer frames; correspondences None."""
    rng = rng if rng is not None else noise.rng("track", frames.clip_name if frames else "", gt_obj.track_id)
    stamps = {f.timestamp for f in frames.frames} if frames is not None else None
    entries = sorted((e for e in gt_obj.track if e.box[2] > e.box[0] and e.box[3] > e.box[1]
                      and (stamps is None or e.timestamp in stamps)), key=lambda e: e.timestamp)
    from tasks.human.manual_tracks import regular_keyframes  # the manual-track task's own spacing

    entries = [entries[i] for i in regular_keyframes([e.timestamp for e in entries], noise.track_keyframes)]
    out = []
    for e in entries:
        box = np.asarray(e.box, np.float64)
        h, w = box[2] - box[0], box[3] - box[1]
        if noise.box_noise > 0:
            box = box + rng.normal(0.0, 1.0, 4) * noise.box_noise * np.array([h, w, h, w])
        box = np.clip(box, 0.0, 1.0)
        y0, y1 = sorted(box[[0, 2]])
        x0, x1 = sorted(box[[1, 3]])
        out.append(TrackEntry(e.timestamp, (float(y0), float(x0), float(y1), float(x1)), None))
    return out
