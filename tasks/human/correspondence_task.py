"""Stage ``correspondence_task`` (paper 3.3), after ``cad_selection``: per track with a chosen model, the model's
  mesh and key-frames to click on (a track seen on one frame only is not asked: one view gives no pose). The clicks that answer each item (given on this task, or on an
  earlier one and still holding: :mod:`tasks.human.clicks_in_force`) go to ``correspondences``
  (the ``pose`` stage's input), here and at ingest; with no task to ask, the task is withdrawn and it is emptied.

How it waits for people: :mod:`tasks.human.cad_selection`.
"""

from __future__ import annotations

from cadestate.config import CorrespondenceTaskConfig
from cadestate.lineage import digest, table_digest
from schemas.labels import CorrespondenceItem, CorrespondenceTask
from tasks.human.answers_in_force import current_answers, sync_correspondences
from tasks.human.cad_selection import selected_models, model_facts
from tasks.human.clicks_in_force import held_clicks, item_key
from tasks.human.inputs import correspondence_inputs
from tasks.human.labels import new_task_id, utc_now
from tasks.human.shared import (INSTRUCTIONS, boxes_now, image_size, made_up_cameras, task_output, track_keyframes,
                                 withdraw_task, write_task_once)
from tasks.stage import StageContext, StageDef, StageOutput
from tasks.tracking.clip_tracks import clip_tracks
from tasks.tracking.relations import manual_statements
from warehouse import Warehouse


def correspondence_task_stage(wh: Warehouse, cfg: CorrespondenceTaskConfig, clip: str, run_id: str) -> StageOutput:
    """Write the correspondences task of the tracks with a chosen model, each carrying the earlier
    clicks that still hold; write the clicks in force to ``correspondences``; paused until every
    track has some."""
    chosen = {t: c for t, c in selected_models(wh, clip).items() if c is not None}
    if not chosen:
        return _nothing_asked(wh, clip, digest("correspondence_task", "nothing chosen"), "no track has a chosen CAD model")
    tracks = clip_tracks(wh, clip)
    keyframes = track_keyframes(wh, clip, tracks, sorted(chosen), cfg.keyframes, posed=True)
    # one view gives no depth: a track seen on one frame can never be posed (pose's single_keyframe)
    track_ids = [t for t in sorted(chosen) if len(keyframes[t]) >= 2]
    one_frame = len(chosen) - len(track_ids)
    not_asked = f"; {one_frame} track(s) seen on one frame only not asked (one view gives no pose)" if one_frame else ""
    if not track_ids:
        return _nothing_asked(wh, clip, digest("correspondence_task", "one frame", *map(str, sorted(chosen))),
                              "no track with a chosen CAD model is seen on two frames", not_asked)
    task_id = new_task_id("correspondences", clip, *(item_key(t, chosen[t], keyframes[t]) for t in track_ids))
    now = boxes_now(tracks, made_up_cameras(wh, clip), manual_statements(wh, clip)[1])  # clicks on a camera SfM
    # interpolates now hold no more; a drawn fragment's boxes are its track's
    tasks = wh.read("label_tasks", [clip], columns=["task_id", "kind", "created_at", "document"])
    held = held_clicks(task_id, chosen, now, current_answers(wh, "correspondences", [clip]), tasks)  # every chosen track
    held = {t: a for t, a in held.items() if t in track_ids}  # (matched among all) but only items answer the task
    models, renders = model_facts(wh, set(chosen.values()))
    labels = {t: track.label for t, track in tracks.items()}
    items = []
    for t in track_ids:
        m = models.get(chosen[t]) or {}
        items.append(CorrespondenceItem(track_id=t, label=labels.get(t, m.get("class") or ""), cad_id=chosen[t],
                                        library=m.get("library") or "", mesh_path=m.get("mesh_path") or "",
                                        render_paths=renders.get(chosen[t], ()), symmetry=int(m.get("symmetry") or 1),
                                        keyframes=keyframes[t], previous=held.get(t)))
    task = CorrespondenceTask(task_id=task_id, clip=clip, created_at=utc_now().isoformat(), image_size=image_size(wh, clip),
                              instructions=INSTRUCTIONS["correspondences"], items=tuple(items))
    path = wh.relative(write_task_once(wh, task))
    clicks, _ = sync_correspondences(wh, clip)
    output = digest("correspondence_task", task_id, table_digest(clicks))
    waiting = len(track_ids) - len(held)
    summary = f"{len(held)} of {len(track_ids)} tracks have correspondences{not_asked}"
    return task_output(len(held), output, summary, "correspondences", path, waiting, len(track_ids))


def _nothing_asked(wh: Warehouse, clip: str, output: str, why: str, note: str = "") -> StageOutput:
    """Nothing to ask (``why``): withdraw the clip's correspondences task, which empties its
    ``correspondences`` (the clicks of an earlier task, of tracks whose model is no longer chosen,
    stayed there, though pose leaves them out; a label answering that task later adds none)."""
    withdrawn = withdraw_task(wh, clip, "correspondences", why)
    sync_correspondences(wh, clip)
    return StageOutput(0, output, f"{why}{note}{withdrawn}")


def _run(ctx: StageContext) -> StageOutput:
    return correspondence_task_stage(ctx.wh, ctx.cfg, ctx.unit, ctx.run_id)


STAGE = StageDef(
    name="correspondence_task", section="correspondence_task", scope="clip", upstream=("cad_selection", "frames"), tables=("label_tasks",),
    description="human task (3.3): people click 3D<->2D correspondences on the chosen models; pauses until answered",
    run=_run, clip_inputs=correspondence_inputs,
)
