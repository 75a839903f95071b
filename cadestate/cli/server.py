"""``cadestate server``: a real Prefect server for this warehouse, in the background."""

from __future__ import annotations

import asyncio
import logging
import threading
import warnings
from pathlib import Path
from typing import Annotated, Optional
from urllib.parse import urlsplit

import typer
from rich.markup import escape

from cadestate.cli.common import CliError, app, err, out

server_app = typer.Typer(help="A Prefect server for this warehouse (its database under the warehouse, or PostgreSQL): "
                              "while it is up every command uses it instead of starting Prefect's ephemeral API (~3 s more per command), "
                              "and its UI shows every flow run.", no_args_is_help=True)
app.add_typer(server_app, name="server")


@server_app.command("start")
def server_start(
    ctx: typer.Context,
    host: Annotated[Optional[str], typer.Option(help="Address to listen on.  [default: 127.0.0.1]",
                                                show_default=False)] = None,
    port: Annotated[Optional[int], typer.Option(min=0, max=65535, help="Port (0: a free one).  [default: 4200]",
                                                show_default=False)] = None,
    database_url: Annotated[str, typer.Option(help="SQLAlchemy URL of a PostgreSQL database "
                                                   "(postgresql+asyncpg://user:password@host/db); default: SQLite under "
                                                   "<warehouse>/_prefect/home.")] = "",
) -> None:
    """Start the server in the background (a no-op when it is up) and wait until it answers.

    Its PID, URL and log are kept under <warehouse>/_prefect/ (server.json, server.log);
    `cadestate server stop` stops it.

    \b
    Examples:
      cadestate server start
      # reachable from other machines, on a free port
      cadestate server start --host 0.0.0.0 --port 0
    """
    from flows.server import running_server, start_server

    root = ctx.obj.root()
    if (up := running_server(root)) is not None:  # what was asked of a new server, and is not so: said
        where = urlsplit(up.api_url)
        for option, given, now in (("--port", port, where.port), ("--host", host, where.hostname),
                                   ("--database-url", database_url or None, up.database_url)):
            if given not in (None, 0, now):
                err.print(f"already up at {escape(up.api_url)}: {option} {escape(str(given))} is not taken "
                          "(`cadestate server stop` first to change it)")
    info = up or start_server(root, host or "127.0.0.1", 4200 if port is None else port, database_url,
                              timeout_s=ctx.obj.config().prefect.startup_timeout_s)
    out.print(f"Prefect server up: {escape(info.api_url)} (UI {escape(info.api_url.removesuffix('/api'))}, "
              f"pid {info.pid}, log {escape(info.log)})")


@server_app.command("stop")
def server_stop(ctx: typer.Context) -> None:
    """Stop the server of this warehouse, and its `cadestate serve` first; commands fall back to
    ephemeral mode.

    \b
    Example:
      cadestate server stop
    """
    from flows.server import stop_server

    info, served = stop_server(ctx.obj.root())
    if served is not None:
        out.print(f"stopped `cadestate serve` (pid {served}); its schedules are paused until it serves again")
    out.print(f"stopped the Prefect server at {escape(info.api_url)} (pid {info.pid})" if info else "no server was started")


@server_app.command("status")
def server_status(ctx: typer.Context) -> None:
    """Whether this warehouse's server is up (exit status 0) or down (exit status 1).

    \b
    Example:
      cadestate server status || cadestate server start
    """
    from flows.server import read_server, running_server

    root = ctx.obj.root()
    if (info := running_server(root)) is not None:
        out.print(f"up: {escape(info.api_url)} (pid {info.pid}, since {info.started_at}, log {escape(info.log)})")
        return
    known = read_server(root)
    out.print(f"down (last started at {escape(known.api_url)}, pid {known.pid}: not answering; see {escape(known.log)})"
              if known else "down: commands run Prefect in ephemeral mode; `cadestate server start` starts one")
    raise typer.Exit(1)


@app.command()
def serve(ctx: typer.Context) -> None:
    """Serve the dataset-building deployments on this warehouse's Prefect server until stopped (Ctrl-C).

    \b
      build_dataset   on [schedule] inbox_cron: every new <name>.mp4 (.mov, ...)
                      + <name>.txt of [schedule] inbox gets an annotate_clip
                      run (half-copied files wait; <name>.done marks a pair
                      ready)
      ingest_labels   on [schedule] labels_cron: the label files of [schedule]
                      labels_inbox are ingested, the clips they answer resumed
      annotate_clip   one run per clip, suspended while people answer its tasks
      dataset_report  on [schedule] report_cron: statistics and an HTML report in
                      [schedule] report

    Start the server first (`cadestate server start`); its UI shows the runs, and a run can be
    started by hand there or with `PREFECT_API_URL=<URL of server status> prefect deployment run
    build_dataset_inbox/build_dataset`. Each scheduled flow runs one at a time. The schedules are
    set when serve starts: restart it after changing a [schedule] *_cron. One serve per warehouse;
    it ends when the server stops (`cadestate server stop` stops it first).

    \b
    Examples:
      cadestate server start
      cadestate serve
    """
    import os

    from flows.runtime import prepare_prefect_environment
    from flows.server import ServerError, end_with_server, running_server, serving_lock

    cfg = ctx.obj.config()
    root = ctx.obj.root()
    if (server := running_server(root)) is None:
        raise CliError(f"no Prefect server is up for {root}: start one with `cadestate server start`")
    if os.environ.get("PREFECT_API_URL", server.api_url).rstrip("/") != server.api_url:  # the same, named otherwise?
        err.print(f"warning: PREFECT_API_URL is {escape(os.environ['PREFECT_API_URL'])}, not the URL of this "
                  f"warehouse's server ({escape(server.api_url)}): the deployments are served there")
    try:
        lock = serving_lock(root)
    except ServerError as e:
        raise CliError(str(e)) from None
    end_with_server(server, lambda: _server_ended(server.api_url))
    # the server found above, not found again: a second look missed by a busy machine left the URL
    # unset, and the schedules went to a throwaway API of this process
    os.environ.setdefault("PREFECT_API_URL", server.api_url)
    prepare_prefect_environment(root, True, cfg.prefect.startup_timeout_s)  # serving shows Prefect's logs
    os.environ.setdefault("PREFECT_LOCAL_STORAGE_PATH", str(root / "_prefect" / "results"))
    from prefect import serve as prefect_serve

    from flows.deployments import crash_runs_left_running, deployments

    config_path = ctx.obj.config_path or (Path(cfg.source) if cfg.source else None)
    logging.getLogger("asyncio").addFilter(_quiet_cancelled_reads)
    # Prefect's runner calls its async stop without awaiting it on SIGTERM (it then stops anyway): a
    # RuntimeWarning with its "enable tracemalloc" line closed every clean `server stop`
    warnings.filterwarnings("ignore", message="coroutine 'Runner.astop' was never awaited", category=RuntimeWarning)
    try:
        if left := crash_runs_left_running(str(root)):  # an earlier serve's: they would block their clips
            err.print(f"marked Crashed {len(left)} run(s) an earlier serve left running: {escape(', '.join(left))} "
                      "(the inbox's next tick runs their clips again)")
        prefect_serve(*deployments(cfg, str(config_path.resolve()) if config_path else ""))
    except Exception:
        if not server.process_alive:  # ended while the deployments were being registered (or runs read)
            _server_ended(server.api_url)
        raise
    finally:
        lock.close()


def _quiet_cancelled_reads(record: logging.LogRecord) -> bool:
    """Drop asyncio's "Exception in callback" for a task cancelled as the loop ends: Prefect's runner
    ends its loop on SIGTERM (`server stop`) while a flow run's process may still be connected to
    its control channel, whose pending read is then cancelled (a traceback in the serve's log for
    a clean stop)."""
    exc = record.exc_info[1] if record.exc_info else None
    return not isinstance(exc, asyncio.CancelledError)


_ENDING = threading.Lock()


def _server_ended(api_url: str) -> None:
    """The server stopped under a serve: say so in one line and end, with the runs it started
    (their API is gone too: :func:`flows.runtime.exit_now`), instead of a traceback per poll."""
    from flows.runtime import exit_now

    if not _ENDING.acquire(blocking=False):  # the watch and the main thread both saw it: one says it
        threading.Event().wait()
    err.print(f"the Prefect server at {escape(api_url)} stopped: serve ends (`cadestate server start`, then serve again)")
    exit_now(1)
