"""Flows over clips: ``annotate_clip`` for one clip, ``build_dataset`` for many (parallel on the task runner).

Per clip the clip stages of :data:`tasks.registry.STAGES` are chained: cameras -> ingest -> frames -> detect ->
embed -> tracking -> manual_tracks -> retrieval -> cad_selection -> correspondence_task, and
frames -> pose -> verification. A failing clip does not stop the others: each stage run is
reported as completed, cached (no work: unchanged inputs, config and code), failed, skipped (an upstream stage failed),
paused (a human task waits for labels; what is answered goes on) or waiting (not run: an upstream
human task has nothing answered yet). The flow ends Failed when any stage failed, else Completed,
named ``Paused`` with a message naming the waiting tasks when a human task waits.
"""

from __future__ import annotations

from pathlib import Path

from prefect import flow
from prefect.futures import PrefectFuture
from prefect.states import State

from cadestate.config import Config
from cadestate.lineage import file_sha256
from flows.reports import StageReport, finish
from flows.runtime import run_flow, run_tags
from tasks.video.ingest import ClipSource
from tasks.retrieval.label_similarity import detector_labels
from tasks.prefect_tasks import (cad_selection_task, cameras_task, correspondence_task_task, detect_task, embed_task, frames_task,
                                 ingest_task, manual_tracks_task, pose_task, retrieval_task, tracking_task,
                                 verification_task)
from tasks.registry import STAGES, clip_inputs, extra_inputs
from tasks.stage import settle_interrupted
from warehouse import Warehouse


def _submit_clip(root: str, source: ClipSource, config: Config, show_progress: bool) -> list[tuple[str, PrefectFuture]]:
    """Submit the stage tasks of one clip, each fed by its upstream's future (runs of it that a killed
    process left unrecorded are recorded as interrupted first)."""
    settle_interrupted(Warehouse(root), source.clip)
    video_sha = file_sha256(source.video)
    cameras_sha = file_sha256(source.cameras) if source.cameras is not None else None
    cameras = cameras_task.submit(root, source.clip, source, config.cameras, video_sha, cameras_sha, source.intrinsics,
                                  STAGES["cameras"].code_hash)
    ingest = ingest_task.submit(root, source.clip, source, config.ingest, video_sha, cameras, source.split,
                                source.time_offset_us, STAGES["ingest"].code_hash)
    frames = frames_task.submit(root, source.clip, config.frames, ingest, STAGES["frames"].code_hash, show_progress)
    wh = Warehouse(root)

    def more(stage: str) -> list[str]:  # what the stage reads besides upstream outputs: as `cadestate status` sees it
        return extra_inputs(stage, config) + clip_inputs(stage, wh, source.clip)

    detect = detect_task.submit(root, source.clip, config.detect, frames, more("detect"), STAGES["detect"].code_hash,
                                show_progress)
    embed = embed_task.submit(root, source.clip, config.embed, detect, STAGES["embed"].code_hash, show_progress)
    tracking = tracking_task.submit(root, source.clip, config.tracking, frames, detect, embed, STAGES["tracking"].code_hash)
    manual = manual_tracks_task.submit(root, source.clip, config.manual_tracks, config.embed, detector_labels(config.detect),
                                       ingest, frames, tracking, more("manual_tracks"), STAGES["manual_tracks"].code_hash)
    retrieval = retrieval_task.submit(root, source.clip, config.retrieval, tracking, manual, more("retrieval"),
                                      STAGES["retrieval"].code_hash)
    selection = cad_selection_task.submit(root, source.clip, config.cad_selection, retrieval, more("cad_selection"),
                                          STAGES["cad_selection"].code_hash)
    clicks = correspondence_task_task.submit(root, source.clip, config.correspondence_task, selection,
                                             more("correspondence_task"), STAGES["correspondence_task"].code_hash)
    pose = pose_task.submit(root, source.clip, config.pose, frames, more("pose"), STAGES["pose"].code_hash)
    verify = verification_task.submit(root, source.clip, config.verification, pose, more("verification"),
                                      STAGES["verification"].code_hash)
    return [("cameras", cameras), ("ingest", ingest), ("frames", frames), ("detect", detect), ("embed", embed), ("tracking", tracking),
            ("manual_tracks", manual), ("retrieval", retrieval), ("cad_selection", selection),
            ("correspondence_task", clicks), ("pose", pose), ("verification", verify)]


def _run(root: str, sources: list[ClipSource], config: Config, show_progress: bool) -> State:
    submitted: list[tuple[str, str, PrefectFuture]] = []
    reports: list[StageReport] = []
    for source in sources:
        try:
            submitted += [(source.clip, stage, fut) for stage, fut in _submit_clip(root, source, config, show_progress)]
        except OSError as e:  # unreadable input files: report the clip, go on with the others
            reports.append(StageReport(source.clip, "ingest", "failed", message=str(e)))
    return finish(submitted, reports, f"{len(sources)} clip(s)")


@flow(name="annotate_clip", log_prints=True)
def annotate_clip(root: str, source: ClipSource, config: Config, show_progress: bool = True) -> State:
    """Run every stage of one clip."""
    return _run(root, [source], config, show_progress)


@flow(name="build_dataset", log_prints=True)
def build_dataset(root: str, sources: list[ClipSource], config: Config, show_progress: bool = True) -> State:
    """Run every stage of many clips; clips run in parallel on the configured task runner."""
    return _run(root, sources, config, show_progress)


def run_clips(sources: list[ClipSource], config: Config, show_progress: bool = True) -> list[StageReport]:
    """Run the pipeline on ``sources`` with ``config`` and return one report per stage run."""
    root = str(Path(config.warehouse.root).expanduser().resolve())
    tags = run_tags(Path(root), {s.clip: s.split for s in sources})
    if len(sources) == 1:
        return run_flow(annotate_clip, config, root, sources[0], config, show_progress,
                        run_name=f"annotate_clip/{sources[0].clip}", tags=tags)
    return run_flow(build_dataset, config, root, sources, config, show_progress,
                    run_name=f"build_dataset/{len(sources)} clips", tags=tags)
