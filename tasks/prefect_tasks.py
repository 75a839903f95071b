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

from cadestate.config import (CadEmbedConfig, CadIngestConfig, CadSelectionConfig, CadViewsConfig, CamerasConfig, CorrespondenceTaskConfig,
                              DetectConfig, EmbedConfig, FramesConfig, IngestConfig, LabelSimilarityConfig,
                              ManualTracksConfig, PoseConfig, RetrievalConfig, TrackingConfig, VerificationConfig,
                              section_hash)
from cadestate.lineage import digest, file_sha256
from tasks.cad.embed import embed_library
from tasks.cad.ingest import ingest_library
from tasks.cad.sources import CadItem
from tasks.cad.views import render_library
from tasks.video.cameras import cameras_stage
from tasks.detection.detect import detect_clip
from tasks.detection.embed import embed_clip
from tasks.video.frames import extract_frames
from tasks.video.ingest import ClipSource, cameras_file, ingest_clip, ingest_source_digest
from tasks.retrieval.label_similarity import label_similarity
from tasks.human.manual_tracks import manual_tracks_stage
from tasks.pose.pose import solve_clip
from tasks.registry import config_hash, upstream_inputs_hash
from tasks.retrieval.retrieval import retrieve_clip
from tasks.human.human_tasks import cad_selection_stage, correspondence_task_stage, verification_stage
from tasks.stage import StageRun, run_stage, waiting_run
from tasks.tracking.tracking import track_clip
from warehouse import Warehouse

NOT_IN_KEY = ("source", "items", "show_progress")
"""Parameters that do not change a task's result given the others (paths of inputs whose content
digest is a parameter too, display)."""


def _cache_key(context: Any, parameters: dict[str, Any]) -> str | None:
    key = {k: (v.output_hash if isinstance(v, StageRun) else v) for k, v in parameters.items() if k not in NOT_IN_KEY}
    return hash_objects(key)


CACHE_POLICY = TASK_SOURCE + CacheKeyFnPolicy(cache_key_fn=_cache_key)


@task(name="cameras", cache_policy=CACHE_POLICY, persist_result=True)
def cameras_task(root: str, clip: str, source: ClipSource, cfg: CamerasConfig, video_sha256: str,
                 cameras_sha256: str | None, intrinsics: tuple[float, ...] | None, code_hash: str) -> StageRun:
    """``cameras_sha256``: the given camera file's (None: SfM); ``intrinsics`` is ``source.intrinsics``,
    given apart because ``source`` is not in the cache key."""
    wh = Warehouse(root)
    return run_stage(
        wh, clip, "cameras", config_hash=section_hash("cameras", cfg), code_hash=code_hash,
        inputs_hash=digest("cameras-inputs", video_sha256, cameras_sha256 or "sfm", str(intrinsics)),
        body=lambda run_id: cameras_stage(wh, cfg, source, cameras_sha256, run_id),
    )


@task(name="ingest", cache_policy=CACHE_POLICY, persist_result=True)
def ingest_task(root: str, clip: str, source: ClipSource, cfg: IngestConfig, video_sha256: str,
                cameras: StageRun, split: str, time_offset_us: int, code_hash: str) -> StageRun:
    """``split`` and ``time_offset_us`` are ``source``'s, given apart because ``source`` is not in the cache key."""
    wh = Warehouse(root)
    return run_stage(
        wh, clip, "ingest", config_hash=section_hash("ingest", cfg), code_hash=code_hash,
        inputs_hash=upstream_inputs_hash([cameras.output_hash, ingest_source_digest(video_sha256, split, time_offset_us)]),
        body=lambda run_id: ingest_clip(wh, cfg, source, video_sha256, file_sha256(cameras_file(wh, source)), run_id),
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


@task(name="detect", cache_policy=CACHE_POLICY, persist_result=True)
def detect_task(root: str, clip: str, cfg: DetectConfig, frames: StageRun, more_inputs: list[str], code_hash: str,
                show_progress: bool = True) -> StageRun:
    wh = Warehouse(root)
    return run_stage(
        wh, clip, "detect", config_hash=section_hash("detect", cfg), code_hash=code_hash,
        inputs_hash=upstream_inputs_hash([frames.output_hash, *more_inputs]),
        body=lambda run_id: detect_clip(wh, cfg, clip, run_id, show_progress),
    )


@task(name="embed", cache_policy=CACHE_POLICY, persist_result=True)
def embed_task(root: str, clip: str, cfg: EmbedConfig, detect: StageRun, code_hash: str,
               show_progress: bool = True) -> StageRun:
    wh = Warehouse(root)
    return run_stage(
        wh, clip, "embed", config_hash=section_hash("embed", cfg), code_hash=code_hash,
        inputs_hash=upstream_inputs_hash([detect.output_hash]),
        body=lambda run_id: embed_clip(wh, cfg, clip, run_id, show_progress),
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


@task(name="cad_embed", cache_policy=CACHE_POLICY, persist_result=True)
def cad_embed_task(root: str, library: str, embed_cfg: EmbedConfig, cfg: CadEmbedConfig, cad_views: StageRun,
                   code_hash: str, show_progress: bool = True) -> StageRun:
    wh = Warehouse(root)
    return run_stage(
        wh, library, "cad_embed", config_hash=config_hash("cad_embed", {"cad_embed": cfg, "embed": embed_cfg}),
        code_hash=code_hash, inputs_hash=upstream_inputs_hash([cad_views.output_hash]),
        body=lambda run_id: embed_library(wh, embed_cfg, cfg, library, run_id, show_progress),
    )


@task(name="tracking", cache_policy=CACHE_POLICY, persist_result=True)
def tracking_task(root: str, clip: str, cfg: TrackingConfig, frames: StageRun, detect: StageRun, embed: StageRun,
                  code_hash: str) -> StageRun:
    wh = Warehouse(root)
    return run_stage(
        wh, clip, "tracking", config_hash=section_hash("tracking", cfg), code_hash=code_hash,
        inputs_hash=upstream_inputs_hash([frames.output_hash, detect.output_hash, embed.output_hash]),
        body=lambda run_id: track_clip(wh, cfg, clip, run_id),
    )


@task(name="manual_tracks", cache_policy=CACHE_POLICY, persist_result=True)
def manual_tracks_task(root: str, clip: str, cfg: ManualTracksConfig, embed_cfg: EmbedConfig,
                       detector_labels: tuple[str, ...], ingest: StageRun, frames: StageRun, tracking: StageRun,
                       more_inputs: list[str], code_hash: str) -> StageRun:
    wh = Warehouse(root)
    return run_stage(
        wh, clip, "manual_tracks", config_hash=config_hash("manual_tracks", {"manual_tracks": cfg, "embed": embed_cfg}),
        code_hash=code_hash,
        inputs_hash=upstream_inputs_hash([ingest.output_hash, frames.output_hash, tracking.output_hash, *more_inputs]),
        body=lambda run_id: manual_tracks_stage(wh, cfg, embed_cfg, detector_labels, clip, run_id),
    )


@task(name="retrieval", cache_policy=CACHE_POLICY, persist_result=True)
def retrieval_task(root: str, clip: str, cfg: RetrievalConfig, tracking: StageRun, manual_tracks: StageRun,
                   more_inputs: list[str], code_hash: str) -> StageRun:
    """``waiting`` (not run) while the manual-track task waits with nothing answered."""
    waiting = waiting_run(clip, "retrieval", [manual_tracks])
    if waiting is not None:
        return waiting
    wh = Warehouse(root)
    return run_stage(
        wh, clip, "retrieval", config_hash=section_hash("retrieval", cfg), code_hash=code_hash,
        inputs_hash=upstream_inputs_hash([tracking.output_hash, manual_tracks.output_hash, *more_inputs]),
        body=lambda run_id: retrieve_clip(wh, cfg, clip, run_id),
    )


@task(name="label_similarity", cache_policy=CACHE_POLICY, persist_result=True)
def label_similarity_task(root: str, library: str, cfg: LabelSimilarityConfig, detect_cfg: DetectConfig,
                          cad_ingest: StageRun, more_inputs: list[str], code_hash: str) -> StageRun:
    wh = Warehouse(root)
    return run_stage(
        wh, library, "label_similarity", config_hash=section_hash("label_similarity", cfg), code_hash=code_hash,
        inputs_hash=upstream_inputs_hash([cad_ingest.output_hash, *more_inputs]),
        body=lambda run_id: label_similarity(wh, cfg, detect_cfg, library, run_id),
    )


@task(name="pose", cache_policy=CACHE_POLICY, persist_result=True)
def pose_task(root: str, clip: str, cfg: PoseConfig, frames: StageRun, more_inputs: list[str],
              code_hash: str) -> StageRun:
    wh = Warehouse(root)
    return run_stage(
        wh, clip, "pose", config_hash=section_hash("pose", cfg), code_hash=code_hash,
        inputs_hash=upstream_inputs_hash([frames.output_hash, *more_inputs]),
        body=lambda run_id: solve_clip(wh, cfg, clip, run_id),
    )


def _human_task(root: str, clip: str, stage: str, cfg, upstream: StageRun, more_inputs: list[str], code_hash: str,
                body) -> StageRun:
    """A human-task stage: ``waiting`` (not run) while its upstream waits with nothing answered,
    else run (completed, or paused until its labels are in)."""
    waiting = waiting_run(clip, stage, [upstream])
    if waiting is not None:
        return waiting
    wh = Warehouse(root)
    return run_stage(
        wh, clip, stage, config_hash=section_hash(stage, cfg), code_hash=code_hash,
        inputs_hash=upstream_inputs_hash([upstream.output_hash, *more_inputs]),
        body=lambda run_id: body(wh, cfg, clip, run_id),
    )


@task(name="cad_selection", cache_policy=CACHE_POLICY, persist_result=True)
def cad_selection_task(root: str, clip: str, cfg: CadSelectionConfig, retrieval: StageRun, more_inputs: list[str],
                       code_hash: str) -> StageRun:
    return _human_task(root, clip, "cad_selection", cfg, retrieval, more_inputs, code_hash, cad_selection_stage)


@task(name="correspondence_task", cache_policy=CACHE_POLICY, persist_result=True)
def correspondence_task_task(root: str, clip: str, cfg: CorrespondenceTaskConfig, cad_selection: StageRun,
                             more_inputs: list[str], code_hash: str) -> StageRun:
    return _human_task(root, clip, "correspondence_task", cfg, cad_selection, more_inputs, code_hash,
                       correspondence_task_stage)


@task(name="verification", cache_policy=CACHE_POLICY, persist_result=True)
def verification_task(root: str, clip: str, cfg: VerificationConfig, pose: StageRun, more_inputs: list[str],
                      code_hash: str) -> StageRun:
    return _human_task(root, clip, "verification", cfg, pose, more_inputs, code_hash, verification_stage)


STAGE_TASKS = {"cameras": cameras_task, "ingest": ingest_task, "frames": frames_task, "detect": detect_task, "embed": embed_task,
               "tracking": tracking_task, "manual_tracks": manual_tracks_task, "retrieval": retrieval_task,
               "cad_selection": cad_selection_task, "correspondence_task": correspondence_task_task, "pose": pose_task, "verification": verification_task,
               "cad_ingest": cad_ingest_task, "cad_views": cad_views_task, "cad_embed": cad_embed_task,
               "label_similarity": label_similarity_task}
"""One task per stage of :data:`tasks.registry.STAGES`, in pipeline order (a test checks it)."""
