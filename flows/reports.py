"""What a flow run reports: one :class:`StageReport` per stage run, and the flow's final state."""

from __future__ import annotations

from dataclasses import dataclass

from prefect.futures import PrefectFuture, wait
from prefect.states import Completed, Failed, State

from tasks.stage import StageRun


@dataclass(frozen=True)
class StageReport:
    """Outcome of one stage for one clip (or CAD library) in a flow run."""

    clip: str
    stage: str
    state: str  # completed | cached | failed | skipped | paused | waiting
    rows_written: int = 0
    duration_s: float = 0.0
    message: str = ""


def report(clip: str, stage: str, future: PrefectFuture) -> StageReport:
    """The report of a finished task future."""
    state = future.state
    if state.is_completed():
        run: StageRun = state.result()
        if run.status in ("paused", "waiting"):
            return StageReport(clip, stage, run.status, run.rows_written, run.duration_s, run.message)
        if state.name == "Cached":
            return StageReport(clip, stage, "cached")
        return StageReport(clip, stage, "completed", run.rows_written, run.duration_s, run.message)
    if state.is_failed():
        error = state.result(raise_on_failure=False)
        if "upstream" not in str(state.message or "").lower():
            return StageReport(clip, stage, "failed", message=str(error))
    return StageReport(clip, stage, "skipped", message="an upstream stage failed")


def finish(submitted: list[tuple[str, str, PrefectFuture]], reports: list[StageReport], what: str) -> State:
    """Wait for the submitted tasks; the flow's final state carries every report."""
    wait([fut for _, _, fut in submitted])
    reports = reports + [report(clip, stage, fut) for clip, stage, fut in submitted]
    failed = [r for r in reports if r.state == "failed"]
    message = f"{what}: {len(reports)} stage runs, {len(failed)} failed"
    if failed:
        return Failed(message=message, data=reports)
    paused = [r for r in reports if r.state == "paused"]
    if paused:
        # Prefect's Paused state carries no result and expects a resume through its API; the
        # labels resume a clip instead (a new flow run), so the run completes, named Paused.
        waits = "; ".join(f"{r.clip} {r.stage}: {r.message}" for r in paused)
        return Completed(name="Paused", message=f"{message}, {len(paused)} paused: {waits}", data=reports)
    return Completed(message=message, data=reports)
