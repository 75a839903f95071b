"""The focal length of a video's camera for SfM (:mod:`tasks.video.sfm`): field-of-view hypotheses.

COLMAP refining the focal length while it maps a walkthrough lets it drift (forward motion, few
frames at the start: 0.96 instead of 0.785 of the width, and rotation errors of several degrees).
Instead, before mapping every frame:

1. ``[cameras] fov_hypotheses`` focal lengths, evenly spaced in log focal between the horizontal
   fields of view ``fov_max_deg`` and ``fov_min_deg`` (of the image width);
2. for each, incremental mapping of about ``focal_frames`` of the sampled frames, evenly spaced,
   with the focal length held fixed; its score is the model's mean reprojection error (px), infinite when it
   registers fewer than half of those frames;
3. the estimate is the minimum of a parabola through the best hypothesis and its two neighbours
   (in log focal; the best one itself when it lies at an end of the range; the middle of the
   range when none registered enough frames, and the full mapping decides).

The full mapping then holds the estimate fixed; a last bundle adjustment frees the focal length
and keeps its result only when the focal length moves by less than ``max_focal_change``.
Deterministic: the hypotheses run one after another with the seeded mapper.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cadestate.config import CamerasConfig


@dataclass(frozen=True)
class FocalEstimate:
    """``focal_px`` the estimate (px) for images ``width`` px wide; ``hypotheses_px`` float[H] the
    focal lengths tried and ``errors_px`` float[H] their mean reprojection errors (inf: too few
    frames registered)."""

    focal_px: float
    width: int
    hypotheses_px: np.ndarray
    errors_px: np.ndarray


def focal_hypotheses(width: int, cfg: CamerasConfig) -> np.ndarray:
    """float[H] focal lengths (px) from ``fov_max_deg`` to ``fov_min_deg`` (horizontal FOV of
    ``width`` px), evenly spaced in log focal."""
    f = [0.5 * width / math.tan(math.radians(fov) / 2) for fov in (cfg.fov_max_deg, cfg.fov_min_deg)]
    return np.geomspace(f[0], f[1], cfg.fov_hypotheses)


def best_focal(hypotheses: np.ndarray, errors: np.ndarray) -> float:
    """The focal length (px) minimising the parabola through the lowest of ``errors`` float[H]
    and its neighbours, in log ``hypotheses`` float[H] (ascending); the best hypothesis itself at
    an end of the range or when the parabola opens downwards; their geometric mean when none is
    finite (the full mapping then fails with its own error, or succeeds)."""
    if not np.any(np.isfinite(errors)):
        return float(np.exp(np.log(hypotheses).mean()))
    k = int(np.argmin(errors))
    if k == 0 or k == len(errors) - 1 or not np.all(np.isfinite(errors[k - 1:k + 2])):
        return float(hypotheses[k])
    x, y = np.log(hypotheses[k - 1:k + 2]), errors[k - 1:k + 2]
    a, b, _ = np.polyfit(x, y, 2)
    if a <= 0:
        return float(hypotheses[k])
    return float(np.exp(np.clip(-b / (2 * a), x[0], x[2])))


def set_focal(db_path: Path, focal_px: float) -> None:
    """Set every camera of the COLMAP database to ``focal_px`` with the principal point at the image
    centre (``SIMPLE_PINHOLE`` parameters f, cx, cy), flagged as a prior."""
    import pycolmap

    db = pycolmap.Database.open(str(db_path))
    try:
        for camera in db.read_all_cameras():
            camera.params = [focal_px, camera.width / 2, camera.height / 2]
            camera.has_prior_focal_length = True
            db.update_camera(camera)
    finally:
        db.close()


def hypothesis_error(db_path: Path, image_dir: Path, names: list[str], focal_px: float, mapping, out_dir: Path) -> float:
    """Mean reprojection error (px) of mapping the frames ``names`` with the focal length held at
    ``focal_px`` (``mapping``: pycolmap options, focal refinement off); inf when the largest model
    registers fewer than half of them."""
    import pycolmap

    set_focal(db_path, focal_px)
    mapping = pycolmap.IncrementalPipelineOptions(mapping.todict())
    mapping.image_names = names
    out_dir.mkdir()
    models = pycolmap.incremental_mapping(db_path, image_dir, out_dir, mapping)
    best = max(models.values(), key=lambda m: m.num_reg_images(), default=None)
    if best is None or 2 * best.num_reg_images() < len(names):
        return math.inf
    return float(best.compute_mean_reprojection_error())


def estimate_focal(db_path: Path, image_dir: Path, names: list[str], width: int, cfg: CamerasConfig, mapping,
                   work_dir: Path) -> FocalEstimate:
    """The focal length (px) of the module docstring for the frames ``names`` (in time order) of
    ``width`` px; ``mapping``: the pycolmap mapping options with focal refinement off."""
    hypotheses = focal_hypotheses(width, cfg)
    subset = names[::max(1, round(len(names) / cfg.focal_frames))]
    errors = np.array([hypothesis_error(db_path, image_dir, subset, f, mapping, work_dir / f"focal-{i}")
                       for i, f in enumerate(hypotheses)])
    return FocalEstimate(best_focal(hypotheses, errors), width, hypotheses, errors)


def refine_focal(reconstruction, max_change: float, threads: int):
    """(``reconstruction`` bundle-adjusted with its focal length free, True) when the focal length
    moves by less than ``max_change`` (a fraction), else (``reconstruction`` untouched, False);
    ``reconstruction``: a pycolmap Reconstruction with one camera."""
    import pycolmap

    refined = pycolmap.Reconstruction(reconstruction)
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = True
    options.refine_principal_point = False
    options.refine_extra_params = False
    options.print_summary = False
    options.ceres.solver_options.num_threads = threads
    pycolmap.bundle_adjustment(refined, options)
    camera_id = next(iter(reconstruction.cameras))
    change = refined.cameras[camera_id].focal_length / reconstruction.cameras[camera_id].focal_length - 1
    return (refined, True) if abs(change) < max_change else (reconstruction, False)
