"""Thin Prefect task wrappers around the stage functions (the logic lives in the stage modules).

Caching: a task's cache key is its source (``TASK_SOURCE``) plus its inputs, where an upstream
:class:`StageRun` counts only by its ``output_hash`` and the stage's code digest is an input. So
an unchanged rerun does no work, a config change reruns the stages whose section changed, and a
stage downstream of a rerun stage reruns only if that stage's output changed. Results persist
under ``<warehouse>/_prefect/results`` (see :mod:`flows.runtime`).
"""

from __future__ import annotations

from typing import Any

from prefect import task
from prefect.cache_policies import TASK_SOURCE, CacheKeyFnPolicy
from prefect.utilities.hashing import hash_objects

from cadestate.config import FramesConfig, IngestConfig, section_hash
from tasks.frames import extract_frames
from tasks.ingest import ClipSource, ingest_clip, ingest_inputs_hash
from tasks.registry import upstream_inputs_hash
from tasks.stage import StageRun, run_stage
from warehouse import Warehouse

NOT_IN_KEY = ("source", "show_progress")
"""Parameters that do not change a task's result (paths of identical inputs, display)."""


def _cache_key(context: Any, parameters: dict[str, Any]) -> str | None:
    key = {k: (v.output_hash if isinstance(v, StageRun) else v) for k, v in parameters.items() if k not in NOT_IN_KEY}
    return hash_objects(key)


CACHE_POLICY = TASK_SOURCE + CacheKeyFnPolicy(cache_key_fn=_cache_key)


@task(name="ingest", cache_policy=CACHE_POLICY, persist_result=True)
def ingest_task(root: str, clip: str, source: ClipSource, cfg: IngestConfig, video_sha256: str,
                cameras_sha256: str, code_hash: str) -> StageRun:
    wh = Warehouse(root)
    return run_stage(
        wh, clip, "ingest", config_hash=section_hash("ingest", cfg), code_hash=code_hash,
        inputs_hash=ingest_inputs_hash(clip, video_sha256, cameras_sha256),
        body=lambda run_id: ingest_clip(wh, cfg, source, video_sha256, cameras_sha256, run_id),
    )


@task(name="frames", cache_policy=CACHE_POLICY, persist_result=True)
def frames_task(root: str, clip: str, cfg: FramesConfig, ingest: StageRun, code_hash: str,
                show_progress: bool = True) -> StageRun:
    wh = Warehouse(root)
    return run_stage(
        wh, clip, "frames", config_hash=section_hash("frames", cfg), code_hash=code_hash,
        inputs_hash=upstream_inputs_hash([ingest.output_hash]),
        body=lambda run_id: extract_frames(wh, cfg, clip, run_id, show_progress),
    )


STAGE_TASKS = {"ingest": ingest_task, "frames": frames_task}
"""One task per stage of :data:`tasks.registry.STAGES`, in pipeline order (a test checks it)."""
