"""One Prefect task per stage of :data:`tasks.registry.STAGES`, generated from its declaration, and
the submission of a unit's (a clip's or a CAD library's) stages wired from the stage graph.

Caching: a task's cache key is its source (``TASK_SOURCE``) plus its inputs, where an upstream
:class:`StageRun` counts only by its ``output_hash``, the stage's code digest, config digest and
input digests are inputs, and the warehouse counts by its identity (:mod:`warehouse.identity`), not
its path. So an unchanged rerun does no work, a config change reruns the stages whose section
changed, a stage downstream of a rerun stage reruns only if that stage's output changed, a copied
or moved warehouse reruns nothing, and two warehouses never share a result. Results persist under
``<warehouse>/_prefect/results`` (see :mod:`flows.runtime`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from prefect import Task, task
from prefect.cache_policies import TASK_SOURCE, CacheKeyFnPolicy
from prefect.futures import PrefectFuture
from prefect.utilities.hashing import hash_objects

from cadestate.config import Config
from tasks.inputs_memo import InputsMemo
from tasks.registry import STAGES, config_hash, stages_of, upstream_inputs_hash
from tasks.stage import StageContext, StageRun, run_stage, settle_interrupted, waiting_run
from warehouse import Warehouse
from warehouse.identity import warehouse_id

NOT_IN_KEY = ("root", "config", "source", "show_progress")
"""Parameters that do not change a task's result given the others: the root (the warehouse counts
by its identity instead), the config (the stage's sections count through ``config_hash``, the files
it names through ``inputs``), the source (its files count through ``inputs``), display."""


def _cache_key(context: Any, parameters: dict[str, Any]) -> str | None:
    key = {k: v for k, v in parameters.items() if k not in NOT_IN_KEY}
    key["warehouse"] = warehouse_id(Path(parameters["root"]))
    key["upstream"] = [u.output_hash for u in parameters["upstream"]]
    return hash_objects(key)


CACHE_POLICY = TASK_SOURCE + CacheKeyFnPolicy(cache_key_fn=_cache_key)


def run_declared_stage(root: str, unit: str, stage: str, config_hash: str, code_hash: str, inputs: list[str],
                       upstream: list[StageRun], config: Config, source: Any = None,
                       show_progress: bool = True) -> StageRun:
    """Run ``stage`` on ``unit`` (a clip or a CAD library): ``waiting`` (not run) while an upstream
    run waits for people with nothing answered, else run and recorded (completed, paused or failed).
    ``upstream``: the runs of its upstream stages in declaration order; ``inputs``: the digests of
    what else it reads (see :func:`submit_stages`)."""
    waiting = waiting_run(unit, stage, upstream)
    if waiting is not None:
        return waiting
    wh = Warehouse(root, compact_after=config.warehouse.compact_after_files)
    declared = STAGES[stage]
    return run_stage(
        wh, unit, stage, config_hash=config_hash, code_hash=code_hash,
        inputs_hash=upstream_inputs_hash([u.output_hash for u in upstream] + inputs),
        body=lambda run_id: declared.run(StageContext(wh, stage, declared.section, unit, run_id, config, source, show_progress)),
    )


STAGE_TASKS: dict[str, Task] = {
    name: task(name=name, cache_policy=CACHE_POLICY, persist_result=True)(run_declared_stage) for name in STAGES
}
"""One task per stage, in pipeline order."""


def submit_stages(root: str, scope: str, unit: str, config: Config, source: Any,
                  show_progress: bool = True) -> list[tuple[str, PrefectFuture]]:
    """Submit every stage of ``scope`` for ``unit``, each fed by its upstream stages' futures, in
    pipeline order (runs of it that a killed process left unrecorded are recorded as interrupted
    first). The digests of what each stage reads besides its upstream outputs are taken now, as
    ``cadestate status`` sees them."""
    wh = Warehouse(root)
    settle_interrupted(wh, unit)
    memo = InputsMemo(wh, unit)  # status finds the digests taken here (tasks.inputs_memo)
    futures: dict[str, PrefectFuture] = {}
    for stage in stages_of(scope):
        inputs = (stage.submitted_inputs(config, source) if stage.has("source_inputs")
                  else stage.config_inputs(config) + memo.clip_inputs(stage, fresh=True))
        futures[stage.name] = STAGE_TASKS[stage.name].submit(
            root, unit, stage.name, config_hash(stage.name, config), stage.code_hash,
            inputs, [futures[u] for u in stage.upstream], config, source, show_progress)
    memo.save()
    return list(futures.items())
