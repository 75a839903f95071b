"""SfM cameras (the ``cameras`` stage, :mod:`tasks.video.sfm`) on benchmark clips whose camera files are withheld.

Per clip: the registered fraction of the sampled frames, the median rotation error and the
trajectory error (% of the path length) after a similarity alignment to the true cameras
(:mod:`bench.sfm_eval`), SfM's wall time and focal length (``fx / width``: the true one, SfM's, its
error in %, the field-of-view hypotheses' estimate, :func:`tasks.video.sfm.focal_report`); then the
pose accuracy downstream: the simulated annotators' clicks on the ground-truth tracks (``<bench>/simulated_clicks/<clip>.json``, written by ``cadestate
bench run``) solved with the SfM cameras and with the true cameras, each turned to +Y up as ingest
does (:func:`tasks.video.ingest.find_up`: the cameras, refined by the video's vertical lines), the SfM poses mapped into the true world by the same similarity
(translation and scale scaled), scored as :mod:`bench.pose_bench` scores (Scan2CAD criterion).

A second row turns each clip's true world by a random rotation before ingest: the pose accuracy
must equal that of the original world (the up estimate undoes it).

``python -m bench.sfm_bench [BENCH_DIR] [N_CLIPS] [WAREHOUSE]``; ``python -m bench`` runs it on the first
:data:`DEFAULT_CLIPS` clips of the default benchmark and of the fresh seed's. The summary's errors
are medians over clips, beside the worst clip's.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
from scipy.spatial.transform import Rotation

from bench.benchmark import read_manifest
from bench.eval_pose import PosedObject
from bench.labels import CLICKS, clicks_path, correspondence_rows
from bench.pose_bench import _class_of, _gt, score
from bench.sfm_eval import Similarity, align, camera_errors
from cadestate.config import CamerasConfig, IngestConfig, PoseConfig
from cadestate.geometry import camera_to_world, matrix_to_quaternion, quaternion_to_matrix
from schemas.pose import CORRESPONDENCES
from tasks.pose.pose import MODEL_FACTS, solve_tracks, solver_options, track_inputs
from tasks.video.camera_file import CameraTrack, parse_camera_file
from tasks.video.decode import probe_video
from tasks.video.frames import frames_table
from tasks.video.ingest import find_up
from tasks.video.world_up import align_extrinsics, pose_to_input_world
from warehouse import Warehouse

DEFAULT_BENCH = Path("data/bench/default")
DEFAULT_CLIPS = 2
"""Clips SfM runs on in ``make bench`` (each takes about a minute or two on 2 cores)."""


def _centres(track: CameraTrack) -> np.ndarray:
    return camera_to_world(track.R, track.t)[1]


def _solve(clip: str, video: Path, track: CameraTrack, size: tuple[int, int], corr: pa.Table, models: dict,
           cfg: PoseConfig, to_true: Similarity | None = None) -> list[PosedObject]:
    """Poses of the clip's clicked tracks with cameras ``track`` of ``video`` (turned +Y up as ingest
    does), in ``track``'s world, then mapped by ``to_true`` (a similarity into the true world) when given."""
    Q = find_up(video, track, 0, IngestConfig()).rotation
    frames = frames_table(clip, track, [""] * len(track), size[0], size[1], track.timestamps_us, 0, Q)
    tracks = track_inputs(corr, frames, models, cfg.upright_classes, cfg.floor_classes, cfg.wall_classes)
    results = solve_tracks(tracks, solver_options(cfg), [clip] * len(tracks))
    out = []
    for t, r in zip(tracks, results):
        if r.status != "ok":
            continue
        T, q = pose_to_input_world(r.translation, r.rotation, Q)
        s = np.asarray(r.scale, dtype=np.float64)
        if to_true is not None:
            T = tuple(to_true.apply(np.asarray(T)[None])[0])
            q = tuple(matrix_to_quaternion(to_true.rotation @ quaternion_to_matrix(np.asarray(q))))
            s = s * to_true.scale
        out.append(PosedObject(t.track_id, t.cls, tuple(map(float, T)), tuple(map(float, q)), tuple(map(float, s)),
                               t.mirrored, t.cad_id, clip))
    return out


def _turned(track: CameraTrack, seed: int) -> CameraTrack:
    """``track`` in its world turned by a random rotation (X' = W X)."""
    W = Rotation.random(random_state=seed).as_matrix()
    R, t = align_extrinsics(track.R, track.t, W)
    return dataclasses.replace(track, world_to_camera=np.concatenate([R, t[:, :, None]], axis=2))


def run(bench_dir: Path = DEFAULT_BENCH, wh: Warehouse | None = None, clips: int = DEFAULT_CLIPS,
        cfg: CamerasConfig = CamerasConfig()) -> dict:
    """Every number of the module docstring, per clip and overall."""
    from tasks.video.sfm import SfmError, focal_report, run_sfm

    wh = wh or Warehouse("data/warehouse")
    bench_dir = Path(bench_dir)
    if not (bench_dir / CLICKS).is_dir():
        return {"skipped": f"{bench_dir}: no simulated labels (run `cadestate bench run {bench_dir}`)"}
    names = list(read_manifest(bench_dir).clips)[:clips]
    models = {r["cad_id"]: r for r in wh.read("cad_models", columns=list(MODEL_FACTS)).to_pylist()}
    symmetries = {k: int(m["symmetry"]) for k, m in models.items()}
    pose_cfg = PoseConfig()
    rows, preds = [], {"true": [], "sfm": [], "turned": []}
    for i, clip in enumerate(names):
        video, truth = bench_dir / f"{clip}.mp4", parse_camera_file(bench_dir / f"{clip}.txt")
        info = probe_video(video)
        t0 = time.perf_counter()
        try:
            result = run_sfm(video, cfg)
        except SfmError as e:
            rows.append({"clip": clip, "error": str(e), "sfm_s": round(time.perf_counter() - t0, 1)})
            continue
        seconds = time.perf_counter() - t0
        sfm = result.track
        common = np.intersect1d(sfm.timestamps_us, truth.timestamps_us)
        a, b = np.searchsorted(truth.timestamps_us, common), np.searchsorted(sfm.timestamps_us, common)
        errors = camera_errors(truth.R[a], _centres(truth)[a], sfm.R[b], _centres(sfm)[b])
        sim = align(truth.R[a], _centres(truth)[a], sfm.R[b], _centres(sfm)[b])
        focal = focal_report(result)
        rows.append({"clip": clip, "frames": len(sfm), "registered_pct": round(100 * result.registered_fraction, 1),
                     **errors.summary(), "sfm_s": round(seconds, 1), "sfm_steps_s": result.seconds,
                     "true_fx_over_width": round(float(truth.intrinsics[0, 0]), 4),
                     "focal_error_pct": round(100 * (float(sfm.intrinsics[0, 0] / truth.intrinsics[0, 0]) - 1), 2),
                     **focal, "models": result.models})
        label_file = clicks_path(bench_dir, clip)
        if not label_file.is_file():
            continue
        corr = pa.Table.from_pylist(correspondence_rows(json.loads(label_file.read_text())), schema=CORRESPONDENCES.schema)
        size = (info.width, info.height)
        preds["true"] += _solve(clip, video, truth, size, corr, models, pose_cfg)
        preds["turned"] += _unturn(_solve(clip, video, _turned(truth, 1000 + i), size, corr, models, pose_cfg), 1000 + i)
        preds["sfm"] += _solve(clip, video, sfm, size, corr, models, pose_cfg, sim)
    gt = [dataclasses.replace(g, cls=_class_of(g.cls)) for g in _gt(bench_dir, names)]
    annotated = {(p.clip, p.track_id) for p in preds["true"]}
    accuracy = {k: score(v, gt, symmetries, annotated)["instance_accuracy_pct"] for k, v in preds.items()}
    ok = [r for r in rows if "error" not in r]
    summary = {"clips": len(names), "failed": len(rows) - len(ok)}
    if ok:
        summary |= {"registered_pct": round(float(np.mean([r["registered_pct"] for r in ok])), 1),
                    "median_rotation_error_deg": round(float(np.median([r["median_rotation_error_deg"] for r in ok])), 3),
                    "median_trajectory_error_pct": round(float(np.median([r["median_trajectory_error_pct"] for r in ok])), 3),
                    "worst_clip_trajectory_error_pct": round(float(np.max([r["median_trajectory_error_pct"] for r in ok])), 3),
                    "max_abs_focal_error_pct": round(float(np.max([abs(r["focal_error_pct"]) for r in ok])), 2),
                    "sfm_s_per_clip": round(float(np.mean([r["sfm_s"] for r in ok])), 1),
                    "worst_clip_sfm_s": round(float(np.max([r["sfm_s"] for r in ok])), 1)}
    return {"bench": str(bench_dir), "config": dataclasses.asdict(cfg), "summary": summary,
            "pose_accuracy_pct": {"true cameras": accuracy["true"], "SfM cameras": accuracy["sfm"],
                                  "true cameras, world turned at random": accuracy["turned"]},
            "targets": {"registered_pct": ">= 95", "median_rotation_error_deg": "< 1",
                        "median_trajectory_error_pct": "< 2", "pose accuracy, SfM vs true": "within 5 points",
                        "worst_clip_sfm_s": "< 120 (138 frames, 2 cores)"},
            "per_clip": rows}


def _unturn(preds: list[PosedObject], seed: int) -> list[PosedObject]:
    """Poses solved in a world turned by ``_turned(.., seed)`` back in the original world."""
    W = Rotation.random(random_state=seed).as_matrix()
    out = []
    for p in preds:
        T, q = pose_to_input_world(p.translation, p.rotation, W)
        out.append(dataclasses.replace(p, translation=T, rotation=q))
    return out


if __name__ == "__main__":
    args = sys.argv[1:]
    print(json.dumps(run(Path(args[0]) if args else DEFAULT_BENCH, Warehouse(args[2]) if len(args) > 2 else None,
                         int(args[1]) if len(args) > 1 else DEFAULT_CLIPS), indent=1))
