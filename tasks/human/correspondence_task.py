"""Stage ``correspondence_task`` (paper 3.3), after ``cad_selection``: per track with a chosen model, the model's
  mesh and key-frames to click on. The answers go to ``correspondences`` at ingest (the ``pose``
  stage's input); a track counts as answered when its newest correspondences use the chosen model.

How it waits for people: :mod:`tasks.human.cad_selection`.
"""

from __future__ import annotations

from cadestate.config import CorrespondenceTaskConfig
from cadestate.lineage import digest
from schemas.labels import CorrespondenceItem, CorrespondenceTask
from tasks.human.cad_selection import selected_models, model_facts
from tasks.human.label_ingest import current_answers
from tasks.human.inputs import correspondence_inputs
from tasks.human.labels import new_task_id, utc_now
from tasks.human.shared import INSTRUCTIONS, image_size, task_output, track_keyframes, write_task_once
from tasks.stage import StageContext, StageDef, StageOutput
from tasks.tracking.clip_tracks import clip_tracks
from warehouse import Warehouse


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
    models, renders = model_facts(wh, set(chosen.values()))
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


def _run(ctx: StageContext) -> StageOutput:
    return correspondence_task_stage(ctx.wh, ctx.cfg, ctx.unit, ctx.run_id)


STAGE = StageDef(
    name="correspondence_task", section="correspondence_task", scope="clip", upstream=("cad_selection",), tables=("label_tasks",),
    description="human task (3.3): people click 3D<->2D correspondences on the chosen models; pauses until answered",
    run=_run, clip_inputs=correspondence_inputs,
)
