"""How flows run: Prefect settings per warehouse, and the task runner from ``[prefect]``.

Prefect talks to the warehouse's server when ``cadestate server start`` left one up
(:mod:`flows.server`), or to ``PREFECT_API_URL`` when the user set it; otherwise it runs in
ephemeral mode: a temporary local API with its SQLite database under ``<warehouse>/_prefect/home``
(no server to start, ~20 s per command). Cached task results live under
``<warehouse>/_prefect/results``, so a warehouse carries its own cache and deleting the warehouse
deletes it too. Flow runs are named after what they run (``annotate_clip/<clip>``) and tagged with
the clips, their splits and the warehouse's CAD libraries, so the Prefect UI finds them.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

from cadestate.config import Config, PrefectConfig
from flows.server import ServerError, prefect_home, running_server


def prepare_prefect_environment(root: Path, verbose: bool = False, startup_timeout_s: float = 180.0) -> str:
    """Set Prefect's environment defaults. Call before the first ``import prefect``. Returns the API
    Prefect will use: the warehouse's running server, ``$PREFECT_API_URL``, or '' (ephemeral)."""
    home = prefect_home(Path(root))
    home.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("PREFECT_HOME", str(home))
    if "PREFECT_API_URL" not in os.environ and (server := running_server(Path(root))) is not None:
        os.environ["PREFECT_API_URL"] = server.api_url
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", str(int(startup_timeout_s)))
    os.environ.setdefault("PREFECT_RESULTS_PERSIST_BY_DEFAULT", "true")
    # Stage failures are reported by the caller (one line each); Prefect's own logs, tracebacks
    # included, show with --verbose.
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "INFO" if verbose else "CRITICAL")
    return os.environ.get("PREFECT_API_URL", "")


@contextlib.contextmanager
def warehouse_results(root: Path) -> Iterator[None]:
    """Within the block, persisted task results (the cache) go to ``<root>/_prefect/results``."""
    from prefect.settings import PREFECT_LOCAL_STORAGE_PATH, temporary_settings

    with temporary_settings(updates={PREFECT_LOCAL_STORAGE_PATH: str(Path(root) / "_prefect" / "results")}):
        yield


def run_flow(flow, config: Config, *args, run_name: str, tags: list[str]):
    """Run ``flow(*args)`` as a flow run named ``run_name`` with ``tags``, with this warehouse's
    Prefect settings and the configured task runner; returns the reports its final state carries
    (see :mod:`flows.reports`). Prefect's API failing to start is a :class:`ServerError` (one line)."""
    root = Path(config.warehouse.root).expanduser().resolve()
    prepare_prefect_environment(root, startup_timeout_s=config.prefect.startup_timeout_s)
    from prefect import tags as prefect_tags

    try:
        with warehouse_results(root), prefect_tags(*tags):
            state = flow.with_options(task_runner=task_runner(config.prefect), flow_run_name=run_name)(*args, return_state=True)
    except RuntimeError as e:
        if "Prefect API" not in str(e):
            raise
        raise ServerError(f"Prefect's API could not be reached ({e}): start a server once with `cadestate server start` "
                          "(commands then reuse it), or give it longer with [prefect] startup_timeout_s") from None
    return state.result(raise_on_failure=False)


def run_tags(root: Path, clips: dict[str, str]) -> list[str]:
    """Tags of a flow run over ``clips`` (name -> split): ``clip:<name>`` (up to 20 clips),
    ``split:<split>`` and ``library:<name>`` for each CAD library of the warehouse."""
    from warehouse import Warehouse

    libraries = Warehouse(root).partitions("cad_models")
    clip_tags = [f"clip:{c}" for c in sorted(clips)] if len(clips) <= 20 else []
    return clip_tags + [f"split:{s}" for s in sorted(set(clips.values()))] + [f"library:{lib}" for lib in libraries]


def task_runner(cfg: PrefectConfig):
    """The task runner for ``[prefect] task_runner``: local threads, or Dask (local cluster or an address)."""
    if cfg.task_runner == "dask":
        from prefect_dask import DaskTaskRunner

        return DaskTaskRunner(address=cfg.dask_address) if cfg.dask_address else DaskTaskRunner()
    from prefect.task_runners import ThreadPoolTaskRunner

    return ThreadPoolTaskRunner(max_workers=cfg.max_workers)
