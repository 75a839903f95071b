"""Clips on a real Dask cluster (``[prefect] task_runner = "dask"``, issue 21 part 6): a ``dask
scheduler`` and two ``dask worker`` processes on loopback, each worker running whole clips against
the one warehouse, with real Prefect (this session's ephemeral API, handed to the workers)."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from bench.demo_clip import make_demo_clip
from cadestate.config import Config, DetectConfig, PrefectConfig, WarehouseConfig
from flows.annotate_clip import run_clips
from tasks.registry import stages_of
from tasks.video.ingest import ClipSource
from tests.conftest import SMALL_CLIP
from warehouse import Warehouse, connect

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
DASK = Path(sys.executable).with_name("dask")
CLIP_STAGES = [s.name for s in stages_of("clip")]


def _start(args: list[str], log: Path, prefix: tuple[str, ...] = ()) -> subprocess.Popen:
    """A ``dask`` command (after ``prefix``: a command that runs it) in its own process group (so
    that its worker process goes with it), its output to ``log``, importing this checkout."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    env.pop("PREFECT_API_URL", None)
    with open(log, "wb") as out:  # in a folder of its own: the clips' relative paths are not the workers'
        return subprocess.Popen([*prefix, str(DASK), *args], stdout=out, stderr=subprocess.STDOUT, env=env,
                                start_new_session=True, cwd=log.parent)


def _stop(proc: subprocess.Popen) -> None:
    """End the process group of ``proc`` (one this test started): SIGTERM, then SIGKILL after 30 s."""
    if proc.poll() is not None:
        return
    os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


@contextlib.contextmanager
def _cluster(tmp_path: Path, prefixes: list[tuple[str, ...]]) -> Iterator[str]:
    """The address of a scheduler on 127.0.0.1 (a free port, read from its scheduler file) with one
    single-threaded worker per entry of ``prefixes`` (the command each is started under) connected."""
    from distributed import Client

    scheduler_file = tmp_path / "scheduler.json"
    procs = [_start(["scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard", "--scheduler-file",
                     str(scheduler_file)], tmp_path / "scheduler.log")]
    try:
        deadline = time.monotonic() + 120
        while not scheduler_file.is_file() and time.monotonic() < deadline and procs[0].poll() is None:
            time.sleep(0.2)
        assert scheduler_file.is_file(), (tmp_path / "scheduler.log").read_text()
        address = json.loads(scheduler_file.read_text())["address"]
        procs += [_start(["worker", address, "--nthreads", "1", "--host", "127.0.0.1", "--no-dashboard",
                          "--name", f"w{i}"], tmp_path / f"worker{i}.log", prefix) for i, prefix in enumerate(prefixes)]
        if prefixes:
            with Client(address, timeout=60) as client:
                client.wait_for_workers(len(prefixes), timeout=180)
        yield address
    finally:
        for proc in reversed(procs):
            _stop(proc)


@pytest.fixture
def cluster(tmp_path) -> Iterator[str]:
    """The address of a scheduler on 127.0.0.1 with two single-threaded workers connected."""
    with _cluster(tmp_path, [(), ()]) as address:
        yield address


def test_a_dask_cluster_runs_whole_clips_on_both_workers(tmp_path, cluster):
    from distributed import Client

    clips = [make_demo_clip(tmp_path / "clips", dataclasses.replace(SMALL_CLIP, name=f"d{i}", seed=10 + i)) for i in range(4)]
    sources = [ClipSource(f"d{i}", c.video_path, c.cameras_path, split="val" if i == 3 else "train")
               for i, c in enumerate(clips)]
    sources[1] = dataclasses.replace(sources[1], video=Path(os.path.relpath(clips[1].video_path)),
                                     cameras=Path(os.path.relpath(clips[1].cameras_path)))  # relative to this process
    broken = ClipSource("gone", tmp_path / "missing.mp4", clips[0].cameras_path)
    config = Config(warehouse=WarehouseConfig(root=str(tmp_path / "warehouse")),
                    prefect=PrefectConfig(task_runner="dask", dask_address=cluster))
    with Client(cluster) as client:
        client.get_task_stream()  # the scheduler records the task stream from now on
        reports = run_clips([*sources, broken], config, show_progress=False)
        stream = client.get_task_stream()

    states = {(r.clip, r.stage): r.state for r in reports}
    for clip in ("d0", "d1", "d2"):
        assert [states[(clip, s)] for s in CLIP_STAGES] == ["completed"] * len(CLIP_STAGES), reports
    assert states[("d3", "manual_tracks")] == "paused"  # a val clip waits for its manual tracks, as with threads
    assert states[("d3", "retrieval")] == "waiting"
    # one clip, one line: the first stage that reads the missing video
    [gone] = [r for r in reports if r.clip == "gone"]
    assert (gone.stage, gone.state) == ("cameras", "failed") and "missing.mp4" in gone.message

    ran = [t for t in stream if str(t["key"]).startswith("annotate_clip-")]
    assert len(ran) == 5 and len({t["worker"] for t in ran}) == 2  # one task per clip, spread over both workers

    wh = Warehouse(config.warehouse.root)
    assert sorted(wh.partitions("clips")) == ["d0", "d1", "d2", "d3"]
    con = connect(wh)
    try:
        frames = dict(con.execute("SELECT clip, count(*) FROM frames GROUP BY clip").fetchall())
        runs = dict(con.execute("SELECT clip, count(DISTINCT stage) FROM runs WHERE status IN ('completed', 'paused') "
                                "GROUP BY clip").fetchall())
    finally:
        con.close()
    assert frames == {f"d{i}": 30 for i in range(4)}
    assert runs == {c: sum(r.clip == c and r.state in ("completed", "paused") for r in reports) for c in frames}
    assert not list((wh.root / "_running").rglob("*.json"))  # no run left in progress

    again = run_clips(sources[:3], config, show_progress=False)  # the cache is shared: workers find each other's results
    assert {r.state for r in again} == {"cached"}

    from flows.dask_clips import _worker_api, check_workers_api, check_workers_reach_api
    from flows.server import ServerError

    with Client(cluster) as client:  # the next command's own local API: refused before any clip, in one line
        [api] = set(client.run(_worker_api).values())
        check_workers_api(client, api)
        with pytest.raises(ServerError, match=r"^the Dask workers talk to Prefect's API at http.*, not this command's "
                                              r"\(http://127.0.0.1:1/api\): .*`cadestate server start`"):
            check_workers_api(client, "http://127.0.0.1:1/api")
        check_workers_reach_api(client, api, 2.0)  # the API of the clips above answers every worker
        # an API the workers cannot reach (a loopback one, from workers on other machines): refused
        # before any clip, naming every worker, where each clip failed alone
        with pytest.raises(ServerError, match=r"^the Dask worker\(s\) tcp://127\.0\.0\.1:\d+, tcp://127\.0\.0\.1:\d+ "
                                              r"cannot reach Prefect's API at http://127.0.0.1:1/api: it listens on "
                                              r"this machine's loopback: .*PREFECT_API_URL"):
            check_workers_reach_api(client, "http://127.0.0.1:1/api", 2.0)
        check_workers_reach_api(client, "https://127.0.0.1:1/api", 2.0)  # HTTPS: left to Prefect's client settings


def test_a_dask_scheduler_that_does_not_answer_is_one_line(tmp_path):
    from flows.dask_clips import dask_client
    from flows.server import ServerError

    with pytest.raises(ServerError, match=r"^\[prefect\] dask_address tcp://127.0.0.1:9: no Dask scheduler answered "
                                          r"within 2 s \(.*\); start it") as e:
        with dask_client(PrefectConfig(task_runner="dask", dask_address="tcp://127.0.0.1:9", startup_timeout_s=2), ""):
            pass
    assert "\n" not in str(e.value)


def test_a_scheduler_without_workers_is_one_line(tmp_path):
    """A scheduler that no worker joined: every check passed (no worker to refuse) and the command
    waited for ever on its clips, saying nothing."""
    from flows.dask_clips import dask_client
    from flows.server import ServerError

    with _cluster(tmp_path, []) as address:
        with pytest.raises(ServerError, match=rf"^\[prefect\] dask_address {address}: the scheduler has no worker after "
                                              rf"2 s; start some \(`dask worker {address}`\)$"):
            with dask_client(PrefectConfig(task_runner="dask", dask_address=address, startup_timeout_s=2), ""):
                pass


def test_workers_that_cannot_run_our_code_or_read_other_models_are_refused_in_one_line(tmp_path):
    """A worker that cannot import cadestate (another environment) failed the command with a
    traceback and no clip ran; a worker on a machine whose $CADESTATE_MODELS holds other models ran
    its clips with another detector, said completed, and `status` then called them stale."""
    from distributed import Client

    from flows.dask_clips import check_workers_read_the_same_models
    from flows.server import ServerError

    (tmp_path / "no_cadestate.py").write_text(  # a worker whose Python does not import this checkout
        "import sys\n"
        f"sys.path[:] = [p for p in sys.path if p not in ({str(ROOT)!r}, '', '.')]\n"
        "for m in [m for m in sys.modules if m.split('.')[0] in ('flows', 'tasks', 'cadestate', 'warehouse')]:\n"
        "    del sys.modules[m]\n")
    (tmp_path / "other_models").mkdir()
    root = tmp_path / "warehouse"
    clip = make_demo_clip(tmp_path / "clips", dataclasses.replace(SMALL_CLIP, name="e0"))
    source = ClipSource("e0", clip.video_path, clip.cameras_path)
    other_models = ("env", f"CADESTATE_MODELS={tmp_path / 'other_models'}")
    with _cluster(tmp_path, [(), other_models, ("env", f"DASK_DISTRIBUTED__WORKER__PRELOAD=['{tmp_path / 'no_cadestate.py'}']")]) as address:
        config = Config(warehouse=WarehouseConfig(root=str(root)),
                        prefect=PrefectConfig(task_runner="dask", dask_address=address))
        with Client(address) as client:
            names = {info["name"]: w for w, info in client.scheduler_info()["workers"].items()}
        with pytest.raises(ServerError, match=rf"^the Dask worker\(s\) {re.escape(names['w2'])} cannot run cadestate's "
                                              r"code \(.*No module named '\w+'.*\): .*environment"):
            run_clips([source], config, show_progress=False)
        with Client(address) as client:
            client.retire_workers([names["w2"]], close_workers=True)
            with pytest.raises(ServerError, match=rf"^the Dask worker\(s\) {re.escape(names['w1'])} read other model "
                                                  r"files than this command \(stage\(s\) detect\): .*CADESTATE_MODELS"):
                check_workers_read_the_same_models(client, config)
        with pytest.raises(ServerError, match=r"read other model files"):  # refused before any clip
            run_clips([source], config, show_progress=False)
    assert not Warehouse(root).partitions("clips")


def _hides_folders() -> bool:
    """Whether this machine lets a process have its own view of the file system (user and mount
    namespaces: ``unshare -rm``)."""
    return subprocess.run(["unshare", "-rm", "true"], capture_output=True).returncode == 0 if shutil.which("unshare") else False


@pytest.mark.skipif(not _hides_folders(), reason="no user and mount namespaces here (unshare -rm)")
def test_a_worker_that_does_not_see_the_warehouse_is_refused(tmp_path):
    """A worker whose warehouse path is another folder (a tmpfs mounted over it in its own mount
    namespace: a machine without the shared file system) ran every stage into a warehouse of its own,
    and the command said completed."""
    from distributed import Client

    from flows.server import ServerError

    root = tmp_path / "warehouse"
    root.mkdir()
    clip = make_demo_clip(tmp_path / "clips", dataclasses.replace(SMALL_CLIP, name="b0"))
    source = ClipSource("b0", clip.video_path, clip.cameras_path)
    hidden = ("unshare", "-rm", "sh", "-c", f'mount -t tmpfs none "{root}" && exec "$0" "$@"')
    with _cluster(tmp_path, [(), hidden]) as address:
        config = Config(warehouse=WarehouseConfig(root=str(root)), prefect=PrefectConfig(task_runner="dask",
                                                                                          dask_address=address))
        with pytest.raises(ServerError, match=r"^the Dask worker\(s\) tcp://127\.0\.0\.1:\d+ do not see the warehouse "
                                              rf"at {re.escape(str(root))} \(.*\): .*shared file system$"):
            run_clips([source], config, show_progress=False)
        assert not list(Warehouse(root).partitions("clips"))
        from flows.dask_clips import annotate_clip_here, warehouse_probe

        with Client(address) as client:
            [blind] = [w for w, info in client.scheduler_info()["workers"].items() if info["name"] == "w1"]
            # a worker that joins after the check: its clip fails in one line, and it writes nothing
            with warehouse_probe(str(root)) as probe:
                future = client.submit(annotate_clip_here, str(root), source, config, "http://127.0.0.1:1/api", probe,
                                       workers=[blind], pure=False)
                with pytest.raises(RuntimeError, match=rf"^the Dask worker\(s\) {blind} do not see the warehouse"):
                    future.result()
            assert client.run(os.listdir, str(root), workers=[blind]) == {blind: []}
        assert not [p.name for p in root.iterdir() if p.name.startswith(".dask-probe-")]  # the probe goes with the command


def test_a_relative_model_path_is_the_drivers_on_the_workers(tmp_path, cluster, monkeypatch):
    """``[detect] model = "models/det.onnx"`` is taken from the command's folder, as with threads;
    the workers run in another (``tmp_path``). The runs it records digest the config as a command
    here does (``cadestate status`` says fresh)."""
    from tasks.detection.model_inputs import BUILT_IN, detector_path
    from tasks.registry import config_hash

    coco = detector_path(DetectConfig(model="coco"))
    if not coco.is_file():
        pytest.skip(f"{coco} missing: `make models` builds it ({BUILT_IN['coco'][0]})")
    project = tmp_path / "project"
    (project / "models").mkdir(parents=True)
    shutil.copy(coco, project / "models" / "det.onnx")
    clip = make_demo_clip(tmp_path / "clips", dataclasses.replace(SMALL_CLIP, name="m0"))
    monkeypatch.chdir(project)
    config = Config(warehouse=WarehouseConfig(root="warehouse"), detect=DetectConfig(model="models/det.onnx"),
                    prefect=PrefectConfig(task_runner="dask", dask_address=cluster))
    reports = run_clips([ClipSource("m0", clip.video_path, clip.cameras_path)], config, show_progress=False)
    [detect] = [r for r in reports if r.stage == "detect"]
    assert detect.state == "completed", detect.message
    con = connect(Warehouse(project / "warehouse"))
    try:
        [(recorded,)] = con.execute("SELECT config_hash FROM runs WHERE stage = 'detect'").fetchall()
    finally:
        con.close()
    assert recorded == config_hash("detect", config)


def _kill_the_second_clips_worker(root: Path, killed: list[tuple[str, str]], stop: threading.Event) -> None:
    """Once a second clip has a stage running (one single-threaded worker: the first clip is done),
    ``kill -9`` the worker process running it; ``killed`` gets (first clip, second clip)."""
    first = ""
    while not stop.wait(0.1):
        for marker in sorted((root / "_running").glob("*/*.json")):
            with contextlib.suppress(OSError, ValueError):
                pid = json.loads(marker.read_text())["pid"]
                first = first or marker.parent.name
                if marker.parent.name != first:
                    time.sleep(1)  # the first clip's result reaches the client meanwhile
                    os.kill(pid, signal.SIGKILL)
                    killed.append((first, marker.parent.name))
                    return


def test_a_lost_worker_does_not_run_finished_clips_again(tmp_path):
    """distributed recomputes the results of a lost worker that a client still holds: a clip that had
    finished ran again (its stages cached, another flow run) when the worker was killed later."""
    from distributed import Client

    clips = [make_demo_clip(tmp_path / "clips", dataclasses.replace(SMALL_CLIP, name=f"k{i}", seed=20 + i))
             for i in range(2)]
    sources = [ClipSource(f"k{i}", c.video_path, c.cameras_path) for i, c in enumerate(clips)]
    root = tmp_path / "warehouse"
    with _cluster(tmp_path, [()]) as address, Client(address) as client:
        config = Config(warehouse=WarehouseConfig(root=str(root)),
                        prefect=PrefectConfig(task_runner="dask", dask_address=address))
        killed: list[tuple[str, str]] = []
        stop = threading.Event()
        killer = threading.Thread(target=_kill_the_second_clips_worker, args=(root, killed, stop), daemon=True)
        client.get_task_stream()
        killer.start()
        try:
            reports = run_clips(sources, config, show_progress=False)
        finally:
            stop.set()
            killer.join()
        stream = client.get_task_stream()
    [(first, second)] = killed
    ran = [str(t["key"]).split("-")[1] for t in stream if str(t["key"]).startswith("annotate_clip-")]
    assert sorted(ran) == [first, second]  # the killed clip ran again (Dask's retry), the finished one did not
    assert {r.state for r in reports if r.clip == first} == {"completed"}


def test_a_command_on_a_local_cluster_says_a_line_per_clip_and_nothing_of_dask(tmp_path):
    """`cadestate ingest` on a local cluster without --verbose: a line per finished clip on stderr
    (there was no progress at all), and none of distributed's ~40 log lines."""
    clips = [make_demo_clip(tmp_path / "clips", dataclasses.replace(SMALL_CLIP, name=f"q{i}", seed=30 + i))
             for i in range(2)]
    cfg = tmp_path / "dask.toml"
    cfg.write_text('[prefect]\ntask_runner = "dask"\nmax_workers = 2\n')
    env = {**{k: v for k, v in os.environ.items() if k not in ("PREFECT_LOGGING_LEVEL", "PREFECT_API_URL")},
           "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    done = subprocess.run([sys.executable, "-m", "cadestate", "-c", str(cfg), "-w", str(tmp_path / "w"), "ingest",
                           str(clips[0].video_path.parent)], capture_output=True, text=True, env=env, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    lines = done.stderr.splitlines()
    assert not [line for line in lines if "distributed" in line or "Traceback" in line], done.stderr
    finished = sorted(line for line in lines if line.startswith("["))
    assert [line.split(":")[0] for line in finished] == ["[1/2] q0_0", "[2/2] q1_0"] or \
        [line.split(":")[0] for line in finished] == ["[1/2] q1_0", "[2/2] q0_0"], done.stderr
    assert all(re.fullmatch(r"\[\d/2\] q\d_0: \d+ completed \(tcp://127\.0\.0\.1:\d+\)", line) for line in finished), finished


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_ctrl_c_ends_a_command_on_a_local_cluster_at_once(tmp_path, sig):
    """Ctrl-C (SIGINT to the process group, as a terminal sends it) or SIGTERM (to the command) while
    clips run on a local cluster: the command ends within seconds, status 128 + the signal, saying
    what the thread runner says; the workers stop (the stage reads as interrupted), and their flow
    runs read Cancelled. Before, SIGTERM ended it silently after ~7 s and Ctrl-C printed distributed's
    tracebacks, the flow runs left Running."""
    import sqlite3

    import psutil

    signum = getattr(signal, sig)
    clip = make_demo_clip(tmp_path / "clips", dataclasses.replace(SMALL_CLIP, name="i0"))
    cfg = tmp_path / "dask.toml"
    cfg.write_text('[prefect]\ntask_runner = "dask"\nmax_workers = 1\n')
    w = tmp_path / "w"
    env = {**{k: v for k, v in os.environ.items() if k not in ("PREFECT_LOGGING_LEVEL", "PREFECT_API_URL")},
           "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    proc = subprocess.Popen([sys.executable, "-m", "cadestate", "-c", str(cfg), "-w", str(w), "ingest",
                             str(clip.video_path), str(clip.cameras_path)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # as in a terminal
    deadline = time.monotonic() + 120
    while not (markers := list((w / "_running" / "i0_0").glob("detect.*.json"))) and time.monotonic() < deadline \
            and proc.poll() is None:
        time.sleep(0.01)  # until the detect stage runs on the worker (its run marker)
    assert proc.poll() is None, proc.communicate()
    worker = json.loads(markers[0].read_text())["pid"]
    sent = time.monotonic()
    os.killpg(proc.pid, signum) if signum == signal.SIGINT else proc.send_signal(signum)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signum and time.monotonic() - sent < 10, err
    said = "interrupted" if signum == signal.SIGINT else "terminated"
    assert f"{said}: the stages in progress stop unfinished (the command run again resumes them)" in err, err
    assert "Traceback" not in err and "distributed" not in err, err
    deadline = time.monotonic() + 10
    while psutil.pid_exists(worker) and psutil.Process(worker).status() != psutil.STATUS_ZOMBIE \
            and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not psutil.pid_exists(worker) or psutil.Process(worker).status() == psutil.STATUS_ZOMBIE
    assert not [p.name for p in w.iterdir() if p.name.startswith(".dask-probe-")]
    with sqlite3.connect(Path(os.environ["PREFECT_HOME"]) / "prefect.db") as db:  # not left "Running" in the UI
        states = db.execute("SELECT state_type FROM flow_run WHERE name = 'annotate_clip/i0_0' AND parameters "
                            "LIKE ?", (f"%{w}%",)).fetchall()  # the tests share one Prefect home
    assert states == [("CANCELLED",)]


def test_a_clip_whose_workers_died_says_what_may_have_killed_them():
    """distributed's KilledWorker names no cause: a clip whose workers died under it (a local
    cluster's worker memory is the machine's / max_workers, killed at 95 %) says memory and the knob."""
    from distributed.scheduler import KilledWorker, WorkerState

    from flows.dask_clips import WHOLE_CLIP, _failed

    last = WorkerState(address="tcp://127.0.0.1:1", status=None, pid=1, name="w", memory_limit=0, local_directory="/tmp",
                       nanny=None, server_id="s")
    [report] = _failed("c0", KilledWorker("annotate_clip-c0", last, 3), local=True).reports
    assert report.stage == WHOLE_CLIP and report.state == "failed" and "\n" not in report.message
    assert report.message.startswith("KilledWorker: every worker that ran it died (the last: tcp://127.0.0.1:1): out of "
                                     "memory? ") and "max_workers" in report.message
    [remote] = _failed("c0", KilledWorker("annotate_clip-c0", last, 3), local=False).reports
    assert "max_workers" not in remote.message and "--memory-limit" in remote.message  # the knob of its workers
    [other] = _failed("c0", RuntimeError("boom"), local=True).reports
    assert other.message == "RuntimeError: boom"
