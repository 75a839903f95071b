"""Stage ``verification`` (paper 3.5), after ``pose``: per solved (``ok``) pose, the posed CAD rendered over its
  key-frames; verdicts go to ``verified_poses``.

Duplicates caught after pose: an item lists in ``maybe_same_as`` the other tracks whose posed CAD
box overlaps its own by at least ``[verification] duplicate_overlap`` (:mod:`tasks.pose.duplicates`),
and the annotator may answer ``same_as_track`` (:mod:`tasks.tracking.relations`: the export keeps
the pose of the track named, so each physical object is exported once). The task id digests the
poses only; an item without flags is written as before the flags existed. When one pose is solved
anew (a new task), the verdicts given earlier on poses whose overlays have not visibly moved are
carried in the items' ``previous`` and count as given (:mod:`tasks.human.verdicts_in_force`); on
an item flagged as maybe a duplicate, only a verdict given on an item flagged too.


How it waits for people: :mod:`tasks.human.cad_selection`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from cadestate.config import VerificationConfig
from cadestate.lineage import table_digest
from schemas.labels import KeyframeView, Pose, VerificationAnswer, VerificationItem, VerificationTask
from tasks.human.answers_in_force import current_answers
from tasks.human.inputs import verification_inputs
from tasks.human.labels import new_task_id, utc_now
from tasks.human.shared import INSTRUCTIONS, evenly_spaced, image_size, task_output, withdraw_task, write_task_once
from tasks.human.verdicts_in_force import NEAR_M, FrameCamera, held_verdicts
from tasks.stage import StageContext, StageDef, StageOutput
from tasks.tracking.relations import left_out_tracks
from warehouse import Warehouse


POSE_COLUMNS = ["track_id", "cad_id", "class", "translation", "rotation", "scale", "is_mirrored", "keyframe_timestamps_us"]


def ok_poses(wh: Warehouse, clip: str) -> pa.Table:
    poses = wh.read("poses", [clip])
    mask = pa.array([s == "ok" for s in poses.column("status").to_pylist()], pa.bool_())
    poses = poses.filter(mask).select(POSE_COLUMNS)
    return poses.take(pc.sort_indices(pc.cast(poses["track_id"], pa.int64())))  # by number: the ids are text here


def verification_task_id(clip: str, poses: pa.Table) -> str:
    return new_task_id("verification", clip, table_digest(poses))


def poses_to_verify(wh: Warehouse, clip: str) -> pa.Table:
    """The clip's solved poses (:func:`ok_poses`) but those of the tracks left out
    (:func:`tasks.tracking.relations.left_out_tracks`): the verification task's tracks."""
    poses = ok_poses(wh, clip)
    left_out = left_out_tracks(wh, clip)
    return poses.filter(pa.array([int(t) not in left_out for t in poses.column("track_id").to_pylist()], pa.bool_()))


def flagged_duplicates(poses: list[dict], extents: Mapping[str, Sequence[float]], threshold: float) -> dict[int, tuple[int, ...]]:
    """Per track of ``poses`` (rows of :func:`poses_to_verify`), the other tracks whose posed CAD
    box overlaps its own by at least ``threshold`` (:func:`tasks.pose.duplicates.duplicate_candidates`);
    poses whose model has no extent (``extents``: cad_id -> box size) are left out."""
    from tasks.pose.duplicates import duplicate_candidates, posed_box

    boxes = {int(p["track_id"]): posed_box(extents[p["cad_id"]], p["translation"], p["rotation"], p["scale"], p["is_mirrored"])
             for p in poses if extents.get(p["cad_id"]) is not None}
    return duplicate_candidates(boxes, threshold)


def render_overlays(wh: Warehouse, clip: str, task_id: str, poses: list[dict], k: int, alpha: float,
                    frames: Mapping[int, dict], meshes: Mapping[str, str]) -> dict[str, list[tuple[int, str]]]:
    """Per track (poses.track_id), up to ``k`` of its key-frames with the posed CAD drawn over the
    frame at opacity ``alpha``: (timestamp_us, overlay path relative to the warehouse root). Existing
    overlays are kept (the task id digests the poses; the file name holds the opacity, so another
    ``[verification] overlay_alpha`` renders anew). ``frames``: the clip's ``frames`` rows by
    timestamp (µs; image_path, width, height, K, the camera); ``meshes``: cad_id -> mesh_path."""
    from PIL import Image

    from cadestate.render import Camera, Instance, Renderer, RenderMesh, object_to_world

    folder = wh.root / "media" / "verification" / clip / task_id
    out: dict[str, list[tuple[int, str]]] = {}
    todo = []
    for p in poses:
        stamps = [t for t in p["keyframe_timestamps_us"] if t in frames]
        stamps = [stamps[i] for i in evenly_spaced(len(stamps), k)]
        paths = {t: folder / f"{p['track_id']}_{t}_alpha{alpha:g}.jpg" for t in stamps}
        out[p["track_id"]] = [(t, wh.relative(path)) for t, path in paths.items()]
        todo += [(p, t, path) for t, path in paths.items() if not path.is_file()]
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
                            np.array(f["world_to_camera_t"]), W, H, NEAR_M, 1000.0)
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

    poses = poses_to_verify(wh, clip)
    if poses.num_rows == 0:
        empty = VERIFIED_POSES.schema.empty_table()
        wh.write("verified_poses", clip, empty)
        return StageOutput(0, table_digest(empty), "no solved pose to verify" + withdraw_task(wh, clip, "verification", "no solved pose"))
    task_id = verification_task_id(clip, poses)
    rows = poses.to_pylist()
    in_force = current_answers(wh, "verification", [clip])
    answers = {int(r["track_id"]): r for r in in_force.to_pylist() if r["task_id"] == task_id}
    tasks = wh.read("label_tasks", [clip], columns=["task_id", "kind", "created_at", "document"])
    models = wh.read("cad_models", columns=["cad_id", "extent", "mesh_path"]).to_pylist()
    extents = {r["cad_id"]: r["extent"] for r in models}
    meshes = {r["cad_id"]: r["mesh_path"] for r in models}
    frames = {r["timestamp_us"]: r for r in wh.read("frames", [clip], columns=[
        "timestamp_us", "frame_index", "image_path", "width", "height", "K", "world_to_camera_R", "world_to_camera_t"]).to_pylist()}
    cameras = {ts: FrameCamera.of(f) for ts, f in frames.items()}
    overlays = render_overlays(wh, clip, task_id, rows, cfg.keyframes, cfg.overlay_alpha, frames, meshes)
    rows = [p for p in rows if overlays[p["track_id"]]]  # a pose on no frame of the clip is not asked about
    flagged = flagged_duplicates(rows, extents, cfg.duplicate_overlap)
    answers |= held_verdicts(task_id, rows, in_force, tasks, extents, cameras, cfg.carry_max_px, flagged)
    items = []
    for p in rows:
        t = int(p["track_id"])
        kfs = tuple(KeyframeView(timestamp_us=ts, frame_index=int(frames[ts]["frame_index"]), image_path=frames[ts]["image_path"],
                                 overlay_path=path) for ts, path in overlays[p["track_id"]])
        a = answers.get(t)
        previous = VerificationAnswer(track_id=t, verdict="accept" if a["accepted"] else "reject", comment=a["comment"],
                                      same_as_track=a.get("same_as_track")) if a else None
        items.append(VerificationItem(
            track_id=t, label=p["class"] or "", cad_id=p["cad_id"], mesh_path=meshes.get(p["cad_id"], ""),
            pose=Pose(translation=tuple(p["translation"]), rotation=tuple(p["rotation"]), scale=tuple(p["scale"]),
                      is_mirrored=bool(p["is_mirrored"])),
            keyframes=kfs, maybe_same_as=flagged.get(t, ()), previous=previous))
    if not items:
        empty = VERIFIED_POSES.schema.empty_table()
        wh.write("verified_poses", clip, empty)
        why = "no solved pose on a frame of the clip"
        return StageOutput(0, table_digest(empty), why + withdraw_task(wh, clip, "verification", why))
    task = VerificationTask(task_id=task_id, clip=clip, created_at=utc_now().isoformat(), image_size=image_size(wh, clip),
                            instructions=INSTRUCTIONS["verification"], items=tuple(items))
    path = wh.relative(write_task_once(wh, task))
    verified = [{"clip": clip, "track_id": p["track_id"], "cad_id": p["cad_id"], "class": p["class"],
                 "accepted": bool(answers[int(p["track_id"])]["accepted"]), "translation": p["translation"],
                 "rotation": p["rotation"], "scale": p["scale"], "is_mirrored": p["is_mirrored"], "task_id": task_id,
                 "comment": answers[int(p["track_id"])]["comment"]}
                for p in rows if int(p["track_id"]) in answers]
    table = pa.Table.from_pylist(verified, schema=VERIFIED_POSES.schema)
    wh.write("verified_poses", clip, table)
    waiting = len(items) - len(verified)
    accepted = sum(r["accepted"] for r in verified)
    summary = f"{accepted} of {len(items)} poses accepted, {len(verified) - accepted} rejected"
    return task_output(len(verified), table_digest(table), summary, "verification", path, waiting, len(items), "poses")


def _run(ctx: StageContext) -> StageOutput:
    return verification_stage(ctx.wh, ctx.cfg, ctx.unit, ctx.run_id)


STAGE = StageDef(
    name="verification", section="verification", scope="clip", upstream=("pose", "frames"), tables=("label_tasks", "verified_poses"),
    description="human task (3.5): people accept or reject each solved pose over its key-frames; pauses until answered",
    run=_run, clip_inputs=verification_inputs,
)
