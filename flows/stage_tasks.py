"""One Prefect task per stage of :data:`tasks.registry.STAGES`, generated from its declaration, and
the submission of a unit's (a clip's or a CAD library's) stages wired from the stage graph.

Caching: a task's cache key is this module's source plus the task's inputs, where an upstream
:class:`StageRun` counts only by its ``output_hash``, the stage's code digest, config digest and
input digests are inputs, and the warehouse counts by its identity (:mod:`warehouse.identity`), not
its path. So an unchanged rerun does no work, a config change reruns the stages whose section
changed, a stage downstream of a rerun stage reruns only if that stage's output changed, a copied
or moved warehouse reruns nothing, and two warehouses never share a result. Results persist under
``<warehouse>/_prefect/results`` (see :mod:`flows.runtime`), one file per key. A cached result
holds a run's record; the rows it wrote are in the tables, which a later run of other inputs may
have replaced: before a key is looked up, its result is dropped when the tables hold another
output than the runs of those inputs wrote (config A, then B, then A again reruns A's stages
whose output B changed).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from prefect import Task, task
from prefect.cache_policies import CacheKeyFnPolicy
from prefect.futures import PrefectFuture
from prefect.utilities.hashing import hash_objects

from cadestate.config import Config
from cadestate.lineage import digest
from flows.runtime import RESULTS
from tasks.inputs_memo import InputsMemo
from tasks.registry import STAGES, config_hash, stages_of, upstream_inputs_hash
from tasks.stage import StageContext, StageRun, run_stage, settle_interrupted, waiting_run
from warehouse import Warehouse
from warehouse.identity import warehouse_id
from warehouse.query import read_rows

NOT_IN_KEY = ("root", "config", "source", "show_progress")
"""Parameters that do not change a task's result given the others: the root (the warehouse counts
by its identity instead), the config (the stage's sections count through ``config_hash``, the files
it names through ``inputs``), the source (its files count through ``inputs``), display."""


TASK_SOURCE_DIGEST = digest(Path(__file__).read_text(encoding="utf-8"))
"""This module's source: how a stage is run and recorded counts in every key (a stage's own code
counts through ``code_hash``)."""


def _cache_key(context: Any, parameters: dict[str, Any]) -> str:
    """The task's cache key (see the module); its cached result is dropped first when the
    warehouse's tables no longer hold what it wrote (:func:`_tables_moved_on`)."""
    key = {k: v for k, v in parameters.items() if k not in NOT_IN_KEY}
    key["warehouse"] = warehouse_id(Path(parameters["root"]))
    key["upstream"] = [u.output_hash for u in parameters["upstream"]]
    key["task_source"] = TASK_SOURCE_DIGEST
    value = hash_objects(key)
    if _tables_moved_on(parameters):
        (Path(parameters["root"]) / RESULTS / value).unlink(missing_ok=True)
    return value


def _tables_moved_on(parameters: dict[str, Any]) -> bool:
    """Whether the stage's tables hold another output than its runs with these parameters wrote:
    a later run with other config, code or inputs wrote a different output (e.g. config A, then
    B, then A again). A cached result of A would then be stale (its output_hash is not what the
    tables hold), so A must run again; with the same output (B wrote what A had) it need not."""
    signature = (parameters["config_hash"], parameters["code_hash"],
                 upstream_inputs_hash([u.output_hash for u in parameters["upstream"]] + parameters["inputs"]))
    rows = read_rows(Warehouse(parameters["root"]), "runs", RUN_SIGNATURE, [parameters["unit"]], timestamps=("started_at",))
    ok = sorted((r for r in rows if r["stage"] == parameters["stage"] and r["status"] in ("completed", "paused")),
                key=lambda r: r["started_at"])
    same = [r for r in ok if (r["config_hash"], r["code_hash"], r["inputs_hash"]) == signature]
    return bool(same) and same[-1]["output_hash"] != ok[-1]["output_hash"]


RUN_SIGNATURE = ("stage", "status", "config_hash", "code_hash", "inputs_hash", "output_hash", "started_at")
CACHE_POLICY = CacheKeyFnPolicy(cache_key_fn=_cache_key)


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
