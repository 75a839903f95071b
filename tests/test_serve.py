"""`cadestate serve`: deployments on a real Prefect server build a dataset from an inbox on a schedule;
a clip waiting for people is a suspended flow run, resumed through the API when `labels ingest`
answers it."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from flows.deployments import official_names, pairs_to_run, ready_pairs
from flows.server import read_server
from tasks.video.ingest import ClipSource
from warehouse import Warehouse


def test_only_completely_copied_pairs_are_taken(tmp_path):
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    for name in ("old", "fresh", "marked", "alone", "VID_0001"):
        (inbox / f"{name}.{'MOV' if name.startswith('VID') else 'mp4'}").write_bytes(b"v")
        if name != "alone":
            (inbox / f"{name}.txt").write_text("c")
    (inbox / "marked.done").touch()
    (inbox / "notes.json").write_text("{}")
    now = time.time()
    for p in (inbox / "old.mp4", inbox / "old.txt"):
        os.utime(p, (now - 60, now - 60))
    assert [p.clip for p in ready_pairs(inbox, 10.0, "val", now)] == ["marked", "old"]
    assert {p.split for p in ready_pairs(inbox, 10.0, "val", now)} == {"val"}
    # every video `cadestate ingest FOLDER` takes, in any case (a phone's .MOV was never taken)
    assert [p.clip for p in ready_pairs(inbox, 0.0, now=now)] == ["VID_0001", "fresh", "marked", "old"]
    assert ready_pairs(tmp_path / "missing", 0.0) == []


def test_two_inbox_pairs_naming_one_clip_start_one_run(tmp_path):
    """Two videos with the same camera file get the same official name: only the first is run (two
    runs of one clip would write its tables at once), the other is named in a warning; a bad camera
    file is left out naming its line."""
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    lines = ["https://www.youtube.com/watch?v=abcdefghijk"] + [
        f"{t} 0.8 1.4 0.5 0.5 0 0 1 0 0 0 0 1 0 0 0 0 1 0" for t in (1_000_000, 1_033_333)]
    for name in ("a", "b"):
        (inbox / f"{name}.mp4").write_bytes(name.encode())
        (inbox / f"{name}.txt").write_text("\n".join(lines) + "\n")
    (inbox / "c.mp4").write_bytes(b"c")
    (inbox / "c.txt").write_text(lines[0] + "\nnot a camera line\n")
    warnings = []
    named = official_names(ready_pairs(inbox, 0.0), warnings.append)
    assert [(p.clip, p.video.name) for p in named] == [("abcdefghijk_1000000", "a.mp4")]
    assert len(warnings) == 2 and any("b.mp4: its camera file names clip abcdefghijk_1000000, as" in w for w in warnings)
    assert any("c.txt:2: expected 19 columns" in w for w in warnings), warnings


def test_an_odd_file_name_or_a_shared_video_id_leaves_out_one_pair_not_the_inbox(tmp_path):
    """A video named "living room.mp4" raised while the inbox was listed (its file name was checked
    as a clip name), so no clip of the inbox was taken; two pairs of different videos sharing a
    video id, or one sharing it with a registered clip, were both taken (`cadestate ingest`
    refuses them: their frames would mix in the official layout)."""
    from conftest import table_rows

    inbox = tmp_path / "inbox"
    inbox.mkdir()

    def pair(name: str, url: str, start: int) -> None:
        (inbox / f"{name}.mp4").write_bytes(name.encode())
        (inbox / f"{name}.txt").write_text("\n".join([url] + [
            f"{t} 0.8 1.4 0.5 0.5 0 0 1 0 0 0 0 1 0 0 0 0 1 0" for t in (start, start + 33_333)]) + "\n")

    pair("living room", "file:///videos/a/room.mp4", 0)
    pair("other room", "file:///videos/b/room.mp4", 5_000_000)  # another video, the same id: room
    pair("hall", "file:///videos/hall.mp4", 0)  # its id registered from another video
    pair("kitchen", "file:///videos/kitchen.mp4", 0)  # its id is no other clip's
    wh = Warehouse(tmp_path / "w")
    wh.write("clips", "hall_7", table_rows("clips", [{"clip": "hall_7", "url": "file:///elsewhere/hall.mp4"}]))
    for clip, url in (("attic_0", "file:///a/attic.mp4"), ("attic_9", "file:///b/attic.mp4")):  # a clash of old: no one else's
        wh.write("clips", clip, table_rows("clips", [{"clip": clip, "url": url}]))
    ready = ready_pairs(inbox, 0.0)
    assert [p.clip for p in ready] == ["hall", "kitchen", "living_room", "other_room"]
    warnings = []
    named = official_names(ready, warnings.append, wh)
    assert [(p.clip, p.video.name) for p in named] == [("kitchen_0", "kitchen.mp4"), ("room_0", "living room.mp4")]
    assert len(warnings) == 2 and all("which share its video id" in w for w in warnings), warnings
    assert f"left out of the inbox: {inbox / 'hall.txt'}: clip hall_0 comes from another video (line 1: " \
           "file:///videos/hall.mp4) than hall_7, which share its video id 'hall'; ingest it with `cadestate ingest " \
           "VIDEO CAMERAS --clip NAME`, a name of its own" in warnings, warnings
    assert any(w.startswith(f"left out of the inbox: {inbox / 'other room.txt'}: clip room_5000000 ") for w in warnings)


def test_clips_done_are_not_run_again(tmp_path, small_clip):
    import datetime as dt
    import json
    import os
    import shutil
    import socket

    import psutil

    from conftest import table_rows
    from cadestate.lineage import file_sha256
    from tasks.registry import stages_of

    wh = Warehouse(tmp_path / "w")
    pair = ClipSource("room", small_clip.video_path, small_clip.cameras_path)
    assert pairs_to_run(wh, [pair]) == [pair]
    wh.write("clips", "room", table_rows("clips", [{"clip": "room", "video_sha256": file_sha256(pair.video),
                                                     "cameras_sha256": file_sha256(pair.cameras)}]))
    stages = [s.name for s in stages_of("clip")]
    at = [dt.datetime(2026, 1, 1, tzinfo=dt.timezone.utc) + dt.timedelta(seconds=i) for i in range(len(stages) + 1)]

    def runs(rows):  # the runs table appends: the clip's runs are these alone
        shutil.rmtree(wh.root / "tables" / "runs", ignore_errors=True)
        wh.write("runs", "room", table_rows("runs", [{"clip": "room", "run_id": f"r{i}", "started_at": at[i], **r}
                                                     for i, r in enumerate(rows)]))

    runs([{"stage": s, "status": "completed"} for s in stages])
    assert pairs_to_run(wh, [pair]) == []
    runs([{"stage": s, "status": "failed" if s == "detect" else "completed"} for s in stages])
    assert pairs_to_run(wh, [pair]) == [pair]  # its last detect run failed: it runs again
    # A process killed between two stages (tracking's run never started): it runs again. A clip
    # whose cad_selection waits for people has no run of the stages after it: done for now.
    runs([{"stage": s, "status": "completed"} for s in stages[:stages.index("tracking")]])
    assert pairs_to_run(wh, [pair]) == [pair]
    i = stages.index("cad_selection")
    runs([{"stage": s, "status": "completed"} for s in stages[:i]] + [{"stage": "cad_selection", "status": "paused", "rows_written": 0}]
         + [{"stage": s, "status": "completed"} for s in ("pose", "verification")])  # those read label files only
    assert pairs_to_run(wh, [pair]) == []
    # A process killed within a stage leaves its marker, and no row: it runs again.
    marker = wh.root / "_running" / "room" / "pose.r9.json"
    marker.parent.mkdir(parents=True)
    marker.write_text(json.dumps({"clip": "room", "stage": "pose", "run_id": "r9", "pid": 2 ** 22 + 7, "host": socket.gethostname(),
                                  "process_start": 0.0, "process_ticks": 1, "started_at": at[0].isoformat()}))
    assert pairs_to_run(wh, [pair]) == [pair]
    marker.write_text(json.dumps({**json.loads(marker.read_text()), "pid": os.getpid(), "process_ticks": None,
                                  "process_start": psutil.Process().create_time()}))
    assert pairs_to_run(wh, [pair]) == []  # its run is under way (this process): not submitted again


def test_a_clip_whose_stage_keeps_failing_is_not_run_again_until_its_config_or_code_changes(tmp_path, small_clip):
    """Each inbox tick ran a clip whose stage fails for good (a bad file, a bug) again, for ever:
    after [schedule] failed_runs failures in a row with the config and code of now it is left, and
    said so; a change of the stage's config (or code) gives it another run."""
    import dataclasses
    import datetime as dt

    from conftest import table_rows
    from cadestate.config import Config
    from cadestate.lineage import file_sha256
    from tasks.registry import STAGES, config_hash

    wh, config = Warehouse(tmp_path / "w"), Config()
    pair = ClipSource("room", small_clip.video_path, small_clip.cameras_path)
    wh.write("clips", "room", table_rows("clips", [{"clip": "room", "video_sha256": file_sha256(pair.video),
                                                     "cameras_sha256": file_sha256(pair.cameras)}]))
    at = dt.datetime(2026, 1, 1, tzinfo=dt.timezone.utc)
    now = {"config_hash": config_hash("detect", config), "code_hash": STAGES["detect"].code_hash}
    warned: list[str] = []
    for i in range(3):
        assert pairs_to_run(wh, [pair], config, warned.append) == [pair] and not warned
        wh.write("runs", "room", table_rows("runs", [{"clip": "room", "run_id": f"r{i}", "stage": "detect", "status": "failed",
                                                     "started_at": at + dt.timedelta(seconds=i), **now}]))
    assert pairs_to_run(wh, [pair], config, warned.append) == []
    assert warned == ["clip room: its stage detect failed 3 runs in a row with this config, code and inputs: not run again "
                      "until its files, the config, the code or what it reads change (a model file made, answers given; "
                      "`cadestate status` shows why; `cadestate run` runs it)"]
    changed = dataclasses.replace(config, detect=dataclasses.replace(config.detect, score_threshold=0.3))
    assert pairs_to_run(wh, [pair], changed, warned.append) == [pair]
    assert pairs_to_run(wh, [pair], dataclasses.replace(config, schedule=dataclasses.replace(config.schedule, failed_runs=0)),
                        warned.append) == [pair]
    # its files replaced (the user fixed the bad file): the failures were the old bytes', it is run again
    fixed = tmp_path / "fixed.txt"
    fixed.write_text(small_clip.cameras_path.read_text() + "\n")
    warned.clear()
    assert pairs_to_run(wh, [dataclasses.replace(pair, cameras=fixed)], config, warned.append) == [
        dataclasses.replace(pair, cameras=fixed)] and not warned


def test_a_clip_whose_stage_failed_for_a_missing_model_runs_again_once_the_model_is_made(tmp_path, small_clip):
    """detect failed three inbox ticks in a row for its model file missing; `make models` (what its
    error asks) changes neither its config nor its code, so the clip was left for good: the failed
    runs' inputs (the model file's digest among them) are compared with today's too."""
    import dataclasses
    import datetime as dt

    from conftest import table_rows
    from cadestate.config import Config
    from cadestate.lineage import file_sha256
    from tasks.inputs_memo import InputsMemo
    from tasks.registry import STAGES, config_hash, upstream_inputs_hash

    model = tmp_path / "det.onnx"
    config = Config()
    config = dataclasses.replace(config, detect=dataclasses.replace(config.detect, model=str(model)))
    wh = Warehouse(tmp_path / "w")
    pair = ClipSource("room", small_clip.video_path, small_clip.cameras_path)
    wh.write("clips", "room", table_rows("clips", [{"clip": "room", "video_sha256": file_sha256(pair.video),
                                                     "cameras_sha256": file_sha256(pair.cameras)}]))
    detect, at = STAGES["detect"], dt.datetime(2026, 1, 1, tzinfo=dt.timezone.utc)
    ups = [{"stage": u, "status": "completed", "output_hash": f"out-{u}"} for u in detect.upstream]
    inputs = upstream_inputs_hash([u["output_hash"] for u in ups] + detect.config_inputs(config)
                                  + InputsMemo(wh, "room").clip_inputs(detect))  # as the stage chain digests them
    failed = {"stage": "detect", "status": "failed", "config_hash": config_hash("detect", config),
              "code_hash": detect.code_hash, "inputs_hash": inputs}
    wh.write("runs", "room", table_rows("runs", [{"clip": "room", "run_id": f"r{i}", "started_at": at + dt.timedelta(seconds=i), **r}
                                                 for i, r in enumerate(ups + [failed] * 3)]))
    warned: list[str] = []
    assert pairs_to_run(wh, [pair], config, warned.append) == [] and len(warned) == 1
    model.write_bytes(b"a model made since")
    assert pairs_to_run(wh, [pair], config, warned.append) == [pair] and len(warned) == 1


def test_inbox_files_are_hashed_once_until_they_change(tmp_path, monkeypatch):
    """Each served build_dataset tick runs in a new process (Prefect's runner): the digests are kept
    in the warehouse, and a tick hashes only files new or changed since the last (each tick read
    every video of the inbox again, done clips included: ~1.5 s a GB)."""
    import cadestate.lineage
    from flows import deployments

    wh, f, g = Warehouse(tmp_path / "w"), tmp_path / "clip.txt", tmp_path / "other.txt"
    f.write_text("a")
    g.write_text("b")
    read: list[Path] = []
    monkeypatch.setattr(deployments, "file_sha256", lambda p: (read.append(p), cadestate.lineage.file_sha256(p))[1])
    first = deployments.inbox_sha256s(wh, [f, g])
    assert read == [f, g] and first[f] == cadestate.lineage.file_sha256(f)
    assert deployments.inbox_sha256s(wh, [f, g]) == first and read == [f, g]  # the next tick reads neither
    f.write_text("c")  # same size, new bytes (and mtime)
    os.utime(f, ns=(f.stat().st_atime_ns, f.stat().st_mtime_ns + 1_000_000))
    again = deployments.inbox_sha256s(wh, [f, g])
    assert read == [f, g, f] and again[f] != first[f] and again[g] == first[g]
    assert list(json.loads((wh.root / "_cache" / deployments.INBOX_SHA256).read_text())) == [str(f.resolve()), str(g.resolve())]
    deployments.inbox_sha256s(wh, [g])  # a file gone from the inbox leaves the cache
    assert list(json.loads((wh.root / "_cache" / deployments.INBOX_SHA256).read_text())) == [str(g.resolve())]


@pytest.mark.slow
def test_a_served_clip_whose_stage_failed_ends_failed(tmp_path, small_clip):
    """The served annotate_clip run of a clip whose ingest failed (a broken video) ends Failed in the
    Prefect UI, as a command's run does; it ended Completed, a broken clip looking done."""
    from flows.deployments import annotate_clip_served

    (tmp_path / "broken.mp4").write_bytes(b"\x00" * 1000)
    state = annotate_clip_served(str(tmp_path / "w"), "", "broken", str(tmp_path / "broken.mp4"),
                                 str(small_clip.cameras_path), return_state=True)
    assert state.is_failed() and "1 failed: ingest: " in state.message and "broken.mp4" in state.message, state
    runs = Warehouse(tmp_path / "w").read("runs", ["broken"]).sort_by("started_at").to_pylist()
    assert [(r["stage"], r["status"]) for r in runs][:2] == [("cameras", "completed"), ("ingest", "failed")]


@pytest.mark.slow
def test_a_new_serve_crashes_the_runs_an_earlier_one_left_running(tmp_path):
    """A serve stopped (`server stop`) or killed while it ran a clip left that flow run Running on the
    server for good, and build_dataset never started the clip again (it had an active run). A new
    serve marks its warehouse's runs left pending or running Crashed; suspended runs, and another
    warehouse's runs, are left as they are."""
    from prefect.client.orchestration import get_client
    from prefect.deployments.runner import EntrypointType
    from prefect.states import Paused, Pending, Running

    from flows.deployments import ANNOTATE_DEPLOYMENT, annotate_clip_served, crash_runs_left_running

    mine, other = str(tmp_path / "w"), str(tmp_path / "other")
    deployment_id = annotate_clip_served.to_deployment(name=ANNOTATE_DEPLOYMENT,
                                                       entrypoint_type=EntrypointType.MODULE_PATH).apply()

    def run(name: str, warehouse: str, state) -> str:
        with get_client(sync_client=True) as client:
            return client.create_flow_run_from_deployment(
                deployment_id, name=name, state=state, parameters={"warehouse": warehouse, "config_path": "", "clip": name,
                                                                   "video": "v.mp4", "cameras": "v.txt"}).id

    runs = {name: run(name, warehouse, state) for name, warehouse, state in (
        ("a", mine, Running()), ("b", mine, Pending()), ("c", mine, Paused(reschedule=True, timeout_seconds=600)),
        ("d", other, Running()))}
    assert crash_runs_left_running(mine) == ["a", "b"]
    with get_client(sync_client=True) as client:
        assert {name: client.read_flow_run(i).state.type.value for name, i in runs.items()} == \
            {"a": "CRASHED", "b": "CRASHED", "c": "PAUSED", "d": "RUNNING"}
    assert crash_runs_left_running(mine) == []


@pytest.mark.slow
def test_two_ticks_starting_one_clip_start_one_run(tmp_path, monkeypatch):
    """The inbox's tick and the labels inbox's (two deployments: each runs once at a time, not once
    with the other) both found no active run of a clip and each started one: its stages ran twice
    over. The check and the start now hold the clip's lock. The API's answer is slowed by a second
    (a busy server), so that both checks come before either start unless the lock orders them."""
    from concurrent.futures import ThreadPoolExecutor

    from prefect.client.orchestration import get_client
    from prefect.deployments.runner import EntrypointType
    from prefect.states import Cancelled

    from flows import deployments
    from flows.deployments import ACTIVE, ANNOTATE_DEPLOYMENT, annotate_clip_served, start_clip_once

    annotate_clip_served.to_deployment(name=ANNOTATE_DEPLOYMENT, entrypoint_type=EntrypointType.MODULE_PATH).apply()
    real = deployments.active_clip_runs

    def slow_answer(clip, states):
        found = real(clip, states)
        time.sleep(1.0)
        return found

    monkeypatch.setattr(deployments, "active_clip_runs", slow_answer)
    clip = f"twice_{os.getpid()}"
    source = ClipSource(clip, tmp_path / "v.mp4", tmp_path / "v.txt", "train")
    with ThreadPoolExecutor(2) as pool:
        started = list(pool.map(lambda _: start_clip_once(str(tmp_path / "w"), "", source), range(2)))
    runs = real(clip, ACTIVE)
    with get_client(sync_client=True) as client:  # not left scheduled on the tests' API
        for run in runs:
            client.set_flow_run_state(run.id, Cancelled(), force=True)
    assert sorted(started) == [False, True] and len(runs) == 1, (started, len(runs))


@pytest.mark.slow
def test_a_served_run_on_a_config_file_that_does_not_load_fails_in_one_line(tmp_path):
    """A config file edited under a serve into one that does not load (a typo'd key): each run ends
    Failed with the config error's one line as its message; raised, it printed two tracebacks a flow
    in the serve's log (three flows a tick)."""
    from flows.deployments import build_dataset_inbox, dataset_report, ingest_labels_inbox

    config = tmp_path / "c.toml"
    config.write_text("[tracking]\nmin_detection = 3\n")
    for served in (build_dataset_inbox, ingest_labels_inbox, dataset_report):
        state = served(str(tmp_path / "w"), str(config), return_state=True)
        assert state.is_failed() and state.message.startswith(f"{config}: [tracking] unknown key 'min_detection'"), state


@pytest.mark.slow
def test_an_inbox_that_is_no_folder_is_said_in_the_runs_log(tmp_path):
    """A [schedule] inbox or labels_inbox naming no folder (a typo, a relative path from another
    folder) was watched in silence: "0 new clip(s) started" every tick. (The runs' log, in a process
    of its own as a served run's: Prefect's console handler writes to the stderr it found first.)"""
    config = tmp_path / "c.toml"
    config.write_text('[schedule]\ninbox = "inbx"\nlabels_inbox = "labls"\n')
    runs = subprocess.run([sys.executable, "-c", "import sys; from flows.deployments import build_dataset_inbox, "
                           "ingest_labels_inbox; w, c = sys.argv[1:]; print(build_dataset_inbox(w, c), ingest_labels_inbox(w, c))",
                           str(tmp_path / "w"), str(config)], capture_output=True, text=True, cwd=tmp_path, timeout=600,
                          env={**os.environ, "PYTHONPATH": str(Path(__file__).parents[1])})
    assert runs.returncode == 0 and runs.stdout == "[] []\n", runs.stderr
    assert f"[schedule] inbox: {tmp_path / 'inbx'} is no folder" in runs.stderr, runs.stderr
    assert f"[schedule] labels_inbox: {tmp_path / 'labls'} is no folder" in runs.stderr, runs.stderr


@contextlib.contextmanager
def served(tmp_path: Path, w: Path, config: Path) -> Iterator[tuple[list[str], subprocess.Popen]]:
    """A Prefect server for warehouse ``w`` and a `cadestate serve` of ``config`` (its output in
    serve.log): the common CLI arguments and the serve's process; both stopped after."""
    common = ["-c", str(config), "-w", str(w)]
    assert cli(*common, "server", "start", "--port", "0", cwd=tmp_path).returncode == 0
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    serving = subprocess.Popen([sys.executable, "-m", "cadestate", *common, "serve"], cwd=tmp_path, env=env,
                               stdout=open(tmp_path / "serve.log", "w"), stderr=subprocess.STDOUT, start_new_session=True)
    try:
        yield common, serving
    finally:
        if serving.poll() is None:
            os.killpg(serving.pid, signal.SIGTERM)
            serving.wait(60)
        cli(*common, "server", "stop", cwd=tmp_path)


def cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    return subprocess.run([sys.executable, "-m", "cadestate", *args], capture_output=True, text=True, env=env, cwd=cwd,
                          timeout=600)


class Api:
    """The few REST calls of Prefect's API the test needs."""

    def __init__(self, url: str):
        self.url = url

    def post(self, path: str, body: dict) -> object:
        """POST, retrying while the server answers 503: Prefect's server sends it for errors it calls retryable
        (its SQLite database busy or timing out under load, as on CI), and its own client retries the same way."""
        for attempt in range(10):
            response = httpx.post(f"{self.url}{path}", json=body, timeout=30)
            if response.status_code != 503 or attempt == 9:
                break
            time.sleep(float(response.headers.get("Retry-After") or 2))
        response.raise_for_status()
        return response.json()

    def deployment_id(self, name: str) -> str | None:
        found = self.post("/deployments/filter", {"deployments": {"name": {"any_": [name]}}, "limit": 5})
        return found[0]["id"] if found else None

    def run(self, deployment: str) -> None:
        self.post(f"/deployments/{self.deployment_id(deployment)}/create_flow_run", {})

    def flow_run(self, name: str) -> dict | None:
        found = self.post("/flow_runs/filter", {"flow_runs": {"name": {"any_": [name]}}, "limit": 5, "sort": "START_TIME_DESC"})
        return found[0] if found else None


def wait_for(what: str, check, timeout_s: float = 420.0, every_s: float = 3.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if (value := check()) is not None:
            return value
        time.sleep(every_s)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.mark.slow
def test_an_inbox_clip_is_built_on_schedule_and_resumed_by_its_labels(tmp_path, small_clip):
    w, inbox, labels = tmp_path / "w", tmp_path / "inbox", tmp_path / "labels"
    inbox.mkdir()
    labels.mkdir()
    config = tmp_path / "c.toml"
    config.write_text(f'[schedule]\ninbox = "{inbox}"\nlabels_inbox = "{labels}"\ninbox_split = "val"\n'
                      f'report = "{tmp_path / "report"}"\ninbox_cron = "0 0 1 1 *"\nlabels_cron = "0 0 1 1 *"\n'
                      f'report_cron = "0 0 1 1 *"\n')  # runs are triggered by the test
    with served(tmp_path, w, config) as (common, serving):
        api = Api(read_server(w).api_url)
        names = {"annotate_clip", "build_dataset", "ingest_labels", "dataset_report"}
        deployments = wait_for("the four deployments", lambda: (found := api.post("/deployments/filter", {"limit": 10}))
                               and names <= {d["name"] for d in found} and found or None)
        crons = {d["name"]: [(x["schedule"].get("cron"), x["active"]) for x in d["schedules"]] for d in deployments}
        assert crons["build_dataset"] == crons["ingest_labels"] == crons["dataset_report"] == [("0 0 1 1 *", True)]
        assert crons["annotate_clip"] == []  # run on demand, per clip
        one_at_a_time = {d["name"]: ((d.get("global_concurrency_limit") or {}).get("limit"),
                                     (d.get("concurrency_options") or {}).get("collision_strategy"))
                         for d in deployments}  # missed ticks come due together after an outage: one runs
        assert one_at_a_time["build_dataset"] == one_at_a_time["ingest_labels"] == one_at_a_time["dataset_report"] == \
            (1, "CANCEL_NEW"), one_at_a_time
        assert one_at_a_time["annotate_clip"] == (2, "ENQUEUE")  # [schedule] clip_runs: more clips wait for a slot
        second = cli(*common, "serve", cwd=tmp_path)  # stopping either would pause the schedules of both
        assert second.returncode == 2 and "`cadestate serve` already serves" in second.stderr, second.stderr
        shutil.copy(small_clip.video_path, inbox / "room_1.mp4")  # named small_0 from its camera file
        shutil.copy(small_clip.cameras_path, inbox / "room_1.txt")
        (inbox / "room_1.done").touch()
        lines = small_clip.cameras_path.read_text().splitlines(keepends=True)  # broken_0, a video that does not decode
        (inbox / "broken.txt").write_text("synthetic://demo/broken\n" + "".join(lines[1:]))
        (inbox / "broken.mp4").write_bytes(b"\x00" * 1000)
        (inbox / "broken.done").touch()
        api.run("build_dataset")
        failed = wait_for("the broken clip's run", lambda: (r := api.flow_run("annotate_clip/broken_0")) and
                          r["state"]["type"] in ("COMPLETED", "FAILED", "CRASHED") and r or None)
        assert failed["state"]["type"] == "FAILED" and "1 failed: ingest: " in failed["state"]["message"], failed["state"]
        assert "broken.mp4: cannot open video" in failed["state"]["message"]
        run = wait_for("a suspended clip", lambda: (r := api.flow_run("annotate_clip/small_0")) and
                       r["state"]["name"] in ("Suspended", "Failed", "Crashed", "Completed") and r or None)
        assert run["state"]["name"] == "Suspended", (tmp_path / "serve.log").read_text()[-3000:]
        assert {"clip:small_0", "split:val"} <= set(run["tags"])
        wh = Warehouse(w)
        assert wh.read("frames", partitions=["small_0"]).num_rows == 30
        [task] = (w / "label_tasks" / "small_0").glob("*.json")
        (labels / "small_0.json").write_text(json.dumps({
            "format": "cadestate-label/1", "kind": "manual_track", "clip": "small_0", "task_id": task.stem,
            "annotator": "test", "created_at": "2026-11-23T00:00:00Z", "answers": []}))
        answered = cli(*common, "labels", "ingest", str(labels), cwd=tmp_path)  # through the API, not a local run
        assert answered.returncode == 0 and "resumed the suspended run of small_0" in answered.stdout, answered.stderr
        assert "Prefect's local API starts alongside" not in answered.stderr
        done = wait_for("the resumed clip", lambda: (r := api.flow_run("annotate_clip/small_0")) and
                        r["state"]["type"] in ("COMPLETED", "FAILED", "CRASHED") and r or None)
        assert done["id"] == run["id"] and done["state"]["type"] == "COMPLETED"
        assert wh.read("manual_track_labels", partitions=["small_0"]).num_rows == 0  # "nothing missing" answers it
        assert {r["stage"]: r["status"] for r in wh.read("runs", partitions=["small_0"]).to_pylist()}["manual_tracks"] == "completed"
        api.run("build_dataset")  # a clip done costs nothing: no new run for it
        api.run("ingest_labels")  # its labels were ingested before: nothing to resume
        wait_for("the labels inbox", lambda: (r := api.flow_run("ingest_labels/inbox")) and
                 r["state"]["type"] == "COMPLETED" and r or None)
        assert api.flow_run("annotate_clip/small_0")["id"] == run["id"]
        api.run("dataset_report")
        report = wait_for("the dataset report", lambda: (r := api.flow_run("dataset_report")) and
                          r["state"]["type"] in ("COMPLETED", "FAILED", "CRASHED") and r or None)
        assert report["state"]["type"] == "COMPLETED" and json.loads((tmp_path / "report" / "stats.json").read_text())
        stopped = cli(*common, "server", "stop", cwd=tmp_path)  # the serve first: it polled a dead API for good
        assert f"stopped `cadestate serve` (pid {serving.pid})" in stopped.stdout, stopped.stdout
        assert serving.wait(60) is not None
        log = (tmp_path / "serve.log").read_text()
        # the tracebacks are the broken clip's failed stage (once a run: the second build_dataset runs
        # it again); Prefect's engine logged one more for each run ending Failed
        assert log.count("Traceback") == log.count("broken_0 ingest failed\nTraceback") > 0, log[-3000:]
        assert "Engine execution exited" not in log
        assert "RuntimeWarning" not in log  # Prefect's un-awaited stop


@pytest.mark.slow
def test_served_clips_beyond_clip_runs_wait_for_a_slot_and_the_labels_inbox_resumes_an_unrun_one(tmp_path, small_clip):
    """[schedule] clip_runs = 1 and two new clips: the second waits (AwaitingConcurrencySlot) until
    the first is suspended waiting for people, then runs; their running spans never overlap. Then
    labels ingested without a resume (an ingest killed before it): the labels inbox resumes the clip."""
    w, inbox = tmp_path / "w", tmp_path / "inbox"
    inbox.mkdir()
    config = tmp_path / "c.toml"
    config.write_text(f'[schedule]\ninbox = "{inbox}"\nlabels_inbox = "{tmp_path / "labels"}"\nclip_runs = 1\n'
                      'inbox_split = "val"\n'
                      'inbox_cron = "0 0 1 1 *"\nlabels_cron = "0 0 1 1 *"\nreport_cron = "0 0 1 1 *"\n')
    with served(tmp_path, w, config) as (common, serving):
        api = Api(read_server(w).api_url)
        wait_for("the deployments", lambda: api.deployment_id("build_dataset"))
        cameras = small_clip.cameras_path.read_text().split("\n", 1)
        for name, video_id in (("room_1", cameras[0]), ("room_2", cameras[0] + "2")):  # clips small_0, small2_0
            shutil.copy(small_clip.video_path, inbox / f"{name}.mp4")
            (inbox / f"{name}.txt").write_text(f"{video_id}\n{cameras[1]}")
            (inbox / f"{name}.done").touch()
        api.run("build_dataset")
        names = ["annotate_clip/small_0", "annotate_clip/small2_0"]
        runs = wait_for("two suspended clips", lambda: (r := [api.flow_run(n) for n in names]) and
                        all(x and x["state"]["name"] in ("Suspended", "Failed", "Crashed", "Completed") for x in r) and r or None,
                        timeout_s=600)
        assert [r["state"]["name"] for r in runs] == ["Suspended", "Suspended"], (tmp_path / "serve.log").read_text()[-3000:]
        histories = [sorted(httpx.get(f"{api.url}/flow_run_states/", params={"flow_run_id": r["id"]}, timeout=30).json(),
                            key=lambda s: s["timestamp"]) for r in runs]
        spans = [(next(s["timestamp"] for s in h if s["type"] == "RUNNING"), next(s["timestamp"] for s in h if s["type"] == "PAUSED"))
                 for h in histories]
        first, second = sorted(range(2), key=lambda i: spans[i][0])
        assert spans[first][1] <= spans[second][0], spans  # one clip ran at a time
        assert "AwaitingConcurrencySlot" in [s["name"] for s in histories[second]], [s["name"] for s in histories[second]]
        # labels ingested by an ingest that never resumed the clip (killed between the two, as
        # --no-resume leaves it): the labels inbox, seeing the file again, resumes the clip
        [task] = (w / "label_tasks" / "small_0").glob("*.json")
        (tmp_path / "labels").mkdir()
        (tmp_path / "labels" / "small_0.json").write_text(json.dumps({
            "format": "cadestate-label/1", "kind": "manual_track", "clip": "small_0", "task_id": task.stem,
            "annotator": "test", "created_at": "2026-11-23T00:00:00Z", "answers": []}))
        assert cli(*common, "labels", "ingest", "--no-resume", str(tmp_path / "labels"), cwd=tmp_path).returncode == 0
        api.run("ingest_labels")
        done = wait_for("the resumed clip", lambda: (r := api.flow_run("annotate_clip/small_0")) and
                        r["state"]["type"] in ("COMPLETED", "FAILED", "CRASHED") and r or None)
        assert done["id"] == runs[0]["id"] and done["state"]["type"] == "COMPLETED", (tmp_path / "serve.log").read_text()[-3000:]
        assert api.flow_run("annotate_clip/small2_0")["state"]["name"] == "Suspended"  # no label of its own: left waiting
