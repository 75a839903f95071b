"""The stages of the pipeline, in order: what each reads (upstream stages) and writes (tables).

A stage's name is also its config section and its ``runs.stage`` value. ``modules`` are the
source files of its logic; their digest is the stage's ``code_hash``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

from cadestate.lineage import code_digest, digest


@dataclass(frozen=True)
class StageDef:
    name: str
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
        StageDef("ingest", (), ("clips",), ("tasks.ingest", "tasks.cameras", "tasks.video"),
                 "validate the video and camera file, keep them, register the clip"),
        StageDef("frames", ("ingest",), ("frames",), ("tasks.frames", "tasks.cameras", "tasks.video"),
                 "extract the frame at every camera timestamp"),
    )
}


def upstream_inputs_hash(output_hashes: list[str]) -> str:
    """``inputs_hash`` of a stage from its upstream stages' output hashes (in ``upstream`` order)."""
    return digest(*output_hashes)
