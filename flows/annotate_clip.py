"""Flows over clips: ``annotate_clip`` for one clip, ``build_dataset`` for many (parallel on the task runner;
on Dask, one ``annotate_clip`` per clip on the workers: :mod:`flows.dask_clips`).

Per clip the clip stages of :data:`tasks.registry.STAGES` are chained as their ``upstream`` says
(``cadestate stages`` lists them), in one Prefect task per clip (:mod:`flows.stage_chain`, whose
cache is the ``runs`` table). A failing clip does not stop the others: each stage run is reported
as completed, cached (no work: unchanged inputs, config and code), failed, skipped (an upstream
stage failed), paused (a human task waits for labels; what is answered goes on) or waiting (not
run: an upstream human task has nothing answered yet). The flow ends Failed when any stage failed, else Completed,
named ``Paused`` with a message naming the waiting tasks when a human task waits.
"""

from __future__ import annotations

from pathlib import Path

from prefect import flow
from prefect.states import State

from cadestate.config import Config
from flows.reports import finish
from flows.runtime import run_flow, run_tags
from flows.stage_chain import submit_unit
from tasks.stage_chain import StageReport
from tasks.video.ingest import ClipSource


def _run(root: str, sources: list[ClipSource], config: Config, show_progress: bool) -> State:
    submitted = [(s.clip, submit_unit(root, "clip", s.clip, config, s, show_progress)) for s in sources]
    return finish(submitted, f"{len(sources)} clip(s)")


@flow(name="annotate_clip", log_prints=True)
def annotate_clip(root: str, source: ClipSource, config: Config, show_progress: bool = True) -> State:
    """Run every stage of one clip."""
    return _run(root, [source], config, show_progress)


@flow(name="build_dataset", log_prints=True)
def build_dataset(root: str, sources: list[ClipSource], config: Config, show_progress: bool = True) -> State:
    """Run every stage of many clips; clips run in parallel on the configured task runner."""
    return _run(root, sources, config, show_progress)


def run_clips(sources: list[ClipSource], config: Config, show_progress: bool = True) -> list[StageReport]:
    """Run the pipeline on ``sources`` with ``config`` and return one report per stage run. With
    ``[prefect] task_runner = "dask"`` each clip runs whole on a Dask worker (:mod:`flows.dask_clips`),
    and progress is a line per finished clip."""
    if config.prefect.task_runner == "dask":
        from flows.dask_clips import run_clips_on_dask

        return [r for outcome in run_clips_on_dask(sources, config, show_progress) for r in outcome.reports]
    root = str(Path(config.warehouse.root).expanduser().resolve())
    tags = run_tags(Path(root), {s.clip: s.split for s in sources})
    if len(sources) == 1:
        return run_flow(annotate_clip, config, root, sources[0], config, show_progress,
                        run_name=f"annotate_clip/{sources[0].clip}", tags=tags)
    return run_flow(build_dataset, config, root, sources, config, show_progress,
                    run_name=f"build_dataset/{len(sources)} clips", tags=tags)
