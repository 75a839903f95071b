"""Stage ``cad_selection`` (paper 3.2), after ``retrieval``: per track, its candidates (renders from ``cad_views``,
  meshes from ``cad_models``) on evenly spaced key-frames of the track with its boxes. Output:
  the chosen model per answered track (:func:`selected_models`, from ``cad_selection_labels``).
  A track answered "same object as track N" has no model (it is posed through N).

How the human-task stages work (this one, ``correspondence_task``, ``verification``):
The human-task stages (paper 3.2, 3.3, 3.5; 3.1 is :mod:`tasks.human.manual_tracks`): write a task file, pause until labels answer it.

Each stage writes its task file (:func:`tasks.human.labels.write_task`) with a task id derived from what
the task shows (:func:`tasks.human.labels.new_task_id`), so an unchanged upstream keeps the id and labels
given before still answer it. When upstream changed, an answer given on an earlier task that still fits
is carried in the item's ``previous`` and counts as given (:mod:`tasks.human.choices_in_force`,
:mod:`tasks.human.clicks_in_force`). If every item is answered the run completes; otherwise it is recorded
``paused`` (:class:`tasks.stage.StageOutput`) with a message naming the task file and how many
items wait, and what is answered already goes on (partial labels advance). The answers in force
(:func:`tasks.human.answers_in_force.answers_digest`) are part of each stage's inputs, so ingesting labels
makes the stage stale and a rerun resumes it, reusing every cached upstream stage.

Tracks are the clip's automatic and manual ones alike (:func:`tasks.tracking.clip_tracks.clip_tracks`),
but for those the manual-track answer in force says are no object, or are an existing track
(:func:`tasks.tracking.relations.left_out_tracks`): no task asks about them, and
:func:`selected_models` leaves them out, so no correspondences or pose follow from an earlier
choice. The task ids stay digests of what upstream gives (the candidates, the chosen models, the
solved poses), so the answers to the other tracks stay in force; the left-out tracks are part of
these stages' inputs (:func:`tasks.registry.clip_inputs`).
"""

from __future__ import annotations

import json
from collections import defaultdict

import pyarrow as pa

from cadestate.config import CadSelectionConfig
from cadestate.lineage import digest, table_digest
from schemas.labels import CadCandidate, CadSelectionAnswer, CadSelectionItem, CadSelectionTask
from tasks.human.answers_in_force import current_answers
from tasks.human.choices_in_force import held_choices
from tasks.human.inputs import cad_selection_inputs
from tasks.human.labels import new_task_id, utc_now
from tasks.human.shared import (INSTRUCTIONS, boxes_now, image_size, task_output, track_keyframes, withdraw_task,
                                 write_task_once)
from tasks.stage import StageContext, StageDef, StageOutput
from tasks.tracking.clip_tracks import clip_tracks
from tasks.tracking.relations import left_out_tracks, manual_statements, same_as_statements
from warehouse import Warehouse


def candidates(wh: Warehouse, clip: str) -> pa.Table:
    return wh.read("cad_candidates", [clip]).sort_by([("track_id", "ascending"), ("rank", "ascending")])


def cad_selection_task_id(wh: Warehouse, clip: str, cands: pa.Table | None = None) -> str | None:
    """The id of the clip's cad_selection task for its current candidates (None: no candidates)."""
    cands = candidates(wh, clip) if cands is None else cands
    return new_task_id("cad_selection", clip, table_digest(cands)) if cands.num_rows else None


def selected_models(wh: Warehouse, clip: str) -> dict[int, str | None]:
    """The answers in force of the current cad_selection task: track -> chosen cad_id (None: no
    candidate fits, or a fragment of another track), given under its id or carried from an earlier
    task in the item's ``previous`` (:mod:`tasks.human.choices_in_force`). Tracks without an answer
    are absent, and so are the tracks left out (:func:`tasks.tracking.relations.left_out_tracks`)."""
    from tasks.human.labels import latest_task

    task_id = cad_selection_task_id(wh, clip)
    if task_id is None:
        return {}
    chosen = {int(r["track_id"]): r["cad_id"] for r in current_answers(wh, "cad_selection", [clip], task_id).to_pylist()}
    row = latest_task(wh, clip, task_id)
    for item in json.loads(row["document"])["items"] if row is not None else ():
        if item.get("previous") is not None and int(item["track_id"]) not in chosen:
            chosen[int(item["track_id"])] = item["previous"]["cad_id"]
    left_out = left_out_tracks(wh, clip)
    return {t: c for t, c in chosen.items() if t not in left_out}


def model_facts(wh: Warehouse, cad_ids: set[str]) -> tuple[dict[str, dict], dict[str, tuple[str, ...]]]:
    """Of the models ``cad_ids``: their ``cad_models`` rows, and their render paths in view order.
    Those rows alone are read (every library's were made Python rows: 0.35 s and 67 MB per run for
    300,000 views)."""
    if not cad_ids:
        return {}, {}
    only = [("cad_id", "in", sorted(cad_ids))]
    models = {r["cad_id"]: r for r in wh.read("cad_models", columns=["cad_id", "library", "class", "symmetry", "mesh_path"],
                                              filters=only).to_pylist()}
    renders: dict[str, list[tuple[int, str]]] = defaultdict(list)
    for r in wh.read("cad_views", columns=["cad_id", "view", "image_path"], filters=only).to_pylist():
        renders[r["cad_id"]].append((r["view"], r["image_path"]))
    return models, {c: tuple(p for _, p in sorted(v)) for c, v in renders.items()}


def cad_selection_stage(wh: Warehouse, cfg: CadSelectionConfig, clip: str, run_id: str) -> StageOutput:
    """Write the clip's cad_selection task; completed when every track is answered, else paused."""
    cands = candidates(wh, clip)
    if cands.num_rows == 0:
        return StageOutput(0, digest("cad_selection", "no candidates"),
                           f"no CAD candidates: nothing to choose{withdraw_task(wh, clip, 'cad_selection', 'no CAD candidates')}")
    task_id = cad_selection_task_id(wh, clip, cands)
    answers = {int(r["track_id"]): r["cad_id"] for r in current_answers(wh, "cad_selection", [clip], task_id).to_pylist()}
    rows = cands.to_pylist()
    by_track: dict[int, list[dict]] = defaultdict(list)
    for r in rows:
        by_track[int(r["track_id"])].append(r)
    left_out = left_out_tracks(wh, clip)
    track_ids = sorted(t for t in by_track if t not in left_out)
    if not track_ids:
        why = f"all {len(by_track)} tracks are said to be no object or another track"
        return StageOutput(0, digest("cad_selection", task_id, "all left out"),
                           f"{why}: nothing to choose{withdraw_task(wh, clip, 'cad_selection', why)}")
    tracks = clip_tracks(wh, clip)
    labels = {t: track.label for t, track in tracks.items()}
    models, renders = model_facts(wh, {r["cad_id"] for r in rows})
    keyframes = track_keyframes(wh, clip, tracks, track_ids, cfg.keyframes)
    now = boxes_now(tracks, fragments=manual_statements(wh, clip)[1])
    tasks = wh.read("label_tasks", [clip], columns=["task_id", "kind", "created_at", "document"])
    held = held_choices(task_id, {t: {r["cad_id"] for r in by_track[t]} for t in track_ids}, now,
                        current_answers(wh, "cad_selection", [clip]), tasks)
    answers.update(held)
    fragment_of = same_as_statements(wh, clip, "cad_selection", task_id)  # a fragment's answer: "same object as track N"
    items = []
    for t in track_ids:
        cs = tuple(CadCandidate(rank=int(r["rank"]), cad_id=r["cad_id"], library=r["library"], cad_class=r["cad_class"],
                                score=float(r["score"]), mesh_path=(models.get(r["cad_id"]) or {}).get("mesh_path") or "",
                                render_paths=renders.get(r["cad_id"], ())) for r in by_track[t])
        previous = (CadSelectionAnswer(track_id=t, cad_id=answers[t], same_as_track=fragment_of.get(t))
                    if t in answers else None)
        items.append(CadSelectionItem(track_id=t, label=labels.get(t, by_track[t][0]["cad_class"]), keyframes=keyframes[t],
                                      candidates=cs, previous=previous))
    task = CadSelectionTask(task_id=task_id, clip=clip, created_at=utc_now().isoformat(), image_size=image_size(wh, clip),
                            instructions=INSTRUCTIONS["cad_selection"], items=tuple(items))
    path = wh.relative(write_task_once(wh, task))
    answered = [t for t in track_ids if t in answers]
    chosen = [t for t in answered if answers[t] is not None]
    fragments = sum(t in fragment_of for t in answered if answers[t] is None)
    output = digest("cad_selection", task_id, *(f"{t}\t{answers[t]}" for t in answered))
    waiting = len(track_ids) - len(answered)
    summary = (f"{len(chosen)} of {len(track_ids)} tracks have a CAD model, {len(answered) - len(chosen) - fragments} none"
               + (f", {fragments} the same object as another track" if fragments else ""))
    if len(by_track) > len(track_ids):
        summary += f" ({len(by_track) - len(track_ids)} left out: no object, or another track)"
    return task_output(len(chosen), output, summary, "cad_selection", path, waiting, len(track_ids))


def _run(ctx: StageContext) -> StageOutput:
    return cad_selection_stage(ctx.wh, ctx.cfg, ctx.unit, ctx.run_id)


STAGE = StageDef(
    name="cad_selection", section="cad_selection", scope="clip", upstream=("retrieval", "frames"), tables=("label_tasks",),
    description="human task (3.2): people choose each track's CAD model among its candidates; pauses until answered",
    run=_run, clip_inputs=cad_selection_inputs,
)
