"""Flow ``build_cad_library``: ingest a CAD source, one library at a time (in parallel on the task runner).

Per library the library stages of :data:`tasks.registry.STAGES`, chained as their ``upstream`` says:
cad_ingest (canonical meshes, symmetry, surface samples) -> cad_views (renders) -> cad_embed (view
descriptors and their whitening); cad_ingest -> label_similarity (detector labels x the library's
classes).
Reports like the clip flows: completed, cached, failed or skipped per stage and library.
"""

from __future__ import annotations

from itertools import groupby
from pathlib import Path

from prefect import flow
from prefect.states import State

from cadestate.config import Config
from flows.reports import finish
from flows.runtime import run_flow
from flows.stage_chain import submit_unit
from tasks.cad.sources import CadItem
from tasks.stage_chain import StageReport


@flow(name="build_cad_library", log_prints=True)
def build_cad_library(root: str, items: list[CadItem], config: Config, show_progress: bool = True) -> State:
    """Ingest and render every library of ``items``."""
    by_library = groupby(sorted(items, key=lambda i: i.library), key=lambda i: i.library)
    submitted = [(library, submit_unit(root, "library", library, config, list(group), show_progress))
                 for library, group in by_library]
    return finish(submitted, f"{len({i.library for i in items})} CAD librar(y/ies)")


def run_cad_library(items: list[CadItem], config: Config, show_progress: bool = True) -> list[StageReport]:
    """Build the CAD library from ``items`` with ``config``; one report per stage run."""
    root = str(Path(config.warehouse.root).expanduser().resolve())
    libraries = sorted({i.library for i in items})
    return run_flow(build_cad_library, config, root, items, config, show_progress,
                    run_name=f"build_cad_library/{', '.join(libraries)}", tags=[f"library:{lib}" for lib in libraries])
