"""Pose solving on the synthetic benchmark: Scan2CAD accuracy, ablation, timing.

- :func:`pose_accuracy`: the ``poses`` and ``verified_poses`` tables of the warehouse (what
  `cadestate bench run` wrote) against the ground truth (``bench report``) in the three scoring
  modes of :mod:`bench.scoring` (``pose``, ``scan2cad-class``, ``scan2cad-exact``), every track
  scored; with the verification verdicts' agreement.
- :func:`run` (``python -m bench``, ``make bench``): the solver on the ground-truth tracks of the
  default benchmark at click noise 0, 3 and 6 px (the default ``[pose]`` config), the paper's
  ablation (base, + co-planar, + symmetry, + up-axis), the paper's L1 loss vs Huber, LM (Adam as
  fallback) vs Adam alone, with the scale prior on axes the clicks hardly span (``axis_prior`` 10;
  off by default), with free scales (no ``proportion_prior``, the paper's), with vs without the support prior of :mod:`tasks.pose.support` (off;
  the floor only, no host tops; the floor prior for floor classes only, as before host supports;
  every other row keeps the default prior on), and time per object and for 1,000 objects in one
  batch. Tracks are solved with their clip, so each clip gets its floor and its hosts.

Click noise: 3 px uses the label files as the simulated annotators wrote them; 0 and 6 px redraw
only the clicks of those same label files (same key-frames, 3D points, symmetric swaps and
co-planar sets): the exact projection of each 3D point under the ground-truth pose, plus
N(0, sigma) px per axis, clipped to the image.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pyarrow as pa

from bench.annotators import KeyframeCorrespondences, frame_camera
from bench.benchmark import read_manifest
from bench.eval_pose import PosedObject, match_and_score
from bench.labels import CLICKS, clicks_path, correspondence_rows
from bench.sfm_eval import Similarity, align
from cadestate.config import PoseConfig
from cadestate.geometry import camera_to_world, matrix_to_quaternion, project, quaternion_to_matrix
from cadestate.render import object_to_world
from schemas.official import FramesFile, read_frames, read_objects
from schemas.pose import CORRESPONDENCES
from tasks.cad.classes import BY_NAME
from tasks.cad.symmetry import rotation_y
from tasks.pose.pose import MODEL_FACTS, TrackInput, solve_tracks, solver_options, track_inputs
from tasks.video.world_up import pose_to_input_world, stored_rotation
from warehouse import Warehouse

DEFAULT_BENCH = Path("data/bench/default")


def _gt(bench_dir: Path, clips) -> list[PosedObject]:
    """The posed ground-truth objects of ``clips`` that the clip shows (a box on some frame): the
    room's objects the camera never sees could be posed by no one (they made the pose section
    read 5 of 10 where the yield read 5 of the 7 in view)."""
    return [PosedObject(o.track_id, o.cls, o.translation, o.rotation, o.scale, o.is_mirrored, o.cad_id, c)
            for c in clips for o in read_objects(Path(bench_dir) / c / "objects.json").objects
            if o.translation is not None and o.track]


def _class_of(cls_id: str) -> str:
    return next((c.name for c in BY_NAME.values() if c.id == cls_id), cls_id)


def score(predictions: list[PosedObject], gt: list[PosedObject], symmetries: dict[str, int],
          annotated: set[tuple[str, str]]) -> dict:
    """Scan2CAD accuracy over every ground-truth object and over those with correspondences."""
    full = match_and_score(predictions, gt, symmetries, "track", require_class=False)
    ann = match_and_score(predictions, [g for g in gt if g.key in annotated], symmetries, "track", require_class=False)
    pct = lambda v: round(100 * v, 1)  # noqa: E731
    return {"annotated_objects": ann.num_gt, "correct": ann.num_correct,
            "instance_accuracy_pct": pct(ann.instance_accuracy), "class_accuracy_pct": pct(ann.class_accuracy),
            "all_objects": full.num_gt, "instance_accuracy_all_pct": pct(full.instance_accuracy),
            "class_accuracy_all_pct": pct(full.class_accuracy)}


def _ground_truth_map(bench_dir: Path, wh: Warehouse, clip: str) -> dict[str, str]:
    """The clip's pipeline track id -> the ground-truth object it follows.

    Correspondences that came through label files (``bench run``, the simulated annotators
    answering the pipeline's tasks) are on pipeline tracks: each is mapped to its ground-truth
    object by :func:`bench.retrieval_bench.track_truth` (tracks matching no object are absent;
    several tracks may follow one object). A clip with no correspondence label (a warehouse written
    on the ground-truth tracks, as the tests' are) has tracks keyed by ground-truth ids already:
    the identity. (A clip with labels whose ``correspondences`` partition differed from them by a
    row, stale, was taken for such a warehouse too, and its tracks scored as other objects.)"""
    from bench.retrieval_bench import track_truth

    if clip not in wh.partitions("correspondence_labels"):
        return {o.track_id: o.track_id for o in read_objects(Path(bench_dir) / clip / "objects.json").objects}
    return {str(t): gt for t, gt in track_truth(bench_dir, wh, clip).items()}


def _predictions(rows: list[dict]) -> list[PosedObject]:
    return [PosedObject(r["track_id"], r["class"], tuple(r["translation"]), tuple(r["rotation"]), tuple(r["scale"]),
                        r["is_mirrored"], r["cad_id"], r["clip"]) for r in rows]


def scoring_inputs(bench_dir: Path, wh: Warehouse, clips: list[str]
                   ) -> tuple[list[PosedObject], dict[tuple[str, str], str], dict[str, int], dict[str, tuple]]:
    """What :func:`bench.scoring.score_all` scores against, for ``clips``: the posed ground truth
    (class names), the pipeline track -> ground-truth object map (:func:`_ground_truth_map`), the
    symmetry order and the bounding-box size (m) of every CAD model."""
    truth = {(c, t): gt for c in clips for t, gt in _ground_truth_map(bench_dir, wh, c).items()}
    gt = [dataclasses.replace(g, cls=_class_of(g.cls)) for g in _gt(bench_dir, clips)]
    models = wh.read("cad_models", columns=["cad_id", "symmetry", "extent"]).to_pylist()
    return gt, truth, {r["cad_id"]: r["symmetry"] for r in models}, {r["cad_id"]: tuple(r["extent"]) for r in models}


def accepted_predictions(wh: Warehouse, clips: list[str], bench_dir: Path | None = None) -> list[PosedObject]:
    """The poses the dataset publishes for ``clips``, in the ground truth's worlds (:func:`in_truth_world`): those accepted in
    verification (``verified_poses``), one per object people named (:func:`tasks.tracking.relations.relations_in_force`:
    none for tracks of no object, the one pose of an object's tracks that the export keeps,
    :meth:`~tasks.tracking.relations.TrackRelations.pose_speakers`)."""
    from tasks.tracking.relations import relations_in_force

    rows = [r for r in wh.read("verified_poses", clips).to_pylist() if r["accepted"]]
    kept: set[tuple[str, int]] = set()
    for c in {r["clip"] for r in rows}:
        keyframes = {int(p["track_id"]): p["num_keyframes"] or 0
                     for p in wh.read("poses", [c], columns=["track_id", "num_keyframes"]).to_pylist()}
        posed = {int(r["track_id"]): keyframes.get(int(r["track_id"]), 0) for r in rows if r["clip"] == c}
        kept |= {(c, t) for t in relations_in_force(wh, c).pose_speakers(posed)}
    rows = [r for r in rows if (r["clip"], int(r["track_id"])) in kept]
    return in_truth_world(_predictions(rows), wh, bench_dir)


def pose_accuracy(bench_dir: Path, wh: Warehouse) -> dict | None:
    """The warehouse's poses of the benchmark's clips scored in every mode of :mod:`bench.scoring`
    (None before the pose stage ran): the solver's (``poses``, status ok) and the dataset's (the
    poses accepted in verification, ``verified_poses``; None before any verdict), and how the
    verification verdicts relate to the ``pose`` criterion."""
    from bench.dataset_yield import tried_clip_splits
    from bench.scoring import score_all

    every = list(read_manifest(bench_dir).clips)
    clips = [c for c in every if c in wh.partitions("poses")]
    if not clips:
        return None
    ran = sorted(tried_clip_splits(wh, every))
    rows = [r for c in clips for r in wh.read("poses", [c]).to_pylist()]
    verdicts = [r for r in wh.read("verified_poses", clips).to_pylist()]
    # the objects of every clip that ran: one that never reached the pose stage (no cameras, still
    # waiting) has its objects missed, not left out (as the yield counts them)
    gt, truth, symmetries, extents = scoring_inputs(bench_dir, wh, ran)
    statuses: dict[str, int] = {}
    for r in rows:
        statuses[r["status"]] = statuses.get(r["status"], 0) + 1
    solved_poses = in_truth_world(_predictions([r for r in rows if r["status"] == "ok"]), wh, bench_dir)
    solved = score_all(solved_poses, gt, truth, symmetries, extents)
    accepted = score_all(accepted_predictions(wh, clips, bench_dir), gt, truth, symmetries, extents) if verdicts else None
    annotated = {(r["clip"], truth[(r["clip"], r["track_id"])]) for r in rows if (r["clip"], r["track_id"]) in truth}
    return {"clips": len(clips), "clips_run": len(ran), "ground_truth_objects": len(gt),
            "annotated_objects": len(annotated),
            "statuses": statuses,
            "solved": {m: v.as_dict() for m, v in solved.items()},
            "accepted": accepted and {m: v.as_dict() for m, v in accepted.items()},
            "verification": _verification_agreement(verdicts, solved_poses, gt, truth, symmetries, extents)}


def _verification_agreement(verdicts: list[dict], solved: list[PosedObject], gt: list[PosedObject],
                            truth: dict[tuple[str, str], str], symmetries: dict[str, int],
                            extents: dict[str, tuple]) -> dict | None:
    """Accepted / rejected verdicts of ``verified_poses`` against the ``pose`` criterion on the
    object each judged track follows (``solved``: the solver's poses in the ground truth's world;
    None: no verdicts)."""
    from bench.scoring import score_pose

    if not verdicts:
        return None
    by_key = {p.key: p for p in solved}
    judged = []
    for v in verdicts:
        key = (v["clip"], v["track_id"])
        if key in truth and key in by_key:
            ok = score_pose([by_key[key]], gt, truth, symmetries, extents).num_correct == 1
            judged.append((v["accepted"], ok))
    accepted = [ok for acc, ok in judged if acc]
    correct = [acc for acc, ok in judged if ok]
    return {"verdicts": len(verdicts), "judged_on_ground_truth": len(judged), "accepted": len(accepted),
            "accepted_correct_pct": round(100 * sum(accepted) / len(accepted), 1) if accepted else None,
            "correct_accepted_pct": round(100 * sum(correct) / len(correct), 1) if correct else None}


_MODE_NOTES = {"pose": "pose only (mirror flag, 4-way x/z scale swap; class and model not checked)",
               "scan2cad-class": "Scan2CAD as its benchmark states it: the class must match",
               "scan2cad-exact": "Scan2CAD's evaluation script: the CAD model must be one of the ground truth's"}


def pose_markdown(result: dict | None) -> list[str]:
    """Lines of the report's pose section (empty before the pose stage ran)."""
    if not result:
        return []
    head = ["| mode | poses | correct objects | instance mean | class mean | duplicates | false positives |",
            "|---|---|---:|---:|---:|---:|---:|"]
    rows = []
    for which, label in (("accepted", "accepted in verification"), ("solved", "solved (status ok)")):
        for mode, m in (result.get(which) or {}).items():
            rows.append(f"| `{mode}` | {label}: {m['predictions']} | {m['correct']} of {m['ground_truth']} | "
                        f"{m['instance_accuracy_pct']} % | {m['class_accuracy_pct']} % | {m['duplicates']} | "
                        f"{m['false_positives']} |")
    posed_only = f" ({result['clips']} reached the pose stage)" if result["clips_run"] != result["clips"] else ""
    return [f"## Pose accuracy (Scan2CAD thresholds: <= 20 cm, 20 deg, 20 %; {result['clips_run']} clips{posed_only}, "
            f"{result['ground_truth_objects']} posed ground-truth objects the clips show, {result['annotated_objects']} with "
            "correspondences)", "",
            "Every pose is scored; an object is credited once by any of its poses, further poses on it are duplicates. "
            "Modes: " + "; ".join(f"`{k}`: {v}" for k, v in _MODE_NOTES.items()) + ".", "", *head, *rows, "",
            f"Solver statuses: {', '.join(f'{k} {v}' for k, v in sorted(result['statuses'].items()))}.", "",
            *_verification_markdown(result.get("verification"))]


def _verification_markdown(v: dict | None) -> list[str]:
    if not v:
        return []
    return [f"Verification (simulated annotators' verdicts on {v['judged_on_ground_truth']} poses of ground-truth "
            f"objects): {v['accepted']} accepted, of which {v['accepted_correct_pct']} % are correct by `pose`; "
            f"{v['correct_accepted_pct']} % of the correct poses were accepted.", ""]


def _renoise(labels: dict, bench_dir: Path, clip: str, sigma: float, seed: int) -> dict:
    """``labels`` with every click redrawn at ``sigma`` px around its exact projection (module docstring)."""
    frames = read_frames(Path(bench_dir) / clip / "frames.json")
    by_ts = {f.timestamp: f for f in frames.frames}
    gt = {o.track_id: o for o in read_objects(Path(bench_dir) / clip / "objects.json").objects}
    H, W = frames.image_size
    rng = np.random.default_rng([seed, int(sigma * 1000), sum(map(ord, clip))])
    out = json.loads(json.dumps(labels))
    for obj in out["objects"]:
        o = gt[obj["track_id"]]
        M = object_to_world(o.translation, o.rotation, o.scale, o.is_mirrored)
        for kfj in obj["correspondences"]:
            kf = KeyframeCorrespondences.from_json(kfj)
            cam = frame_camera(by_ts[kf.timestamp], W, H)
            true_xyz = np.asarray(kf.xyz, float) @ rotation_y(kf.symmetry_deg)  # undo the symmetric swap
            uv, _ = project(cam.K, cam.R, cam.t, true_xyz @ M[:3, :3].T + M[:3, 3])
            uv = uv + rng.normal(0.0, sigma, uv.shape) if sigma > 0 else uv
            xy = np.clip(uv / [W, H], 0.0, 1.0)
            for c, p in zip(kfj["correspondences"], xy.tolist()):
                c["2d"] = p
    return out


def bench_tracks(bench_dir: Path, wh: Warehouse, cfg: PoseConfig, sigma: float | None = None,
                 seed: int = 0) -> tuple[list[tuple[str, TrackInput]], list[PosedObject], dict[str, int]]:
    """(clip, track) inputs from the label files (clicks redrawn at ``sigma`` px unless None), the
    ground truth and the symmetry of every model."""
    clips = read_manifest(bench_dir).clips
    models = {r["cad_id"]: r for r in wh.read("cad_models", columns=list(MODEL_FACTS)).to_pylist()}
    tracks = []
    for clip in clips:
        path = clicks_path(bench_dir, clip)
        if not path.is_file():
            continue
        labels = json.loads(path.read_text())
        if sigma is not None:
            labels = _renoise(labels, bench_dir, clip, sigma, seed)
        corr = pa.Table.from_pylist(correspondence_rows(labels), schema=CORRESPONDENCES.schema)
        tracks += [(clip, t) for t in track_inputs(corr, wh.read("frames", [clip]), models, cfg.upright_classes,
                                                   cfg.floor_classes, cfg.wall_classes)]
    gt = [dataclasses.replace(g, cls=_class_of(g.cls)) for g in _gt(bench_dir, clips)]
    return tracks, gt, {k: int(m["symmetry"]) for k, m in models.items()}


def in_truth_world(preds: list[PosedObject], wh: Warehouse | None, bench_dir: Path | None = None) -> list[PosedObject]:
    """Predicted poses (the aligned world of the warehouse's frames, +Y up) in the world of each
    clip's ground truth: for a clip of a camera file, that file's world (``clips.up_rotation``
    undone, :mod:`tasks.video.world_up`); for a clip whose cameras are SfM's (``clips.cameras_source``
    'sfm': ``bench run --sfm-cameras``), the true world, by the similarity that best maps the clip's
    cameras onto the true ones of ``<bench_dir>/<clip>/frames.json`` (:func:`bench.sfm_eval.align`;
    the scale too)."""
    if wh is None:
        return preds
    maps: dict[str, Callable[[PosedObject], PosedObject]] = {}
    out = []
    for p in preds:
        if p.clip not in maps:
            maps[p.clip] = _to_truth(wh, p.clip, bench_dir)
        out.append(maps[p.clip](p))
    return out


def _to_truth(wh: Warehouse, clip: str, bench_dir: Path | None) -> Callable[[PosedObject], PosedObject]:
    """The map of :func:`in_truth_world` for one clip (an unregistered one: the identity)."""
    rows = (wh.read("clips", [clip], columns=["cameras_source", "up_rotation"]).to_pylist()
            if wh.has_partition("clips", clip) else [])
    row = rows[0] if rows else {"cameras_source": None, "up_rotation": None}
    if row["cameras_source"] != "sfm":
        Q = stored_rotation(row["up_rotation"])

        def unturn(p: PosedObject) -> PosedObject:
            T, q = pose_to_input_world(p.translation, p.rotation, Q)
            return dataclasses.replace(p, translation=T, rotation=q)
        return unturn
    if bench_dir is None:
        raise ValueError(f"clip {clip}: SfM cameras; its poses are scored in the true world, which needs the benchmark folder")
    sim = _sfm_to_truth(wh, clip, read_frames(Path(bench_dir) / clip / "frames.json"))

    def move(p: PosedObject) -> PosedObject:
        R = sim.rotation @ quaternion_to_matrix(np.asarray(p.rotation, np.float64))
        return dataclasses.replace(p, translation=tuple(map(float, sim.apply(np.asarray(p.translation)[None])[0])),
                                   rotation=tuple(map(float, matrix_to_quaternion(R))),
                                   scale=tuple(float(v) * sim.scale for v in p.scale))
    return move


def _sfm_to_truth(wh: Warehouse, clip: str, truth: FramesFile) -> Similarity:
    """X_true = s A X + b from the clip's cameras (the warehouse's frames) to the true ones, frame for frame by timestamp."""
    from bench.simulated_labels import frames_like_truth
    from tasks.dataset.objects import camera_centres

    ours = frames_like_truth(wh, clip, truth)
    R_true = np.stack([quaternion_to_matrix(np.asarray(f.rotation, np.float64)) for f in truth.frames])
    t_true = np.stack([np.asarray(f.translation, np.float64) for f in truth.frames])
    return align(R_true, camera_to_world(R_true, t_true)[1], np.stack([f.R for f in ours]), camera_centres(ours))


def evaluate(tracks, gt, symmetries, cfg: PoseConfig, wh: Warehouse | None = None, bench_dir: Path | None = None) -> dict:
    """Solve ``tracks`` with ``cfg`` and score them in the ground truth's worlds (:func:`in_truth_world`,
    with ``wh``'s clips); adds the seconds the solve took."""
    t0 = time.perf_counter()
    results = solve_tracks([t for _, t in tracks], solver_options(cfg), [c for c, _ in tracks])
    seconds = time.perf_counter() - t0
    preds = [PosedObject(t.track_id, t.cls, tuple(r.translation), tuple(r.rotation), tuple(r.scale), t.mirrored, t.cad_id, c)
             for (c, t), r in zip(tracks, results) if r.status == "ok"]
    preds = in_truth_world(preds, wh, bench_dir)
    statuses: dict[str, int] = {}
    for r in results:
        statuses[r.status] = statuses.get(r.status, 0) + 1
    return {**score(preds, gt, symmetries, {(c, t.track_id) for c, t in tracks}), "statuses": statuses,
            "solve_s": round(seconds, 2)}


def timing(tracks, cfg: PoseConfig, singles: int = 10, batch: int = 1000) -> dict:
    """Seconds per object solved alone (mean over ``singles`` objects; alone, it gets no floor
    prior) and for ``batch`` objects in one call (the benchmark's tracks repeated, each repetition
    a clip of its own, so the floor prior's re-solve is included)."""
    problems = [(c, t) for c, t in tracks if t.problem is not None]
    opts = solver_options(cfg)
    solve_tracks([problems[0][1]], opts)  # warm-up (torch's first call)
    t0 = time.perf_counter()
    for _, t in problems[:singles]:
        solve_tracks([t], opts)
    per_object = (time.perf_counter() - t0) / min(singles, len(problems))
    many = [problems[i % len(problems)] for i in range(batch)]
    clips = [f"{c}/{i // len(problems)}" for i, (c, _) in enumerate(many)]
    t0 = time.perf_counter()
    solve_tracks([t for _, t in many], opts, clips)
    return {"per_object_s": round(per_object, 3), f"batch_{batch}_s": round(time.perf_counter() - t0, 1),
            "threads": cfg.threads}


def run(bench_dir: Path = DEFAULT_BENCH, wh: Warehouse | None = None, batch: int = 1000) -> dict:
    """Every number of the module docstring, as a dict (``python -m bench``)."""
    wh = wh or Warehouse("data/warehouse")
    if not (Path(bench_dir) / CLICKS).is_dir():
        return {"skipped": f"{bench_dir}: no simulated labels (run `cadestate bench run {bench_dir}`)"}
    cfg = PoseConfig()
    tracks3, gt, sym = bench_tracks(bench_dir, wh, cfg)
    out: dict = {"bench": str(bench_dir), "objects_with_correspondences": len(tracks3), "accuracy": {}}
    for sigma in (0.0, 3.0, 6.0):
        tracks = tracks3 if sigma == 3.0 else bench_tracks(bench_dir, wh, cfg, sigma)[0]
        out["accuracy"][f"{sigma:g}px"] = evaluate(tracks, gt, sym, cfg, wh, bench_dir)
    ablation = {"base": dataclasses.replace(cfg, coplanar=False, symmetry=False, alpha=0.0),
                "+coplanar": dataclasses.replace(cfg, symmetry=False, alpha=0.0),
                "+symmetry": dataclasses.replace(cfg, alpha=0.0),
                "full, L1 loss (paper)": dataclasses.replace(cfg, huber_px=0.0),
                "full, Adam only": dataclasses.replace(cfg, lm_iterations=0),
                "full, L1 loss and Adam only (paper)": dataclasses.replace(cfg, huber_px=0.0, lm_iterations=0),
                "full, with the narrow-axis prior (axis_prior 10)": dataclasses.replace(cfg, axis_prior=10.0),
                "full, free scales (no proportion prior, as the paper)": dataclasses.replace(cfg, proportion_prior=0.0),
                "full, no floor prior": dataclasses.replace(cfg, floor_prior=0.0),
                "full, floor only (no host supports)": dataclasses.replace(cfg, host_supports=False)}
    out["ablation_3px"] = {name: evaluate(tracks3, gt, sym, c, wh, bench_dir) for name, c in ablation.items()}
    # The floor prior as it was before host supports: floor classes only (every upright class in
    # wall_classes, so none but the floor classes rests), the floor only.
    floor_only = dataclasses.replace(cfg, host_supports=False, wall_classes=cfg.upright_classes)
    out["ablation_3px"]["full, floor prior for floor classes only"] = evaluate(
        bench_tracks(bench_dir, wh, floor_only)[0], gt, sym, floor_only, wh, bench_dir)
    out["ablation_3px"]["+up-axis (full)"] = out["accuracy"]["3px"]
    out["timing"] = timing(tracks3, cfg, batch=batch)
    return out


if __name__ == "__main__":
    from bench.script_args import no_arguments

    no_arguments(__doc__)
    print(json.dumps(run(), indent=1))
