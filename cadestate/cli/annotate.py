"""``cadestate annotate``: the human tasks in a browser (:mod:`cadestate.webapp`)."""

from __future__ import annotations

from typing import Annotated, Optional

import typer
from rich.markup import escape

from cadestate.cli.common import CliError, app, err


@app.command("annotate")
def annotate(
    ctx: typer.Context,
    host: Annotated[str, typer.Option(help="Address to listen on (127.0.0.1: this machine only).")] = "127.0.0.1",
    port: Annotated[int, typer.Option(min=1, max=65535, help="Port to listen on.")] = 8765,
    annotator: Annotated[Optional[str], typer.Option(help="Name recorded in every label file (default: the user name).")] = None,
) -> None:
    """Open the annotation app: the clips' waiting human tasks (manual tracks, CAD selection,
    correspondences, verification) as web pages. Each answer is validated as `labels ingest`
    validates a file, written to <warehouse>/labels/<clip>/, ingested, and its clip resumed in the
    background.

    \b
    Examples:
      # on this machine: open the address it prints
      cadestate annotate
      # for annotators on the network, each named in the label files
      cadestate annotate --host 0.0.0.0 --port 8080 --annotator alice
    """
    from flows.runtime import prepare_prefect_environment

    check_listen(host, port)
    cfg = ctx.obj.config()
    root = ctx.obj.open_warehouse(must_exist=True).root  # a typo in -w is no new, empty warehouse
    prepare_prefect_environment(root, ctx.obj.verbose, cfg.prefect.startup_timeout_s, start_api=True)  # before Prefect is imported
    import uvicorn

    from cadestate.webapp.app import create_app, three_dir

    if not three_dir().is_dir():
        err.print(f"[yellow]warning:[/] three.js not found at {escape(str(three_dir()))} (run `make web-vendor`): "
                  "the correspondences page cannot show models", highlight=False)
    shown = f"[{host}]" if ":" in host else host  # an IPv6 address goes in brackets in a URL
    err.print(f"annotation app for {escape(str(root))}: http://{escape(shown)}:{port}/  (Ctrl-C stops it)", highlight=False)
    application = create_app(cfg, annotator)
    try:
        uvicorn.run(application, host=host, port=port, log_level="warning")  # SIGTERM: flows.local_api
    except (KeyboardInterrupt, SystemExit) as e:
        _end_under_busy_worker(application.state.resumer, 130 if isinstance(e, KeyboardInterrupt) else e.code)
        raise
    _end_under_busy_worker(application.state.resumer, 0)


def _end_under_busy_worker(resumer, code: int | str | None) -> None:
    """End the process now, exit handlers run (the Prefect API it launched stopped), when the
    resume worker still runs after the app stopped: Python's own exit ends such a thread where it
    stands, and inside a native library's code (torch imported by the warm-up, a model running) that
    aborted the process (SIGABRT, "FATAL: exception not rethrown"). A clip's stages stopped so read
    as interrupted and run again on the next resume."""
    import atexit
    import os
    import sys

    if not resumer.alive():
        return
    err.print("stopped while the background resume was running: a clip it ran resumes on the next start", highlight=False)
    atexit._run_exitfuncs()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code if isinstance(code, int) else 0 if code is None else 1)


def check_listen(host: str, port: int) -> None:
    """Raise a one-line :class:`CliError` when nothing could listen on ``host:port`` (the port taken,
    the address not this machine's), before Prefect starts and the app's address is printed."""
    import errno

    from flows.server import bind_error

    if (e := bind_error(host, port)) is not None:
        hint = " (another app on it? choose another --port)" if e.errno == errno.EADDRINUSE else ""
        raise CliError(f"--host {host} --port {port}: cannot listen there: {e.strerror or e}{hint}")
