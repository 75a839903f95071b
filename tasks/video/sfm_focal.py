"""The focal length of a video's camera for SfM (:mod:`tasks.video.sfm`): field-of-view hypotheses.

COLMAP refining the focal length while it maps a walkthrough lets it drift (forward motion, few
frames at the start: 0.96 instead of 0.785 of the width, and rotation errors of several degrees).
Instead, before mapping every frame:

1. ``[cameras] fov_hypotheses`` focal lengths, evenly spaced in log focal between the horizontal
   fields of view ``fov_max_deg`` and ``fov_min_deg`` (of the image width);
2. for each, incremental mapping of about ``focal_frames`` of the sampled frames, evenly spaced,
   with the focal length held fixed (a start that does not drift), then a bundle adjustment of
   that model with the focal length free; its score is the adjusted model's mean reprojection
   error (px), infinite when it registers fewer than half of those frames;
3. the estimate is the adjusted focal length of the best-scoring hypothesis, clipped to the range
   (the middle of the range when none registered enough frames, and the full mapping decides).

The full mapping then holds the estimate fixed; a last bundle adjustment frees the focal length
and keeps its result only when the focal length moves by less than ``max_focal_change`` of the
one the mapping held. When it
moves farther, the estimate was off (the hypotheses map a subset of the frames, and their errors
can be near equal: 0.63 px at 0.93 of the width beside 0.65 px at 0.83 on a benchmark clip whose
true focal length is 0.785), and the adjustment of every keyframe knows better: the keyframes are
mapped again holding the focal length it moved to, up to ``focal_remaps`` times, and the last
mapping is kept (refined when its adjustment stayed within the bound). A move out of the
hypotheses' range is not followed: on a 2-second clip the adjustment drifted from a focal length
0.8 % off to past the range's end, and mapping there kept it 28 % off. A mapping again that finds
no model, or registers fewer keyframes than the one before, is dropped: the one before is kept.
Deterministic: each hypothesis sets its focal length, then runs the seeded mapper on its lane's
copy of the database (``[cameras] workers`` lanes side by side, each taking its hypotheses one
after another; the first lane works on the database itself).
"""

from __future__ import annotations

import math
import shutil
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cadestate.config import CamerasConfig


@dataclass(frozen=True)
class FocalEstimate:
    """``focal_px`` the estimate (px) for images ``width`` px wide; per hypothesis (float[H] each):
    ``hypotheses_px`` the focal length it started from, ``adjusted_px`` its focal length after the
    bundle adjustment (nan: no model) and ``errors_px`` the adjusted model's mean reprojection
    error (inf: too few frames registered)."""

    focal_px: float
    width: int
    hypotheses_px: np.ndarray
    adjusted_px: np.ndarray
    errors_px: np.ndarray


def focal_hypotheses(width: int, cfg: CamerasConfig) -> np.ndarray:
    """float[H] focal lengths (px) from ``fov_max_deg`` to ``fov_min_deg`` (horizontal FOV of
    ``width`` px), evenly spaced in log focal."""
    f = [0.5 * width / math.tan(math.radians(fov) / 2) for fov in (cfg.fov_max_deg, cfg.fov_min_deg)]
    return np.geomspace(f[0], f[1], cfg.fov_hypotheses)


def best_focal(hypotheses: np.ndarray, adjusted: np.ndarray, errors: np.ndarray) -> float:
    """The adjusted focal length (``adjusted`` float[H], px) of the lowest of ``errors`` float[H],
    clipped to the range of ``hypotheses`` float[H]; their geometric mean when no error is finite."""
    lo, hi = float(hypotheses.min()), float(hypotheses.max())
    if not np.any(np.isfinite(errors)):
        return math.sqrt(lo * hi)
    return float(np.clip(adjusted[int(np.argmin(errors))], lo, hi))


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


def hypothesis_error(db_path: Path, image_dir: Path, names: list[str], focal_px: float, mapping, threads: int,
                     out_dir: Path) -> tuple[float, float]:
    """(mean reprojection error px, focal length px) of mapping the frames ``names`` with the focal
    length held at ``focal_px`` (``mapping``: pycolmap options, focal refinement off), then bundle
    adjusting the largest model with it free; (inf, its focal length or nan) when that model
    registers fewer than half of the frames."""
    import pycolmap

    set_focal(db_path, focal_px)
    mapping = pycolmap.IncrementalPipelineOptions(mapping.todict())
    mapping.image_names = names
    out_dir.mkdir()
    models = pycolmap.incremental_mapping(db_path, image_dir, out_dir, mapping)
    best = max(models.values(), key=lambda m: m.num_reg_images(), default=None)
    if best is None:
        return math.inf, math.nan
    bundle_adjust(best, ba_options(threads))
    focal = float(best.cameras[next(iter(best.cameras))].focal_length)
    if 2 * best.num_reg_images() < len(names):
        return math.inf, focal
    return float(best.compute_mean_reprojection_error()), focal


def estimate_focal(db_path: Path, image_dir: Path, names: list[str], width: int, cfg: CamerasConfig, mapping,
                   work_dir: Path) -> FocalEstimate:
    """The focal length (px) of the module docstring for the frames ``names`` (in time order) of
    ``width`` px; ``mapping``: the pycolmap mapping options with focal refinement off."""
    hypotheses = focal_hypotheses(width, cfg)
    subset = names[::max(1, round(len(names) / cfg.focal_frames))]
    lanes = max(1, min(cfg.workers, len(hypotheses)))
    dbs = [db_path] + [work_dir / f"focal-database-{k}.db" for k in range(1, lanes)]
    for copy in dbs[1:]:
        shutil.copyfile(db_path, copy)

    def lane(k: int) -> list[tuple[int, tuple[float, float]]]:
        """Hypotheses k, k + lanes, ... one after another on database copy k (each sets its focal first)."""
        return [(i, hypothesis_error(dbs[k], image_dir, subset, hypotheses[i], mapping, cfg.threads, work_dir / f"focal-{i}"))
                for i in range(k, len(hypotheses), lanes)]

    with ThreadPoolExecutor(lanes) as pool:  # pycolmap releases the GIL while it maps
        done = dict(pair for pairs in pool.map(lane, range(lanes)) for pair in pairs)
    runs = np.array([done[i] for i in range(len(hypotheses))])
    errors, adjusted = runs[:, 0], runs[:, 1]
    return FocalEstimate(best_focal(hypotheses, adjusted, errors), width, hypotheses, adjusted, errors)


def ba_options(threads: int, focal: bool = True):
    """pycolmap bundle adjustment options: poses and points free, the focal length too when ``focal``
    (the principal point fixed)."""
    import pycolmap

    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = focal
    options.refine_principal_point = False
    options.refine_extra_params = False
    options.print_summary = False
    options.ceres.solver_options.num_threads = threads
    return options


def bundle_adjust(reconstruction, options) -> None:
    """A global bundle adjustment of ``reconstruction`` (every registered image; the gauge fixed
    by two cameras), as ``pycolmap.bundle_adjustment`` does it, through the adjuster it makes.
    Not that binding: pycolmap 4.2.1's builds a COLMAP ``OptionManager`` per call, which sets
    glog's ``minloglevel`` to 0 and ``alsologtostderr`` on, for the whole process: its own lines
    and those of every mapper running beside it printed (thousands in the benchmark's log), quiet
    as ``$GLOG_minloglevel`` asked. Same result to the bit (tests/test_sfm.py)."""
    import pycolmap

    if reconstruction.num_reg_images() < 2:  # as the binding: nothing to adjust
        return
    pycolmap.ObservationManager(reconstruction).filter_observations_with_negative_depth()  # avoids degeneracies
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in reconstruction.reg_image_ids():
        config.add_image(image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    pycolmap.create_default_bundle_adjuster(options, config, reconstruction).solve()
    reconstruction.update_point_3d_errors()


def refine_focal(reconstruction, max_change: float, threads: int):
    """(``reconstruction`` bundle-adjusted with its focal length free, True, that focal length px)
    when the focal length moves by less than ``max_change`` (a fraction), else (``reconstruction``
    untouched, False, the focal length it moved to); ``reconstruction``: a pycolmap Reconstruction
    with one camera."""
    import pycolmap

    refined = pycolmap.Reconstruction(reconstruction)
    bundle_adjust(refined, ba_options(threads))
    camera_id = next(iter(reconstruction.cameras))
    focal = float(refined.cameras[camera_id].focal_length)
    change = focal / reconstruction.cameras[camera_id].focal_length - 1
    return (refined, True, focal) if abs(change) < max_change else (reconstruction, False, focal)
