"""Clips on a Dask cluster (``[prefect] task_runner = "dask"``): one Dask task per clip, each running
that clip's whole ``annotate_clip`` flow inside a worker process.

Shipping every stage to Dask as a Prefect task cost 2.9x the CPU of threads (issue 21): each stage
paid a round trip and a Prefect task run in a fresh worker context. Here a worker takes a whole clip
and runs its stage chain there with Prefect's thread runner (as ``task_runner = "threads"`` runs
it), so a clip's stages stay in one process and the per-process caches (the detector session, the
retrieval index) serve every stage of every clip the worker takes.

What the workers share: the warehouse, at the same absolute path on every worker (a shared file
system, checked: each worker must read a token file the command leaves in the warehouse root, else
the command is refused in one line naming the workers, :func:`check_workers_see`, and a clip given
to a worker that joined later fails so; partition files are swapped in by atomic renames, a
replace-mode partition by the ``renameat2`` exchange of two folders (:func:`cadestate.atomic.exchange`: not on NFS), and
append-mode partitions are locked with ``flock``, so several processes write it safely), and the
clips' input files. The CAD library is
built beforehand (``cadestate cad ingest``): clip stages only read it.

Prefect in the workers: every worker process talks to one Prefect API, handed to it with the clip.
That is the warehouse's server or ``$PREFECT_API_URL`` when one is in use; otherwise the ephemeral
API that this process starts (as the thread runner does), which listens on 127.0.0.1: workers on
this machine (a local cluster, or one on loopback) reach it, workers on other machines need a
server they can reach (``PREFECT_API_URL``; workers that cannot reach the API are refused before any
clip, in one line naming them: :func:`check_workers_reach_api`). A worker keeps the API of its first clip (Prefect
reads its settings once per process), and the ephemeral API ends with its command: a cluster that
outlives commands needs a server (``cadestate server start``), else the next command is refused
in one line (:func:`check_workers_api`). So flow runs, their names and tags are the same as with
threads, and so is the cache (the warehouse's ``runs`` table, :mod:`tasks.stage_chain`): an
unchanged rerun on Dask is cached, a clip waiting for people ends
``paused``. A worker must not import Prefect before its first clip (Prefect reads its settings
when imported): :func:`annotate_clip_here` sets them first.

Before any clip, the workers are checked, each refusal one line naming them: a scheduler no worker
joined (within ``startup_timeout_s``), workers that cannot run cadestate's code (another environment:
:func:`on_workers`), that do not see the warehouse, talk to or cannot reach another Prefect API, or
would read other model files than this command (their own ``$CADESTATE_MODELS``:
:func:`check_workers_read_the_same_models`). A clip whose task fails as a whole (its worker lost
three times, a worker that joined later and cannot run it) is one ``failed`` report of stage
``annotate_clip``; the other clips go on.
Ctrl-C or SIGTERM ends the command at once, as with threads (:func:`signals_end_the_clips`), and so
does the warehouse's Prefect server stopping under it (:func:`flows.runtime.ends_with_its_server`,
status 1): a local cluster's workers are killed; a remote cluster's finish the clips they run.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as dt
import os
import signal
import sys
import threading
import urllib.parse
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from cadestate.config import Config, PrefectConfig, absolute_paths

if TYPE_CHECKING:
    from distributed import Client, Future

    from tasks.stage_chain import StageReport
    from tasks.video.ingest import ClipSource

WHOLE_CLIP = "annotate_clip"
"""The stage name of the report of a clip whose Dask task failed as a whole."""

API_CHECK_TIMEOUT_S = 10.0
"""Seconds a worker waits for Prefect's API to answer its health check (:func:`check_workers_reach_api`)."""

_WORKER_API: list[str] = []
"""The Prefect API this worker process was set up for (at most one entry)."""


@dataclass(frozen=True)
class ClipOutcome:
    """One clip's Dask task: its stage reports and where it ran (``worker``: the Dask worker's
    address; ``pid``: its process)."""

    clip: str
    reports: list[StageReport]
    worker: str
    pid: int


def _prepare_worker(root: str, api_url: str) -> None:
    """Point this worker process's Prefect at ``api_url`` (before Prefect is imported here; a later
    clip for another API is refused: Prefect's settings are read once per process)."""
    if _WORKER_API:
        if _WORKER_API[0] != api_url:
            raise RuntimeError(f"this Dask worker talks to Prefect's API at {_WORKER_API[0]}, not {api_url}: "
                               "restart the workers to change the API")
        return
    if "prefect" in sys.modules and os.environ.get("PREFECT_API_URL") != api_url:
        raise RuntimeError(f"Prefect was imported in this Dask worker before cadestate set its API ({api_url}): "
                           "start the workers without preloading Prefect, or with PREFECT_API_URL set to it")
    os.environ["PREFECT_API_URL"] = api_url
    from flows.runtime import prepare_prefect_environment

    prepare_prefect_environment(Path(root))
    _WORKER_API.append(api_url)


PROBE_PREFIX = ".dask-probe-"
"""Name prefix of the token file a command leaves in the warehouse root while its clips run on Dask
(:func:`warehouse_probe`): a worker that reads the token there sees the driver's warehouse."""


@contextlib.contextmanager
def warehouse_probe(root: str) -> Iterator[tuple[str, str]]:
    """A token file in the warehouse root (``root``: absolute, existing) for the block: ``(its path,
    the token it holds)``, removed after."""
    token = uuid.uuid4().hex
    path = Path(root) / f"{PROBE_PREFIX}{token[:12]}"
    path.write_text(token, encoding="utf-8")
    try:
        yield str(path), token
    finally:
        path.unlink(missing_ok=True)


def _sees_probe(path: str, token: str) -> bool:
    """Whether this process reads ``token`` in the file at ``path`` (the driver's warehouse probe)."""
    try:
        return Path(path).read_text(encoding="utf-8") == token
    except (OSError, UnicodeDecodeError):
        return False


def _blind_line(workers: list[str], root: str) -> str:
    """The one line for Dask workers that do not see the warehouse at ``root``."""
    return (f"the Dask worker(s) {', '.join(workers)} do not see the warehouse at {root} (its files are not "
            "those of this machine): workers need it at the same path on a shared file system")


def on_workers(client: Client, function: Callable[..., object], *args: object) -> dict[str, object]:
    """``function(*args)`` on every worker of ``client``: worker address -> result. Refuses
    (:class:`flows.server.ServerError`, one line naming them) workers where it raised: cadestate's
    code not importable there (another environment or checkout) failed the command with a traceback."""
    from flows.server import ServerError

    results = client.run(function, *args, on_error="return")
    broken = sorted(w for w, r in results.items() if isinstance(r, BaseException))
    if broken:
        raise ServerError(f"the Dask worker(s) {', '.join(broken)} cannot run cadestate's code "
                          f"({_first_line(results[broken[0]])}): start them in this checkout's environment "
                          "(its virtual environment, or PYTHONPATH naming it)")
    return results


def check_workers_see(client: Client, root: str, probe: tuple[str, str]) -> None:
    """Refuse (:class:`flows.server.ServerError`, one line naming them) workers that do not read the
    token of ``probe`` (:func:`warehouse_probe`): without a shared file system they would write a
    warehouse of their own, and every stage would report ``completed`` into nothing."""
    from flows.server import ServerError

    blind = sorted(w for w, sees in on_workers(client, _sees_probe, *probe).items() if not sees)
    if blind:
        raise ServerError(_blind_line(blind, root))


def _worker_api() -> str:
    """The Prefect API this worker process was set up for ('' before its first clip)."""
    return _WORKER_API[0] if _WORKER_API else ""


def check_workers_api(client: Client, api_url: str) -> None:
    """Refuse (:class:`flows.server.ServerError`, one line) a cluster whose workers were set up for
    another Prefect API than ``api_url``: a cluster that outlives a command, which started its own
    local API, would refuse every clip."""
    from flows.server import ServerError

    other = sorted({api for api in on_workers(client, _worker_api).values() if api and api != api_url})
    if other:
        raise ServerError(f"the Dask workers talk to Prefect's API at {other[0]}, not this command's ({api_url}): "
                          "a cluster that outlives one command needs a Prefect server they all keep "
                          "(`cadestate server start`), or restart the workers")


def _unreached_line(workers: list[str], api_url: str) -> str:
    """The one line for Dask workers whose health check of Prefect's API at ``api_url`` failed."""
    loopback = urllib.parse.urlsplit(api_url).hostname in ("127.0.0.1", "localhost", "::1")
    fix = ("it listens on this machine's loopback: run `cadestate server start --host 0.0.0.0` and set "
           "PREFECT_API_URL to its address as the workers see it" if loopback else
           "start the workers where it can be reached, or set PREFECT_API_URL to an address they reach")
    return f"the Dask worker(s) {', '.join(workers)} cannot reach Prefect's API at {api_url}: {fix}"


def check_workers_reach_api(client: Client, api_url: str, timeout_s: float) -> None:
    """Refuse (:class:`flows.server.ServerError`, one line naming them) workers on which Prefect's
    API at ``api_url`` (plain HTTP: an HTTPS one is left to Prefect's client, whose certificate and
    key settings a bare health check would not apply) does not answer its health check within
    ``timeout_s``: each of their clips would fail alone, after its worker had set Prefect up for that API."""
    from flows.server import ServerError, healthy

    if urllib.parse.urlsplit(api_url).scheme != "http":  # TLS: Prefect's client settings (certificates, keys) decide
        return
    unreached = sorted(w for w, ok in on_workers(client, healthy, api_url, timeout_s).items() if not ok)
    if unreached:
        raise ServerError(_unreached_line(unreached, api_url))


def environment_inputs(config: Config) -> dict[str, list[str]]:
    """What each clip stage reads from files its config and this process's environment name (its
    ``config_inputs``: the detector's model file, the descriptor under ``$CADESTATE_MODELS``)."""
    from tasks.registry import stages_of

    return {stage.name: stage.config_inputs(config) for stage in stages_of("clip")}


def check_workers_read_the_same_models(client: Client, config: Config) -> None:
    """Refuse (:class:`flows.server.ServerError`, one line naming them) workers whose stages would
    read other model files than this command's (:func:`environment_inputs`): a worker on another
    machine finds the models under its own ``$CADESTATE_MODELS`` (else ``~/.cache/cadestate/models``),
    and ran its clips with another detector, which ``cadestate status`` then called stale."""
    from flows.server import ServerError

    mine = environment_inputs(config)
    other = {w: theirs for w, theirs in on_workers(client, environment_inputs, config).items() if theirs != mine}
    if other:
        first = sorted(other)[0]
        stages = [name for name, inputs in mine.items() if other[first].get(name) != inputs]
        raise ServerError(f"the Dask worker(s) {', '.join(sorted(other))} read other model files than this command "
                          f"(stage(s) {', '.join(stages)}): give them the same files ($CADESTATE_MODELS, else "
                          "~/.cache/cadestate/models, on each; `make models` builds them)")


def annotate_clip_here(root: str, source: ClipSource, config: Config, api_url: str,
                       probe: tuple[str, str]) -> ClipOutcome:
    """Run in a Dask worker: the whole ``annotate_clip`` flow of ``source`` with Prefect's thread
    runner (as many threads as the worker has), against the Prefect API at ``api_url``. A worker
    that does not read the token of ``probe`` (one that joined after :func:`check_workers_see`) is
    refused in one line before it touches anything: it never creates a warehouse of its own."""
    from distributed import get_worker

    worker = get_worker()
    if not _sees_probe(*probe):
        raise RuntimeError(_blind_line([worker.address], root))
    _prepare_worker(root, api_url)
    from flows.annotate_clip import annotate_clip
    from flows.runtime import run_flow, run_tags

    here = dataclasses.replace(config, prefect=dataclasses.replace(
        config.prefect, task_runner="threads", max_workers=max(1, worker.state.nthreads)))
    reports = run_flow(annotate_clip, here, root, source, here, False, run_name=f"annotate_clip/{source.clip}",
                       tags=run_tags(Path(root), {source.clip: source.split}))
    return ClipOutcome(source.clip, reports, worker.address, os.getpid())


@contextlib.contextmanager
def _environ(name: str, value: str) -> Iterator[None]:
    """``$name`` is ``value`` within the block, as it was after."""
    before = os.environ.get(name)
    os.environ[name] = value
    try:
        yield
    finally:
        if before is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = before


@contextlib.contextmanager
def dask_client(cfg: PrefectConfig, api_url: str) -> Iterator[Client]:
    """A client of the scheduler at ``[prefect] dask_address``; without one, of a local cluster of
    ``max_workers`` worker processes with one thread each, closed after the block. The local workers
    are spawned with ``$PREFECT_API_URL`` = ``api_url``: a spawned process imports the parent's main
    module again, and when that imports Prefect, Prefect reads its settings there, before any clip."""
    from distributed import Client, LocalCluster

    from flows.server import ServerError

    if cfg.dask_address:
        try:
            client = Client(cfg.dask_address, timeout=cfg.startup_timeout_s)
        except (OSError, TimeoutError) as e:
            raise ServerError(f"[prefect] dask_address {cfg.dask_address}: no Dask scheduler answered within "
                              f"{cfg.startup_timeout_s:g} s ({_first_line(e)}); start it (`dask scheduler`), or leave "
                              "dask_address empty for a local cluster") from None
        with client:
            try:
                client.wait_for_workers(1, timeout=cfg.startup_timeout_s)
            except TimeoutError:
                raise ServerError(f"[prefect] dask_address {cfg.dask_address}: the scheduler has no worker after "
                                  f"{cfg.startup_timeout_s:g} s; start some (`dask worker {cfg.dask_address}`)") from None
            yield client
        return
    try:
        with _environ("PREFECT_API_URL", api_url):
            # the scheduler's web server always starts: on a free loopback port, without the dashboard
            cluster = LocalCluster(n_workers=cfg.max_workers, threads_per_worker=1, processes=True,
                                   dashboard_address="127.0.0.1:0", scheduler_kwargs={"dashboard": False})
    except (OSError, TimeoutError, RuntimeError) as e:
        raise ServerError(f"a local Dask cluster of {cfg.max_workers} worker(s) did not start ({_first_line(e)}); "
                          "lower [prefect] max_workers, or use task_runner = \"threads\"") from None
    with cluster, Client(cluster) as client:
        yield client


CANCEL_WAIT_S = 3.0
"""How long Ctrl-C or SIGTERM waits for the scheduler to cancel the clips (and Prefect's API to mark
their flow runs Cancelled) before the command ends."""

REMOTE_CLIPS_GO_ON = ("the clips not started are cancelled; those running on the cluster's workers run to their end "
                      "(`cadestate run` does the rest)")
"""What a command's Ctrl-C or SIGTERM does to its clips on a cluster of ``dask_address``."""


def _cancel_flow_runs(api_url: str, clips: list[str], since: dt.datetime) -> None:
    """Mark Cancelled the running ``annotate_clip`` flow runs of ``clips`` started since ``since``
    on the Prefect API at ``api_url`` (their worker processes were killed: else the Prefect UI shows
    them running for ever); failures to reach the API are ignored."""
    from prefect.client.orchestration import SyncPrefectClient
    from prefect.client.schemas.filters import (FlowRunFilter, FlowRunFilterName, FlowRunFilterStartTime,
                                                FlowRunFilterState, FlowRunFilterStateType)
    from prefect.client.schemas.objects import StateType
    from prefect.client.schemas.sorting import FlowRunSort
    from prefect.states import Cancelled

    running = FlowRunFilter(name=FlowRunFilterName(any_=[f"{WHOLE_CLIP}/{c}" for c in clips]),
                            state=FlowRunFilterState(type=FlowRunFilterStateType(any_=[StateType.RUNNING])),
                            start_time=FlowRunFilterStartTime(after_=since))
    with contextlib.suppress(Exception), SyncPrefectClient(api_url) as prefect:
        for run in prefect.read_flow_runs(flow_run_filter=running, sort=FlowRunSort.START_TIME_DESC,
                                          limit=len(clips)):
            prefect.set_flow_run_state(run.id, Cancelled(message="interrupted (Ctrl-C or SIGTERM); `cadestate run` "
                                                                 "resumes its clip"), force=True)


def _stop_clips_now(client: Client, futures: dict[Future, int], probe: str,
                    then: Callable[[], None] | None = None) -> None:
    """Stop the clips of ``futures`` at once: a local cluster's worker processes are killed (the
    stages in progress stop unfinished, read as interrupted: `cadestate run` resumes them), the
    clips cancelled on the scheduler (on a cluster of ``dask_address``, those not started: Dask does
    not stop a running task), then ``then()``, both given at most :data:`CANCEL_WAIT_S`; the token
    file ``probe`` is removed."""
    for nanny in client.cluster.workers.values() if client.cluster is not None else ():
        with contextlib.suppress(AttributeError, OSError):  # a worker process not started, or gone
            os.kill(nanny.process.process.pid, signal.SIGKILL)

    def cancel() -> None:
        client.cancel(list(futures), force=True)
        if then is not None:
            then()

    stopping = threading.Thread(target=cancel, daemon=True)
    stopping.start()
    stopping.join(CANCEL_WAIT_S)
    with contextlib.suppress(OSError):
        Path(probe).unlink(missing_ok=True)


def _what_stops(client: Client) -> str:
    """What ending the command does to its clips on the cluster of ``client`` (local or not)."""
    from flows.runtime import STAGES_STOP

    return STAGES_STOP if client.cluster is not None else REMOTE_CLIPS_GO_ON


@contextlib.contextmanager
def signals_end_the_clips(client: Client, futures: dict[Future, int], clips: list[str], api_url: str,
                          probe: str) -> Iterator[None]:
    """Within the block (the main thread waiting for ``futures``, future -> index in ``clips``, a
    dict it empties as they end), Ctrl-C or SIGTERM ends the command at once, status 128 + the
    signal, as with threads (:func:`flows.runtime.ctrl_c_ends_the_run`): the clips stop
    (:func:`_stop_clips_now`), a local cluster's flow runs are marked Cancelled on the Prefect API at
    ``api_url``, and the Prefect API the command launched is stopped. Elsewhere, or where the
    signals are not ours, nothing changes."""
    from flows.local_api import stop_launched_now  # not in the handler: an import there may wait on the main thread's
    from flows.runtime import ending_signals, exit_now, say_ended

    signals = ending_signals()
    if not signals:
        yield
        return
    since = dt.datetime.now(dt.timezone.utc)

    def end(signum, frame) -> None:
        local = client.cluster is not None
        say_ended(signum, _what_stops(client))
        unfinished = [clips[i] for i in list(futures.values())]
        _stop_clips_now(client, futures, probe, then=lambda: local and _cancel_flow_runs(api_url, unfinished, since))
        stop_launched_now()
        exit_now(128 + signum)

    before = {s: signal.signal(s, end) for s in signals}
    try:
        yield
    finally:
        for s, handler in before.items():
            signal.signal(s, handler)


def _first_line(e: BaseException) -> str:
    """``Type: first line of the message`` of ``e``."""
    return f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"


def prefect_api_url(config: Config) -> str:
    """The Prefect API the workers talk to: the one in use (the warehouse's server or
    ``$PREFECT_API_URL``), else this process's ephemeral API, started now."""
    from flows.runtime import prepare_prefect_environment, start_ephemeral_api

    root = Path(config.warehouse.root).expanduser().resolve()
    api = prepare_prefect_environment(root, startup_timeout_s=config.prefect.startup_timeout_s)
    return api or start_ephemeral_api(config.prefect.startup_timeout_s)


def _failed(clip: str, e: BaseException, local: bool) -> ClipOutcome:
    """The failed outcome of a clip whose Dask task failed as a whole: its error, one line; for
    distributed's ``KilledWorker`` (which names no cause, and a long URL) what may have killed them
    (``local``: on a local cluster, whose memory limits the config sets)."""
    from tasks.stage_chain import StageReport
    from warehouse.catalog import one_line

    message = f"{type(e).__name__}: {e}"
    if type(e).__name__ == "KilledWorker":
        last = getattr(getattr(e, "last_worker", None), "address", "?")
        message = f"KilledWorker: every worker that ran it died (the last: {last}): out of memory? " + (
            "a local cluster gives each worker the machine's memory / [prefect] max_workers and kills it at 95 %: "
            "lower max_workers, or use task_runner = \"threads\"" if local else
            "a worker is killed at 95 % of its --memory-limit: see the workers' logs, give them more memory")
    return ClipOutcome(clip, [StageReport(clip, WHOLE_CLIP, "failed", message=one_line(message))], "", 0)


def progress_line(outcome: ClipOutcome, done: int, total: int) -> str:
    """One line for a finished clip: ``[done/total] clip: N completed, N paused, ... (worker)``."""
    counts: dict[str, int] = {}
    for report in outcome.reports:
        counts[report.state] = counts.get(report.state, 0) + 1
    states = ", ".join(f"{n} {state}" for state, n in counts.items())
    return f"[{done}/{total}] {outcome.clip}: {states}" + (f" ({outcome.worker})" if outcome.worker else "")


def run_clips_on_dask(sources: list[ClipSource], config: Config, show_progress: bool = False) -> list[ClipOutcome]:
    """Run every clip of ``sources`` as one Dask task on the cluster of ``config.prefect``, in
    ``sources`` order; a clip whose task fails is a failed outcome, the others go on. A clip's
    result is let go once read, so a worker lost later does not run its finished clips again; with
    ``show_progress`` a line on stderr says how it ended (:func:`progress_line`). The workers
    get absolute paths (the warehouse, the clips' files, the files the config names: theirs may
    run in another folder)."""
    from distributed import as_completed

    from flows.runtime import ServerError, api_error_line, api_failure, ends_with_its_server
    from warehouse import Warehouse
    from warehouse.catalog import ensure_catalog

    root = str(Path(config.warehouse.root).expanduser().resolve())
    # Workers resolve paths in their own working directory: theirs are absolute
    config = absolute_paths(dataclasses.replace(config, warehouse=dataclasses.replace(config.warehouse, root=root)))
    ensure_catalog(Warehouse(root))
    try:
        api_url = prefect_api_url(config)
    except Exception as e:
        cause = api_failure(e)
        if cause is None:
            raise
        raise ServerError(api_error_line(os.environ.get("PREFECT_API_URL", ""), cause)) from None
    sources = [dataclasses.replace(s, video=s.video.resolve(), cameras=s.cameras and s.cameras.resolve()) for s in sources]
    outcomes: dict[int, ClipOutcome] = {}
    with dask_client(config.prefect, api_url) as client, warehouse_probe(root) as probe:
        check_workers_see(client, root, probe)
        check_workers_api(client, api_url)
        check_workers_reach_api(client, api_url, API_CHECK_TIMEOUT_S)
        check_workers_read_the_same_models(client, config)
        futures: dict[Future, int] = {}
        taking = threading.Lock()  # a clip's outcome is taken under it

        def server_ended() -> None:
            taking.acquire()  # for good: no clip's outcome (its workers killed) is said after the server's line
            _stop_clips_now(client, futures, probe[0])

        with signals_end_the_clips(client, futures, [s.clip for s in sources], api_url, probe[0]), \
                ends_with_its_server(Path(root), api_url, _what_stops(client), server_ended):
            futures.update({client.submit(annotate_clip_here, root, s, config, api_url, probe, pure=False,
                                          key=f"{WHOLE_CLIP}-{s.clip}-{uuid.uuid4().hex[:8]}"): i
                            for i, s in enumerate(sources)})
            for future in as_completed(list(futures)):
                with taking:
                    i = futures.pop(future)
                    try:
                        outcomes[i] = future.result()
                    except Exception as e:  # the clip's task as a whole: report it, go on with the others
                        outcomes[i] = _failed(sources[i].clip, e, client.cluster is not None)
                    future.release()  # a result still wanted is recomputed when its worker is lost: the clip again
                    if show_progress:
                        print(progress_line(outcomes[i], len(outcomes), len(sources)), file=sys.stderr, flush=True)
    return [outcomes[i] for i in range(len(sources))]
