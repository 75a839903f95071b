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

from cadestate.config import CadIngestConfig, CadViewsConfig, FramesConfig, IngestConfig, section_hash
from tasks.cad_ingest import ingest_library
from tasks.cad_sources import CadItem
from tasks.cad_views import render_library
from tasks.frames import extract_frames
from tasks.ingest import ClipSource, ingest_clip, ingest_inputs_hash
from tasks.registry import upstream_inputs_hash
from tasks.stage import StageRun, run_stage
from warehouse import Warehouse

NOT_IN_KEY = ("source", "items", "show_progress")
"""Parameters that do not change a task's result given the others (paths of inputs whose content
digest is a parameter too, display)."""


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


@task(name="cad_ingest", cache_policy=CACHE_POLICY, persist_result=True)
def cad_ingest_task(root: str, library: str, items: list[CadItem], items_digest: str, cfg: CadIngestConfig,
                    code_hash: str, show_progress: bool = True) -> StageRun:
    wh = Warehouse(root)
    return run_stage(
        wh, library, "cad_ingest", config_hash=section_hash("cad_ingest", cfg), code_hash=code_hash,
        inputs_hash=items_digest, body=lambda run_id: ingest_library(wh, cfg, library, items, run_id, show_progress),
    )


@task(name="cad_views", cache_policy=CACHE_POLICY, persist_result=True)
def cad_views_task(root: str, library: str, cfg: CadViewsConfig, cad_ingest: StageRun, code_hash: str,
                   show_progress: bool = True) -> StageRun:
    wh = Warehouse(root)
    return run_stage(
        wh, library, "cad_views", config_hash=section_hash("cad_views", cfg), code_hash=code_hash,
        inputs_hash=upstream_inputs_hash([cad_ingest.output_hash]),
        body=lambda run_id: render_library(wh, cfg, library, run_id, show_progress),
    )


STAGE_TASKS = {"ingest": ingest_task, "frames": frames_task, "cad_ingest": cad_ingest_task, "cad_views": cad_views_task}
"""One task per stage of :data:`tasks.registry.STAGES`, in pipeline order (a test checks it)."""
