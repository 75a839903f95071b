"""The background resume of clips that got answers: one worker thread, a queue, never the page's wait.

:class:`Resumer` keeps a FIFO of clips. A clip asked for while queued is not queued twice; asked
for while it runs, it runs once more afterwards (its newest answers came after the run read them).

Before its first resume the worker warms up (:func:`warm_up`: the modules of the stages an answer
can make run are imported while the annotator reads the first task), so the first answer does not
wait for them. A resume has two phases, and a page waits only for the first:

1. ``running``: the clip's stages run here, as plain calls (:func:`run_stages`:
   :func:`tasks.stage_chain.run_unit`, the chain one Prefect task of a flow runs; cached stages do no
   work). When it ends, the clip's next task is in the warehouse and a waiting page is answered.
2. ``recording``: Prefect learns of it (:func:`record_in_prefect`, :data:`RECORD_DELAY_S` later): the clip's suspended flow run on
   the warehouse's Prefect server is resumed through the API (as ``cadestate labels ingest`` does),
   else the clip's flow runs here (:func:`flows.annotate_clip.run_clips`). Either finds every stage
   cached, so Prefect's UI shows the clip's run and its state, and no stage runs twice.

A page used to wait for a whole flow run: on a small clip with the server up, 0.35 s of the
0.53 s from an answer to the next task were Prefect's (flow and task runs, their API calls and
events) around 0.17 s of stage work. A request that comes while a clip is recorded queues it
again at once (a page never reads a clip as ready before its newest answers have run). Records
wait while any clip is queued: another clip's page does not wait for this one's record (it did,
the worker taking clips and records in one line), though a record under way is finished first.
Prefect's environment must be prepared (:func:`flows.runtime.prepare_prefect_environment`) before
the worker starts.
"""

from __future__ import annotations

import dataclasses
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from cadestate.config import Config
from warehouse.read_cache import ReadCache

RECORD_DELAY_S = 1.0
"""How long after its stages ran a clip is recorded in Prefect: the page that was waiting loads the
next task (its document, frames and models) first, not beside a flow run. A clip asked for again
meanwhile is recorded after that run instead."""
BUSY = ("queued", "running")
"""States in which a clip's next task may not be in the warehouse yet (a page waits)."""


@dataclass
class ClipRun:
    """The worker's view of one clip: ``state`` idle | queued | running | recording | failed, runs
    of its stages done, the last run's summary (or error) and when it ended (epoch seconds), whether
    it failed (``failed``: an error, or a stage that failed; such a run is still recorded in Prefect,
    and its state ends ``failed``), and what the last record in Prefect said (``prefect``; '' before
    one)."""

    state: str = "idle"
    runs: int = 0
    message: str = ""
    failed: bool = False
    finished_at: float | None = None
    prefect: str = ""
    again: bool = field(default=False, repr=False)

    def as_dict(self) -> dict:
        return {"state": self.state, "runs": self.runs, "message": self.message, "finished_at": self.finished_at,
                "failed": self.failed, "prefect": self.prefect}


def summary(reports: list) -> str:
    """One line of stage reports: '2 cached, 1 completed, 1 paused' (failures named)."""
    states: dict[str, int] = {}
    for r in reports:
        states[r.state] = states.get(r.state, 0) + 1
    failed = [f"{r.stage}: {r.message}" for r in reports if r.state == "failed"]
    return ", ".join(f"{n} {s}" for s, n in sorted(states.items())) + (f" ({'; '.join(failed)})" if failed else "")


class StagesFailed(RuntimeError):
    """A resume in which a stage failed (the stages' summary): the clip's resume is ``failed``, and
    the page says so (it said "nothing waits for people" with the failure inside the line)."""

    def __str__(self) -> str:
        return f"a stage failed: {super().__str__()}"


def first_line(e: BaseException) -> str:
    """``Type: message`` of ``e``, its first line."""
    return f"{type(e).__name__}: {e}".splitlines()[0]


def run_stages(config: Config, clip: str, read_cache: ReadCache | None = None) -> str:
    """Phase 1 (module docstring): the clip's stages here, without Prefect; a one-line summary
    (:class:`StagesFailed` with it when a stage failed).
    ``read_cache``: the worker's, kept from one resume to the next (the input digests read the CAD
    libraries' runs and the clip's other answers again, unchanged)."""
    from tasks.stage_chain import run_unit
    from tasks.video.ingest import registered_source
    from warehouse import Warehouse

    root = Path(config.warehouse.root).expanduser().resolve()
    wh = Warehouse(root, compact_after=config.warehouse.compact_after_files)
    if read_cache is not None:
        wh.cache_reads(cache=read_cache)
    reports = run_unit(str(root), "clip", clip, config, registered_source(wh, clip), show_progress=False, read_cache=read_cache)
    if any(r.state == "failed" for r in reports):
        raise StagesFailed(summary(reports))
    return summary(reports)


WARM_CLIPS = 4
"""How many clips with items waiting the warm-up reads ahead (their first answer is the likeliest),
among the first :data:`WARM_SCAN` clips (a warehouse of 10,000 clips is not scanned whole)."""
WARM_SCAN = 64


def warm_up(config: Config, read_cache: ReadCache | None = None) -> str:
    """What the first answer would otherwise wait for: the modules of the stages an answer can make
    run (every clip stage from the first human one on, with the modules their digests come from;
    the pose solver's torch alone takes about 2 s), the check of the warehouse's catalog that
    a process's first write makes (:func:`warehouse.catalog.after_write`: DuckDB imported, the
    catalog rebuilt if stale), and, into ``read_cache``, what a resume of the first
    :data:`WARM_CLIPS` clips with items waiting reads before its stages run (their input digests
    and runs: ~30 ms of the first answer's round on the demo clip). A one-line summary."""
    from cadestate.webapp import queue
    from tasks.inputs_memo import InputsMemo
    from tasks.registry import stages_of
    from tasks.status import read_runs
    from warehouse import Warehouse
    from warehouse.catalog import after_write

    stages = stages_of("clip")
    first = next(i for i, s in enumerate(stages) if s.module.startswith("tasks.human."))
    for stage in stages[first:]:
        for name, _ in stage.functions:
            stage.function(name)
    wh = Warehouse(Path(config.warehouse.root).expanduser().resolve())
    after_write(wh)
    if read_cache is None:
        return f"{len(stages) - first} stages imported, the catalog checked"
    wh.cache_reads(cache=read_cache)
    waiting = [c for c in queue.clips(wh)[:WARM_SCAN] if queue.first_waiting(queue.clip_tasks(wh, c))][:WARM_CLIPS]
    for clip in waiting:
        memo = InputsMemo(wh, clip)
        for stage in stages:
            if not stage.has("source_inputs"):
                memo.clip_inputs(stage, fresh=True)
        read_runs(wh, [clip])
    return f"{len(stages) - first} stages imported, the catalog checked, {len(waiting)} clip(s) with items waiting read"


def record_in_prefect(config: Config, clip: str) -> str:
    """Phase 2 (module docstring): resume the clip's suspended run on the warehouse's server, else
    run its flow here; a one-line summary."""
    from flows.server import running_server

    root = Path(config.warehouse.root).expanduser().resolve()
    if running_server(root) is not None:
        from flows.deployments import resume_clips

        if resume_clips([clip]):
            return "its suspended run on the Prefect server resumed"
    from flows.annotate_clip import run_clips
    from tasks.video.ingest import registered_source
    from warehouse import Warehouse

    # on threads whatever [prefect] task_runner says: phase 1 ran the stages here, so the flow finds
    # them cached, and a Dask cluster made for it cost 3.4 s a record (0.1 s on threads)
    here = dataclasses.replace(config, prefect=dataclasses.replace(config.prefect, task_runner="threads"))
    reports = run_clips([registered_source(Warehouse(root), clip)], here, show_progress=False)
    return f"flow run annotate_clip/{clip}: {summary(reports)}"


class Resumer:
    """One worker thread resuming queued clips (module docstring). ``run(clip)`` runs the stages and
    ``record(clip)`` tells Prefect; each returns a one-line summary; ``warm()``, run first, too.
    Defaults: :func:`run_stages`, :func:`record_in_prefect` and :func:`warm_up` with ``config``, the
    stages reading through ``read_cache`` (the app's, so that a page finds what a resume wrote without
    reading it; default: the resumer's own); a resumer given ``run`` only records and warms nothing (tests)."""

    def __init__(self, config: Config, run: Callable[[str], str] | None = None,
                 record: Callable[[str], str] | None = None, record_delay_s: float = RECORD_DELAY_S,
                 warm: Callable[[], str] | None = None, read_cache: ReadCache | None = None):
        self.record_delay_s = record_delay_s
        if run is None:
            cache = read_cache or ReadCache()
            run = lambda clip: run_stages(config, clip, cache)  # noqa: E731
            record = record or (lambda clip: record_in_prefect(config, clip))
            warm = warm or (lambda: warm_up(config, cache))
        self._run, self._record, self._warm = run, record, warm
        self.warmed = threading.Event()
        """Set once the warm-up is over (at once without one); :attr:`warm_message` says how it went."""
        self.warm_message = ""
        self._queue: deque[str] = deque()
        self._records: dict[str, float] = {}  # clips whose record waits, in order: when it is due (monotonic s)
        self._clips: dict[str, ClipRun] = {}
        self._cond = threading.Condition()
        self._stop = False
        self._thread = threading.Thread(target=self._work, name="cadestate-resume", daemon=True)

    def start(self) -> Resumer:
        self._thread.start()
        return self

    def stop(self, timeout: float = 10.0) -> None:
        """Ask the worker to stop and wait for it (the warm-up or a clip's stages may outlast
        ``timeout``: :meth:`alive` then says so)."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        self._thread.join(timeout)

    def alive(self) -> bool:
        """Whether the worker thread still runs (after :meth:`stop`: in the warm-up or a clip's stages)."""
        return self._thread.is_alive()

    def request(self, clip: str) -> None:
        """Queue ``clip`` for a resume (see the module docstring for repeats)."""
        with self._cond:
            run = self._clips.setdefault(clip, ClipRun())
            if run.state == "running":
                run.again = True
            elif run.state != "queued":  # idle, failed, or recording: the worker takes it after the record
                run.state = "queued"
                self._queue.append(clip)
                self._cond.notify_all()

    def status(self, clip: str) -> dict:
        with self._cond:
            return self._clips.get(clip, ClipRun()).as_dict()

    def busy(self, clip: str) -> bool:
        """Whether ``clip``'s next task may not be ready yet (queued, or its stages running)."""
        return self.status(clip)["state"] in BUSY

    def wait_idle(self, clip: str, timeout: float, settled: bool = False) -> bool:
        """Block until ``clip`` is not busy (with ``settled``: nor being recorded in Prefect); False on timeout."""
        states = (*BUSY, "recording") if settled else BUSY
        end = time.monotonic() + timeout
        with self._cond:
            while self._clips.get(clip, ClipRun()).state in states:
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
            return True

    def _work(self) -> None:
        if self._warm is not None:
            self.warm_message = self._attempt(lambda _: self._warm(), "")[1]
        self.warmed.set()
        while True:
            with self._cond:
                clip = self._next_clip()
                if clip is None:
                    return
                run = self._clips[clip]
                recording = run.state == "recording"
                if not recording:
                    run.state, run.again = "running", False
            if recording:
                _, recorded = self._attempt(self._record, clip)
                with self._cond:
                    run.prefect = recorded
                    if run.state == "recording":  # else a request queued it meanwhile
                        run.state = "failed" if run.failed else "idle"
                    self._cond.notify_all()
                continue
            try:
                message, ran, failed = self._run(clip), True, False
            except StagesFailed as e:  # the stages ran (the failed one logged its error): recorded in Prefect too
                message, ran, failed = str(e), True, True
            except Exception as e:  # reported on the page
                traceback.print_exc()
                message, ran, failed = first_line(e), False, True
            with self._cond:
                run.runs += 1
                run.message, run.finished_at, run.failed = message, time.time(), failed
                if run.again:  # newer answers: run again first (that run gets recorded)
                    run.state, run.again = "queued", False
                    self._queue.append(clip)
                else:
                    run.state = "recording" if ran and self._record else ("failed" if failed else "idle")
                if run.state == "recording":  # the page loads the next task first
                    self._records.pop(clip, None)
                    self._records[clip] = time.monotonic() + self.record_delay_s
                self._cond.notify_all()

    def _next_clip(self) -> str | None:
        """The worker's next clip (called with the lock held): a queued one first (a page may wait
        for it), else the first whose record is due, waited for; None when stopping (records not
        made are dropped, their clips idle)."""
        while True:
            if self._stop:
                for clip in self._records:
                    if self._clips[clip].state == "recording":
                        self._clips[clip].state = "idle"
                self._records.clear()
                self._cond.notify_all()
                return None
            if self._queue:
                return self._queue.popleft()
            for clip in [c for c in self._records if self._clips[c].state != "recording"]:
                del self._records[clip]  # asked for again meanwhile: that run is recorded
            if not self._records:
                self._cond.wait()
                continue
            clip, due = next(iter(self._records.items()))
            if (left := due - time.monotonic()) > 0:
                self._cond.wait(left)
                continue
            del self._records[clip]
            return clip

    @staticmethod
    def _attempt(call: Callable[[str], str], clip: str) -> tuple[bool, str]:
        """``call(clip)``: (True, its line), or (False, the error's first line); the worker goes on."""
        try:
            return True, call(clip)
        except Exception as e:  # reported on the page
            traceback.print_exc()
            return False, first_line(e)
