"""Prefect's ephemeral API launched before Prefect is imported, then adopted (flows/local_api.py)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import psutil
import pytest

REPO = Path(__file__).resolve().parents[1]

ADOPTED = textwrap.dedent("""
    import sys
    from pathlib import Path
    from flows import local_api
    from flows.runtime import prepare_prefect_environment, start_ephemeral_api
    assert prepare_prefect_environment(Path(sys.argv[1]), start_api=True) == ""
    assert "prefect" not in sys.modules  # launched before Prefect is imported
    launched = local_api._LAUNCHED
    url = start_ephemeral_api(120)
    from prefect import flow
    @flow(name="adopted")
    def adopted() -> int:
        return 7
    assert adopted() == 7
    print(launched.process.pid, launched.port, url)
""")

NEVER_ADOPTED = textwrap.dedent("""
    import sys
    from pathlib import Path
    from flows import local_api
    from flows.runtime import prepare_prefect_environment
    prepare_prefect_environment(Path(sys.argv[1]), start_api=True)
    print(local_api._LAUNCHED.process.pid)
""")

WEDGED = textwrap.dedent("""
    import sys, httpx
    from pathlib import Path
    from flows import local_api
    from flows.runtime import prepare_prefect_environment, start_ephemeral_api
    local_api.uvicorn_command = lambda port: [sys.executable, "-c", "import time; time.sleep(600)"]  # never answers
    prepare_prefect_environment(Path(sys.argv[1]), start_api=True)
    wedged = local_api._LAUNCHED
    url = start_ephemeral_api(float(sys.argv[2]))
    assert httpx.get(url + "/health", timeout=30).status_code == 200
    print(wedged.port, wedged.process.poll() is not None, url)
""")


def run_script(script: str, *args: str) -> list[str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    done = subprocess.run([sys.executable, "-c", script, *args], env=env, capture_output=True, text=True, timeout=300, cwd=REPO)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout.split()


def test_the_launched_api_is_the_one_prefect_uses_and_it_ends_with_the_process(tmp_path):
    pid, port, url = run_script(ADOPTED, str(tmp_path / "w"))
    assert url == f"http://127.0.0.1:{port}/api"
    assert not psutil.pid_exists(int(pid)) or psutil.Process(int(pid)).status() == psutil.STATUS_ZOMBIE
    assert (tmp_path / "w" / "_prefect" / "home" / "prefect.db").is_file()  # the warehouse's own database


def test_a_launched_api_no_flow_took_is_stopped_at_exit(tmp_path):
    [pid] = run_script(NEVER_ADOPTED, str(tmp_path / "w"))
    assert not psutil.pid_exists(int(pid)) or psutil.Process(int(pid)).status() == psutil.STATUS_ZOMBIE


@pytest.mark.slow
def test_a_launched_api_that_never_answers_is_replaced_by_prefects_own(tmp_path):
    wedged_port, wedged_killed, url = run_script(WEDGED, str(tmp_path / "w"), "45")
    assert wedged_killed == "True" and f":{wedged_port}/" not in url


KILLED = textwrap.dedent("""
    import os, signal, sys
    from pathlib import Path
    from flows import local_api
    from flows.runtime import prepare_prefect_environment
    prepare_prefect_environment(Path(sys.argv[1]), start_api=True)
    print(local_api._LAUNCHED.process.pid, flush=True)
    os.kill(os.getpid(), signal.SIGKILL)  # no exit handler runs
""")


@pytest.mark.skipif(sys.platform != "linux", reason="Linux's parent-death signal")
def test_a_launched_api_ends_when_its_command_is_killed(tmp_path):
    """The API runs in a session of its own (a terminal's Ctrl-C goes to the command alone), so
    nothing would end it after a kill -9 of the command but the parent-death signal."""
    import time

    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    done = subprocess.run([sys.executable, "-c", KILLED, str(tmp_path / "w")], env=env, capture_output=True, text=True,
                          timeout=300, cwd=REPO)
    pid = int(done.stdout.split()[0])
    deadline = time.monotonic() + 20
    while psutil.pid_exists(pid) and psutil.Process(pid).status() != psutil.STATUS_ZOMBIE and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not psutil.pid_exists(pid) or psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
