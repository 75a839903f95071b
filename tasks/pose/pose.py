"""Stage ``pose``: a 9-DoF pose per annotated track from its 3D<->2D correspondences (section 3.4).

Reads: the clip's ``correspondences`` partition (normalised clicks, CAD-frame points, mirror
flag) of the tracks whose chosen model they use (:func:`tasks.pose.inputs.answered_correspondences`), its
``frames`` (the key-frames' cameras: K in pixels, world->camera R, t) and ``cad_models`` (class,
symmetry and bounding box of each model). Writes: the clip's ``poses`` partition, one
row per track, with a status (only ``ok`` poses are fit for use; see :mod:`tasks.pose.checks`).
A clip without correspondences gets an empty partition, and the run's message says so.

The solver is :mod:`tasks.pose.solver`; poses follow the official object-to-world order
mirror => scale => rotation => translation (:func:`cadestate.render.object_to_world`).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pyarrow as pa

from cadestate.config import PoseConfig, section_hash
from cadestate.lineage import table_digest
from tasks.pose.inputs import MODEL_FACTS, answered_correspondences, input_digests
from tasks.pose.solver import ObjectCorrespondences, PoseResult, SolverOptions
from tasks.pose.support import solve_with_support
from tasks.stage import StageContext, StageDef, StageOutput
from warehouse import Warehouse

SOLVER_FIELDS = {f.name for f in dataclasses.fields(SolverOptions)}


def solver_options(cfg: PoseConfig) -> SolverOptions:
    """The solver knobs of a ``[pose]`` section."""
    return SolverOptions(**{k: v for k, v in dataclasses.asdict(cfg).items() if k in SOLVER_FIELDS})


@dataclasses.dataclass(frozen=True)
class TrackInput:
    """One track's solver input (``problem`` None with ``status``/``message`` when it cannot be built)."""

    track_id: str
    cad_id: str
    cls: str
    symmetry: int
    upright: bool
    on_floor: bool
    mirrored: bool
    timestamps: tuple[int, ...]
    num_points: int
    problem: ObjectCorrespondences | None
    status: str = ""
    message: str = ""


def track_inputs(corr: pa.Table, frames: pa.Table, models: dict[str, dict], upright_classes: tuple[str, ...],
                 floor_classes: tuple[str, ...], wall_classes: tuple[str, ...] = ()) -> list[TrackInput]:
    """Group correspondence rows by track and attach the key-frame cameras and model facts.

    ``corr``: rows of ``correspondences``; ``frames``: rows of ``frames`` (K, world_to_camera_R/t,
    width, height); ``models``: cad_id -> {"class", "symmetry", "extent"} (extent may be missing:
    then the support prior does not apply to the track). Upright classes but ``wall_classes`` rest
    on a support (:mod:`tasks.pose.support`).
    """
    cams = {r["timestamp_us"]: r for r in frames.select(["timestamp_us", "K", "world_to_camera_R", "world_to_camera_t",
                                                         "width", "height"]).to_pylist()}
    rows = corr.to_pylist()
    by_track: dict[str, list[dict]] = {}
    for r in rows:
        by_track.setdefault(r["track_id"], []).append(r)
    out = []
    for track_id in sorted(by_track):
        rs = sorted(by_track[track_id], key=lambda r: (r["timestamp_us"], r["point_index"]))
        cad_ids, mirrors = {r["cad_id"] for r in rs}, {r["is_mirrored"] for r in rs}
        stamps = tuple(sorted({r["timestamp_us"] for r in rs}))
        cad_id = sorted(cad_ids)[0]
        model = models.get(cad_id)
        cls = model["class"] if model else ""
        base = dict(track_id=track_id, cad_id=cad_id, cls=cls, symmetry=int(model["symmetry"]) if model else 1,
                    upright=cls in upright_classes, on_floor=cls in floor_classes, mirrored=bool(rs[0]["is_mirrored"]),
                    timestamps=stamps, num_points=len(rs))
        if len(cad_ids) > 1 or len(mirrors) > 1:
            out.append(TrackInput(**base, problem=None, status="invalid_input",
                                  message=f"a track's rows must share one cad_id and mirror flag: {sorted(cad_ids)}, {sorted(mirrors)}"))
            continue
        if model is None:
            out.append(TrackInput(**base, problem=None, status="unknown_cad", message=f"CAD model {cad_id!r} is not in cad_models"))
            continue
        missing = [t for t in stamps if t not in cams]
        if missing:
            out.append(TrackInput(**base, problem=None, status="missing_camera",
                                  message=f"no frame at key-frame timestamp(s) {missing[:3]} µs"))
            continue
        index = {t: i for i, t in enumerate(stamps)}
        c = [cams[t] for t in stamps]
        size = np.array([[cams[r["timestamp_us"]]["width"], cams[r["timestamp_us"]]["height"]] for r in rs], np.float64)
        problem = ObjectCorrespondences(
            xy=np.array([r["point_2d"] for r in rs], np.float64).reshape(-1, 2) * size,
            xyz=np.array([r["point_3d"] for r in rs], np.float64).reshape(-1, 3),
            keyframe=np.array([index[r["timestamp_us"]] for r in rs], np.int64),
            K=np.array([x["K"] for x in c], np.float64).reshape(-1, 3, 3),
            R=np.array([x["world_to_camera_R"] for x in c], np.float64).reshape(-1, 3, 3),
            t=np.array([x["world_to_camera_t"] for x in c], np.float64).reshape(-1, 3),
            mirrored=base["mirrored"], symmetry=base["symmetry"], upright=base["upright"],
            extent=None if model.get("extent") is None else np.asarray(model["extent"], np.float64),
            on_floor=base["on_floor"], rests=base["upright"] and cls not in wall_classes)
        out.append(TrackInput(**base, problem=problem))
    return out


def poses_table(clip: str, tracks: list[TrackInput], results: list[PoseResult], config_hash: str) -> pa.Table:
    """Rows of ``poses`` (see :data:`schemas.pose.POSES`). ``PoseResult.support`` indexes the
    solved tracks (those with a problem, in order; :func:`solve_tracks`)."""
    hosts = dict(enumerate(t.track_id for t in tracks if t.problem is not None))
    def vec(a):
        return None if a is None else [float(v) for v in a]

    def num(v):
        return None if v is None or not np.isfinite(v) else float(v)

    rows = []
    for t, r in zip(tracks, results):
        rows.append({
            "clip": clip, "track_id": t.track_id, "cad_id": t.cad_id, "class": t.cls, "status": r.status,
            "message": r.message, "translation": vec(r.translation), "rotation": vec(r.rotation), "scale": vec(r.scale),
            "is_mirrored": t.mirrored, "symmetry": t.symmetry, "upright": t.upright, "coplanar_axis": r.coplanar_axis,
            "num_keyframes": len(t.timestamps), "num_points": t.num_points, "loss_total": num(r.loss_total),
            "loss_reprojection": num(r.loss_reprojection), "loss_up": num(r.loss_up), "loss_front": num(r.loss_front),
            "keyframe_timestamps_us": list(t.timestamps), "keyframe_error_px": [float(v) for v in r.keyframe_error_px],
            "parallax_deg": num(r.parallax_deg), "iterations": r.iterations, "start": r.start, "loss_floor": num(r.loss_floor),
            "floor_prior": r.floor_prior, "floor_height": num(r.floor_height),
            "support_track": hosts.get(r.support), "support_height": num(r.support_height), "config_hash": config_hash,
        })
    from schemas.pose import POSES

    return pa.Table.from_pylist(rows, schema=POSES.schema) if rows else POSES.schema.empty_table()


def solve_tracks(tracks: list[TrackInput], opts: SolverOptions, clips: list[str] | None = None) -> list[PoseResult]:
    """Solve every track that has a problem (with the support prior of :mod:`tasks.pose.support`,
    one floor per clip: ``clips`` names each track's clip, None = all of one clip); the others keep
    their input status. A result's ``support`` indexes the tracks that have a problem, in order."""
    clips = clips or [""] * len(tracks)
    todo = [(t.problem, c) for t, c in zip(tracks, clips) if t.problem is not None]
    solved = iter(solve_with_support([p for p, _ in todo], [c for _, c in todo], opts))
    return [next(solved) if t.problem is not None else PoseResult(t.status, t.message) for t in tracks]


def solve_clip(wh: Warehouse, cfg: PoseConfig, clip: str, run_id: str) -> StageOutput:
    """Solve the clip's tracks and write its ``poses`` partition (see module docstring)."""
    corr = answered_correspondences(wh, clip)
    if corr.num_rows == 0:
        rows = wh.write("poses", clip, poses_table(clip, [], [], section_hash("pose", cfg)))
        return StageOutput(rows, table_digest(wh.read("poses", [clip])), "no correspondences for this clip: nothing to pose")
    frames = wh.read("frames", [clip])
    needed = sorted(set(corr.column("cad_id").to_pylist()))
    models = {r["cad_id"]: r for r in wh.read("cad_models", columns=list(MODEL_FACTS)).to_pylist()
              if r["cad_id"] in needed}
    tracks = track_inputs(corr, frames, models, cfg.upright_classes, cfg.floor_classes, cfg.wall_classes)
    results = solve_tracks(tracks, solver_options(cfg))
    table = poses_table(clip, tracks, results, section_hash("pose", cfg))
    rows = wh.write("poses", clip, table)
    ok = sum(r.status == "ok" for r in results)
    return StageOutput(rows, table_digest(table), f"{ok} of {len(results)} track(s) posed (status ok)")


def _run(ctx: StageContext) -> StageOutput:
    return solve_clip(ctx.wh, ctx.cfg, ctx.unit, ctx.run_id)


STAGE = StageDef(
    name="pose", section="pose", scope="clip", upstream=("frames",), tables=("poses",), after=("correspondence_task",),
    description="9-DoF pose of every annotated track from its 3D<->2D correspondences",
    run=_run, clip_inputs=input_digests,
)
