"""Stage ``manual_tracks`` (human task, paper Sec. 3.1): people draw the objects automatic tracking missed.

Only clips of the ``[manual_tracks] splits`` (``clips.split``; val and test by default) get the
task; any other clip completes at once with an empty ``manual_tracks`` partition. For the others
the stage writes a ``manual_track`` task file (:class:`schemas.labels.ManualTrackTask`): the
clip's ``[manual_tracks] keyframes`` frames regularly spaced in time, every automatic track with
its boxes on them, the classes to choose from (:func:`task_classes`) and the answer given
before; then it pauses until a label answers the task. The newest label of the task is the
answer in force (a newer one replaces it whole); an empty answer ("nothing is missing")
completes the stage with no manual track.

Each drawn object becomes a track with an id from ``MANUAL_TRACK_BASE`` on, a digest of the
object (:func:`tasks.tracking.relations.manual_track_ids`; :data:`schemas.tracking.MANUAL_TRACK_BASE`), one
``manual_tracks`` row per box, each box embedded exactly as the ``embed`` stage embeds
detections (:func:`tasks.detection.embed.embed_frame_boxes` with ``[embed]``), so retrieval and the later human tasks take it as any track
(:mod:`tasks.tracking.clip_tracks`). A drawn object said to be existing track N ("this is track N") still
becomes a manual track, a fragment of N: the later human tasks leave it out and the export merges
it into N's object, as they leave out and drop the tracks said to be no object
(:mod:`tasks.tracking.relations`). The task id is a digest of what the task asks (key-frame timestamps,
the tracks' boxes on them, the classes), not of image paths, so labels keep answering it when the
frames are extracted again.

Reads: ``clips`` (split), ``frames``, the automatic tracks, ``label_similarity``, the manual-track
labels. Writes: ``manual_tracks``, the task file and its ``label_tasks`` row.
"""

from __future__ import annotations

import json
from collections import defaultdict

import numpy as np
import pyarrow as pa

from cadestate.config import EmbedConfig, ManualTracksConfig
from cadestate.lineage import digest, table_digest
from schemas.dataclass_json import to_json
from schemas.labels import ExistingTrack, KeyframeView, ManualTrackAnswer, ManualTrackTask, TimedBox
from schemas.tracking import MANUAL_TRACKS
from tasks.detection.embed import embed_frame_boxes, vectors_array
from tasks.detection.model_inputs import detector_labels, label_map_inputs
from tasks.detection.models.embedder import load_embedder
from tasks.human.inputs import manual_track_inputs
from tasks.human.answers_in_force import answered_tasks, current_answers
from tasks.human.labels import new_task_id, utc_now
from tasks.human.keyframes import regular_keyframes
from tasks.human.shared import INSTRUCTIONS, image_size, task_output, withdraw_task, write_task_once
from tasks.retrieval.label_similarity import similarity_labels
from tasks.stage import StageContext, StageDef, StageOutput
from tasks.tracking.clip_tracks import clip_tracks
from tasks.tracking.relations import manual_answer_statements, manual_track_ids
from tasks.video.ingest import clip_inputs, clip_split
from warehouse import Warehouse

KIND = "manual_track"


def task_classes(wh: Warehouse, detector_labels: tuple[str, ...]) -> tuple[str, ...]:
    """The classes annotators choose from: the detector labels retrieval can score
    (:func:`similarity_labels`), else (no CAD library yet) the detector's label map."""
    return similarity_labels(wh) or tuple(dict.fromkeys(detector_labels))


def _empty(wh: Warehouse, clip: str) -> pa.Table:
    table = MANUAL_TRACKS.schema.empty_table()
    wh.write("manual_tracks", clip, table)
    return table


def _answers(rows: list[dict], same_as: dict[int, int] | None = None) -> tuple[ManualTrackAnswer, ...]:
    """The objects of one label's ``manual_track_labels`` rows, in label order; ``same_as``: {object
    index: the existing track it was said to be} (:func:`manual_answer_statements`)."""
    objects: dict[int, list[dict]] = defaultdict(list)
    for r in rows:
        objects[r["object_index"]].append(r)
    same_as = same_as or {}
    return tuple(ManualTrackAnswer(label=rs[0]["label"], source_id=rs[0]["source_id"], same_as_track=same_as.get(i),
                                   boxes=tuple(TimedBox(timestamp_us=r["timestamp_us"], box=tuple(r["box"]))
                                               for r in sorted(rs, key=lambda r: r["timestamp_us"])))
                 for i, rs in sorted(objects.items()))


def previous_answer(wh: Warehouse, clip: str, task_id: str, answered: bool) -> tuple[tuple[ManualTrackAnswer, ...], tuple[int, ...]]:
    """(objects drawn, tracks said to be no object) of this task's answer in force; a new task gets
    the boxes of the clip's newest earlier answer (none when it said nothing is missing; its
    statements named another task's tracks)."""
    rows = current_answers(wh, KIND, [clip]).to_pylist()
    if not answered:
        times = wh.read("label_files", [clip], filters=[("kind", "=", KIND)], columns=["ingested_at"]).column(
            "ingested_at").to_pylist() if wh.has_partition("label_files", clip) else []
        newest = max(times, default=None)  # ingested_at is strictly increasing in a clip: one file's
        return _answers([r for r in rows if r["ingested_at"] == newest]), ()
    not_objects, same_as = manual_answer_statements(wh, clip, task_id)
    return _answers([r for r in rows if r["task_id"] == task_id], same_as), tuple(sorted(not_objects))


def manual_track_table(wh: Warehouse, embed_cfg: EmbedConfig, clip: str, task_id: str, rows: list[dict]) -> pa.Table:
    """``manual_tracks`` of the answer in force (``manual_track_labels`` rows of one label): one row
    per box, with its descriptor."""
    frames = wh.read("frames", [clip], columns=["timestamp_us", "frame_index"]).to_pylist()
    frame_of = {f["timestamp_us"]: f["frame_index"] for f in frames}
    rows = sorted(rows, key=lambda r: (r["object_index"], r["timestamp_us"]))
    if not rows:
        return MANUAL_TRACKS.schema.empty_table()
    lost = sorted({r["timestamp_us"] for r in rows} - set(frame_of))
    if lost:
        raise ValueError(f"clip {clip}: the manual-track label {rows[0]['label_sha256'][:12]} of task {task_id} has boxes "
                         f"on timestamps that are no frame of the clip any more: {lost[:5]} (µs); answer the new task")
    ids = manual_track_ids(rows)
    embedder = load_embedder(embed_cfg)
    vectors = embed_frame_boxes(wh, embedder, embed_cfg, clip, [(frame_of[r["timestamp_us"]], r["box"]) for r in rows])
    n = len(rows)
    return pa.table({
        "clip": [clip] * n, "track_id": pa.array([ids[r["object_index"]] for r in rows], pa.int32()),
        "label": [r["label"] for r in rows], "source_id": [r["source_id"] for r in rows],
        "timestamp_us": [r["timestamp_us"] for r in rows], "frame_index": [frame_of[r["timestamp_us"]] for r in rows],
        "box": [list(r["box"]) for r in rows], "vector": vectors_array(vectors), "model_sha256": [embedder.sha256] * n,
        "task_id": [task_id] * n,
    }, schema=MANUAL_TRACKS.schema)


def manual_tracks_stage(wh: Warehouse, cfg: ManualTracksConfig, embed_cfg: EmbedConfig, detector_labels: tuple[str, ...],
                        clip: str, run_id: str) -> StageOutput:
    """Write the clip's manual-track task and its answer's ``manual_tracks`` (module docstring);
    paused until a label answers the task."""
    split = clip_split(clip_inputs(wh, clip)[2])
    if split not in cfg.splits:
        empty = _empty(wh, clip)
        why = f"split {split!r} is not one of [manual_tracks] splits ({', '.join(cfg.splits) or 'none'})"
        return StageOutput(0, table_digest(empty), f"{why}: no manual-track task{withdraw_task(wh, clip, KIND, why)}")
    frames = wh.read("frames", [clip], columns=["timestamp_us", "frame_index", "image_path"]).sort_by("timestamp_us").to_pylist()
    if not frames:
        empty = _empty(wh, clip)
        return StageOutput(0, table_digest(empty), f"no frames: no manual-track task{withdraw_task(wh, clip, KIND, 'no frames')}")
    keyframes = [frames[i] for i in regular_keyframes([f["timestamp_us"] for f in frames], cfg.keyframes)]
    stamps = {f["timestamp_us"] for f in keyframes}
    existing = tuple(ExistingTrack(track_id=t.track_id, label=t.label,
                                   boxes=tuple(TimedBox(timestamp_us=b.timestamp_us, box=b.box)
                                               for b in t.boxes if b.timestamp_us in stamps))
                     for t in clip_tracks(wh, clip).values() if not t.manual)
    classes = task_classes(wh, detector_labels)
    task_id = new_task_id(KIND, clip, digest(*map(str, sorted(stamps))), digest(*classes),
                          digest(json.dumps([to_json(e) for e in existing], sort_keys=True)))
    answered = task_id in answered_tasks(wh, KIND, clip)
    previous, not_objects = previous_answer(wh, clip, task_id, answered)
    task = ManualTrackTask(task_id=task_id, clip=clip, created_at=utc_now().isoformat(), image_size=image_size(wh, clip),
                           instructions=INSTRUCTIONS[KIND],
                           keyframes=tuple(KeyframeView(timestamp_us=f["timestamp_us"], frame_index=f["frame_index"],
                                                        image_path=f["image_path"]) for f in keyframes),
                           existing_tracks=existing, classes=classes, previous=previous, previous_not_objects=not_objects)
    path = wh.relative(write_task_once(wh, task))
    if not answered:
        _empty(wh, clip)
        return task_output(0, digest("manual_tracks", task_id, "unanswered"), f"{len(existing)} automatic tracks shown",
                           KIND, path, len(keyframes), len(keyframes), "key-frames")
    table = manual_track_table(wh, embed_cfg, clip, task_id, current_answers(wh, KIND, [clip], task_id).to_pylist())
    written = wh.write("manual_tracks", clip, table)
    objects = len(set(table.column("track_id").to_pylist()))
    summary = f"{objects} manual tracks ({written} boxes) drawn" if objects else "nothing missing: no manual track"
    return StageOutput(written, table_digest(table), f"{summary} in task {task_id}")


def _run(ctx: StageContext) -> StageOutput:
    return manual_tracks_stage(ctx.wh, ctx.cfg, ctx.config.embed, detector_labels(ctx.config.detect), ctx.unit, ctx.run_id)


STAGE = StageDef(
    name="manual_tracks", section="manual_tracks", scope="clip", upstream=("ingest", "frames", "tracking"), tables=("manual_tracks", "label_tasks"),
    description="human task (3.1): on val/test clips people draw the objects the tracks missed; pauses until answered",
    extra_sections=("embed",), run=_run, config_inputs=label_map_inputs, clip_inputs=manual_track_inputs,
)
