"""A unit's stages (a clip's, or a CAD library's) as one Prefect task: :func:`tasks.stage_chain.run_unit`.

One task per unit, not one per stage: Prefect's engine cost about 160 ms per task run (and a dozen
events on its API), more than most stages of a small clip take (issue 21: a 20-clip batch spent 3.5x
its stage work outside it). The stages of a unit still show one by one: in ``runs`` and ``cadestate
status``, in the flow's reports, and as lines of the task's log (at the level of Prefect's logging:
``--verbose`` shows them).
"""

from __future__ import annotations

from typing import Any

from prefect import get_run_logger, task
from prefect.cache_policies import NO_CACHE
from prefect.context import TagsContext
from prefect.futures import PrefectFuture

from cadestate.config import Config
from tasks.stage_chain import StageReport, run_unit


def submit_unit(root: str, scope: str, unit: str, config: Config, source: Any = None,
                show_progress: bool = True) -> PrefectFuture:
    """Submit :func:`unit_stages` for ``unit`` to the flow's task runner, untagged: the flow run
    carries the clip, split and library tags. A tagged task run first asks Prefect's API for
    concurrency slots of each tag, which took about 1.3 s per task on a busy 2-core machine."""
    with TagsContext(current_tags=set()):
        return unit_stages.submit(root, scope, unit, config, source, show_progress)


@task(name="stages", task_run_name="{scope}/{unit}", cache_policy=NO_CACHE, persist_result=False)
def unit_stages(root: str, scope: str, unit: str, config: Config, source: Any = None,
                show_progress: bool = True) -> list[StageReport]:
    """The Prefect task of one unit: :func:`run_unit`, logging each stage's outcome to the run's log."""
    return run_unit(root, scope, unit, config, source, show_progress, log=get_run_logger())
