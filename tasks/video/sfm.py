"""Cameras of a video by structure from motion (pycolmap, CPU): the ``cameras`` stage's logic.

Steps: sample the video's frames at ``[cameras] sample_fps`` (each sampled frame keeps its exact
decoded time, µs since the video's start), SIFT features, sequential matching, mapping of every
``[cameras] keyframe_every``-th frame (``[cameras] mapper``: global SfM, GLOMAP's rotation
averaging, global positioning and bundle adjustment, or COLMAP's incremental mapper) with one
camera shared by every frame (pinhole: ``SIMPLE_PINHOLE`` with the principal point at the image
centre and its focal length estimated from field-of-view hypotheses and held fixed while mapping,
or ``PINHOLE`` fixed to the given ``intrinsics``), a polish (observations past
``[cameras] polish_reproj_error_px`` dropped and the model adjusted again, :func:`polish`), a last
bundle adjustment with the estimated focal length free (:mod:`tasks.video.sfm_focal`; where it
moves the focal length too far, the keyframes are mapped again holding the one it moved to), the
frames between keyframes registered to that model (:mod:`tasks.video.sfm_register`), and so are
keyframes the mapping left out or put in another model (a benchmark clip registered 75 % of its
frames without them, 100 % with them), then one camera line per sampled frame: SfM's own pose
when the frame was registered (mapped or registered to the model), else interpolated between its
registered neighbours (slerp of the rotation, linear camera centre; the nearest one's pose at the
ends) and flagged.

Frames: COLMAP's ``cam_from_world`` is world->camera with OpenCV camera axes, as RealEstate10K
(:mod:`cadestate.geometry`); the world is SfM's, of arbitrary origin and up (the ``ingest`` stage
finds up), and of its scale (GLOMAP's: 7-11 units per metre on two benchmark clips) brought to
about metres (:func:`room_scale`): its points' median depth, from the frames that see them, made
:data:`ROOM_DEPTH_M`; the stages' metric constants (tracking's 3D cues, :mod:`tasks.tracking.track3d`)
assume a room's scale. Several disconnected models: the largest is kept, the others are reported.
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import av
import numpy as np
from PIL import Image
from scipy.spatial.transform import Rotation, Slerp

from cadestate.config import CamerasConfig
from cadestate.geometry import camera_to_world, world_to_camera
from tasks.video.camera_file import CameraTrack
from tasks.video.decode import VideoError, probe_video, upright
from tasks.video.sfm_focal import FocalEstimate, ba_options, bundle_adjust, estimate_focal, refine_focal, set_focal
from tasks.video.sfm_register import frame_correspondences, point_ids, register_frames


class SfmError(ValueError):
    """Structure from motion failed for a video (one line naming the video and what went wrong)."""


@dataclass(frozen=True)
class SampledFrames:
    """Frames sampled from a video: ``times_us`` int64[N] decoded presentation times (µs since the
    stream's start, increasing), ``paths`` the N image files (PNG, upright, full resolution in square
    pixels: a video of non-square pixels is stretched to its shown width), ``width``/``height`` px of
    those images."""

    times_us: np.ndarray
    paths: list[Path]
    width: int
    height: int


@dataclass(frozen=True)
class SfmResult:
    """What SfM made of a video.

    Attributes:
      track: one camera line per sampled frame (world->camera, OpenCV axes, SfM's world).
      registered: bool[N], True where the camera is SfM's own, mapped or registered to the model
        (False: interpolated).
      models: mapped frames (keyframes) of every model found, largest first (the first one is kept).
      seconds: {step: wall seconds} (sampling, features, matching, focal, mapping, polish, refine:
        summed over the mappings; between: registering the frames the kept mapping left without a
        pose, total).
      focal: the focal length estimate (None with given intrinsics): the hypotheses' one.
      focal_refined: whether the last bundle adjustment's focal length was kept.
      focal_held: the focal length (px) each kept mapping held: the estimate's, then the one the
        bundle adjustment of the mapping before moved to, past ``max_focal_change`` and within
        the hypotheses' range (``[cameras] focal_remaps``; :mod:`tasks.video.sfm_focal`); empty
        with given intrinsics.
      polished: observations the polish dropped (:func:`polish`; 0 when it is off).
      reprojection_px: the kept model's mean reprojection error, px.
      scale: the factor :func:`room_scale` applied to SfM's world (track units per SfM unit).
      focal_note: how the focal length search ended, one line ('' with given intrinsics): refined,
        or why not (remaps spent, a move out of the range, a mapping again dropped, and where the
        last adjustment moved it).
    """

    track: CameraTrack
    registered: np.ndarray
    models: list[int] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)
    focal: FocalEstimate | None = None
    focal_refined: bool = False
    focal_held: list[float] = field(default_factory=list)
    polished: int = 0
    reprojection_px: float = 0.0
    scale: float = 1.0
    focal_note: str = ""

    @property
    def registered_fraction(self) -> float:
        return float(self.registered.mean())


def sample_frames(video: Path, sample_fps: float, out_dir: Path) -> SampledFrames:
    """Decode ``video`` and keep every k-th frame, k = max(1, round(fps / sample_fps)), as PNGs in
    ``out_dir`` (:class:`SampledFrames`; a frame whose time is not after the last kept one is skipped)."""
    pixel_aspect = probe_video(video).pixel_aspect
    try:
        container = av.open(str(video))
    except (av.error.FFmpegError, OSError) as e:
        raise VideoError(f"{video}: cannot open video: {e}") from None
    with container:
        if not container.streams.video:
            raise VideoError(f"{video}: no video stream")
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        fps = float(stream.average_rate) if stream.average_rate else sample_fps
        every = max(1, round(fps / sample_fps))
        start, base = stream.start_time or 0, stream.time_base
        times, paths, size = [], [], (0, 0)
        try:
            for i, frame in enumerate(container.decode(stream)):
                if i % every or frame.pts is None:
                    continue
                time_us = int(round((frame.pts - start) * base * 1_000_000))
                if times and time_us <= times[-1]:
                    continue
                path = out_dir / f"{len(paths):06d}.png"
                image = Image.fromarray(upright(frame))
                if pixel_aspect != 1.0:
                    image = image.resize((round(image.width * pixel_aspect), image.height), Image.Resampling.BICUBIC)
                image.save(path, compress_level=1)
                size = image.size
                times.append(time_us)
                paths.append(path)
        except av.error.FFmpegError as e:
            raise VideoError(f"{video}: decoding failed (corrupt or truncated video?): {e}") from None
    if len(paths) < 2:
        raise SfmError(f"{video}: {len(paths)} frame(s) sampled at {sample_fps:g} fps; SfM needs at least 2")
    return SampledFrames(np.asarray(times, dtype=np.int64), paths, size[0], size[1])


def _options(cfg: CamerasConfig, intrinsics: tuple[float, ...] | None, pixel_aspect: float = 1.0):
    """pycolmap's reader, extraction, matching, pairing, two-view verification and mapping options for ``cfg``;
    ``intrinsics`` (fx, fy, cx, cy) in pixels of the upright picture (a display rotation applied,
    :func:`tasks.video.decode.upright`), of ``pixel_aspect`` (their width over their height), are handed over in the square pixels of :func:`sample_frames` (fx and cx scaled)."""
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    if intrinsics:
        fx, fy, cx, cy = (float(v) for v in intrinsics)
        reader.camera_model = "PINHOLE"
        reader.camera_params = ",".join(repr(v) for v in (fx * pixel_aspect, fy, cx * pixel_aspect, cy))
    else:
        reader.camera_model = "SIMPLE_PINHOLE"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = cfg.max_image_size
    extraction.num_threads = cfg.workers  # the images are in the database first (run_sfm), so their ids keep time order
    extraction.sift.max_num_features = cfg.max_features
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = 1  # more threads verify pairs with other random draws: another model each run
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = cfg.overlap
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = cfg.seed  # default -1: seeded from the clock, a different model every run
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = cfg.threads
    mapping.random_seed = cfg.seed
    mapping.mapper.random_seed = cfg.seed
    mapping.min_model_size = MIN_KEYFRAMES
    mapping.ba_global_frames_ratio = mapping.ba_global_points_ratio = 1 + cfg.global_ba_growth
    mapping.ba_refine_focal_length = False  # fixed: the given one, or estimated first (tasks/video/sfm_focal.py)
    mapping.ba_refine_principal_point = False
    mapping.ba_refine_extra_params = False
    mapping.mapper.abs_pose_refine_focal_length = False
    mapping.mapper.init_min_tri_angle = cfg.init_min_tri_angle_deg
    return reader, extraction, matching, pairing, verification, mapping


def _global_options(cfg: CamerasConfig, names: list[str]):
    """pycolmap's global mapping (GLOMAP) options for the frames ``names``: seeded, on
    ``cfg.threads`` threads, the camera held (its focal length is given, or estimated first)."""
    import pycolmap

    options = pycolmap.GlobalPipelineOptions()
    options.image_names = names
    options.min_model_size = MIN_KEYFRAMES
    options.num_threads = options.mapper.num_threads = cfg.threads
    mapper = options.mapper
    for part in (options, mapper, mapper.rotation_averaging, mapper.global_positioning, mapper.retriangulation):
        part.random_seed = cfg.seed
    mapper.bundle_adjustment.refine_focal_length = False
    mapper.bundle_adjustment.refine_principal_point = False
    mapper.bundle_adjustment.refine_extra_params = False
    mapper.bundle_adjustment.ceres.solver_options.num_threads = cfg.threads
    return options


def _interpolate(times: np.ndarray, registered: np.ndarray, R: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fill the unregistered rows of world->camera rotations ``R`` float[N, 3, 3] and camera
    centres ``c`` float[N, 3] from the registered ones, by time (slerp; linear centre; the
    nearest registered pose outside their span)."""
    idx = np.flatnonzero(registered)
    t = times.astype(np.float64)
    clamped = np.clip(t, t[idx[0]], t[idx[-1]])
    if len(idx) == 1:
        return np.repeat(R[idx], len(t), 0), np.repeat(c[idx], len(t), 0)
    slerp = Slerp(t[idx], Rotation.from_matrix(R[idx]))
    R_all = slerp(clamped).as_matrix()
    c_all = np.stack([np.interp(clamped, t[idx], c[idx, k]) for k in range(3)], axis=1)
    R_all[idx], c_all[idx] = R[idx], c[idx]
    return R_all, c_all


POLISH_ROUNDS = 3
"""Rounds of :func:`polish` (on a benchmark clip they dropped 5,501, then 590, then 217 observations)."""


def polish(reconstruction, max_error_px: float, min_tri_angle_deg: float, threads: int):
    """A copy of ``reconstruction`` (pycolmap) without its observations that reproject farther than
    ``max_error_px`` or whose point is seen under less than ``min_tri_angle_deg``, bundle-adjusted
    with the camera held; :data:`POLISH_ROUNDS` times (each adjustment moves some observations
    past the bound). The mappers keep looser matches (COLMAP's incremental mapper up to 4 px while
    the model grows); at the end those stray matches are what bends a walk. Returns (the copy,
    observations dropped)."""
    import pycolmap

    polished, dropped = pycolmap.Reconstruction(reconstruction), 0
    for _ in range(POLISH_ROUNDS):
        dropped += pycolmap.ObservationManager(polished).filter_all_points3D(max_error_px, min_tri_angle_deg)
        bundle_adjust(polished, ba_options(threads, focal=False))
    return polished, dropped


def check_registered(video: Path | str, registered: np.ndarray, cfg: CamerasConfig, models: list[int]) -> str:
    """Raise :class:`SfmError` when fewer than ``cfg.min_registered_fraction`` of the frames
    (bool[N] ``registered``) are registered; ``models``: registered frames per model, the kept one
    first. Returns the note on the dropped models ("" when there is one model)."""
    others = "" if len(models) <= 1 else (f"; {len(models) - 1} other disconnected model(s) of "
                                          f"{', '.join(map(str, models[1:]))} frames dropped")
    fraction = float(np.mean(registered))
    if fraction < cfg.min_registered_fraction:
        raise SfmError(f"{video}: SfM registered {int(np.sum(registered))} of {len(registered)} sampled frames "
                       f"({fraction:.0%}), fewer than [cameras] min_registered_fraction = {cfg.min_registered_fraction:g}"
                       f"{others}")
    return others


ROOM_DEPTH_M = 3.0
"""The median depth (m) of an indoor walkthrough's SfM points, seen from the frames that see them:
:func:`room_scale` makes SfM's world's median this. 3.6 and 2.7 m in the true world on two
benchmark clips of seed 3000101 (bench/seeds.py), whose SfM worlds it brought to 1.21 and 0.89 m per
unit (from 0.09 and 0.14); the true depth varies with the room, so the world keeps a scale of its
own, within a small factor of metres."""


def unposed(reconstruction, names: list[str]) -> list[str]:
    """The frames of ``names`` (image names) without a pose in ``reconstruction``, sorted: those
    between keyframes, and keyframes the mapping left out or put in another model (they were
    interpolated: a benchmark clip registered 75 % of its frames so, 100 % registering them too)."""
    posed = {image.name for image in reconstruction.images.values() if image.has_pose}
    return sorted(set(names) - posed)


def room_scale(reconstruction) -> float:
    """The factor that brings ``reconstruction``'s world to a room's scale: :data:`ROOM_DEPTH_M`
    over the median camera-frame depth of every observation of its 3D points (1 when it has none)."""
    depths = []
    for image in reconstruction.images.values():
        ids = point_ids(image) if image.has_pose else np.zeros(0, np.int64)
        ids = ids[ids >= 0]
        if len(ids):
            X = np.array([reconstruction.points3D[int(i)].xyz for i in ids])
            pose = image.cam_from_world()
            depths.append(X @ pose.rotation.matrix()[2] + pose.translation[2])
    median = float(np.median(np.concatenate(depths))) if depths else 0.0
    return ROOM_DEPTH_M / median if median > 0 else 1.0


MIN_KEYFRAMES = 3
"""The fewest keyframes a model is made of (the mappers' ``min_model_size``)."""


def _map_keyframes(db: Path, tmp: Path, out: Path, keyframes: list[str], cfg: CamerasConfig, mapping,
                   seconds: dict[str, float], video: Path, n: int):
    """Map ``keyframes`` of the database ``db`` (images in ``tmp``/images, the models into the new
    folder ``out``) with its camera as it is, then :func:`polish` the largest model; returns (every
    model, largest first; the polished largest; observations the polish dropped). Adds the wall
    seconds to ``seconds`` (mapping, polish). Raises :class:`SfmError` when there is no model
    (``n``: the sampled frames of ``video``)."""
    import pycolmap

    t = time.perf_counter()
    out.mkdir()
    if cfg.mapper == "global":
        models = pycolmap.global_mapping(db, tmp / "images", out, _global_options(cfg, keyframes))
    else:
        if cfg.keyframe_every > 1:
            mapping.image_names = keyframes
        models = pycolmap.incremental_mapping(db, tmp / "images", out, mapping)
    seconds["mapping"] = seconds.get("mapping", 0.0) + time.perf_counter() - t
    if not models:
        raise SfmError(f"{video}: SfM found no model in {len(keyframes)} keyframes of {n} sampled frames (too little "
                       "texture or parallax?)")
    ranked = sorted(models.values(), key=lambda m: m.num_reg_images(), reverse=True)
    best, dropped = ranked[0], 0
    if cfg.polish_reproj_error_px > 0:
        t = time.perf_counter()
        best, dropped = polish(best, cfg.polish_reproj_error_px, mapping.mapper.filter_min_tri_angle, cfg.threads)
        seconds["polish"] = seconds.get("polish", 0.0) + time.perf_counter() - t
    return ranked, best, dropped


def run_sfm(video: Path, cfg: CamerasConfig, intrinsics: tuple[float, float, float, float] | None = None,
            url: str | None = None, work_dir: Path | None = None) -> SfmResult:
    """Cameras of ``video`` by SfM (module docstring); ``url`` is the camera file's line 1
    (default: the video's ``file://`` URI); ``intrinsics`` (fx, fy, cx, cy) px fix the camera, in
    pixels of the upright picture, as :func:`sample_frames` turns it (a video of non-square pixels
    is sampled in square ones: x scaled by its pixel aspect, and so are fx and cx).

    Raises:
      SfmError: no model, or fewer than ``cfg.min_registered_fraction`` of the frames registered.
      VideoError: an unreadable video.
    """
    import pycolmap

    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(dir=work_dir, prefix="sfm-") as tmp:
        tmp = Path(tmp)
        (tmp / "images").mkdir()
        frames = sample_frames(video, cfg.sample_fps, tmp / "images")
        seconds["sampling"] = time.perf_counter() - t0
        options = _options(cfg, intrinsics, probe_video(video).pixel_aspect if intrinsics else 1.0)
        reader, extraction, matching, pairing, verification, mapping = options
        db, names = tmp / "database.db", [p.name for p in frames.paths]
        keyframes = names[::cfg.keyframe_every]  # too few: said before minutes of features, matching and focal search
        if len(keyframes) < MIN_KEYFRAMES:
            raise SfmError(f"{video}: {len(names)} frame(s) sampled at {cfg.sample_fps:g} fps give {len(keyframes)} "
                           f"keyframe(s) ([cameras] keyframe_every = {cfg.keyframe_every}); SfM maps at least {MIN_KEYFRAMES}: "
                           "a longer clip, or a higher sample_fps or a lower keyframe_every")
        t = time.perf_counter()
        pycolmap.Database.open(str(db)).close()
        # Image ids in time order, whatever order the extraction threads finish in: the mapper's choices follow the ids.
        pycolmap.import_images(db, tmp / "images", pycolmap.CameraMode.SINGLE, names, reader)
        pycolmap.extract_features(db, tmp / "images", names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
        seconds["features"] = time.perf_counter() - t
        t = time.perf_counter()
        pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing, verification_options=verification,
                                  device=pycolmap.Device.cpu)
        seconds["matching"] = time.perf_counter() - t
        focal = None
        if not intrinsics:
            t = time.perf_counter()
            focal = estimate_focal(db, tmp / "images", names, frames.width, cfg, mapping, tmp)
            seconds["focal"] = time.perf_counter() - t
        held = [focal.focal_px] if focal else []  # the focal length (px) each kept mapping held
        if focal:
            set_focal(db, focal.focal_px)
        ranked, best, dropped = _map_keyframes(db, tmp, tmp / "sparse-0", keyframes, cfg, mapping, seconds, video, len(names))
        refined, note = False, ""
        while focal:
            t = time.perf_counter()
            adjusted, refined, proposed = refine_focal(best, cfg.max_focal_change, cfg.threads)
            seconds["refine"] = seconds.get("refine", 0.0) + time.perf_counter() - t
            moved = f"the last adjustment moved it to {proposed / focal.width:.4f} of the width"
            if refined:
                best, note = adjusted, "refined: the last adjustment kept"
                break
            if len(held) > cfg.focal_remaps:
                note = f"not refined: {moved}, past max_focal_change, after {cfg.focal_remaps} remap(s) ([cameras] focal_remaps)"
                break
            if not focal.hypotheses_px.min() <= proposed <= focal.hypotheses_px.max():
                note = f"not refined: {moved}, out of the hypotheses' range (not followed)"
                break  # a move out of the hypotheses' range is not followed (sfm_focal's docstring)
            set_focal(db, proposed)
            try:
                again = _map_keyframes(db, tmp, tmp / f"sparse-{len(held)}", keyframes, cfg, mapping, seconds, video, len(names))
            except SfmError as e:
                note = f"not refined: {moved}; mapped again holding it, no model ({e})"
                break
            if again[0][0].num_reg_images() < ranked[0].num_reg_images():  # the mapping before is kept
                note = (f"not refined: {moved}; mapped again holding it, {again[0][0].num_reg_images()} keyframes "
                        f"registered, fewer than {ranked[0].num_reg_images()} (dropped)")
                break
            held.append(proposed)
            ranked, best, dropped = again
        between = unposed(best, names)
        if between:
            t = time.perf_counter()
            extra = register_frames(best, frame_correspondences(db, best, between), mapping.mapper, cfg.seed)
            seconds["between"] = time.perf_counter() - t
        else:
            extra = {}
        scale = room_scale(best)
    n = len(names)
    index = {name: i for i, name in enumerate(names)}
    registered = np.zeros(n, dtype=bool)
    R, c = np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3))
    poses = {image.name: image.cam_from_world() for image in best.images.values() if image.has_pose} | extra
    for name, pose in poses.items():
        i = index[name]
        R[i] = pose.rotation.matrix()
        c[i] = camera_to_world(R[i], np.asarray(pose.translation))[1]
        registered[i] = True
    check_registered(video, registered, cfg, [m.num_reg_images() for m in ranked])
    R, c = _interpolate(frames.times_us, registered, R, c * scale)
    R_wc, t_wc = world_to_camera(np.swapaxes(R, -1, -2), c)
    camera = best.cameras[next(iter(best.cameras))]
    fx, fy = camera.focal_length_x, camera.focal_length_y
    cx, cy = camera.principal_point_x, camera.principal_point_y
    w, h = camera.width, camera.height
    normalised = np.tile([fx / w, fy / h, cx / w, cy / h], (n, 1)).astype(np.float64)
    track = CameraTrack(url or Path(video).resolve().as_uri(), frames.times_us, normalised,
                        np.concatenate([R_wc, t_wc[:, :, None]], axis=2))
    seconds["total"] = time.perf_counter() - t0
    return SfmResult(track, registered, [m.num_reg_images() for m in ranked], {k: round(v, 2) for k, v in seconds.items()},
                     focal, refined, held, dropped, round(float(best.compute_mean_reprojection_error()), 3), scale, note)


def sfm_report(result: SfmResult) -> dict:
    """The JSON report kept beside the SfM camera file (``interpolated`` per camera line)."""
    return {"registered_fraction": round(result.registered_fraction, 4),
            "interpolated": [bool(not r) for r in result.registered],
            "models": result.models, "seconds": result.seconds, "polished_observations": result.polished,
            "reprojection_px": result.reprojection_px, "scale": round(result.scale, 6), **focal_report(result)}


def focal_report(result: SfmResult) -> dict:
    """The focal length found, as a fraction of the image width (``fx / w``): the kept one, the
    hypotheses' estimate, the one each mapping held (:attr:`SfmResult.focal_held`), whether the
    last bundle adjustment was kept and how the search ended (:attr:`SfmResult.focal_note`), and
    per hypothesis [start, adjusted (None: no model), mean reprojection error px (None: too few
    frames registered)]. Empty with given intrinsics."""
    f = result.focal
    if f is None:
        return {}
    return {"focal_fx_over_width": round(float(result.track.intrinsics[0, 0]), 4),
            "focal_estimate_fx_over_width": round(f.focal_px / f.width, 4),
            "focal_held_fx_over_width": [round(h / f.width, 4) for h in result.focal_held],
            "focal_refined": result.focal_refined,
            "focal_note": result.focal_note,
            "focal_hypotheses": [[round(h / f.width, 4), round(a / f.width, 4) if np.isfinite(a) else None,
                                  round(float(e), 3) if np.isfinite(e) else None]
                                 for h, a, e in zip(f.hypotheses_px, f.adjusted_px, f.errors_px)]}
