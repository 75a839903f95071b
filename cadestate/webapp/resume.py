"""The background resume of clips that got answers: one worker thread, a queue, never the page's wait.

:class:`Resumer` keeps a FIFO of clips. A clip asked for while queued is not queued twice; asked
for while it runs, it runs once more afterwards (its newest answers came after the run read them).
A run resumes the clip's suspended flow run on the warehouse's Prefect server if there is one
(as ``cadestate labels ingest`` does, :func:`cadestate.cli.labels.resume_served`), else reruns the
clip's flow here (:func:`flows.annotate_clip.run_clips`; cached stages do no work). Prefect's
environment must be prepared (:func:`flows.runtime.prepare_prefect_environment`) before the worker starts.
"""

from __future__ import annotations

import threading
import time
import traceback
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

from cadestate.config import Config


@dataclass
class ClipRun:
    """The worker's view of one clip: ``state`` idle | queued | running | failed, runs done, the
    last run's summary (or error) and when it ended (epoch seconds)."""

    state: str = "idle"
    runs: int = 0
    message: str = ""
    finished_at: float | None = None
    again: bool = field(default=False, repr=False)

    def as_dict(self) -> dict:
        return {"state": self.state, "runs": self.runs, "message": self.message, "finished_at": self.finished_at}


def resume_clip(config: Config, clip: str) -> str:
    """Resume one clip (module docstring); returns a one-line summary of the run."""
    from pathlib import Path

    from flows.server import running_server
    from tasks.video.ingest import registered_source
    from warehouse import Warehouse

    root = Path(config.warehouse.root).resolve()
    if running_server(root) is not None:
        from flows.deployments import resume_clips

        if resume_clips([clip]):
            return "resumed its suspended run on the Prefect server"
    from flows.annotate_clip import run_clips

    reports = run_clips([registered_source(Warehouse(root), clip)], config, show_progress=False)
    states: dict[str, int] = {}
    for r in reports:
        states[r.state] = states.get(r.state, 0) + 1
    failed = [f"{r.stage}: {r.message}" for r in reports if r.state == "failed"]
    return ", ".join(f"{n} {s}" for s, n in sorted(states.items())) + (f" ({'; '.join(failed)})" if failed else "")


class Resumer:
    """One worker thread resuming queued clips (module docstring). ``run(clip)`` does the work
    (default :func:`resume_clip` with ``config``); tests may pass another."""

    def __init__(self, config: Config, run: Callable[[str], str] | None = None):
        self._run = run or (lambda clip: resume_clip(config, clip))
        self._queue: deque[str] = deque()
        self._clips: dict[str, ClipRun] = {}
        self._cond = threading.Condition()
        self._stop = False
        self._thread = threading.Thread(target=self._work, name="cadestate-resume", daemon=True)

    def start(self) -> Resumer:
        self._thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        self._thread.join(timeout)

    def request(self, clip: str) -> None:
        """Queue ``clip`` for a resume (see the module docstring for repeats)."""
        with self._cond:
            run = self._clips.setdefault(clip, ClipRun())
            if run.state == "running":
                run.again = True
            elif run.state != "queued":
                run.state = "queued"
                self._queue.append(clip)
                self._cond.notify_all()

    def status(self, clip: str) -> dict:
        with self._cond:
            return self._clips.get(clip, ClipRun()).as_dict()

    def busy(self, clip: str) -> bool:
        """Whether ``clip`` is queued or running."""
        return self.status(clip)["state"] in ("queued", "running")

    def wait_idle(self, clip: str, timeout: float) -> bool:
        """Block until ``clip`` is neither queued nor running (tests, benchmarks); False on timeout."""
        end = time.monotonic() + timeout
        with self._cond:
            while self._clips.get(clip, ClipRun()).state in ("queued", "running"):
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
            return True

    def _work(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._stop:
                    self._cond.wait()
                if self._stop:
                    return
                clip = self._queue.popleft()
                run = self._clips[clip]
                run.state, run.again = "running", False
            try:
                message, state = self._run(clip), "idle"
            except Exception as e:  # a failed run is reported on the page; the worker goes on
                message, state = f"{type(e).__name__}: {e}".splitlines()[0], "failed"
                traceback.print_exc()
            with self._cond:
                run.runs += 1
                run.message, run.finished_at = message, time.time()
                if run.again:
                    run.state, run.again = "queued", False
                    self._queue.append(clip)
                else:
                    run.state = state
                self._cond.notify_all()
