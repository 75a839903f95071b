"""How flows run: Prefect settings per warehouse, and the task runner from ``[prefect]``.

Prefect talks to the warehouse's server when ``cadestate server start`` left one up
(:mod:`flows.server`), or to ``PREFECT_API_URL`` when the user set it; otherwise it runs in
ephemeral mode: a temporary local API with its SQLite database under ``<warehouse>/_prefect/home``
(no server to start; its start, launched early by :mod:`flows.local_api`, costs a
command ~3 s more than a server that is up). Prefect caches nothing and persists no result: the cache
is the warehouse's ``runs`` table (:mod:`tasks.stage_chain`). Flow runs are named after what they run (``annotate_clip/<clip>``) and tagged with
the clips, their splits and the warehouse's CAD libraries, so the Prefect UI finds them.
"""

from __future__ import annotations

import contextlib
import functools
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from contextvars import ContextVar, copy_context
from pathlib import Path
from typing import NoReturn

from cadestate.config import Config, PrefectConfig
from flows.server import ServerError, prefect_home, running_server


def prepare_prefect_environment(root: Path, verbose: bool = False, startup_timeout_s: float = 180.0,
                                start_api: bool = False) -> str:
    """Set Prefect's environment defaults (and COLMAP's and Dask's log levels: quiet unless
    ``verbose``). Call before the first ``import prefect``. Returns the API
    Prefect will use: the warehouse's running server, ``$PREFECT_API_URL``, or '' (ephemeral). With
    ``start_api`` (a command that will run flows), the ephemeral API is launched now, in the background
    (:mod:`flows.local_api`)."""
    home = prefect_home(Path(root))
    home.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("PREFECT_HOME", str(home))
    if "PREFECT_API_URL" not in os.environ and (server := running_server(Path(root))) is not None:
        os.environ["PREFECT_API_URL"] = server.api_url
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", str(int(startup_timeout_s)))
    # Stage failures are reported by the caller (one line each); Prefect's own logs, tracebacks
    # included, show with --verbose. The ephemeral API runs in this process and logs under its own
    # level: without it, its shutdown on a busy machine printed ~150 lines of "Error flushing events"
    # tracebacks (run history it had not yet recorded) after a run that had succeeded.
    level = "INFO" if verbose else "CRITICAL"
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", level)
    os.environ.setdefault("PREFECT_SERVER_LOGGING_LEVEL", level)
    # Prefect's internal services log under a level of their own (ERROR): a server stopped under a
    # command printed an "EventsWorker failed to process item Event(...)" line of ~2,700 characters
    # every 7 s for minutes before the command's one-line error. --verbose keeps Prefect's default.
    if not verbose:
        os.environ.setdefault("PREFECT_INTERNAL_LOGGING_LEVEL", level)
    # Dask's (clips on a cluster, flows.dask_clips): ~40 INFO lines a run, a traceback at times when
    # the local cluster shuts down; read when distributed is imported, here and in local workers.
    os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", level.lower())
    # COLMAP (glog, read when pycolmap loads) logs ~2,000 lines per SfM run, and an error line for each
    # focal hypothesis that maps nothing (an expected outcome); the cameras stage reports what matters.
    os.environ.setdefault("GLOG_minloglevel", "0" if verbose else "3")
    api = os.environ.get("PREFECT_API_URL", "")
    if start_api and not api:
        from flows import local_api

        local_api.launch(Path(os.environ["PREFECT_HOME"]))
    return api


def run_flow(flow, config: Config, *args, run_name: str, tags: list[str]):
    """Run ``flow(*args)`` as a flow run named ``run_name`` with ``tags``, with this warehouse's
    Prefect settings and the configured task runner; returns the reports its final state carries
    (see :mod:`flows.reports`). Prefect's API failing to start is a :class:`ServerError` (one line)."""
    root = Path(config.warehouse.root).expanduser().resolve()
    prepare_prefect_environment(root, startup_timeout_s=config.prefect.startup_timeout_s)
    from prefect import tags as prefect_tags

    api = os.environ.get("PREFECT_API_URL", "")
    name = _RUN_NAME.set(run_name)
    try:
        if not api:
            start_ephemeral_api(config.prefect.startup_timeout_s)
        with prefect_tags(*tags), without_heartbeats(), ctrl_c_ends_the_run(), ends_with_its_server(root, api):
            state = configured(flow, config.prefect)(*args, return_state=True)
    except Exception as e:  # the flow's own failures are in its state: what gets here is Prefect's
        cause = api_failure(e)
        if cause is None:
            raise
        raise ServerError(api_error_line(api, cause)) from None
    finally:
        _RUN_NAME.reset(name)
    from flows.reports import state_reports

    return state_reports(state)


STAGES_STOP = "the stages in progress stop unfinished (the command run again resumes them)"
"""What a command's Ctrl-C, SIGTERM or server's end does to the stages it runs (here, or on a local Dask cluster)."""


CANCEL_WAIT_S = 3.0
"""How long Ctrl-C waits for the API to mark the flow run Cancelled before the process ends."""


@contextlib.contextmanager
def ctrl_c_ends_the_run() -> Iterator[None]:
    """Within the block (a flow run in this process's main thread), Ctrl-C ends the process at once:
    "interrupted", the Prefect API the command launched stopped, status 130. The thread runner had
    queued every stage of every clip, and ran them all before a KeyboardInterrupt got out. What a
    stage was writing is not published (partitions go in whole or not at all), and its run reads as
    interrupted: `cadestate run` resumes it; child processes (cad ingest's render pool) end with it
    (:func:`exit_now`). The exit handlers are not run: Prefect's wait on its own threads, which the
    interrupted ones may hold. Elsewhere (the annotation app's threads), or
    where Ctrl-C is ignored (a shell's background job), nothing changes. The flow run is marked
    Cancelled on the API first (:func:`cancel_flow_run`), so the Prefect UI does not show it running
    for ever. SIGTERM (``kill``, a service manager, ``timeout``) ends it the same way, status 143:
    as an exit it waited for every queued stage too (over a minute of `cad ingest`). Prefect's flow
    engine puts its own SIGTERM handler in place during the flow run, so the flow's wait for its
    stages takes this one back (:func:`sigterm_ends_the_run`)."""
    signals = ending_signals()
    if not signals:
        yield
        return
    from flows.local_api import stop_launched_now  # not in the handler: an import there may wait on the main thread's
    from prefect.client.orchestration import get_client
    from prefect.context import FlowRunContext
    from prefect.states import Cancelled

    def cancel_flow_run() -> None:
        """Mark this thread's flow run Cancelled, giving the API at most :data:`CANCEL_WAIT_S`."""
        run = FlowRunContext.get()
        if run is None or run.flow_run is None:
            return
        state = Cancelled(message="interrupted (Ctrl-C); the command run again resumes it")

        def send() -> None:
            with contextlib.suppress(Exception), get_client(sync_client=True) as client:
                client.set_flow_run_state(run.flow_run.id, state, force=True)

        sender = threading.Thread(target=copy_context().run, args=(send,), daemon=True)
        sender.start()
        sender.join(CANCEL_WAIT_S)

    def interrupted(signum, frame) -> None:
        say_ended(signum, STAGES_STOP)
        cancel_flow_run()
        stop_launched_now()
        exit_now(128 + signum)

    before = {s: signal.signal(s, interrupted) for s in signals}
    token = _ENDS_THE_RUN.set(interrupted if signal.SIGTERM in signals else None)
    try:
        yield
    finally:
        _ENDS_THE_RUN.reset(token)
        for s, handler in before.items():
            signal.signal(s, handler)


@contextlib.contextmanager
def ends_with_its_server(root: Path, api: str, what: str = STAGES_STOP,
                         stop_work: Callable[[], None] | None = None) -> Iterator[None]:
    """Within a command's flow run on this warehouse's server (``api`` is the URL it recorded; in
    the main thread), the server ending (``cadestate server stop``, a crash) ends the command within
    seconds, in one line with status 1, as Ctrl-C does: ``what`` happens to the work in progress
    (by default the stages in progress stop unfinished and the command run again resumes them),
    ``stop_work()`` first stops what runs beyond this process's children (:func:`exit_now`; the clips of
    a Dask cluster, :mod:`flows.dask_clips`). Prefect's client retried each call to the dead API
    for ~2.5 minutes before the command failed. A run on another API (``$PREFECT_API_URL``, the
    ephemeral one) or in another thread (the annotation app's resumes) is not watched."""
    from flows.server import end_with_server, read_server

    info = read_server(root)
    if info is None or not api or info.api_url != api.rstrip("/") or threading.current_thread() is not threading.main_thread():
        yield
        return

    over = threading.Lock()  # held by whichever comes first: the run's end, or the server's
    finished = threading.Event()

    def ended() -> None:
        with over:
            if finished.is_set():  # the run ended as the server did: it stands
                return
            with contextlib.suppress(OSError, ValueError):
                sys.stdout.flush()
                sys.stderr.write(f"\nerror: the Prefect server at {api} stopped under this run: {what}; "
                                 "`cadestate server start` starts it again (without it, commands run on their own)\n")
                sys.stderr.flush()
            if stop_work is not None:
                stop_work()
            exit_now(1)

    watching = end_with_server(info, ended)
    try:
        yield
    finally:
        with over:
            finished.set()
        watching.set()


def exit_now(status: int) -> NoReturn:
    """End this process at once with ``status`` (``os._exit``: its exit handlers would wait for the
    threads of the run it leaves), its child processes terminated first (a process pool's workers,
    cad ingest's renders, went on orphaned, holding the command's stderr) and the named semaphores
    of its multiprocessing objects (the pool's queues and locks) unlinked, as their finalizers do at
    a normal exit: else multiprocessing's resource tracker unlinked them after the process ended and
    printed a 2-line "leaked semaphore objects" warning under the command's one line."""
    from multiprocessing import synchronize, util

    import psutil

    for child in psutil.Process().children(recursive=True):
        with contextlib.suppress(psutil.Error):
            child.terminate()
    for finalizer in list(util._finalizer_registry.values()):  # those a normal exit runs
        if getattr(finalizer, "_callback", None) is synchronize.SemLock._cleanup:
            with contextlib.suppress(OSError):
                finalizer()
    os._exit(status)


def ending_signals() -> list[int]:
    """SIGINT and SIGTERM, those this process's main thread (the caller: none elsewhere) may take
    to end a run: not where one is ignored (a shell's background job) or handled already."""
    if threading.current_thread() is not threading.main_thread():
        return []
    import cadestate

    return [s for s, ours in ((signal.SIGINT, (signal.default_int_handler, signal.SIG_DFL)),
                              (signal.SIGTERM, (cadestate._exit_on_signal, signal.SIG_DFL)))
            if signal.getsignal(s) in ours]


def say_ended(signum: int, what: str) -> None:
    """After what was printed (stdout flushed, so it goes out whole), ``interrupted: what`` (SIGINT)
    or ``terminated: what`` on stderr."""
    with contextlib.suppress(OSError, ValueError):
        sys.stdout.flush()
        said = "interrupted" if signum == signal.SIGINT else "terminated"
        sys.stderr.write(f"\n{said}: {what}\n")
        sys.stderr.flush()


_ENDS_THE_RUN: ContextVar[object] = ContextVar("cadestate_ends_the_run", default=None)
"""The handler with which SIGTERM ends a flow run of this process at once (None: not in such a run)."""


@contextlib.contextmanager
def sigterm_ends_the_run() -> Iterator[None]:
    """Within a flow run :func:`ctrl_c_ends_the_run` started (a command's, not a served run's, whose
    SIGTERM is Prefect's cancellation), SIGTERM ends the process at once, as Ctrl-C does; Prefect's
    engine had put its own handler in place, which waited for every queued stage."""
    handler = _ENDS_THE_RUN.get()
    if handler is None or threading.current_thread() is not threading.main_thread():
        yield
        return
    before = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, before)


_NO_HEARTBEATS: dict[int, tuple[object, object]] = {}
"""id of Prefect settings -> (those settings, kept so that the id stays theirs; a copy with flow
heartbeats off)."""


def without_heartbeats():
    """Prefect's settings context with flow run heartbeats off. Their thread's join ended every run
    with up to a second's wait (0.7 s of a 1.4 s label round in the annotation app); served runs
    (`cadestate serve`) run in the runner's processes and keep them. The copy of the settings is made
    once per settings object (``temporary_settings`` rebuilds them: 43 ms a run here)."""
    from prefect.context import SettingsContext, get_settings_context
    from prefect.settings import PREFECT_FLOWS_HEARTBEAT_FREQUENCY

    context = get_settings_context()
    if id(context.settings) not in _NO_HEARTBEATS:
        _NO_HEARTBEATS[id(context.settings)] = (
            context.settings, context.settings.copy_with_update(updates={PREFECT_FLOWS_HEARTBEAT_FREQUENCY: None}))
    return SettingsContext(profile=context.profile, settings=_NO_HEARTBEATS[id(context.settings)][1])


_RUN_NAME: ContextVar[str] = ContextVar("cadestate_flow_run_name", default="")
"""The name :func:`run_flow` gives the flow run it starts (read by :func:`_run_name`)."""


def _run_name() -> str:
    return _RUN_NAME.get() or "cadestate"


@functools.lru_cache(maxsize=32)
def configured(flow, cfg: PrefectConfig):
    """``flow`` with the task runner of ``cfg`` and its run named by :func:`run_flow`, built once
    per process: ``with_options`` rebuilds the flow's parameter schema (0.2 s a call). Prefect
    starts a copy of the task runner for each run, so runs may share it."""
    return flow.with_options(task_runner=task_runner(cfg), flow_run_name=_run_name)


FIRST_TRY_SHARE = 1 / 3
"""Share of ``[prefect] startup_timeout_s`` the ephemeral API's first try gets; a retry gets the rest."""


def start_ephemeral_api(timeout_s: float) -> str:
    """Start this process's ephemeral Prefect API (what Prefect starts on first use when no
    ``PREFECT_API_URL`` is set) and return its URL; started already, return at once. Its server
    subprocess sometimes starts and never answers (PrefectHQ/prefect#16397, #20247; here once in
    CI on a 180 s timeout, where a start takes ~15 s): after :data:`FIRST_TRY_SHARE` of
    ``timeout_s`` the server is killed and another started on a new port, with the rest of the
    time. Its failing too is Prefect's ``RuntimeError`` (see :func:`api_failure`). The first try is
    the API :func:`prepare_prefect_environment` launched if it did (:func:`flows.local_api.adopt`);
    else Prefect starts one, in a home whose new database is copied from a migrated template
    (:func:`flows.prefect_db.seed_home`)."""
    from prefect.server.api.server import SubprocessASGIServer

    from flows import local_api
    from flows.prefect_db import seed_home

    server = SubprocessASGIServer()  # one per process until stopped: get_client() finds this one
    if server.running:
        return server.api_url
    launched = local_api.take()
    try:
        if launched is not None:
            local_api.adopt(server, launched, timeout_s * FIRST_TRY_SHARE)
        else:
            if os.environ.get("PREFECT_HOME"):
                seed_home(Path(os.environ["PREFECT_HOME"]))
            server.start(timeout=timeout_s * FIRST_TRY_SHARE)
    except RuntimeError:
        server.stop()  # kills the subprocess and forgets the instance: the next gets a new port
        server = SubprocessASGIServer()
        server.start(timeout=timeout_s * (1 - FIRST_TRY_SHARE))
    return server.api_url


API_FAILURES = ("Prefect API", "Failed to reach API")
"""Words of the RuntimeErrors Prefect raises when its API (ephemeral or a server) does not start or answer."""


def _chain(e: BaseException) -> Iterator[BaseException]:
    """``e`` and the exceptions it was raised from or while handling, outermost first."""
    seen: set[int] = set()
    current: BaseException | None = e
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        yield current
        current = current.__cause__ or current.__context__


def api_failure(e: BaseException) -> str | None:
    """What went wrong, in one line, when ``e`` means Prefect's API did not start or could not be
    reached (a connection refused or timed out, an HTTP error from the API, Prefect's own "Failed to
    reach API" / "Prefect API" errors); None for any other exception."""
    import httpx

    causes = [c for c in _chain(e) if isinstance(c, (httpx.TransportError, httpx.HTTPStatusError, ConnectionError,
                                                     TimeoutError))]
    prefect_says = isinstance(e, RuntimeError) and any(w in str(e) for w in API_FAILURES)
    if not causes and not prefect_says:
        return None
    parts = ([str(e)] if prefect_says else []) + [f"{type(c).__name__}: {c}" for c in causes[-1:]]
    return " ".join(": ".join(dict.fromkeys(p.rstrip(":. ") for p in parts if p)).split())


def api_error_line(api: str, cause: str) -> str:
    """The one line for Prefect's API failing: the cause, and the fix for the API in use (``api``:
    ``$PREFECT_API_URL`` or the warehouse's server; '' for the ephemeral API)."""
    if api:
        return (f"Prefect's API at {api} could not be reached ({cause}): start that server, or unset "
                "PREFECT_API_URL (then `cadestate server start` runs one for this warehouse)")
    return (f"Prefect's API could not be reached ({cause}): start a server once with `cadestate server start` "
            "(commands then reuse it), or give it longer with [prefect] startup_timeout_s")


def run_tags(root: Path, clips: dict[str, str]) -> list[str]:
    """Tags of a flow run over ``clips`` (name -> split): ``clip:<name>`` (up to 20 clips),
    ``split:<split>`` and ``library:<name>`` for each CAD library of the warehouse."""
    from warehouse import Warehouse

    libraries = Warehouse(root).partitions("cad_models")
    clip_tags = [f"clip:{c}" for c in sorted(clips)] if len(clips) <= 20 else []
    return clip_tags + [f"split:{s}" for s in sorted(set(clips.values()))] + [f"library:{lib}" for lib in libraries]


def task_runner(cfg: PrefectConfig):
    """Prefect's thread runner of ``max_workers`` threads, whatever ``task_runner`` says: on Dask,
    clips go to the cluster whole (:func:`flows.annotate_clip.run_clips`, :mod:`flows.dask_clips`)
    and run there on threads; the other flows (the CAD library's, built before the clips; exports,
    reports) run in this process."""
    from prefect.task_runners import ThreadPoolTaskRunner

    return ThreadPoolTaskRunner(max_workers=cfg.max_workers)
