"""A stage's declaration, and running one stage for one clip and recording it in the ``runs`` table.

A stage is declared once, beside its logic: its module (anywhere under ``tasks/``) assigns
``STAGE = StageDef(...)`` at module level, naming the function that does the work and the
functions that digest what it reads besides its upstream stages' outputs. :mod:`tasks.registry`
finds the declarations and derives the stage graph and code digests; :mod:`tasks.stage_chain`
runs a unit's stages in graph order, in one Prefect task, the ``runs`` table as cache.

A run's body has the form ``body(run_id) -> StageOutput`` and is wrapped by
:func:`run_stage`, which times it, writes a ``runs`` row (completed or failed, with the lineage
digests; ``paused`` when the body says it waits for people) and returns a :class:`StageRun`.

A run in progress is journalled by a marker file, ``<warehouse>/_running/<clip>/<stage>.<run_id>.json``
(the process, its host and start), written before the body starts and removed once its ``runs`` row
is written; while the body runs, a thread touches it every :data:`HEARTBEAT_S` (its modification
time is the run's heartbeat). A process killed mid-stage (``kill -9``, a lost machine) leaves its
marker: ``cadestate status`` shows the stage ``interrupted``, and the next run of the clip records
the run in ``runs`` with status ``interrupted`` (:func:`settle_interrupted`). On the marker's own
host a run is alive while its process is; a marker of another host (a Dask worker's) while its
heartbeat is younger than :data:`STALE_AFTER_S`.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import functools
import json
import os
import socket
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal


from warehouse import Warehouse, atomic_write_bytes, check_name

if TYPE_CHECKING:
    from cadestate.config import Config

RUNNING_DIR = "_running"
"""Folder of the markers of runs in progress, under the warehouse root."""
HEARTBEAT_S = 30.0
"""How often a running stage touches its marker."""
STALE_AFTER_S = 300.0
"""A marker of another host untouched this long is of a run whose process or machine is gone (ten
heartbeats: clocks that NTP keeps and a shared file system's attribute caching stay well inside it)."""


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
class StageContext:
    """What one run of stage ``stage`` (whose config section is ``section``) works with. ``unit``: the clip (clip stages) or the CAD library
    (library stages); ``config``: the whole configuration (a stage's ``config_hash`` covers its own
    section and its ``extra_sections``: anything else it reads must enter through its
    ``config_inputs``); ``source``: what the flow was given for the unit, a
    :class:`tasks.video.ingest.ClipSource` for a clip, the library's list of
    :class:`tasks.cad.sources.CadItem` for a library."""

    wh: Warehouse
    stage: str
    section: str | None
    unit: str
    run_id: str
    config: Config
    source: Any = None
    show_progress: bool = True

    @property
    def cfg(self) -> Any:
        """The stage's own config section."""
        if self.section is None:
            raise KeyError(f"stage {self.stage!r} has no config section")
        return self.config.section(self.section)


@dataclass(frozen=True, kw_only=True)
class StageDef:
    """A stage, declared in its module as ``STAGE = StageDef(...)`` with literal values and names of
    module-level functions (:mod:`tasks.registry` reads the declaration from the source without
    importing the module's dependencies).

    ``name`` is its ``runs.stage`` value; ``section`` its config section (a dataclass of
    :mod:`cadestate.config`, usually named like the stage; None: it has no settings). ``scope``: what one run covers,
    a ``clip`` or a CAD ``library`` (whose runs use the library name as ``runs.clip``). ``upstream``:
    the stages whose outputs it reads (their output digests make its ``inputs_hash``; it does not run,
    and is ``waiting``, while one of them waits for people with nothing answered). ``tables``: what
    it writes. ``extra_sections``: config sections it reads besides its own, or single keys of them
    (``"manual_tracks.keyframes"``; part of its config hash).
    ``after``: stages it is listed after without reading their output (pose reads the answers of the
    correspondence task from the warehouse); it is ``waiting`` too while one of them waits for people
    with nothing answered (pose does not run, and is not recorded completed, before any click).

    ``run(ctx: StageContext) -> StageOutput`` does the work. What it reads besides its upstream
    outputs is digested by ``config_inputs(config) -> list[str]`` (files the config names, such as
    the detector's model), ``clip_inputs(wh, unit) -> list[str]`` (warehouse data, such as people's
    answers) and, for the stages that read the given source (``cameras``, ``ingest``, ``cad_ingest``),
    ``source_inputs(source) -> list[str]``: the flow then uses it in place of ``clip_inputs``, which
    says what the registered source was (what ``cadestate status`` compares)."""

    name: str
    section: str | None
    scope: Literal["clip", "library"]
    upstream: tuple[str, ...]
    tables: tuple[str, ...]
    description: str
    run: Callable[[StageContext], StageOutput]
    extra_sections: tuple[str, ...] = ()
    after: tuple[str, ...] = ()
    config_inputs: Callable[[Config], list[str]] | None = None
    clip_inputs: Callable[[Warehouse, str], list[str]] | None = None
    source_inputs: Callable[[Any], list[str]] | None = None


@dataclass(frozen=True)
class StageRun:
    """One recorded stage run (a row of ``runs``). ``status``: completed | failed | paused |
    interrupted (its process ended first: :func:`settle_interrupted`), or ``waiting`` (not
    recorded: the stage did not run because an upstream stage is paused with nothing answered yet)."""

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
    import pyarrow as pa  # here: `cadestate status` reads markers and runs without pyarrow

    wh.write("runs", run.clip, pa.Table.from_pylist([row]))


@dataclass(frozen=True)
class RunMarker:
    """A stage run in progress (or interrupted), as its marker file records it. ``process_start``:
    the process's creation time (epoch seconds), which tells a live process from a recycled pid;
    ``process_ticks``: the same as clock ticks since boot (Linux; None elsewhere or in an older
    marker), which a step of the wall clock does not move; ``touched``: the marker's last heartbeat
    (its modification time, epoch seconds)."""

    clip: str
    stage: str
    run_id: str
    pid: int
    host: str
    process_start: float
    started_at: dt.datetime
    path: Path
    touched: float
    process_ticks: int | None = None

    @property
    def alive(self) -> bool:
        """Whether the run's process still runs: on this host, asked of the process; on another, its
        heartbeat is younger than :data:`STALE_AFTER_S`."""
        if self.host != socket.gethostname():
            return time.time() - self.touched < STALE_AFTER_S
        if self.process_ticks is not None and (ticks := _start_ticks(self.pid)) is not None:
            return ticks == self.process_ticks  # the creation time in epoch seconds moves when the clock is set
        import psutil  # here: `cadestate status` imports this module and seldom finds a marker

        try:
            return abs(psutil.Process(self.pid).create_time() - self.process_start) < 1.0
        except psutil.Error:
            return False


def _marker_dir(wh: Warehouse, clip: str) -> Path:
    return wh.root / RUNNING_DIR / check_name(clip)


def _start_ticks(pid: int) -> int | None:
    """Process ``pid``'s start time in clock ticks since boot (field 22 of ``/proc/<pid>/stat``; None
    without procfs or without the process)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        return int(stat[stat.rindex(")") + 2:].split()[19])  # fields after the command name start at field 3
    except (OSError, ValueError, IndexError):
        return None


@functools.cache
def _this_process(pid: int) -> tuple[str, float]:
    """The host and creation time (epoch seconds) of process ``pid``, this one (asked by pid: a
    forked child is another process)."""
    import psutil

    return socket.gethostname(), psutil.Process(pid).create_time()


def _start_marker(wh: Warehouse, clip: str, stage: str, run_id: str, started_at: dt.datetime) -> Path:
    """Write the marker of a run that starts now; returns its path."""
    pid = os.getpid()
    host, process_start = _this_process(pid)
    doc = {"clip": clip, "stage": stage, "run_id": run_id, "pid": pid, "host": host,
           "process_start": process_start, "process_ticks": _start_ticks(pid), "started_at": started_at.isoformat()}
    path = _marker_dir(wh, clip) / f"{stage}.{run_id}.json"
    atomic_write_bytes(path, json.dumps(doc).encode(), durable=False)  # lost with the machine: the run left no row
    return path


@contextlib.contextmanager
def heartbeat(marker: Path, every_s: float = HEARTBEAT_S) -> Iterator[None]:
    """Touch ``marker`` every ``every_s`` seconds from a daemon thread while the block runs (a
    marker removed meanwhile is not recreated)."""
    stop = threading.Event()

    def beat() -> None:
        while not stop.wait(every_s):
            with contextlib.suppress(OSError):
                os.utime(marker)

    threading.Thread(target=beat, name=f"heartbeat of {marker.name}", daemon=True).start()
    try:
        yield
    finally:
        stop.set()


def run_markers(wh: Warehouse, clip: str) -> list[RunMarker]:
    """The markers of ``clip``'s runs in progress or interrupted, oldest first (unreadable ones skipped:
    a marker is written atomically, so only a foreign file is unreadable)."""
    folder, markers = _marker_dir(wh, clip), []
    for path in sorted(folder.glob("*.json")) if folder.is_dir() else []:
        try:
            d = json.loads(path.read_text())
            ticks = d.get("process_ticks")
            markers.append(RunMarker(d["clip"], d["stage"], d["run_id"], int(d["pid"]), d["host"], float(d["process_start"]),
                                     dt.datetime.fromisoformat(d["started_at"]), path, path.stat().st_mtime,
                                     None if ticks is None else int(ticks)))
        except (OSError, ValueError, KeyError, TypeError):
            continue
    return sorted(markers, key=lambda m: m.run_id)  # run ids sort by start time


def settle_interrupted(wh: Warehouse, clip: str) -> list[StageRun]:
    """Record every run of ``clip`` whose process ended without recording it (its marker is left)
    as an ``interrupted`` row of ``runs``, and remove its marker (only that for a run whose row is
    in: a second row of its run_id, interrupted, had hidden the completed one). Returns them. The caller holds the
    clip's lock (:func:`tasks.stage_chain.run_unit`), which every run holds while its marker is
    there, so a marker left now is a dead run's whatever its host (a marker of another host was
    taken for a live run until its heartbeat was 5 minutes old, after a Dask retry had finished the
    clip)."""
    settled, markers = [], run_markers(wh, clip)
    recorded = set(wh.read("runs", [clip], columns=["run_id"]).column("run_id").to_pylist()) \
        if markers and wh.has_partition("runs", clip) else set()
    for m in markers:
        if m.run_id in recorded:  # the process ended after recording its run, before removing the marker
            m.path.unlink(missing_ok=True)
            continue
        run = StageRun(clip=clip, stage=m.stage, run_id=m.run_id, status="interrupted", config_hash="", inputs_hash="",
                       output_hash="", code_hash="", rows_written=0, duration_s=0.0,
                       message=f"interrupted: process {m.pid} on {m.host} ended before the run finished (killed or crashed); "
                               "its tables may hold part of its output until it runs again")
        record_run(wh, run, m.started_at)
        m.path.unlink(missing_ok=True)
        settled.append(run)
    return settled


def failure_message(e: BaseException) -> str:
    """A failed stage's message: the error's own, named by its type where the text alone does not
    say what happened (empty: ``MemoryError()``, a bare ``assert``; a built-in error of the code,
    not of the input: a ``KeyError``'s text is only its key). Errors of bad input (``OSError``,
    ``ValueError``) and the project's own errors speak for themselves."""
    text = str(e)
    if text and not (type(e).__module__ == "builtins" and not isinstance(e, (OSError, ValueError))):
        return text
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


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
    marker = _start_marker(wh, clip, stage, run_id, started_at)
    try:
        with heartbeat(marker):
            out = body(run_id)
    except Exception as e:
        failed = StageRun(**common, status="failed", output_hash="", rows_written=0,
                          duration_s=time.perf_counter() - t0, message=failure_message(e))
        record_run(wh, failed, started_at)
        marker.unlink(missing_ok=True)
        raise
    run = StageRun(**common, status="paused" if out.paused else "completed", output_hash=out.output_hash, rows_written=out.rows_written,
                   duration_s=time.perf_counter() - t0, message=out.message)
    record_run(wh, run, started_at)
    marker.unlink(missing_ok=True)
    return run


def waits_for_people(status: str, rows_written: int) -> bool:
    """Whether a run of this status and rows written waits for people with nothing answered yet
    (paused with no rows, or itself waiting): the stages after it do not run on nothing."""
    return status == "waiting" or (status == "paused" and rows_written == 0)


def waiting_run(clip: str, stage: str, upstream: list[StageRun]) -> StageRun | None:
    """A ``waiting`` result when an upstream run waits for people (:func:`waits_for_people`): the
    stage does not run on nothing. Else None."""
    blocked = [u for u in upstream if waits_for_people(u.status, u.rows_written)]
    if not blocked:
        return None
    names = ", ".join(sorted({u.stage for u in blocked}))
    return StageRun(clip=clip, stage=stage, run_id="", status="waiting", config_hash="", inputs_hash="",
                    output_hash="waiting:" + "|".join(u.output_hash for u in blocked), code_hash="", rows_written=0,
                    duration_s=0.0, message=f"waits for {names}: " + "; ".join(u.message for u in blocked if u.message))
