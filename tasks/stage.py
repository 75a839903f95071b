"""Running one stage for one clip and recording it in the ``runs`` table.

Every stage function has the form ``body(run_id) -> StageOutput`` and is wrapped by
:func:`run_stage`, which times it, writes a ``runs`` row (completed or failed, with the lineage
digests; ``paused`` when the body says it waits for people) and returns a small picklable :class:`StageRun` (the Prefect task result).
"""

from __future__ import annotations

import datetime as dt
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass

import pyarrow as pa

from warehouse import Warehouse


@dataclass(frozen=True)
class StageOutput:
    """What a stage body reports: rows it wrote and the digest of its output. ``paused``: the stage
    wrote a task file for people and waits for their labels (what is answered is in the output;
    ``message`` names the task file and how many items wait); the run is recorded as ``paused``."""

    rows_written: int
    output_hash: str
    message: str = ""
    paused: bool = False


@dataclass(frozen=True)
class StageRun:
    """One recorded stage run (a row of ``runs``). ``status``: completed | failed | paused, or
    ``waiting`` (not recorded: the stage did not run because an upstream stage is paused with
    nothing answered yet)."""

    clip: str
    stage: str
    run_id: str
    status: str
    config_hash: str
    inputs_hash: str
    output_hash: str
    code_hash: str
    rows_written: int
    duration_s: float
    message: str


def record_run(wh: Warehouse, run: StageRun, started_at: dt.datetime) -> None:
    """Append ``run`` to the ``runs`` table."""
    row = {
        "clip": run.clip,
        "run_id": run.run_id,
        "stage": run.stage,
        "status": run.status,
        "config_hash": run.config_hash,
        "inputs_hash": run.inputs_hash,
        "output_hash": run.output_hash,
        "code_hash": run.code_hash,
        "started_at": started_at,
        "duration_s": run.duration_s,
        "rows_written": run.rows_written,
        "message": run.message,
    }
    wh.write("runs", run.clip, pa.Table.from_pylist([row]))


def run_stage(
    wh: Warehouse,
    clip: str,
    stage: str,
    *,
    config_hash: str,
    inputs_hash: str,
    code_hash: str,
    body: Callable[[str], StageOutput],
) -> StageRun:
    """Run ``body`` as stage ``stage`` of ``clip`` and record the run (also when it fails).

    A failure is recorded with its message and re-raised unchanged.
    """
    started_at = dt.datetime.now(dt.timezone.utc)
    run_id = f"{started_at:%Y%m%dT%H%M%S%fZ}-{uuid.uuid4().hex[:8]}"  # sorts by time
    t0 = time.perf_counter()
    common = dict(clip=clip, stage=stage, run_id=run_id, config_hash=config_hash, inputs_hash=inputs_hash, code_hash=code_hash)
    try:
        out = body(run_id)
    except Exception as e:
        failed = StageRun(**common, status="failed", output_hash="", rows_written=0,
                          duration_s=time.perf_counter() - t0, message=str(e))
        record_run(wh, failed, started_at)
        raise
    run = StageRun(**common, status="paused" if out.paused else "completed", output_hash=out.output_hash, rows_written=out.rows_written,
                   duration_s=time.perf_counter() - t0, message=out.message)
    record_run(wh, run, started_at)
    return run


def waiting_run(clip: str, stage: str, upstream: list[StageRun]) -> StageRun | None:
    """A ``waiting`` result when an upstream run waits for people with nothing answered yet
    (paused with no rows, or itself waiting): the stage does not run on nothing. Else None."""
    blocked = [u for u in upstream if u.status == "waiting" or (u.status == "paused" and u.rows_written == 0)]
    if not blocked:
        return None
    names = ", ".join(sorted({u.stage for u in blocked}))
    return StageRun(clip=clip, stage=stage, run_id="", status="waiting", config_hash="", inputs_hash="",
                    output_hash="waiting:" + "|".join(u.output_hash for u in blocked), code_hash="", rows_written=0,
                    duration_s=0.0, message=f"waits for {names}: " + "; ".join(u.message for u in blocked if u.message))
