"""`cadestate server`: a real Prefect server per warehouse that every command uses while it is up,
named and tagged flow runs, fallback to ephemeral mode, and Prefect failing to start in one line."""

from __future__ import annotations

import os
import subprocess
import sys

import httpx
import pytest

from flows.server import free_port, read_server, running_server

pytestmark = pytest.mark.slow


def cli(*args: str, cwd) -> subprocess.CompletedProcess:
    """The real command in a fresh process with a user's environment (no Prefect settings of the tests)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    return subprocess.run([sys.executable, "-m", "cadestate", *args], capture_output=True, text=True, env=env, cwd=cwd,
                          timeout=600)


def flow_runs(api_url: str) -> list[dict]:
    response = httpx.post(f"{api_url}/flow_runs/filter", json={"limit": 50, "sort": "START_TIME_ASC"}, timeout=30)
    response.raise_for_status()
    return response.json()


def test_commands_use_the_server_while_it_is_up_and_fall_back_when_it_is_down(tmp_path, small_clip):
    w = tmp_path / "w"
    video, cameras = str(small_clip.video_path), str(small_clip.cameras_path)
    started = cli("-w", str(w), "server", "start", "--port", "0", cwd=tmp_path)
    try:
        assert started.returncode == 0, started.stderr
        info = running_server(w)
        assert info is not None and "Prefect server up" in started.stdout
        assert (w / "_prefect" / "home").is_dir() and (w / "_prefect" / "server.log").is_file()
        assert cli("-w", str(w), "server", "status", cwd=tmp_path).returncode == 0
        again = cli("-w", str(w), "server", "start", cwd=tmp_path)  # already up: the same server
        assert again.returncode == 0 and read_server(w).pid == info.pid and "already up" not in again.stderr
        moved = cli("-w", str(w), "server", "start", "--port", "4399", cwd=tmp_path)  # said, not silently ignored
        assert moved.returncode == 0 and f"already up at {info.api_url}: --port 4399 is not taken" in moved.stderr
        # any free port is the one it has; another host or database was ignored without a word
        assert "already up" not in cli("-w", str(w), "server", "start", "--port", "0", cwd=tmp_path).stderr
        other = cli("-w", str(w), "server", "start", "--host", "0.0.0.0", "--database-url", "postgresql+asyncpg://u@h/db",
                    cwd=tmp_path)
        assert other.returncode == 0 and f"already up at {info.api_url}: --host 0.0.0.0 is not taken" in other.stderr
        assert "--database-url postgresql+asyncpg://u@h/db is not taken" in other.stderr
        run = cli("-w", str(w), "ingest", video, cameras, "--split", "val", "--no-progress", cwd=tmp_path)
        assert f"on the Prefect server at {info.api_url}" in run.stderr, run.stderr
        [flow_run] = flow_runs(info.api_url)
        assert flow_run["name"] == "annotate_clip/small_0"  # the clip's official name, from its camera file
        assert {"clip:small_0", "split:val"} <= set(flow_run["tags"])
    finally:
        stopped = cli("-w", str(w), "server", "stop", cwd=tmp_path)
    assert stopped.returncode == 0 and "stopped the Prefect server" in stopped.stdout
    assert read_server(w) is None and not info.process_alive
    down = cli("-w", str(w), "server", "status", cwd=tmp_path)
    assert down.returncode == 1 and down.stdout.startswith("down")
    rerun = cli("-w", str(w), "run", "--no-progress", cwd=tmp_path)
    assert rerun.returncode == 0 and "Prefect's local API starts alongside" in rerun.stderr, rerun.stderr


def test_prefect_failing_to_start_is_one_line(tmp_path, small_clip):
    """Prefect's API that cannot start (its database out of reach: a 1 s timeout alone was no
    failure on a fast machine, where the local API answers within it)."""
    config = tmp_path / "c.toml"
    config.write_text("[prefect]\nstartup_timeout_s = 1\n")
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    env["PREFECT_SERVER_DATABASE_CONNECTION_URL"] = f"sqlite+aiosqlite:///{tmp_path}/no/such/folder/prefect.db"
    result = subprocess.run([sys.executable, "-m", "cadestate", "-c", str(config), "-w", str(tmp_path / "w"), "ingest",
                             str(small_clip.video_path), str(small_clip.cameras_path), "--no-progress"],
                            capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600)
    assert result.returncode == 1 and "Traceback" not in result.stderr
    errors = [ln for ln in result.stderr.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and "cadestate server start" in errors[0] and "[prefect] startup_timeout_s" in errors[0]


def test_server_start_where_its_folder_cannot_be_made_is_one_line(tmp_path):
    """A warehouse path under a file (or not writable) ended `server start` in a traceback."""
    (tmp_path / "file").write_text("")
    result = subprocess.run([sys.executable, "-m", "cadestate", "-w", str(tmp_path / "file" / "wh"), "server", "start"],
                            capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert result.returncode == 1 and result.stderr == (f"error: {tmp_path / 'file' / 'wh' / '_prefect'}: cannot make the "
                                                       "server's folder: Not a directory\n"), result.stderr


def test_a_dead_prefect_api_url_is_one_line(tmp_path, small_clip):
    api = f"http://127.0.0.1:{free_port('127.0.0.1')}/api"  # bound, then released: nothing listens
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}, "PREFECT_API_URL": api}
    result = subprocess.run([sys.executable, "-m", "cadestate", "-w", str(tmp_path / "w"), "ingest",
                             str(small_clip.video_path), str(small_clip.cameras_path), "--no-progress"],
                            capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600)
    assert result.returncode == 1 and "Traceback" not in result.stderr, result.stderr
    errors = [ln for ln in result.stderr.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1, result.stderr
    assert f"Prefect's API at {api} could not be reached" in errors[0] and "Connection refused" in errors[0]
    assert "PREFECT_API_URL" in errors[0] and "cadestate server start" in errors[0]


def test_server_start_on_a_port_in_use_says_so_and_forgets_the_server(tmp_path):
    """Another process on the port, here one answering every request as a healthy Prefect API would
    (another warehouse's server): refused in one line before anything starts, not taken for ours."""
    import threading
    from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

    class Healthy(BaseHTTPRequestHandler):
        def do_GET(self):
            self.send_response(200)
            self.send_header("Content-Type", "application/json")
            self.end_headers()
            self.wfile.write(b"true")

        def log_message(self, *args):
            pass

    w = tmp_path / "w"
    other = ThreadingHTTPServer(("127.0.0.1", 0), Healthy)
    threading.Thread(target=other.serve_forever, daemon=True).start()
    port = other.server_address[1]
    try:
        result = cli("-w", str(w), "server", "start", "--host", "127.0.0.1", "--port", str(port), cwd=tmp_path)
    finally:
        other.shutdown()
        other.server_close()
    assert result.returncode == 1 and "Traceback" not in result.stderr, result.stderr
    errors = [ln for ln in result.stderr.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and f"127.0.0.1:{port} is taken" in errors[0] and "--port" in errors[0], result.stderr
    assert not (w / "_prefect" / "server.json").exists() and read_server(w) is None


@pytest.mark.parametrize("host, says", [("10.255.255.1", "not an address of this machine"),
                                         ("no-such-host.invalid", "no such host")])
@pytest.mark.parametrize("port", ["0", "4399"])
def test_a_host_that_is_not_this_machines_is_one_line(tmp_path, host, says, port):
    """It said "the port is taken" (with a port), or ended in a traceback (--port 0)."""
    result = cli("-w", str(tmp_path / "w"), "server", "start", "--host", host, "--port", port, cwd=tmp_path)
    assert result.returncode == 1 and "Traceback" not in result.stderr and result.stderr.count("\n") == 1, result.stderr
    assert f"--host {host}: {says}" in result.stderr


def _record(w, pid: int) -> None:
    """A server record of ``w`` naming process ``pid`` (alive), at a URL where nothing answers."""
    import json

    import psutil

    from flows.server import folder_id

    (w / "_prefect").mkdir(parents=True)
    (w / "_prefect" / "server.json").write_text(json.dumps({
        "pid": pid, "process_start": psutil.Process(pid).create_time(), "log": str(w / "_prefect" / "server.log"),
        "api_url": f"http://127.0.0.1:{free_port('127.0.0.1')}/api", "database_url": "", "started_at": "then",
        "root_id": folder_id(w)}))


def test_two_server_starts_at_once_start_one_server(tmp_path):
    """Two `server start` at once each started a server; the second's record replaced the first's,
    and the first ran on, recorded nowhere: `server stop` left it running. The second now waits for
    the first and finds its server up."""
    import re

    w = tmp_path / "w"
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    starts = [subprocess.Popen([sys.executable, "-m", "cadestate", "-w", str(w), "server", "start", "--port", "0"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path)
              for _ in range(2)]
    try:
        said = [p.communicate(timeout=600) for p in starts]
        assert [p.returncode for p in starts] == [0, 0], said
        pids = {int(re.search(r"pid (\d+)", out).group(1)) for out, _ in said}
        assert pids == {read_server(w).pid}, said
    finally:
        cli("-w", str(w), "server", "stop", cwd=tmp_path)
        for p in starts:
            p.kill()


@pytest.mark.parametrize("tail, says", [
    ("ERROR:    Traceback (most recent call last):\n  File \"x.py\", line 1\n    connect()\n"
     "ConnectionRefusedError: [Errno 111] Connect call failed ('127.0.0.1', 1)\n\n"
     "ERROR:    Application startup failed. Exiting.\nServer stopped!\n",
     "ConnectionRefusedError: [Errno 111] Connect call failed ('127.0.0.1', 1); then: ERROR: Application startup "
     "failed. Exiting. Server stopped!"),
    ("Traceback (most recent call last):\n  File \"x.py\", line 1\n"
     "sqlalchemy.exc.NoSuchModuleError: Can't load plugin: sqlalchemy.dialects:bogus\nAn exception occurred.\n",
     "sqlalchemy.exc.NoSuchModuleError: Can't load plugin: sqlalchemy.dialects:bogus; then: An exception occurred."),
    ("Traceback (most recent call last):\n  File \"x.py\", line 1\nValueError: bad\n", "ValueError: bad"),
    ("ERROR:    [Errno 98] address already in use\n", "ERROR: [Errno 98] address already in use"),
    ("", ""),
])
def test_a_failed_start_names_the_exception_of_its_log(tmp_path, tail, says):
    """A --database-url Prefect could not reach or load was told as "Application startup failed.
    Exiting. Server stopped!" or "An exception occurred.", the log's last paragraph alone."""
    from flows.server import log_cause

    log = tmp_path / "server.log"
    log.write_text("Traceback (most recent call last):\nOSError: an earlier start's\n\n" + tail)
    assert log_cause(log, offset=len("Traceback (most recent call last):\nOSError: an earlier start's\n\n")) == says


def test_a_server_on_an_ipv6_address_is_recorded_at_a_url_prefects_client_takes(tmp_path):
    """`server start --host ::1` recorded http://::1:PORT/api: it answered urllib's health check, and
    every command then ended in a traceback (httpx.InvalidURL: Invalid port: ':1:PORT')."""
    try:
        free_port("::1")
    except Exception:
        pytest.skip("no IPv6 loopback here")
    w = tmp_path / "w"
    started = cli("-w", str(w), "server", "start", "--host", "::1", "--port", "0", cwd=tmp_path)
    try:
        assert started.returncode == 0, started.stderr
        url = read_server(w).api_url
        assert url.startswith("http://[::1]:"), url
        assert httpx.get(f"{url}/health", timeout=10).status_code == 200
    finally:
        cli("-w", str(w), "server", "stop", cwd=tmp_path)


def test_a_server_that_runs_but_does_not_answer_is_named_not_orphaned(tmp_path):
    """A hung server (its process alive, its API silent): start says so and points to stop, where
    it recorded a second server over the first, which then outlived `server stop`."""
    w = tmp_path / "w"
    hung = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"], start_new_session=True)
    try:
        _record(w, hung.pid)
        result = cli("-w", str(w), "server", "start", "--port", "0", cwd=tmp_path)
        assert result.returncode == 1 and f"(pid {hung.pid}, " in result.stderr and "runs but does not answer: " \
            "`cadestate server stop` ends it" in result.stderr, result.stderr
        assert cli("-w", str(w), "server", "stop", cwd=tmp_path).returncode == 0
        assert hung.wait(30) is not None
    finally:
        hung.kill()


def test_server_stop_stops_the_serve_of_its_warehouse_first(tmp_path):
    """`server stop` under a running `cadestate serve` left it polling a dead API, a traceback every
    few seconds for good: the serve (the holder of serve.lock) is stopped first, and named."""
    w = tmp_path / "w"
    hung = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"], start_new_session=True)
    serving = subprocess.Popen([sys.executable, "-c", "import sys, time; from pathlib import Path; "
                                "from flows.server import serving_lock; lock = serving_lock(Path(sys.argv[1])); "
                                "print('held', flush=True); time.sleep(120)", str(w)], stdout=subprocess.PIPE, text=True)
    try:
        _record(w, hung.pid)
        assert serving.stdout.readline() == "held\n"
        stop = cli("-w", str(w), "server", "stop", cwd=tmp_path)
        assert stop.returncode == 0 and f"stopped `cadestate serve` (pid {serving.pid})" in stop.stdout, stop.stdout
        assert serving.wait(30) is not None and hung.wait(30) is not None
        again = cli("-w", str(w), "server", "stop", cwd=tmp_path)
        assert again.stdout == "no server was started\n"
    finally:
        hung.kill()
        serving.kill()


def test_a_serve_whose_server_ends_says_so_in_one_line_and_ends(tmp_path):
    """The server killed under a serve (a crash, a reboot of its process): the serve ends at once
    with one line, where it printed a traceback per poll."""
    import signal
    import time

    from flows.server import serving_pid

    w = tmp_path / "w"
    assert cli("-w", str(w), "server", "start", "--port", "0", cwd=tmp_path).returncode == 0
    info = read_server(w)
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    serving = subprocess.Popen([sys.executable, "-m", "cadestate", "-w", str(w), "serve"], cwd=tmp_path, env=env,
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while serving_pid(w) is None and serving.poll() is None and time.monotonic() < deadline:
            time.sleep(0.5)
        assert serving_pid(w) == serving.pid
        os.killpg(info.pid, signal.SIGKILL)
        assert serving.wait(30) == 1
        said = serving.stderr.read()
        assert f"the Prefect server at {info.api_url} stopped: serve ends" in said and "Traceback" not in said, said
    finally:
        serving.kill()
        cli("-w", str(w), "server", "stop", cwd=tmp_path)


def test_a_command_whose_server_stops_under_it_ends_in_one_line(tmp_path):
    """`server stop` under a command running on the warehouse's server (`cad ingest`: minutes of
    stages): the command ends within seconds, in one line with status 1, where Prefect's client
    retried every call to the dead API for ~2.5 minutes before the command failed."""
    import time

    w = tmp_path / "w"
    assert cli("-w", str(w), "server", "start", "--port", "0", cwd=tmp_path).returncode == 0
    info = read_server(w)
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    running = subprocess.Popen([sys.executable, "-m", "cadestate", "-w", str(w), "cad", "ingest", "--no-progress"],
                               cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 180
        while not flow_runs(info.api_url) and running.poll() is None and time.monotonic() < deadline:
            time.sleep(0.5)
        assert running.poll() is None, running.stderr.read()  # its stages are under way
        assert cli("-w", str(w), "server", "stop", cwd=tmp_path).returncode == 0
        assert running.wait(60) == 1
        _, said = running.communicate(timeout=30)  # its render pool's workers, which hold stderr too, are gone
    finally:
        running.kill()
        cli("-w", str(w), "server", "stop", cwd=tmp_path)
    last = said.strip().splitlines()[-1]  # nothing after it: multiprocessing's resource tracker warned of the
    assert last.startswith(f"error: the Prefect server at {info.api_url} stopped under this run: the stages in "
                           "progress stop"), said  # render pool's semaphores, "leaked" by the command's exit
    assert "Traceback" not in said and "leaked semaphore" not in said, said


def test_a_command_on_a_local_dask_cluster_whose_server_stops_ends_in_one_line(tmp_path, small_clip):
    """`server stop` under `ingest` on a local Dask cluster (`task_runner = "dask"`): the command ends
    within seconds, in the one line a command on threads gives, status 1, its worker processes gone.
    Its driver watched nothing: the clip failed ~2.5 minutes later, the worker's client having
    retried the dead API, and the line said so under a progress line."""
    import json
    import time
    from pathlib import Path

    import psutil

    w = tmp_path / "w"
    cfg = tmp_path / "dask.toml"
    cfg.write_text('[prefect]\ntask_runner = "dask"\nmax_workers = 1\n')
    assert cli("-w", str(w), "server", "start", "--port", "0", cwd=tmp_path).returncode == 0
    info = read_server(w)
    root = str(Path(__file__).resolve().parents[1])  # the local workers import this checkout
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")},
           "PYTHONPATH": os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")]))}
    running = subprocess.Popen([sys.executable, "-m", "cadestate", "-c", str(cfg), "-w", str(w), "ingest",
                                str(small_clip.video_path), str(small_clip.cameras_path), "--no-progress"],
                               cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 180
        while not (markers := list((w / "_running" / "small_0").glob("detect.*.json"))) \
                and running.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)  # until the detect stage runs on the worker (its run marker)
        assert running.poll() is None, running.stderr.read()
        worker = psutil.Process(json.loads(markers[0].read_text())["pid"])
        family = psutil.Process(running.pid).children(recursive=True)
        assert worker in family
        assert cli("-w", str(w), "server", "stop", cwd=tmp_path).returncode == 0
        assert running.wait(30) == 1
        _, said = running.communicate(timeout=30)
        _, alive = psutil.wait_procs(family, timeout=10)
        assert not alive, alive
    finally:
        running.kill()
        cli("-w", str(w), "server", "stop", cwd=tmp_path)
    assert said.strip().splitlines()[-1] == (
        f"error: the Prefect server at {info.api_url} stopped under this run: the stages in progress stop unfinished "
        "(the command run again resumes them); `cadestate server start` starts it again (without it, commands run "
        "on their own)"), said
    assert "Traceback" not in said and "distributed" not in said and "leaked semaphore" not in said, said
    assert not [p.name for p in w.iterdir() if p.name.startswith(".dask-probe-")]


def test_a_server_record_copied_with_its_warehouse_is_not_the_copys(tmp_path):
    """`cp -a` of a warehouse copies its server record: the copy's `server stop` stopped the
    original's server. A record names its warehouse folder (device and inode); another's is no
    record, while the folder renamed keeps it."""
    import shutil

    server = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"], start_new_session=True)
    try:
        (tmp_path / "a").mkdir()
        _record(tmp_path / "a", server.pid)
        shutil.copytree(tmp_path / "a", tmp_path / "b")
        assert read_server(tmp_path / "a") is not None and read_server(tmp_path / "b") is None
        stop = cli("-w", str(tmp_path / "b"), "server", "stop", cwd=tmp_path)
        assert stop.returncode == 0 and "no server was started" in stop.stdout and server.poll() is None
        (tmp_path / "a").rename(tmp_path / "renamed")  # a renamed warehouse keeps its server
        assert read_server(tmp_path / "renamed").pid == server.pid
    finally:
        server.kill()


@pytest.mark.parametrize("verbose, level, glog", [(False, "CRITICAL", "3"), (True, "INFO", "0")])
def test_the_ephemeral_api_logs_at_the_commands_level(tmp_path, monkeypatch, verbose, level, glog):
    """The ephemeral API runs in the command's process with a log level of its own: left at Prefect's
    default, its shutdown on a busy machine printed pages of tracebacks after a successful run.
    COLMAP's ~2,000 lines per SfM run show only with --verbose."""
    from flows.runtime import prepare_prefect_environment

    for name in ("PREFECT_HOME", "PREFECT_API_URL", "PREFECT_LOGGING_LEVEL", "PREFECT_SERVER_LOGGING_LEVEL",
                 "PREFECT_INTERNAL_LOGGING_LEVEL", "GLOG_minloglevel"):
        monkeypatch.setenv(name, "")  # so that the test's end restores what was there (or its absence)
        monkeypatch.delenv(name)
    assert prepare_prefect_environment(tmp_path, verbose=verbose) == ""
    assert os.environ["PREFECT_LOGGING_LEVEL"] == os.environ["PREFECT_SERVER_LOGGING_LEVEL"] == level
    # Prefect's internal services: ERROR lines of ~2,700 characters every 7 s under a command whose server stopped
    assert os.environ.get("PREFECT_INTERNAL_LOGGING_LEVEL") == (None if verbose else "CRITICAL")
    assert os.environ["GLOG_minloglevel"] == glog


WEDGED_START = """
import subprocess, sys
import httpx
from prefect.server.api.server import SubprocessASGIServer
from flows.runtime import start_ephemeral_api

real, wedged = SubprocessASGIServer._run_uvicorn_command, []
def first_never_answers(self):  # Prefect's server process that starts and never answers
    if wedged:
        return real(self)
    wedged.append((self.port, subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])))
    return wedged[0][1]
SubprocessASGIServer._run_uvicorn_command = first_never_answers
url = start_ephemeral_api(float(sys.argv[1]))
assert httpx.get(url + "/health", timeout=30).status_code == 200
port, process = wedged[0]
print(port, process.poll() is not None, url)
"""


@pytest.mark.slow
def test_a_local_api_that_never_answers_is_replaced_on_a_new_port(tmp_path):
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}, "PREFECT_HOME": str(tmp_path)}
    done = subprocess.run([sys.executable, "-c", WEDGED_START, "90"], capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    wedged_port, wedged_killed, url = done.stdout.split()
    assert wedged_killed == "True" and f":{wedged_port}/" not in url


def test_in_process_flow_runs_start_no_heartbeat_thread():
    """A run's heartbeat thread cost its end up to a second (its join); runs here go without."""
    from prefect.settings import get_current_settings

    from flows.runtime import without_heartbeats

    outside = get_current_settings()
    assert outside.flows.heartbeat_frequency is not None  # Prefect's default (180 s), which served runs keep
    for _ in range(2):  # the second time from the kept copy
        with without_heartbeats():
            inside = get_current_settings()
            assert inside.flows.heartbeat_frequency is None
            assert (inside.home, inside.api.url, inside.logging.level) == (outside.home, outside.api.url, outside.logging.level)
    assert get_current_settings().flows.heartbeat_frequency == outside.flows.heartbeat_frequency


def test_a_serve_that_holds_its_lock_but_has_not_written_its_pid_yet_is_still_found(tmp_path):
    """The serve lock is taken, then its pid written: ``serving_pid`` read the empty file between
    the two as "nobody serves" (``server stop`` then left the starting serve running)."""
    import fcntl
    import threading

    from flows.server import SERVE_LOCK, prefect_dir, serving_pid

    path = prefect_dir(tmp_path) / SERVE_LOCK
    path.parent.mkdir(parents=True)
    holder = open(path, "a+")
    fcntl.flock(holder.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    writer = threading.Timer(0.3, lambda: (holder.write("4242\n"), holder.flush()))
    writer.start()
    try:
        assert serving_pid(tmp_path) == 4242
    finally:
        writer.join()
        holder.close()
    assert serving_pid(tmp_path) is None  # the lock released: nobody serves
