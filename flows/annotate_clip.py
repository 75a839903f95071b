"""Flows: ``annotate_clip`` for one clip, ``build_dataset`` for many (parallel on the task runner).

Per clip the stages of :data:`tasks.registry.STAGES` are chained: ingest -> frames (later stages
append here). A failing clip does not stop the others: each stage run is reported as completed,
cached (no work: unchanged inputs, config and code), failed, or skipped (an upstream stage failed),
and the flow ends Failed when any stage failed.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from prefect import flow
from prefect.futures import PrefectFuture, wait
from prefect.states import Completed, Failed, State

from cadestate.config import Config
from cadestate.lineage import file_sha256
from flows.runtime import prepare_prefect_environment, task_runner, warehouse_results
from tasks.ingest import ClipSource
from tasks.prefect_tasks import frames_task, ingest_task
from tasks.registry import STAGES
from tasks.stage import StageRun


@dataclass(frozen=True)
class StageReport:
    """Outcome of one stage for one clip in a flow run."""

    clip: str
    stage: str
    state: str  # completed | cached | failed | skipped
    rows_written: int = 0
    duration_s: float = 0.0
    message: str = ""


def _submit_clip(root: str, source: ClipSource, config: Config, show_progress: bool) -> list[tuple[str, PrefectFuture]]:
    """Submit the stage tasks of one clip, each fed by its upstream's future."""
    video_sha, cameras_sha = file_sha256(source.video), file_sha256(source.cameras)
    ingest = ingest_task.submit(root, source.clip, source, config.ingest, video_sha, cameras_sha, STAGES["ingest"].code_hash)
    frames = frames_task.submit(root, source.clip, config.frames, ingest, STAGES["frames"].code_hash, show_progress)
    return [("ingest", ingest), ("frames", frames)]


def _report(clip: str, stage: str, future: PrefectFuture) -> StageReport:
    state = future.state
    if state.is_completed():
        run: StageRun = state.result()
        kind = "cached" if state.name == "Cached" else "completed"
        return StageReport(clip, stage, kind, run.rows_written if kind == "completed" else 0,
                           run.duration_s if kind == "completed" else 0.0)
    if state.is_failed():
        error = state.result(raise_on_failure=False)
        if "upstream" not in str(state.message or "").lower():
            return StageReport(clip, stage, "failed", message=str(error))
    return StageReport(clip, stage, "skipped", message="an upstream stage failed")


def _run(root: str, sources: list[ClipSource], config: Config, show_progress: bool) -> State:
    submitted: list[tuple[str, str, PrefectFuture]] = []
    reports: list[StageReport] = []
    for source in sources:
        try:
            submitted += [(source.clip, stage, fut) for stage, fut in _submit_clip(root, source, config, show_progress)]
        except OSError as e:  # unreadable input files: report the clip, go on with the others
            reports.append(StageReport(source.clip, "ingest", "failed", message=str(e)))
    wait([fut for _, _, fut in submitted])
    reports += [_report(clip, stage, fut) for clip, stage, fut in submitted]
    failed = [r for r in reports if r.state == "failed"]
    done = f"{len(sources)} clip(s), {len(reports)} stage runs, {len(failed)} failed"
    return Failed(message=done, data=reports) if failed else Completed(message=done, data=reports)


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
    root = Path(config.warehouse.root).expanduser().resolve()
    prepare_prefect_environment(root)
    runner = task_runner(config.prefect)
    with warehouse_results(root):
        if len(sources) == 1:
            state = annotate_clip.with_options(task_runner=runner)(str(root), sources[0], config, show_progress, return_state=True)
        else:
            state = build_dataset.with_options(task_runner=runner)(str(root), sources, config, show_progress, return_state=True)
    return state.result(raise_on_failure=False)
