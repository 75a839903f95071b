"""The stages of the pipeline, in order: what each reads (upstream stages) and writes (tables).

A stage's name is also its config section and its ``runs.stage`` value. ``scope`` says what one
run of it covers: a clip, or a CAD library (its runs use the library name as ``runs.clip``).
``modules`` are the source files of its logic; their digest is the stage's ``code_hash``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Literal

from cadestate.lineage import code_digest, digest


@dataclass(frozen=True)
class StageDef:
    name: str
    scope: Literal["clip", "library"]
    upstream: tuple[str, ...]
    tables: tuple[str, ...]
    modules: tuple[str, ...]
    description: str

    @cached_property
    def code_hash(self) -> str:
        return code_digest(*self.modules)


STAGES: dict[str, StageDef] = {
    s.name: s
    for s in (
        StageDef("ingest", "clip", (), ("clips",), ("tasks.ingest", "tasks.cameras", "tasks.video"),
                 "validate the video and camera file, keep them, register the clip"),
        StageDef("frames", "clip", ("ingest",), ("frames",), ("tasks.frames", "tasks.cameras", "tasks.video"),
                 "extract the frame at every camera timestamp"),
        StageDef("cad_ingest", "library", (), ("cad_models", "cad_samples", "cad_issues"),
                 ("tasks.cad_ingest", "tasks.cad_sources", "tasks.cad_classes", "tasks.cad_symmetry"),
                 "canonicalise a CAD library, detect symmetries, sample surfaces"),
        StageDef("cad_views", "library", ("cad_ingest",), ("cad_views",), ("tasks.cad_views", "cadestate.render"),
                 "render every CAD model from random viewpoints"),
    )
}


def stages_of(scope: str) -> list[StageDef]:
    """The stages of one scope, in pipeline order."""
    return [s for s in STAGES.values() if s.scope == scope]


def upstream_inputs_hash(output_hashes: list[str]) -> str:
    """``inputs_hash`` of a stage from its upstream stages' output hashes (in ``upstream`` order)."""
    return digest(*output_hashes)
