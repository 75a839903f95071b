"""The stages of the pipeline, in order: what each reads (upstream stages) and writes (tables).

A stage's name is also its config section and its ``runs.stage`` value. ``scope`` says what one
run of it covers: a clip, or a CAD library (its runs use the library name as ``runs.clip``).
``modules`` are the source files of its logic; their digest is the stage's ``code_hash``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Literal

from cadestate.config import section_hash
from cadestate.lineage import code_digest, digest


@dataclass(frozen=True)
class StageDef:
    name: str
    scope: Literal["clip", "library"]
    upstream: tuple[str, ...]
    tables: tuple[str, ...]
    modules: tuple[str, ...]
    description: str
    extra_sections: tuple[str, ...] = ()  # config sections it reads besides its own


    @cached_property
    def code_hash(self) -> str:
        return code_digest(*self.modules)


STAGES: dict[str, StageDef] = {
    s.name: s
    for s in (
        StageDef("cameras", "clip", (), (), ("tasks.video.cameras", "tasks.video.sfm", "tasks.video.camera_file", "tasks.video.decode"),
                 "the clip's camera file: the given one, else structure from motion on the video (pycolmap)"),
        StageDef("ingest", "clip", ("cameras",), ("clips",), ("tasks.video.ingest", "tasks.video.camera_file", "tasks.video.decode", "tasks.video.world_up"),
                 "validate the video and camera file, find the world's up, keep them, register the clip"),
        StageDef("frames", "clip", ("ingest",), ("frames",), ("tasks.video.frames", "tasks.video.camera_file", "tasks.video.decode"),
                 "extract the frame at every camera timestamp"),
        StageDef("detect", "clip", ("frames",), ("detections",), ("tasks.detection.detect", "tasks.detection.detectors", "tasks.detection.models.nanodet"),
                 "detect objects in every frame (ONNX detector)"),
        StageDef("embed", "clip", ("detect",), ("embeddings",), ("tasks.detection.embed", "tasks.detection.models.embedder", "tasks.detection.detectors", "tasks.detection.models.nanodet"),
                 "one appearance descriptor per detection"),
        StageDef("tracking", "clip", ("frames", "detect", "embed"), ("tracks", "track_detections", "track_appearance"),
                 ("tasks.tracking.tracking", "tasks.tracking.affinity", "tasks.tracking.partition", "tasks.tracking.calibration"),
                 "associate detections into tracks by clique partitioning"),
        StageDef("manual_tracks", "clip", ("ingest", "frames", "tracking"), ("manual_tracks", "label_tasks"),
                 ("tasks.human.manual_tracks", "tasks.retrieval.label_similarity", "tasks.tracking.clip_tracks", "tasks.human.human_tasks", "tasks.video.ingest", "tasks.human.labels",
                  "tasks.tracking.relations",
                  "tasks.human.label_format", "tasks.human.label_ingest", "tasks.detection.embed", "tasks.detection.models.embedder", "tasks.detection.detectors", "tasks.detection.models.nanodet"),
                 "human task (3.1): on val/test clips people draw the objects the tracks missed; pauses until answered",
                 extra_sections=("embed",)),
        StageDef("retrieval", "clip", ("tracking", "manual_tracks"), ("cad_candidates",),
                 ("tasks.retrieval.retrieval", "tasks.retrieval.whitening", "tasks.tracking.clip_tracks"),
                 "top CAD models of every track, automatic and manual (appearance x class-label similarity)"),
        StageDef("cad_selection", "clip", ("retrieval",), ("label_tasks",),
                 ("tasks.human.human_tasks", "tasks.tracking.clip_tracks", "tasks.human.labels", "tasks.human.label_format", "tasks.human.label_ingest",
                  "tasks.tracking.relations"),
                 "human task (3.2): people choose each track's CAD model among its candidates; pauses until answered"),
        StageDef("correspondence_task", "clip", ("cad_selection",), ("label_tasks",),
                 ("tasks.human.human_tasks", "tasks.tracking.clip_tracks", "tasks.human.labels", "tasks.human.label_format", "tasks.human.label_ingest",
                  "tasks.tracking.relations"),
                 "human task (3.3): people click 3D<->2D correspondences on the chosen models; pauses until answered"),
        StageDef("pose", "clip", ("frames",), ("poses",),
                 ("tasks.pose.pose", "tasks.pose.solver", "tasks.pose.initial", "tasks.pose.checks", "tasks.pose.lm",
                  "tasks.pose.batch", "tasks.pose.support", "tasks.pose.inputs", "tasks.human.human_tasks", "tasks.tracking.relations"),
                 "9-DoF pose of every annotated track from its 3D<->2D correspondences"),
        StageDef("verification", "clip", ("pose",), ("label_tasks", "verified_poses"),
                 ("tasks.human.human_tasks", "tasks.tracking.clip_tracks", "tasks.human.labels", "tasks.human.label_format", "tasks.human.label_ingest",
                  "tasks.tracking.relations", "cadestate.render"),
                 "human task (3.5): people accept or reject each solved pose over its key-frames; pauses until answered"),
        StageDef("cad_ingest", "library", (), ("cad_models", "cad_samples", "cad_issues"),
                 ("tasks.cad.ingest", "tasks.cad.sources", "tasks.cad.classes", "tasks.cad.symmetry"),
                 "canonicalise a CAD library, detect symmetries, sample surfaces"),
        StageDef("cad_views", "library", ("cad_ingest",), ("cad_views",), ("tasks.cad.views", "cadestate.render"),
                 "render every CAD model from random viewpoints"),
        StageDef("cad_embed", "library", ("cad_views",), ("cad_embeddings", "embedding_whitening"),
                 ("tasks.cad.embed", "tasks.detection.embed", "tasks.retrieval.whitening", "tasks.detection.models.embedder", "tasks.detection.detectors", "tasks.detection.models.nanodet"),
                 "embed every CAD view, fit the descriptor whitening", extra_sections=("embed",)),
        StageDef("label_similarity", "library", ("cad_ingest",), ("label_similarity",), ("tasks.retrieval.label_similarity",),
                 "similarity of every detector label and CAD class (sentence encoder)"),
    )
}


def stages_of(scope: str) -> list[StageDef]:
    """The stages of one scope, in pipeline order."""
    return [s for s in STAGES.values() if s.scope == scope]


def config_hash(stage: str, sections: Mapping[str, Any]) -> str:
    """``runs.config_hash`` of ``stage``: its section's digest, combined with the digests of its
    ``extra_sections``; ``sections`` maps section names to their dataclasses."""
    own = section_hash(stage, sections[stage])
    extra = STAGES[stage].extra_sections
    return digest(own, *(section_hash(n, sections[n]) for n in extra)) if extra else own


def extra_inputs(stage: str, config: Any) -> list[str]:
    """Digests of what ``stage`` reads besides its upstream stages' outputs (``config``: a
    :class:`cadestate.config.Config`): the detector's model file for ``detect``, the detector's
    label map for ``label_similarity`` and ``manual_tracks`` (its classes without a CAD library)."""
    if stage == "detect":
        from tasks.detection.detect import model_fingerprint

        return [model_fingerprint(config.detect)]
    if stage in ("label_similarity", "manual_tracks"):
        from tasks.retrieval.label_similarity import labels_digest

        return [labels_digest(config.detect)]
    return []


HUMAN_TASK_KINDS = {"manual_tracks": "manual_track", "cad_selection": "cad_selection",
                    "correspondence_task": "correspondences", "verification": "verification"}
"""Stages that wait for people -> the label kind that answers them."""


def clip_inputs(stage: str, wh: Any, clip: str) -> list[str]:
    """Digests of the warehouse data of one clip that ``stage`` reads besides its upstream stages'
    outputs: the clip's ``correspondences`` (human labels, of the tracks whose chosen model they
    use) and the ``cad_models`` facts (class, symmetry, bounding box) of their models for ``pose``, the CAD libraries' descriptors and label
    similarities for ``retrieval``, the detector labels they score for ``manual_tracks`` (its
    classes); for the human-task stages, the answers in force of their label kind (ingesting labels
    makes them stale: a rerun resumes them) and, after ``manual_tracks``, the tracks its answer
    leaves out (:func:`tasks.tracking.relations.left_out_digest`: said to be no object, or another track)."""
    if stage == "ingest":
        from tasks.video.ingest import registered_inputs_digest

        return [registered_inputs_digest(wh, clip)]
    if stage == "retrieval":
        from tasks.retrieval.retrieval import library_digest

        return [library_digest(wh)]
    if stage in HUMAN_TASK_KINDS:
        from tasks.human.label_ingest import answers_digest

        answers = [answers_digest(wh, HUMAN_TASK_KINDS[stage], clip)]
        if stage == "manual_tracks":
            from tasks.retrieval.label_similarity import similarity_labels

            return [digest(*similarity_labels(wh)), *answers]
        from tasks.tracking.relations import left_out_digest

        return [*answers, left_out_digest(wh, clip)]
    if stage == "pose":
        from tasks.pose.inputs import input_digests

        return input_digests(wh, clip)
    return []


def upstream_inputs_hash(output_hashes: list[str]) -> str:
    """``inputs_hash`` of a stage from its upstream stages' output hashes (in ``upstream`` order)."""
    return digest(*output_hashes)
