"""How flows run: Prefect settings per warehouse, and the task runner from ``[prefect]``.

Prefect runs in ephemeral mode unless ``PREFECT_API_URL`` points at a server: a temporary local
API with its SQLite database under ``<warehouse>/_prefect/home`` (no server to start). Cached task
results live under ``<warehouse>/_prefect/results``, so a warehouse carries its own cache and
deleting the warehouse deletes it too.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

from cadestate.config import Config, PrefectConfig


def prepare_prefect_environment(root: Path, verbose: bool = False) -> None:
    """Set Prefect's environment defaults. Call before the first ``import prefect``."""
    home = Path(root) / "_prefect" / "home"
    home.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("PREFECT_HOME", str(home))
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "180")
    os.environ.setdefault("PREFECT_RESULTS_PERSIST_BY_DEFAULT", "true")
    # Stage failures are reported by the caller (one line each); Prefect's own logs, tracebacks
    # included, show with --verbose.
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "INFO" if verbose else "CRITICAL")


@contextlib.contextmanager
def warehouse_results(root: Path) -> Iterator[None]:
    """Within the block, persisted task results (the cache) go to ``<root>/_prefect/results``."""
    from prefect.settings import PREFECT_LOCAL_STORAGE_PATH, temporary_settings

    with temporary_settings(updates={PREFECT_LOCAL_STORAGE_PATH: str(Path(root) / "_prefect" / "results")}):
        yield


def run_flow(flow, config: Config, *args):
    """Run ``flow(*args)`` with this warehouse's Prefect settings and the configured task runner;
    returns the reports its final state carries (see :mod:`flows.reports`)."""
    root = Path(config.warehouse.root).expanduser().resolve()
    prepare_prefect_environment(root)
    with warehouse_results(root):
        state = flow.with_options(task_runner=task_runner(config.prefect))(*args, return_state=True)
    return state.result(raise_on_failure=False)


def task_runner(cfg: PrefectConfig):
    """The task runner for ``[prefect] task_runner``: local threads, or Dask (local cluster or an address)."""
    if cfg.task_runner == "dask":
        from prefect_dask import DaskTaskRunner

        return DaskTaskRunner(address=cfg.dask_address) if cfg.dask_address else DaskTaskRunner()
    from prefect.task_runners import ThreadPoolTaskRunner

    return ThreadPoolTaskRunner(max_workers=cfg.max_workers)
