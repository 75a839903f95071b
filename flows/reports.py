"""What a flow run reports: one :class:`StageReport` per stage run, and the flow's final state."""

from __future__ import annotations

import concurrent.futures

from prefect.futures import PrefectFuture, wait
from prefect.states import Completed, Failed, State

from flows.runtime import sigterm_ends_the_run
from tasks.stage_chain import StageReport


WHOLE_UNIT = "stages"
"""The stage name of the report of a unit whose task failed as a whole (not in one of its stages)."""
_KEPT: dict[str, list[StageReport]] = {}
"""Each flow run's reports, by flow run id, as its final state carried them in this process
(:func:`final_state`): the state Prefect hands back sometimes lacks its data (the server's copy of
it: ``MissingResult``, seen once in a Dask worker on a loaded machine), and no clip's reports may
be lost that way (:func:`state_reports`). The oldest go past :data:`KEEP_AT_MOST` (a served
deployment's runs are never read back here)."""
KEEP_AT_MOST = 256
AWAKE_S = 0.2
"""How often the main thread wakes while it waits for a flow run's tasks (:func:`finish`)."""


def unit_reports(unit: str, future: PrefectFuture) -> list[StageReport]:
    """The reports of a finished unit task (:func:`flows.stage_chain.unit_stages`); a task that
    failed as a whole is one failed report."""
    state = future.state
    if state.is_completed():
        return state.result()
    error = state.result(raise_on_failure=False)
    return [StageReport(unit, WHOLE_UNIT, "failed", message=f"{type(error).__name__}: {error}")]


def finish(submitted: list[tuple[str, PrefectFuture]], what: str) -> State:
    """Wait for the submitted unit tasks (unit, future); the flow's final state carries every report."""
    with sigterm_ends_the_run():
        _wait_awake([fut for _, fut in submitted])
    return final_state([r for unit, fut in submitted for r in unit_reports(unit, fut)], what)


def _wait_awake(futures: list[PrefectFuture]) -> None:
    """Wait for ``futures`` (of Prefect's thread runner), waking every :data:`AWAKE_S`: Python runs a
    signal's handler in the main thread, and the kernel may hand a Ctrl-C or SIGTERM to any of the
    process's threads; one taken by a stage's thread left the main thread asleep on a lock until
    every task had ended (a `cad ingest` interrupted went on rendering the library: 1 run in 5 to 25)."""
    pending = {fut.wrapped_future for fut in futures}
    while pending:
        pending = concurrent.futures.wait(pending, timeout=AWAKE_S).not_done
    wait(futures)


def final_state(reports: list[StageReport], what: str) -> State:
    """The flow's final state over ``reports``: Failed when a stage failed, else Completed (named
    Paused, naming what waits, when a human task waits); it carries the reports."""
    from prefect.runtime import flow_run

    if flow_run.get_id():
        _KEPT[str(flow_run.get_id())] = reports
        while len(_KEPT) > KEEP_AT_MOST:
            del _KEPT[next(iter(_KEPT))]
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


def state_reports(state: State) -> list[StageReport]:
    """The reports a finished flow run's final ``state`` carries; when Prefect handed back a state
    without its data, those its run kept in this process (:data:`_KEPT`). A flow that raised (its
    state carries the exception, not reports) is raised again: a caller iterating it met "object is
    not iterable" and lost the cause."""
    from prefect.exceptions import MissingResult

    run_id = str(state.state_details.flow_run_id)
    try:
        result = state.result(raise_on_failure=False)
        if isinstance(result, BaseException):
            raise result
        return result
    except MissingResult:
        if run_id in _KEPT:
            return _KEPT[run_id]
        raise
    finally:
        _KEPT.pop(run_id, None)
