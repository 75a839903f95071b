"""A real Prefect server per warehouse, run in the background (``cadestate server start|stop|status``).

While it is up, every command of this warehouse talks to it (``PREFECT_API_URL``) instead of starting
Prefect's ephemeral API (~3 s more per command on 2 cores); when it is down, commands fall back to
ephemeral mode. Its state lives under the warehouse:

    _prefect/home/          PREFECT_HOME: the server's SQLite database (unless a database URL is given)
    _prefect/server.json    the running server: pid, process start time, URL, database, log
    _prefect/server.log     its output
    _prefect/serve.lock     held by ``cadestate serve`` while it serves the deployments (its pid)
    _prefect/start.lock     held by ``cadestate server start`` while it starts the server

Nothing here imports Prefect: the server is a separate process (``prefect server start``).
"""

from __future__ import annotations

import contextlib
import datetime as dt
import errno
import fcntl
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import psutil

from flows.prefect_db import seed_home
from warehouse.store import atomic_write_bytes

SERVER_FILE = "server.json"
LOG_FILE = "server.log"
SERVE_LOCK = "serve.lock"
START_LOCK = "start.lock"


class ServerError(RuntimeError):
    """The Prefect server could not be started, reached or stopped; the message says why and what to do."""


@dataclass(frozen=True)
class ServerInfo:
    """A server started by ``cadestate server start``: its process (pid and creation time, which tell
    it from a recycled pid), API URL (``http://HOST:PORT/api``), database URL ('' = SQLite under
    PREFECT_HOME) and log file."""

    pid: int
    process_start: float
    api_url: str
    database_url: str
    log: str
    started_at: str
    root_id: str = ""
    """The warehouse folder it serves, as ``<device>:<inode>`` (:func:`folder_id`): a record copied
    with a warehouse is not the copy's server, while a renamed or moved warehouse keeps its own."""

    @property
    def process_alive(self) -> bool:
        try:
            process = psutil.Process(self.pid)
            return abs(process.create_time() - self.process_start) < 1.0 and process.status() != psutil.STATUS_ZOMBIE
        except psutil.Error:
            return False


def prefect_dir(root: Path) -> Path:
    return Path(root) / "_prefect"


def prefect_home(root: Path) -> Path:
    """PREFECT_HOME of a warehouse (shared by its server and its ephemeral runs)."""
    return prefect_dir(root) / "home"


def read_server(root: Path) -> ServerInfo | None:
    """The server recorded for this warehouse, or None (no record, an unreadable one, or the record
    of another warehouse's server, copied with its folder)."""
    try:
        info = ServerInfo(**json.loads((prefect_dir(root) / SERVER_FILE).read_text()))
    except (OSError, ValueError, TypeError):
        return None
    return info if not info.root_id or info.root_id == folder_id(root) else None


def folder_id(root: Path) -> str:
    """``<device>:<inode>`` of the folder ``root`` ('' when it cannot be read)."""
    try:
        st = Path(root).stat()
    except OSError:
        return ""
    return f"{st.st_dev}:{st.st_ino}"


def healthy(api_url: str, timeout_s: float = 2.0) -> bool:
    """Whether the Prefect API at ``api_url`` answers its health check."""
    try:
        with urllib.request.urlopen(f"{api_url}/health", timeout=timeout_s) as response:
            return response.status == 200
    except (OSError, urllib.error.URLError, ValueError):
        return False


def running_server(root: Path) -> ServerInfo | None:
    """The warehouse's server if its process lives and its API answers, else None."""
    info = read_server(root)
    return info if info is not None and info.process_alive and healthy(info.api_url) else None


def free_port(host: str) -> int:
    """A port free on ``host`` now; :class:`ServerError` when ``host`` is no address of this machine."""
    try:
        infos = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM)
        with socket.socket(infos[0][0], socket.SOCK_STREAM) as s:
            s.bind(infos[0][4])
            return s.getsockname()[1]
    except OSError as e:
        raise ServerError(_address_error(host, e) or f"{host}: cannot listen there ({e.strerror or e})") from None


def _address_error(host: str, e: OSError) -> str | None:
    """The one line of a bind that failed for the address itself (not this machine's, or no such
    name), else None."""
    if isinstance(e, socket.gaierror):
        return f"--host {host}: no such host ({e.strerror or e})"
    if e.errno == errno.EADDRNOTAVAIL:
        return f"--host {host}: not an address of this machine ({e.strerror}); 127.0.0.1 or 0.0.0.0 (every address)"
    return None


def bind_error(host: str, port: int) -> OSError | None:
    """Why nothing could listen on ``host:port`` now (the port taken, the address not this
    machine's), or None. Binds as uvicorn does: a port in TIME_WAIT is free (SO_REUSEADDR)."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
        with socket.socket(infos[0][0], socket.SOCK_STREAM) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind(infos[0][4])
    except OSError as e:
        return e
    return None


def check_port_free(host: str, port: int) -> None:
    """Raise :class:`ServerError` when ``host:port`` is taken: the server's API would be another
    process's (another warehouse's Prefect server answers as ours would, while ours dies on the
    clash), or this warehouse's earlier server that has stopped answering still holds it."""
    if (e := bind_error(host, port)) is not None:
        raise ServerError(_address_error(host, e) or f"{host}:{port} is taken ({e.strerror or e}): another Prefect "
                          "server, perhaps another warehouse's (`cadestate -w W server status`)? choose another --port")


def server_environment(root: Path, database_url: str = "") -> dict[str, str]:
    """The environment of the server process: this warehouse's PREFECT_HOME, no telemetry, and the
    database URL when one is given (e.g. ``postgresql+asyncpg://user:pw@host/db``)."""
    env = {k: v for k, v in os.environ.items() if k not in ("PREFECT_API_URL", "PREFECT_HOME")}
    env.update(PREFECT_HOME=str(prefect_home(root)), PREFECT_SERVER_ANALYTICS_ENABLED="false",
               PREFECT_LOGGING_LEVEL="WARNING", PREFECT_SERVER_LOGGING_LEVEL="WARNING")
    if database_url:
        env["PREFECT_SERVER_DATABASE_CONNECTION_URL"] = database_url
    return env


def start_server(root: Path, host: str = "127.0.0.1", port: int = 0, database_url: str = "",
                 timeout_s: float = 180.0) -> ServerInfo:
    """Start ``prefect server start`` in the background for this warehouse and wait until its API
    answers (at most ``timeout_s``). A server already up is returned as is. ``port`` 0 takes a free one."""
    root = Path(root).resolve()
    with _starting(root):  # a second start at once waits, then finds the first's server up
        return _start_server(root, host, port, database_url, timeout_s)


@contextlib.contextmanager
def _starting(root: Path) -> Iterator[None]:
    """Hold ``<warehouse>/_prefect/start.lock`` (blocking): two ``server start`` at once each
    started a server, the second's record replaced the first's, and the one left running was
    recorded nowhere (``server stop`` did not stop it)."""
    try:
        prefect_dir(root).mkdir(parents=True, exist_ok=True)
        f = open(prefect_dir(root) / START_LOCK, "a")
    except OSError as e:  # a warehouse path that is a file, or not writable: one line, not a traceback
        raise ServerError(f"{prefect_dir(root)}: cannot make the server's folder: {e.strerror or e}") from None
    with f:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX)
        yield


def _start_server(root: Path, host: str, port: int, database_url: str, timeout_s: float) -> ServerInfo:
    if (up := running_server(root)) is not None:
        return up
    if (known := read_server(root)) is not None and known.process_alive:  # alive, not answering: hung
        raise ServerError(f"this warehouse's Prefect server (pid {known.pid}, {known.api_url}) runs but does not "
                          f"answer: `cadestate server stop` ends it (see {known.log})")
    if port:
        check_port_free(host, port)
    prefect_home(root).mkdir(parents=True, exist_ok=True)
    if not database_url:
        seed_home(prefect_home(root))  # a new warehouse's database copied, not migrated (flows.prefect_db)
    port = port or free_port(host)
    log = prefect_dir(root) / LOG_FILE
    offset = log.stat().st_size if log.exists() else 0
    prefect = Path(sys.executable).with_name("prefect")
    command = [str(prefect), "server", "start", "--host", host, "--port", str(port)]
    with open(log, "ab") as out:
        process = subprocess.Popen(command, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                   env=server_environment(root, database_url), start_new_session=True)
    info = ServerInfo(pid=process.pid, process_start=psutil.Process(process.pid).create_time(),
                      api_url=api_url(host, port), database_url=database_url, log=str(log),
                      started_at=dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"), root_id=folder_id(root))
    atomic_write_bytes(prefect_dir(root) / SERVER_FILE, json.dumps(asdict(info), indent=1).encode())
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            forget_server(root)
            raise ServerError(f"the Prefect server exited with status {process.returncode} while starting: "
                              f"{log_cause(log, offset) or 'it said nothing'} (log: {log})")
        if healthy(info.api_url, timeout_s=1.0):
            return info
        time.sleep(0.5)
    _terminate(info)
    forget_server(root)
    raise ServerError(f"the Prefect server did not answer within {timeout_s:.0f} s (see {log}); "
                      "a busy machine may need a longer [prefect] startup_timeout_s")


def api_url(host: str, port: int) -> str:
    """The API URL of a server listening on ``host:port``; an IPv6 address in brackets (``--host ::1``
    was recorded as ``http://::1:4200/api``, and every command then ended in httpx's traceback)."""
    return f"http://{f'[{host}]' if ':' in host else host}:{port}/api"


def forget_server(root: Path) -> None:
    """Remove the warehouse's server record (its server is not running)."""
    (prefect_dir(root) / SERVER_FILE).unlink(missing_ok=True)


def log_cause(log: Path, offset: int = 0, limit: int = 300) -> str:
    """Why the server stopped, in one line, from what the log got after ``offset``: the exception its
    last traceback ended in, then its last paragraph (for a traceback, its last line) where that
    says something else (uvicorn closes a failed start with "Application startup failed", Prefect
    with "An exception occurred.": alone, they hid a database URL it cannot load or reach); at most
    about ``limit`` characters; '' when none."""
    try:
        with open(log, "rb") as f:
            f.seek(offset)
            text = f.read().decode("utf-8", errors="replace").replace("\r", "")
    except OSError:
        return ""
    lines = text.splitlines()
    starts = [i for i, line in enumerate(lines) if TRACEBACK in line]  # uvicorn writes "ERROR:    Traceback ..."
    raised = next((ln for ln in lines[starts[-1] + 1:] if ln.strip() and not ln[0].isspace()), "") if starts else ""
    paragraphs = [p.strip() for p in text.split("\n\n") if p.strip()]
    last = paragraphs[-1] if paragraphs else ""
    if TRACEBACK in last:
        last = last.splitlines()[-1]
    line = "; then: ".join(dict.fromkeys(" ".join(p.split()) for p in (raised, last) if p.strip()))
    return line if len(line) <= limit else line[:limit] + "..."


TRACEBACK = "Traceback (most recent call last)"


def _terminate(info: ServerInfo, timeout_s: float = 20.0) -> None:
    """Stop the server's process group (the server and the services it started): SIGTERM, then SIGKILL."""
    if not info.process_alive:
        return
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(info.pid, sig)
        except ProcessLookupError:
            return
        if _ended(info.pid, timeout_s):
            return


def _ended(pid: int, timeout_s: float) -> bool:
    """Whether process ``pid`` ends within ``timeout_s``: gone, or a zombie its parent has not
    reaped (``psutil.Process.wait`` waits those out, as it must for another's child)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            if psutil.Process(pid).status() == psutil.STATUS_ZOMBIE:
                return True
        except psutil.Error:
            return True
        time.sleep(0.1)
    return False


def stop_server(root: Path) -> tuple[ServerInfo | None, int | None]:
    """Stop the warehouse's ``cadestate serve`` (which would keep polling a dead API) and then its
    server, and forget the server; returns the server stopped and the pid of the serve stopped."""
    served = stop_serving(root)
    info = read_server(root)
    if info is not None:
        _terminate(info)
        forget_server(root)
    return info, served


def serving_lock(root: Path):
    """The open file of ``<warehouse>/_prefect/serve.lock``, locked and holding this pid (held until
    the process ends); :class:`ServerError` when another serve holds it: stopping either would
    pause the deployments both serve (Prefect pauses a served deployment's schedule when its serve stops)."""
    path = prefect_dir(root) / SERVE_LOCK
    path.parent.mkdir(parents=True, exist_ok=True)
    f = open(path, "a+")
    try:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        f.seek(0)
        pid = f.read().strip() or "?"
        f.close()
        raise ServerError(f"`cadestate serve` already serves {root} (pid {pid}): one per warehouse") from None
    f.truncate(0)
    f.write(f"{os.getpid()}\n")
    f.flush()
    return f


def serving_pid(root: Path, wait_s: float = 2.0) -> int | None:
    """The pid of the ``cadestate serve`` holding this warehouse's serve lock, or None. A serve
    writes its pid just after taking the lock: a held lock with no pid yet is read again for up
    to ``wait_s`` (read as "nobody serves", a starting serve would be missed by ``stop``)."""
    path = prefect_dir(root) / SERVE_LOCK
    deadline = time.monotonic() + wait_s
    while True:
        try:
            with open(path) as f:
                try:
                    fcntl.flock(f.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
                    return None  # nobody holds it
                except BlockingIOError:
                    text = f.read().strip()
        except OSError:
            return None
        if text.isdigit():
            return int(text)
        if time.monotonic() > deadline:
            return None
        time.sleep(0.05)


def stop_serving(root: Path, timeout_s: float = 30.0) -> int | None:
    """End the warehouse's ``cadestate serve`` the way Prefect shuts a runner down (SIGTERM: it
    pauses its schedules and stops), SIGKILL after ``timeout_s``; returns its pid, None when none serves."""
    if (pid := serving_pid(root)) is None:
        return None
    try:
        process = psutil.Process(pid)
        process.terminate()
        if not _ended(pid, timeout_s):
            process.kill()
    except psutil.Error:
        pass
    return pid


def end_with_server(info: ServerInfo, on_end, every_s: float = 2.0) -> threading.Event:
    """Watch the server's process in a daemon thread; once it has ended (stopped or crashed),
    call ``on_end()`` (a serve exits: every poll of a dead API would print a traceback; a command's
    run ends instead of retrying for minutes). Setting the event returned ends the watch."""
    done = threading.Event()

    def watch() -> None:
        while info.process_alive:
            if done.wait(every_s):
                return
        if not done.is_set():
            on_end()

    threading.Thread(target=watch, name="server-watch", daemon=True).start()
    return done
