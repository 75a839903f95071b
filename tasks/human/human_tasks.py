"""The human-task stages (paper 3.2, 3.3, 3.5): write a task file, pause until labels answer it.

Each stage writes its task file (:func:`tasks.human.labels.write_task`) with a task id derived from what
the task shows (:func:`tasks.human.labels.new_task_id`), so an unchanged upstream keeps the id and labels
given before still answer it. If every item is answered the run completes; otherwise it is recorded
``paused`` (:class:`tasks.stage.StageOutput`) with a message naming the task file and how many
items wait, and what is answered already goes on (partial labels advance). The answers in force
(:func:`tasks.human.label_ingest.answers_digest`) are part of each stage's inputs, so ingesting labels
makes the stage stale and a rerun resumes it, reusing every cached upstream stage.

Tracks are the clip's automatic and manual ones alike (:func:`tasks.tracking.clip_tracks.clip_tracks`),
but for those the manual-track answer in force says are no object, or are an existing track
(:func:`tasks.tracking.relations.left_out_tracks`): no task asks about them, and
:func:`selected_models` leaves them out, so no correspondences or pose follow from an earlier
choice. The task ids stay digests of what upstream gives (the candidates, the chosen models, the
solved poses), so the answers to the other tracks stay in force; the left-out tracks are part of
these stages' inputs (:func:`tasks.registry.clip_inputs`).

- ``cad_selection`` (after ``retrieval``): per track, its candidates (renders from ``cad_views``,
  meshes from ``cad_models``) on evenly spaced key-frames of the track with its boxes. Output:
  the chosen model per answered track (:func:`selected_models`, from ``cad_selection_labels``).
  A track answered "same object as track N" has no model (it is posed through N).
- ``correspondence_task`` (after ``cad_selection``): per track with a chosen model, the model's
  mesh and key-frames to click on. The answers go to ``correspondences`` at ingest (the ``pose``
  stage's input); a track counts as answered when its newest correspondences use the chosen model.
- ``verification`` (after ``pose``): per solved (``ok``) pose, the posed CAD rendered over its
  key-frames; verdicts go to ``verified_poses``.
"""

from __future__ import annotations

import dataclasses
import json
from collections import defaultdict
from pathlib import Path

import numpy as np
import pyarrow as pa

from cadestate.config import CadSelectionConfig, CorrespondenceTaskConfig, VerificationConfig
from cadestate.lineage import digest, table_digest
from schemas.dataclass_json import to_json
from schemas.labels import (CadCandidate, CadSelectionAnswer, CadSelectionItem, CadSelectionTask, CorrespondenceItem,
                            CorrespondenceTask, KeyframeView, Pose, VerificationAnswer, VerificationItem,
                            VerificationTask)
from tasks.tracking.clip_tracks import ClipTrack, clip_tracks
from tasks.human.label_ingest import answers_digest, current_answers
from tasks.human.labels import latest_task, new_task_id, parse_task, utc_now, write_task
from tasks.stage import StageOutput
from tasks.tracking.relations import left_out_tracks
from warehouse import Warehouse

INSTRUCTIONS = {
    "manual_track": "Draw every object that none of the existing tracks covers: its class and a box on each key-frame "
                    "where it is visible. Answer with no object if nothing is missing.",
    "cad_selection": "For every track, choose the CAD candidate whose shape is closest to the object; "
                     "cad_id null if none is similar enough.",
    "correspondences": "For every track, on each key-frame you annotate, click 4-6 points on the CAD model and the "
                       "same points in the image; mirror the model if it is the mirror image of the object.",
    "verification": "For every track, accept only if the rendered CAD model aligns with the object on every key-frame.",
}


# ------------------------------------------------------------------------------ shared

def evenly_spaced(n: int, k: int) -> list[int]:
    """``min(n, k)`` indices of ``range(n)`` spread evenly, first and last included."""
    if n <= 0:
        return []
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, min(n, k))})


def image_size(wh: Warehouse, clip: str) -> tuple[int, int]:
    frames = wh.read("frames", [clip], columns=["width", "height"])
    if frames.num_rows == 0:
        return (1, 1)
    return int(frames.column("height")[0].as_py()), int(frames.column("width")[0].as_py())


def track_keyframes(wh: Warehouse, clip: str, tracks: dict[int, ClipTrack], track_ids: list[int],
                    k: int) -> dict[int, tuple[KeyframeView, ...]]:
    """Per track of ``track_ids`` (automatic or manual, from ``tracks``: :func:`clip_tracks`),
    ``k`` evenly spaced frames of its boxes with its box there."""
    frames = {f["frame_index"]: f for f in wh.read("frames", [clip], columns=["timestamp_us", "frame_index", "image_path"]).to_pylist()}
    out = {}
    for t in track_ids:
        boxes = tracks[t].boxes if t in tracks else ()
        views = []
        for i in evenly_spaced(len(boxes), k):
            frame = frames.get(boxes[i].frame_index)
            if frame is not None:
                views.append(KeyframeView(timestamp_us=int(frame["timestamp_us"]), frame_index=int(frame["frame_index"]),
                                          image_path=frame["image_path"], box=tuple(float(v) for v in boxes[i].box)))
        out[t] = tuple(views)
    return out


def write_task_once(wh: Warehouse, task) -> Path:
    """Write ``task``; if the newest version of the same task id says the same (but for
    ``created_at``), keep that version (no new file or ``label_tasks`` row)."""
    row = latest_task(wh, task.clip, task.task_id)
    if row is not None:
        old = parse_task(row["document"], f"task {task.task_id}")
        same = dataclasses.replace(task, created_at=old.created_at)
        if to_json(same) == json.loads(row["document"]):
            return write_task(wh, same)
    return write_task(wh, task)


def task_output(rows: int, output_hash: str, summary: str, kind: str, path: str, waiting: int, total: int,
                what: str = "tracks") -> StageOutput:
    """A human-task stage's result: completed, or paused while ``waiting`` of ``total`` items of
    its ``kind`` task at ``path`` are unanswered (the message names the task file)."""
    if not waiting:
        return StageOutput(rows, output_hash, summary)
    return StageOutput(rows, output_hash, f"waits for labels: {waiting} of {total} {what} unanswered in {kind} task {path}; "
                                          f"{summary}", paused=True)


# ------------------------------------------------------------------------------ cad_selection

def candidates(wh: Warehouse, clip: str) -> pa.Table:
    return wh.read("cad_candidates", [clip]).sort_by([("track_id", "ascending"), ("rank", "ascending")])


def cad_selection_task_id(wh: Warehouse, clip: str, cands: pa.Table | None = None) -> str | None:
    """The id of the clip's cad_selection task for its current candidates (None: no candidates)."""
    cands = candidates(wh, clip) if cands is None else cands
    return new_task_id("cad_selection", clip, table_digest(cands)) if cands.num_rows else None


def selected_models(wh: Warehouse, clip: str) -> dict[int, str | None]:
    """The answers in force of the current cad_selection task: track -> chosen cad_id (None: no
    candidate fits, or a fragment of another track). Tracks without an answer are absent, and so
    are the tracks left out (:func:`tasks.tracking.relations.left_out_tracks`)."""
    task_id = cad_selection_task_id(wh, clip)
    if task_id is None:
        return {}
    rows = current_answers(wh, "cad_selection", [clip], task_id).to_pylist()
    left_out = left_out_tracks(wh, clip)
    return {int(r["track_id"]): r["cad_id"] for r in rows if int(r["track_id"]) not in left_out}


def _model_facts(wh: Warehouse, cad_ids: set[str]) -> tuple[dict[str, dict], dict[str, tuple[str, ...]]]:
    models = {r["cad_id"]: r for r in wh.read("cad_models", columns=["cad_id", "library", "class", "symmetry", "mesh_path"]).to_pylist()
              if r["cad_id"] in cad_ids}
    renders: dict[str, list[tuple[int, str]]] = defaultdict(list)
    for r in wh.read("cad_views", columns=["cad_id", "view", "image_path"]).to_pylist():
        if r["cad_id"] in cad_ids:
            renders[r["cad_id"]].append((r["view"], r["image_path"]))
    return models, {c: tuple(p for _, p in sorted(v)) for c, v in renders.items()}


def cad_selection_stage(wh: Warehouse, cfg: CadSelectionConfig, clip: str, run_id: str) -> StageOutput:
    """Write the clip's cad_selection task; completed when every track is answered, else paused."""
    cands = candidates(wh, clip)
    if cands.num_rows == 0:
        return StageOutput(0, digest("cad_selection", "no candidates"), "no CAD candidates: nothing to choose")
    task_id = cad_selection_task_id(wh, clip, cands)
    answers = {int(r["track_id"]): r["cad_id"] for r in current_answers(wh, "cad_selection", [clip], task_id).to_pylist()}
    rows = cands.to_pylist()
    by_track: dict[int, list[dict]] = defaultdict(list)
    for r in rows:
        by_track[int(r["track_id"])].append(r)
    left_out = left_out_tracks(wh, clip)
    track_ids = sorted(t for t in by_track if t not in left_out)
    if not track_ids:
        return StageOutput(0, digest("cad_selection", task_id, "all left out"),
                           f"all {len(by_track)} tracks are said to be no object or another track: nothing to choose")
    tracks = clip_tracks(wh, clip)
    labels = {t: track.label for t, track in tracks.items()}
    models, renders = _model_facts(wh, {r["cad_id"] for r in rows})
    keyframes = track_keyframes(wh, clip, tracks, track_ids, cfg.keyframes)
    items = []
    for t in track_ids:
        cs = tuple(CadCandidate(rank=int(r["rank"]), cad_id=r["cad_id"], library=r["library"], cad_class=r["cad_class"],
                                score=float(r["score"]), mesh_path=(models.get(r["cad_id"]) or {}).get("mesh_path") or "",
                                render_paths=renders.get(r["cad_id"], ())) for r in by_track[t])
        previous = CadSelectionAnswer(track_id=t, cad_id=answers[t]) if t in answers else None
        items.append(CadSelectionItem(track_id=t, label=labels.get(t, by_track[t][0]["cad_class"]), keyframes=keyframes[t],
                                      candidates=cs, previous=previous))
    task = CadSelectionTask(task_id=task_id, clip=clip, created_at=utc_now().isoformat(), image_size=image_size(wh, clip),
                            instructions=INSTRUCTIONS["cad_selection"], items=tuple(items))
    path = wh.relative(write_task_once(wh, task))
    answered = [t for t in track_ids if t in answers]
    chosen = [t for t in answered if answers[t] is not None]
    output = digest("cad_selection", task_id, *(f"{t}\t{answers[t]}" for t in answered))
    waiting = len(track_ids) - len(answered)
    summary = f"{len(chosen)} of {len(track_ids)} tracks have a CAD model, {len(answered) - len(chosen)} none"
    if len(by_track) > len(track_ids):
        summary += f" ({len(by_track) - len(track_ids)} left out: no object, or another track)"
    return task_output(len(chosen), output, summary, "cad_selection", path, waiting, len(track_ids))


# ------------------------------------------------------------------------------ correspondences

def newest_correspondence_models(wh: Warehouse, clip: str) -> dict[int, str]:
    """Per track, the cad_id of its newest correspondence answer (over all tasks of the clip)."""
    rows = current_answers(wh, "correspondences", [clip]).select(["track_id", "cad_id", "ingested_at"]).to_pylist()
    best: dict[int, tuple] = {}
    for r in rows:
        t = int(r["track_id"])
        if t not in best or r["ingested_at"] > best[t][0]:
            best[t] = (r["ingested_at"], r["cad_id"])
    return {t: v[1] for t, v in best.items()}


def correspondence_task_stage(wh: Warehouse, cfg: CorrespondenceTaskConfig, clip: str, run_id: str) -> StageOutput:
    """Write the correspondences task of the tracks with a chosen model; paused until each has clicks."""
    chosen = {t: c for t, c in selected_models(wh, clip).items() if c is not None}
    if not chosen:
        return StageOutput(0, digest("correspondence_task", "nothing chosen"), "no track has a chosen CAD model")
    track_ids = sorted(chosen)
    task_id = new_task_id("correspondences", clip, *(f"{t}:{chosen[t]}" for t in track_ids))
    models, renders = _model_facts(wh, set(chosen.values()))
    tracks = clip_tracks(wh, clip)
    labels = {t: track.label for t, track in tracks.items()}
    keyframes = track_keyframes(wh, clip, tracks, track_ids, cfg.keyframes)
    items = []
    for t in track_ids:
        m = models.get(chosen[t]) or {}
        items.append(CorrespondenceItem(track_id=t, label=labels.get(t, m.get("class") or ""), cad_id=chosen[t],
                                        library=m.get("library") or "", mesh_path=m.get("mesh_path") or "",
                                        render_paths=renders.get(chosen[t], ()), symmetry=int(m.get("symmetry") or 1),
                                        keyframes=keyframes[t]))
    task = CorrespondenceTask(task_id=task_id, clip=clip, created_at=utc_now().isoformat(), image_size=image_size(wh, clip),
                              instructions=INSTRUCTIONS["correspondences"], items=tuple(items))
    path = wh.relative(write_task_once(wh, task))
    newest = newest_correspondence_models(wh, clip)
    answered = [t for t in track_ids if newest.get(t) == chosen[t]]
    output = digest("correspondence_task", task_id, *map(str, answered))
    waiting = len(track_ids) - len(answered)
    summary = f"{len(answered)} of {len(track_ids)} tracks have correspondences"
    return task_output(len(answered), output, summary, "correspondences", path, waiting, len(track_ids))


# ------------------------------------------------------------------------------ verification

POSE_COLUMNS = ["track_id", "cad_id", "class", "translation", "rotation", "scale", "is_mirrored", "keyframe_timestamps_us"]


def ok_poses(wh: Warehouse, clip: str) -> pa.Table:
    poses = wh.read("poses", [clip])
    mask = pa.array([s == "ok" for s in poses.column("status").to_pylist()], pa.bool_())
    return poses.filter(mask).select(POSE_COLUMNS).sort_by([("track_id", "ascending")])


def verification_task_id(clip: str, poses: pa.Table) -> str:
    return new_task_id("verification", clip, table_digest(poses))


def render_overlays(wh: Warehouse, clip: str, task_id: str, poses: list[dict], k: int, alpha: float) -> dict[str, list[tuple[int, str]]]:
    """Per track (poses.track_id), up to ``k`` of its key-frames with the posed CAD drawn over the
    frame: (timestamp_us, overlay path relative to the warehouse root). Existing overlays are kept."""
    from PIL import Image

    from cadestate.render import Camera, Instance, Renderer, RenderMesh, object_to_world

    frames = {r["timestamp_us"]: r for r in wh.read("frames", [clip], columns=["timestamp_us", "frame_index", "image_path", "width",
                                                                            "height", "K", "world_to_camera_R",
                                                                            "world_to_camera_t"]).to_pylist()}
    meshes = {r["cad_id"]: r["mesh_path"] for r in wh.read("cad_models", columns=["cad_id", "mesh_path"]).to_pylist()}
    folder = wh.root / "media" / "verification" / clip / task_id
    out: dict[str, list[tuple[int, str]]] = {}
    todo = []
    for p in poses:
        stamps = [t for t in p["keyframe_timestamps_us"] if t in frames]
        stamps = [stamps[i] for i in evenly_spaced(len(stamps), k)]
        out[p["track_id"]] = [(t, wh.relative(folder / f"{p['track_id']}_{t}.jpg")) for t in stamps]
        todo += [(p, t, folder / f"{p['track_id']}_{t}.jpg") for t in stamps if not (folder / f"{p['track_id']}_{t}.jpg").is_file()]
    if not todo:
        return out
    import trimesh

    folder.mkdir(parents=True, exist_ok=True)
    W, H = int(frames[todo[0][1]]["width"]), int(frames[todo[0][1]]["height"])
    loaded: dict[str, RenderMesh] = {}
    with Renderer(W, H) as renderer:
        for p, t, path in todo:
            if p["cad_id"] not in loaded:
                loaded[p["cad_id"]] = RenderMesh.from_trimesh(trimesh.load(wh.root / meshes[p["cad_id"]], force="scene"))
            f = frames[t]
            camera = Camera(np.array(f["K"]).reshape(3, 3), np.array(f["world_to_camera_R"]).reshape(3, 3),
                            np.array(f["world_to_camera_t"]), W, H, 0.01, 1000.0)
            M = object_to_world(p["translation"], p["rotation"], p["scale"], p["is_mirrored"])
            result = renderer.render([Instance(loaded[p["cad_id"]], M, 1)], camera)
            image = np.asarray(Image.open(wh.root / f["image_path"]).convert("RGB").resize((W, H)), np.float32)
            mask = (result.instance_id == 1)[..., None] * alpha
            blended = image * (1 - mask) + result.rgb.astype(np.float32) * mask
            tmp = path.with_suffix(".tmp.jpg")
            Image.fromarray(np.clip(blended, 0, 255).astype(np.uint8)).save(tmp, quality=90)
            tmp.replace(path)
    return out


def verification_stage(wh: Warehouse, cfg: VerificationConfig, clip: str, run_id: str) -> StageOutput:
    """Write the verification task of the clip's solved poses; paused until each has a verdict.
    Writes ``verified_poses`` (the answered tracks)."""
    from schemas.pose import VERIFIED_POSES

    poses = ok_poses(wh, clip)
    left_out = left_out_tracks(wh, clip)
    poses = poses.filter(pa.array([int(t) not in left_out for t in poses.column("track_id").to_pylist()], pa.bool_()))
    if poses.num_rows == 0:
        empty = VERIFIED_POSES.schema.empty_table()
        wh.write("verified_poses", clip, empty)
        return StageOutput(0, table_digest(empty), "no solved pose to verify")
    task_id = verification_task_id(clip, poses)
    rows = poses.to_pylist()
    answers = {int(r["track_id"]): r for r in current_answers(wh, "verification", [clip], task_id).to_pylist()}
    overlays = render_overlays(wh, clip, task_id, rows, cfg.keyframes, cfg.overlay_alpha)
    frames = {r["timestamp_us"]: r for r in wh.read("frames", [clip], columns=["timestamp_us", "frame_index", "image_path"]).to_pylist()}
    items = []
    for p in rows:
        t = int(p["track_id"])
        kfs = tuple(KeyframeView(timestamp_us=ts, frame_index=int(frames[ts]["frame_index"]), image_path=frames[ts]["image_path"],
                                 overlay_path=path) for ts, path in overlays[p["track_id"]])
        if not kfs:
            continue
        a = answers.get(t)
        previous = VerificationAnswer(track_id=t, verdict="accept" if a["accepted"] else "reject", comment=a["comment"]) if a else None
        items.append(VerificationItem(
            track_id=t, label=p["class"] or "", cad_id=p["cad_id"], mesh_path=_mesh_path(wh, p["cad_id"]),
            pose=Pose(translation=tuple(p["translation"]), rotation=tuple(p["rotation"]), scale=tuple(p["scale"]),
                      is_mirrored=bool(p["is_mirrored"])),
            keyframes=kfs, previous=previous))
    if not items:
        empty = VERIFIED_POSES.schema.empty_table()
        wh.write("verified_poses", clip, empty)
        return StageOutput(0, table_digest(empty), "no solved pose on a frame of the clip")
    task = VerificationTask(task_id=task_id, clip=clip, created_at=utc_now().isoformat(), image_size=image_size(wh, clip),
                            instructions=INSTRUCTIONS["verification"], items=tuple(items))
    path = wh.relative(write_task_once(wh, task))
    verified = [{"clip": clip, "track_id": p["track_id"], "cad_id": p["cad_id"], "class": p["class"],
                 "accepted": bool(answers[int(p["track_id"])]["accepted"]), "translation": p["translation"],
                 "rotation": p["rotation"], "scale": p["scale"], "is_mirrored": p["is_mirrored"], "task_id": task_id,
                 "comment": answers[int(p["track_id"])]["comment"]}
                for p in rows if int(p["track_id"]) in answers and p["track_id"] in {str(it.track_id) for it in items}]
    table = pa.Table.from_pylist(verified, schema=VERIFIED_POSES.schema)
    wh.write("verified_poses", clip, table)
    waiting = len(items) - len(verified)
    accepted = sum(r["accepted"] for r in verified)
    summary = f"{accepted} of {len(items)} poses accepted, {len(verified) - accepted} rejected"
    return task_output(len(verified), table_digest(table), summary, "verification", path, waiting, len(items), "poses")


def _mesh_path(wh: Warehouse, cad_id: str) -> str:
    rows = wh.read("cad_models", filters=[("cad_id", "=", cad_id)], columns=["mesh_path"]).to_pylist()
    return rows[0]["mesh_path"] if rows else ""


def answers_inputs(wh: Warehouse, kind: str, clip: str) -> str:
    """The answers in force of ``kind`` for ``clip`` (all tasks): a stage input digest."""
    return answers_digest(wh, kind, clip)
