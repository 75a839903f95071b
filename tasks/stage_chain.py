"""A unit's stages (a clip's, or a CAD library's) run in pipeline order as plain calls, with the
``runs`` table as the cache: what one Prefect task of a flow runs (:mod:`flows.stage_chain`), and
what a bare batch without Prefect runs (``bench.cluster_throughput``'s baseline).

The cache is the lineage ``runs`` records (:mod:`tasks.stage`): a stage does not run again when a
completed or paused run of it in this warehouse had the same config digest, code digest and inputs
digest (its upstream stages' outputs and what else it reads, taken as ``cadestate status`` takes
them: before the unit's first stage runs, and again before each stage that follows one that ran, as
what a stage writes can be what a later one reads), and the stage's tables still hold what that run
wrote: the output of its latest completed or paused run is the same (config A, then B, then A again
reruns what B overwrote). So an unchanged rerun does no work, a config change reruns the stages
whose section changed, a stage downstream of a rerun stage reruns only if that stage's output
changed, a paused stage with nothing new answered stays paused, and a copied or moved warehouse
reruns nothing: its runs travel with it.

A stage whose upstream stage, or a stage it is listed ``after``, failed (or was skipped) is
skipped; one whose upstream stage waits for people with nothing answered is ``waiting``
(:func:`tasks.stage.waiting_run`); the others still run.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path
from typing import Any

from cadestate.config import Config
from tasks.inputs_memo import InputsMemo
from tasks.registry import Stage, config_hash, stages_of, upstream_inputs_hash
from tasks.stage import StageContext, StageRun, failure_message, run_stage, settle_interrupted, waiting_run
from tasks.status import Signature, cached_run, read_runs
from warehouse import Warehouse, check_name
from warehouse.read_cache import ReadCache
from warehouse.store import file_lock


@dataclasses.dataclass(frozen=True)
class StageReport:
    """Outcome of one stage for one clip (or CAD library) in a run of its stages."""

    clip: str
    stage: str
    state: str  # completed | cached | failed | skipped | paused | waiting
    rows_written: int = 0
    duration_s: float = 0.0
    message: str = ""


def report_of(run: StageRun, cached: bool = False) -> StageReport:
    """The report of a run (a cached completed run reports ``cached``; a paused or waiting one its status)."""
    if run.status in ("paused", "waiting"):
        return StageReport(run.clip, run.stage, run.status, run.rows_written, run.duration_s, run.message)
    if cached:
        return StageReport(run.clip, run.stage, "cached")
    return StageReport(run.clip, run.stage, "completed", run.rows_written, run.duration_s, run.message)


def run_unit(root: str, scope: str, unit: str, config: Config, source: Any = None, show_progress: bool = True,
             log: logging.Logger | logging.LoggerAdapter | None = None, read_cache: ReadCache | None = None) -> list[StageReport]:
    """Run every stage of ``scope`` for ``unit`` in pipeline order (see the module); one report per
    stage. Runs of the unit that a killed process left unrecorded are recorded as interrupted first.
    An input that cannot be digested (a file unreadable or damaged) is one failed report of the
    stage that reads it: before any stage ran, nothing of the unit runs; after, the stages that
    ran keep their reports and the others go on. ``read_cache``: where the input digests' reads are kept (default: a new cache
    for this call); a process that runs the unit again and again passes one that lives on, which
    the stages read and write through too (their next run and the process's other readers find
    the files they wrote without reading them)."""
    log = log or logging.getLogger(__name__)
    wh = Warehouse(root, compact_after=config.warehouse.compact_after_files)
    with file_lock(unit_lock_path(wh, unit)):  # one run of a unit at a time: a second waits, then finds the first's work
        return _run_unit(wh, scope, unit, config, source, show_progress, log, read_cache)


def unit_lock_path(wh: Warehouse, unit: str) -> Path:
    """The lock a run of ``unit`` (a clip or a CAD library) holds (``_locks/_units/<unit>.lock``, apart from the tables' locks):
    two runs of one clip (an inbox tick and `cadestate run`, two workers) would write its tables at
    once, and one's media pruning would delete the other's frames."""
    return wh.root / "_locks" / "_units" / f"{check_name(unit)}.lock"


def _run_unit(wh: Warehouse, scope: str, unit: str, config: Config, source: Any, show_progress: bool,
              log: logging.Logger | logging.LoggerAdapter, read_cache: ReadCache | None) -> list[StageReport]:
    settle_interrupted(wh, unit)
    stages = stages_of(scope)
    memo = InputsMemo(wh, unit)  # status finds the digests taken here (tasks.inputs_memo)
    inputs: dict[str, list[str]] = {}
    wh.cache_reads(cache=read_cache)  # the stages' digests read the same label tables again and again
    try:
        with memo.reading():  # one reading of the warehouse for every stage's digests
            for stage in stages:  # what each reads besides its upstream outputs, taken now, as status takes it
                try:
                    inputs[stage.name] = _inputs(stage, config, source, memo)
                except Exception as e:  # an unreadable or damaged input file: that stage's failed report
                    return [_unreadable(unit, stage, e, log)]
        runs = read_runs(wh, [unit])
        len_before = len(runs)  # each stage that runs appends its run (_one_stage)
    finally:
        if read_cache is None:  # a cache of this call's digests alone; a long-lived one serves the stages too
            wh.cache_reads(0)
    memo.save()
    done: dict[str, StageRun] = {}
    reports = []
    for stage in stages:
        if len(runs) > len_before and not stage.has("source_inputs"):  # an earlier stage ran: what it wrote
            try:  # may be what this one's digests read (pose reads the answers to cad_selection's new task)
                inputs[stage.name] = _inputs(stage, config, source, memo)
            except Exception as e:  # the reports of the stages that ran stay
                reports.append(_unreadable(unit, stage, e, log))
                continue
        report = _one_stage(wh, stage, unit, config, source, show_progress, inputs[stage.name], done, runs, log)
        reports.append(report)
        log.info("%s %s: %s%s", unit, stage.name, report.state, f" ({report.duration_s:.2f} s)" if report.duration_s else "")
    memo.save()  # the digests taken again after a stage ran
    return reports


def _inputs(stage: Stage, config: Config, source: Any, memo: InputsMemo) -> list[str]:
    """What ``stage`` reads besides its upstream outputs: the submitted source's digests, or its
    config's and the warehouse's (digested afresh, :meth:`tasks.inputs_memo.InputsMemo.clip_inputs`)."""
    if stage.has("source_inputs"):
        return stage.submitted_inputs(config, source)
    return stage.config_inputs(config) + memo.clip_inputs(stage, fresh=True)


def _unreadable(unit: str, stage: Stage, error: Exception, log: Any) -> StageReport:
    """The failed report of a stage whose inputs cannot be digested (logged): a file that cannot be
    read (an OSError) or is damaged (a WarehouseError, pyarrow's ValueError), or any other error
    there, named by its type (it escaped as one report named 'stages', the stage unnamed)."""
    message = str(error) if isinstance(error, (OSError, ValueError)) else f"{type(error).__name__}: {error}"
    log.error("%s %s: %s", unit, stage.name, message)
    return StageReport(unit, stage.name, "failed", message=message)


def _one_stage(wh: Warehouse, stage: Stage, unit: str, config: Config, source: Any, show_progress: bool,
               inputs: list[str], done: dict[str, StageRun], runs: list[dict[str, Any]], log: Any) -> StageReport:
    """Run (or find cached, waiting or skipped) one stage; its run goes into ``done`` and ``runs``."""
    upstream = [done.get(u) for u in stage.upstream]
    if any(u is None for u in upstream) or any(a not in done for a in stage.after):  # pose after a skipped correspondence_task
        return StageReport(unit, stage.name, "skipped", message="an upstream stage failed")
    ups = [u for u in upstream if u is not None]
    waiting = waiting_run(unit, stage.name, ups + [done[a] for a in stage.after])  # pose: no clicks yet
    if waiting is not None:
        done[stage.name] = waiting
        return report_of(waiting)
    signature = Signature(config_hash(stage.name, config), stage.code_hash,
                          upstream_inputs_hash([u.output_hash for u in ups] + inputs))
    hit = cached_run(runs, unit, stage.name, signature)
    if hit is not None:
        done[stage.name] = hit
        return report_of(hit, cached=True)
    started = time.monotonic()
    try:
        run = run_stage(wh, unit, stage.name, **dataclasses.asdict(signature),
                        body=lambda run_id: stage.run(StageContext(wh, stage.name, stage.section, unit, run_id,
                                                                   config, source, show_progress)))
    except Exception as e:  # recorded in runs by run_stage; the unit's other stages go on
        log.error("%s %s failed", unit, stage.name, exc_info=True)  # its time too (a failed SfM showed 0.00 s)
        return StageReport(unit, stage.name, "failed", duration_s=time.monotonic() - started, message=failure_message(e))
    done[stage.name] = run
    runs.append(dataclasses.asdict(run))  # the latest: after every recorded run
    return report_of(run)
