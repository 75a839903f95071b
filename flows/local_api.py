"""Prefect's ephemeral API, launched as soon as a command knows it will run flows.

With no server for the warehouse and no ``$PREFECT_API_URL``, Prefect serves its API from a
subprocess of the command (``SubprocessASGIServer``: uvicorn serving
``prefect.server.api.server:create_app``). Prefect starts it on first use, once the command has
imported Prefect and that server module (1.55 s of imports beyond what the flows need, here), and
then waits for its start (4-5 s on 2 cores). :func:`launch` starts the same subprocess, with
Prefect's command line and environment, before Prefect is imported
(:func:`flows.runtime.prepare_prefect_environment` with ``start_api``, in the commands that run
flows), so that its start overlaps the command's own imports and checks.
:func:`flows.runtime.start_ephemeral_api` then hands it to Prefect (:func:`adopt`), which uses it
as one it had started itself (``get_client`` finds it) and stops it when the process ends. A
process launched and never adopted (the command ran no flow) is stopped at exit.
"""

from __future__ import annotations

import atexit
import contextlib
import importlib.util
import os
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from cadestate import exit_on_sigterm
from flows.prefect_db import seed_home
from flows.server import free_port, healthy

SERVER_ENV = {"PREFECT_UI_ENABLED": "0", "PREFECT__SERVER_EPHEMERAL": "1", "PREFECT__SERVER_FINAL": "1"}
"""What Prefect adds to the environment of its ephemeral API (``SubprocessASGIServer._run_uvicorn_command``)."""


@dataclass
class Launched:
    """An ephemeral API subprocess listening (or about to) on 127.0.0.1:``port``."""

    port: int
    process: subprocess.Popen

    @property
    def api_url(self) -> str:
        return f"http://127.0.0.1:{self.port}/api"


_LAUNCHED: Launched | None = None
_EVER_LAUNCHED: list[subprocess.Popen] = []
"""Every API process this process launched, adopted by Prefect or not (:func:`stop_launched_now`)."""


def uvicorn_command(port: int) -> list[str]:
    """Prefect's command line for its ephemeral API on ``port`` (as Prefect 3.8 builds it)."""
    app_dir = Path(importlib.util.find_spec("prefect").origin).parent.parent
    return [sys.executable, "-m", "uvicorn", "--app-dir", str(app_dir), "--factory", "prefect.server.api.server:create_app",
            "--host", "127.0.0.1", "--port", str(port), "--log-level", "error", "--lifespan", "on"]


def launch(home: Path) -> None:
    """Start the ephemeral API's subprocess for the Prefect home ``home`` without waiting for it;
    nothing if one was launched already or Prefect is imported (it starts its own as before)."""
    global _LAUNCHED
    if _LAUNCHED is not None or "prefect" in sys.modules:
        return
    seed_home(home)  # a new warehouse's database copied, not migrated (flows.prefect_db)
    port = free_port("127.0.0.1")
    # its own session: a terminal's Ctrl-C interrupts the command, which stops the API as it exits
    # (in the command's process group it died at once, and the stages still running waited on it)
    _LAUNCHED = Launched(port, subprocess.Popen(uvicorn_command(port), env={**os.environ, **SERVER_ENV},
                                                start_new_session=True, preexec_fn=end_with_parent()))
    _EVER_LAUNCHED.append(_LAUNCHED.process)
    atexit.register(_stop_unadopted)
    # killed by default, the process would leave the API running; as an exit, the exit handlers stop it
    # (`cadestate annotate`'s uvicorn shuts down on SIGTERM, then raises it again: it ends there too)
    exit_on_sigterm()


def end_with_parent() -> Callable[[], None] | None:
    """What the API's process runs before it starts (None: nothing): on Linux, ask for SIGTERM when
    the command's process ends, however it ends (the parent-death signal; elsewhere the exit
    handlers stop it). Loaded here: the child between fork and exec may import nothing."""
    if sys.platform != "linux":
        return None
    import ctypes
    import signal

    prctl, PR_SET_PDEATHSIG, sigterm = ctypes.CDLL(None, use_errno=True).prctl, 1, int(signal.SIGTERM)
    return lambda: prctl(PR_SET_PDEATHSIG, sigterm)


def stop_launched_now() -> None:
    """SIGTERM to every API process this process launched that still runs, waiting for none (the
    process is about to end without its exit handlers)."""
    for process in _EVER_LAUNCHED:
        if process.poll() is None:
            with contextlib.suppress(OSError):
                process.terminate()


def take() -> Launched | None:
    """The launched API, handed over once (None: none was launched, or it was taken)."""
    global _LAUNCHED
    launched, _LAUNCHED = _LAUNCHED, None
    return launched


def _stop_unadopted() -> None:
    launched = take()
    if launched is not None and launched.process.poll() is None:
        launched.process.terminate()
        try:
            launched.process.wait(5)
        except subprocess.TimeoutExpired:
            launched.process.kill()
            launched.process.wait()


def answers(api_url: str, process: subprocess.Popen, timeout_s: float) -> bool:
    """Whether the API at ``api_url`` answers its health check within ``timeout_s`` (False at once
    if its process ended)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and process.poll() is None:
        if healthy(api_url):
            return True
        time.sleep(0.05)
    return False


def adopt(server, launched: Launched, timeout_s: float) -> None:
    """Make Prefect's ephemeral-server instance ``server`` (``SubprocessASGIServer()``) the
    launched process and wait until it answers; a RuntimeError naming the Prefect API if it does
    not within ``timeout_s`` (the instance then holds it, so ``server.stop()`` kills it)."""
    server.port, server.server_process, server.running = launched.port, launched.process, True
    atexit.register(server.stop)
    if not answers(server.api_url, launched.process, timeout_s):
        code = launched.process.poll()
        raise RuntimeError(f"Timed out while attempting to connect to ephemeral Prefect API server at {server.api_url}"
                           + (f" (its process exited with code {code})" if code is not None else ""))
