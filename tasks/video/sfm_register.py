"""Frames between SfM's keyframes, registered to the finished model (:mod:`tasks.video.sfm`).

Mapping costs more than linearly in frames, and consecutive frames of a walkthrough sampled at
15 fps add little but time: on a 138-frame benchmark clip, mapping every second frame took the
whole SfM from 103 s to 65 s with the same accuracy. So the mapper maps every
``[cameras] keyframe_every``-th sampled frame; once that model is polished and its focal length
settled, each frame in between is registered to it alone: its keypoints' verified matches with
the model's registered frames (sequential matching pairs every frame with its neighbours, so with
keyframes on both sides) give 2D-3D correspondences, and an absolute pose (LO-RANSAC P3P, then a
refinement of the pose, the camera held) is kept when it has as many inliers as COLMAP's
incremental mapper asks of a frame it registers. The model is not changed: no point is added and
nothing is re-adjusted.

Coordinates: keypoints in COLMAP's image convention (px, origin at the top-left corner of the
top-left pixel), as the model's own observations; poses are ``cam_from_world`` (world->camera,
OpenCV axes) in the model's world.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class Correspondences:
    """One frame's 2D-3D matches: ``points2D`` float64[m, 2] keypoints (px) and ``points3D``
    float64[m, 3] the model points (world) they were matched with; one row per keypoint."""

    points2D: np.ndarray
    points3D: np.ndarray


def point_ids(image) -> np.ndarray:
    """int64[K] the 3D point id of each of a registered image's keypoints (-1: none)."""
    return np.array([p.point3D_id if p.has_point3D() else -1 for p in image.points2D], dtype=np.int64)


def frame_correspondences(db_path: Path, reconstruction, names: list[str]) -> dict[str, Correspondences]:
    """Per frame of ``names`` (frames of the COLMAP database ``db_path`` that ``reconstruction``
    did not map): its keypoints matched (verified inliers) to a keypoint of a registered frame
    that observes a 3D point, and those points. A keypoint matched to several such frames keeps
    the first frame's point (by pair order)."""
    import pycolmap

    db = pycolmap.Database.open(str(db_path))
    try:
        ids = {image.name: image.image_id for image in db.read_all_images()}
        wanted = {ids[name]: name for name in names}
        registered = {i for i, image in reconstruction.images.items() if image.has_pose}
        seen_ids: dict[int, np.ndarray] = {}
        links: dict[int, dict[int, int]] = {i: {} for i in wanted}
        for pair_id, geometry in zip(*db.read_two_view_geometries()):
            pair = pycolmap.pair_id_to_image_pair(pair_id)
            matches = np.asarray(geometry.inlier_matches, dtype=np.int64).reshape(-1, 2)
            for side in (0, 1):
                mine, other = pair[side], pair[1 - side]
                if mine not in wanted or other not in registered or not len(matches):
                    continue
                if other not in seen_ids:
                    seen_ids[other] = point_ids(reconstruction.images[other])
                seen = seen_ids[other][matches[:, 1 - side]]
                for keypoint, point in zip(matches[seen >= 0, side].tolist(), seen[seen >= 0].tolist()):
                    links[mine].setdefault(keypoint, point)
        out = {}
        for i, name in wanted.items():
            keypoints = sorted(links[i])
            xy = db.read_keypoints(i)[:, :2].astype(np.float64)[keypoints].reshape(-1, 2)
            xyz = np.array([reconstruction.points3D[links[i][k]].xyz for k in keypoints], dtype=np.float64).reshape(-1, 3)
            out[name] = Correspondences(xy, xyz)
    finally:
        db.close()
    return out


def register_frames(reconstruction, correspondences: dict[str, Correspondences], mapper, seed: int) -> dict:
    """{frame name: ``cam_from_world`` (pycolmap Rigid3d)} for the frames whose absolute pose
    against ``reconstruction``'s one camera has at least ``mapper.abs_pose_min_num_inliers``
    inliers (RANSAC at ``mapper.abs_pose_max_error`` px, ``mapper.abs_pose_min_inlier_ratio``,
    seeded with ``seed``); ``mapper``: pycolmap ``IncrementalMapperOptions``. The others are left out."""
    import pycolmap

    camera = reconstruction.cameras[next(iter(reconstruction.cameras))]
    estimation = pycolmap.AbsolutePoseEstimationOptions()
    estimation.ransac.max_error = mapper.abs_pose_max_error
    estimation.ransac.min_inlier_ratio = mapper.abs_pose_min_inlier_ratio
    estimation.ransac.random_seed = seed
    refinement = pycolmap.AbsolutePoseRefinementOptions()
    poses = {}
    for name, c in correspondences.items():
        if len(c.points2D) < mapper.abs_pose_min_num_inliers:
            continue
        found = pycolmap.estimate_and_refine_absolute_pose(c.points2D, c.points3D, camera, estimation, refinement)
        if found is not None and found["num_inliers"] >= mapper.abs_pose_min_num_inliers:
            poses[name] = found["cam_from_world"]
    return poses
