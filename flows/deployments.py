"""Deployments that `cadestate serve` serves on the warehouse's Prefect server (no work pool needed).

- ``annotate_clip`` (run on demand, one flow run per clip, named ``annotate_clip/<clip>``): the
  stages of one clip. When a human task waits, the run is **suspended** (a real Prefect pause,
  ``Suspended`` in the UI, for at most ``[schedule] suspend_timeout_s``); a label ingest that
  answers the clip resumes it through the API and it goes on from its cached stages. A clip with
  a failed stage ends ``Failed``. The runs a stopped or killed ``serve`` left pending or running are
  marked Crashed by the next (:func:`crash_runs_left_running`).
- ``build_dataset`` (cron ``[schedule] inbox_cron``): every clip of ``[schedule] inbox``
  (``<name>.mp4``, or another video `cadestate ingest FOLDER` takes, + ``<name>.txt``, named
  ``<video_id>_<start_us>`` from its camera file) not ingested yet with the same bytes, or whose last run failed, gets an ``annotate_clip`` run. Files still being copied wait: a pair is taken once neither file changed for
  ``[schedule] stable_s`` seconds, or at once when ``<name>.done`` exists.
- ``ingest_labels`` (cron ``[schedule] labels_cron``): ingests the label files of
  ``[schedule] labels_inbox`` and resumes the clips they answer.
- ``dataset_report`` (cron ``[schedule] report_cron``): first what ``cadestate compact`` does
  (append-mode partitions merged, a new snapshot of the tables in the catalog, so SQL stays fast as
  clips pile up), then the dataset's statistics (``cadestate stats``) as ``stats.json`` and an
  HTML report in ``[schedule] report``.

The three scheduled ones run one at a time (a run due while one runs is cancelled). Parameters are
plain strings (the warehouse root and the config file), so the Prefect UI can start a run by hand;
each run reads the config file again, but the schedules are fixed when ``serve`` starts (restart it
after changing a ``*_cron``). Served runs keep their results under the warehouse, as every run does.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import logging
import re
import time
from collections.abc import Callable
from pathlib import Path
from uuid import uuid4

from prefect import flow, get_run_logger
from prefect.client.orchestration import get_client
from prefect.client.schemas.filters import (DeploymentFilter, DeploymentFilterName, FlowRunFilter, FlowRunFilterState,
                                            FlowRunFilterStateType, FlowRunFilterTags)
from prefect.client.schemas.objects import ConcurrencyLimitConfig, ConcurrencyLimitStrategy, StateType
from prefect.client.schemas.sorting import FlowRunSort
from prefect.deployments import run_deployment
from prefect.deployments.runner import EntrypointType
from prefect.exceptions import FailedRun, FlowPauseTimeout, NotPausedError
from prefect.flow_runs import resume_flow_run, suspend_flow_run
from prefect.states import Crashed, Failed, State

from cadestate.config import Config, ConfigError, load_config
from cadestate.lineage import digest, file_sha256
from flows.annotate_clip import _run
from flows.runtime import run_tags
from tasks.stage_chain import StageReport
from tasks.video.camera_file import CameraFileError, parse_camera_file
from tasks.video.clip_names import ClipNameError, shared_video_ids, video_id_of
from tasks.video.ingest import VIDEO_SUFFIXES, ClipSource, official_clip_name
from warehouse import Warehouse, atomic_write_bytes
from warehouse.store import check_name, file_lock, is_name
from warehouse.catalog import one_line

ANNOTATE_DEPLOYMENT = "annotate_clip"
ANNOTATE = f"annotate_clip/{ANNOTATE_DEPLOYMENT}"
"""The deployment (flow name/deployment name) that runs one clip."""
INBOX_DEPLOYMENT, LABELS_DEPLOYMENT, REPORT_DEPLOYMENT = "build_dataset", "ingest_labels", "dataset_report"
DEPLOYMENTS = (ANNOTATE_DEPLOYMENT, INBOX_DEPLOYMENT, LABELS_DEPLOYMENT, REPORT_DEPLOYMENT)
"""The names of the four deployments :func:`deployments` makes, in its order."""
ACTIVE = [StateType.SCHEDULED, StateType.PENDING, StateType.RUNNING, StateType.PAUSED, StateType.CANCELLING]
"""States of a clip's run that keep the inbox from starting another (one being cancelled still runs)."""


class _FailedRunSaidOnce(logging.Filter):
    """Drop the traceback Prefect's engine logs ("Engine execution exited with unexpected
    exception", :class:`prefect.exceptions.FailedRun`) for a served run that ends Failed, in the
    run's own process: its "Finished in state Failed('<why>')" line says it, and a failed stage's
    traceback is in the log above. Any other exception keeps its traceback."""

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        return not (isinstance(exc, FailedRun) and record.getMessage() == "Engine execution exited with unexpected exception")


logging.getLogger("prefect.flow_runs").addFilter(_FailedRunSaidOnce())  # imported where Prefect runs a served flow


def served_config(warehouse: str, config_path: str) -> Config:
    """The config of a served run: the file (or the defaults), with the warehouse given."""
    cfg = load_config(Path(config_path) if config_path else None)
    return dataclasses.replace(cfg, warehouse=dataclasses.replace(cfg.warehouse, root=warehouse))


def config_errors_fail(fn: Callable) -> Callable:
    """A served flow's function whose run ends Failed with the one line of a config file that does
    not load (edited under a serve: each run reads it again), as its message. Raised, it printed two
    tracebacks a flow in the serve's log, three flows a tick."""
    @functools.wraps(fn)
    def run(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except ConfigError as e:
            return Failed(message=str(e))

    return run


def ready_pairs(inbox: Path, stable_s: float, split: str = "train", now: float | None = None) -> list[ClipSource]:
    """The clips of ``inbox`` whose copy is complete: a video (``<name>.mp4``, or another of
    :data:`VIDEO_SUFFIXES` in any case, as `cadestate ingest FOLDER` takes them: a phone's
    ``VID_0001.MOV`` waited in the inbox for ever) with ``<name>.txt``, each unchanged for
    ``stable_s`` seconds (mtime), or with a ``<name>.done`` marker; sorted by name."""
    now = time.time() if now is None else now
    ready = []
    videos = sorted(p for p in inbox.iterdir() if p.suffix.lower() in VIDEO_SUFFIXES and p.is_file()) if inbox.is_dir() else []
    for video in videos:
        cameras = video.with_suffix(".txt")
        if not cameras.is_file():
            continue
        done = video.with_suffix(".done").exists()
        if done or all(now - p.stat().st_mtime >= stable_s for p in (video, cameras)):
            ready.append(ClipSource(_placeholder(video.stem), video, cameras, split))
    return ready


def _placeholder(stem: str) -> str:
    """A clip name for a pair until :func:`official_names` names it from its camera file: its file
    name, made a valid name ("living room.mp4" raised, and no clip of the inbox was taken)."""
    name = re.sub(r"[^A-Za-z0-9_.-]+", "_", stem).lstrip(".")[:200]
    return name if is_name(name) else "clip"


def official_names(pairs: list[ClipSource], warn: Callable[[str], None] | None = None,
                   wh: Warehouse | None = None) -> list[ClipSource]:
    """``pairs`` named ``<video_id>_<start_us>`` from their camera files (as `cadestate ingest` names
    them); a pair whose camera file is bad is left out with a warning naming the file and line, and
    so is every pair after the first that gets a name already taken (two runs of one clip would
    write its tables at once), and, with ``wh``, one whose video id a clip of another video has
    there or among the pairs before it (as `cadestate ingest` refuses it: their frames would mix in
    the official layout; the warehouse's clips are read once). ``warn``: where the warnings go
    (default: the flow run's log)."""
    warn = warn or get_run_logger().warning
    named: dict[str, ClipSource] = {}
    by_id: dict[str, list[tuple[str, str]]] = {}  # video id -> (clip, URL line) of the warehouse's clips and those named
    for r in wh.read("clips", columns=["clip", "url"]).to_pylist() if wh is not None else ():
        by_id.setdefault(video_id_of(r["clip"]), []).append((r["clip"], r["url"]))
    for p in pairs:
        try:
            track = parse_camera_file(p.cameras)
            clip = official_clip_name(track, p.cameras)
        except (CameraFileError, ClipNameError) as e:
            warn(f"left out of the inbox: {e}")
            continue
        # its own video id only: two registered clips that share one (from before the inbox checked) refuse no pair
        same_id = by_id.setdefault(video_id_of(clip), [])
        if wh is not None and (others := shared_video_ids([*same_id, (clip, track.url)]).get(video_id_of(clip))):
            listed = ", ".join(sorted(c for c in others if c != clip)) or clip
            warn(f"left out of the inbox: {p.cameras}: clip {clip} comes from another video (line 1: {track.url.strip()}) "
                 f"than {listed}, which share its video id {video_id_of(clip)!r}; ingest it with `cadestate ingest "
                 "VIDEO CAMERAS --clip NAME`, a name of its own")
            continue
        if clip in named:
            warn(f"left out of the inbox: {p.video}: its camera file names clip {clip}, as {named[clip].video}'s does "
                 "(the same video id and first timestamp); give it a camera file of its own")
            continue
        named[clip] = dataclasses.replace(p, clip=clip)
        same_id.append((clip, track.url))
    return list(named.values())


INBOX_SHA256 = "inbox_sha256.json"
"""``<warehouse>/_cache/inbox_sha256.json``: the sha256 of each inbox file looked at, by path, with
its identity when hashed (:func:`inbox_sha256s`)."""


def inbox_sha256s(wh: Warehouse, paths: list[Path]) -> dict[Path, str]:
    """sha256 of each inbox file of ``paths``, read again only when its identity (inode, size,
    modification and change times) changed. Kept in ``_cache/`` of the warehouse (the files of
    ``paths`` alone): Prefect's runner runs each served flow run in a new process, so a cache in
    the process was empty at every tick, and every tick read every video of the inbox again (about
    1.5 s a GB here, done clips included). Best effort: a read-only warehouse keeps nothing."""
    cache = wh.root / "_cache" / INBOX_SHA256
    try:
        known = json.loads(cache.read_text())
    except (OSError, ValueError):
        known = {}
    kept: dict[str, list] = {}
    for path in paths:
        st = path.stat()  # before reading: a file written meanwhile has another identity at the next tick
        identity = [st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns]
        entry = known.get(str(path.resolve())) if isinstance(known, dict) else None
        sha = entry[1] if isinstance(entry, list) and len(entry) == 2 and entry[0] == identity else file_sha256(path)
        kept[str(path.resolve())] = [identity, sha]
    if kept != known:
        with contextlib.suppress(OSError):
            atomic_write_bytes(cache, json.dumps(kept).encode(), durable=False)  # a cache: lost, files are read again
    return {path: kept[str(path.resolve())][1] for path in paths}


def pairs_to_run(wh: Warehouse, pairs: list[ClipSource], config: Config | None = None,
                 warn: Callable[[str], None] | None = None) -> list[ClipSource]:
    """The pairs that need a run: not ingested yet with these exact bytes (a changed file counts as
    new), or whose last run of some stage failed or was interrupted, or whose run a killed process
    left unfinished (:func:`unfinished`); with ``config``, not a clip whose stage failed
    ``[schedule] failed_runs`` runs in a row with this config and code (:func:`failing`; ``warn``
    says so). Clips done cost a look at their files' identities."""
    known = {(r["clip"], r["video_sha256"], r["cameras_sha256"])
             for r in wh.read("clips", columns=["clip", "video_sha256", "cameras_sha256"]).to_pylist()}
    sha256 = inbox_sha256s(wh, [path for p in pairs for path in (p.video, p.cameras)])
    runs: dict[str, list[dict]] = {}  # a clip's runs, read once for unfinished and failing

    def runs_of(clip: str) -> list[dict]:
        if clip not in runs:
            runs[clip] = clip_runs(wh, clip)
        return runs[clip]

    todo = [p for p in pairs
            if (p.clip, sha256[p.video], sha256[p.cameras]) not in known or unfinished(wh, p.clip, runs_of(p.clip))]
    if config is None or not config.schedule.failed_runs:
        return todo
    kept = []
    for p in todo:  # new bytes are a new try (its failures were of the files before)
        if (p.clip, sha256[p.video], sha256[p.cameras]) in known and (stage := failing(wh, p.clip, runs_of(p.clip), config)):
            (warn or get_run_logger().warning)(
                f"clip {p.clip}: its stage {stage} failed {config.schedule.failed_runs} runs in a row with this config, "
                "code and inputs: not run again until its files, the config, the code or what it reads change (a model "
                "file made, answers given; `cadestate status` shows why; `cadestate run` runs it)")
            continue
        kept.append(p)
    return kept


def clip_runs(wh: Warehouse, clip: str) -> list[dict]:
    """The ``runs`` rows of ``clip``, oldest first, with the columns :func:`unfinished` and
    :func:`failing` look at."""
    columns = ["stage", "status", "rows_written", "config_hash", "code_hash", "inputs_hash", "output_hash", "started_at"]
    return wh.read("runs", partitions=[clip], columns=columns).sort_by("started_at").to_pylist()


def failing(wh: Warehouse, clip: str, runs: list[dict], config: Config) -> str | None:
    """The stage of ``clip`` (its ``runs``: :func:`clip_runs`) whose last ``[schedule] failed_runs``
    runs all failed with the config, code and inputs of now (its config hash, code hash, and the
    inputs hash its next run would have, as the stage chain digests it: its upstream stages'
    outputs, its config's files, what it reads of the warehouse), if any: running it again fails
    again. A model file made since (`make models`, as the detect stage's error asks), answers given
    or an upstream stage's new output is a new try."""
    from tasks.inputs_memo import InputsMemo
    from tasks.registry import STAGES, config_hash, upstream_inputs_hash

    n = config.schedule.failed_runs
    by_stage: dict[str, list[dict]] = {}
    output: dict[str, str] = {}  # each stage's newest valid output (a paused run's too), as the chain's next run takes it
    for r in runs:
        by_stage.setdefault(r["stage"], []).append(r)
        if r["status"] in ("completed", "paused"):
            output[r["stage"]] = r["output_hash"]
    memo = InputsMemo(wh, clip)
    for stage, tried in by_stage.items():
        last, s = tried[-n:], STAGES.get(stage)
        if s is None or len(last) < n or any(r["status"] != "failed" or r["config_hash"] != config_hash(stage, config)
                                             or r["code_hash"] != s.code_hash for r in last):
            continue
        if not s.has("source_inputs") and all(u in output for u in s.upstream):  # a source's bytes: new bytes, new try
            inputs = upstream_inputs_hash([output[u] for u in s.upstream] + s.config_inputs(config) + memo.clip_inputs(s))
            if any(r["inputs_hash"] != inputs for r in last):
                continue
        return stage
    return None


def unfinished(wh: Warehouse, clip: str, runs: list[dict]) -> bool:
    """Whether ``clip``'s stages (its ``runs``: :func:`clip_runs`) need a run to finish what the last left: the last run of some stage
    failed or was interrupted; a killed process left a run's marker (recorded as interrupted only
    by the clip's next run, which nothing else starts); or a stage has no run though none of its
    upstream stages waits for people (paused with nothing answered): the process ended between two
    stages. A stage of a clip that waits for people has no run until the answers come; a clip whose
    run is under way (a live marker) needs none."""
    from tasks.registry import stages_of
    from tasks.stage import run_markers, waits_for_people

    last = {r["stage"]: r for r in runs}
    if {"failed", "interrupted"} & {r["status"] for r in last.values()}:
        return True
    markers = run_markers(wh, clip)
    if any(m.alive for m in markers):  # a run under way (a command's, a Dask worker's): it finishes the clip
        return False
    if markers:
        return True
    waiting: set[str] = set()
    for stage in stages_of("clip"):
        if stage.name in last:
            continue
        if not any(u in waiting or (u in last and waits_for_people(last[u]["status"], last[u]["rows_written"]))
                   for u in stage.upstream + stage.after):
            return True
        waiting.add(stage.name)
    return False


def active_clip_runs(clip: str, states: list[StateType]) -> list:
    """Flow runs of the annotate_clip deployment for ``clip`` in one of ``states``."""
    with get_client(sync_client=True) as client:
        return client.read_flow_runs(
            flow_run_filter=FlowRunFilter(tags=FlowRunFilterTags(all_=[f"clip:{clip}"]),
                                          state=FlowRunFilterState(type=FlowRunFilterStateType(any_=states))),
            deployment_filter=DeploymentFilter(name=DeploymentFilterName(any_=[ANNOTATE_DEPLOYMENT])),
            sort=FlowRunSort.START_TIME_ASC, limit=200)


LEFT_RUNNING = [StateType.PENDING, StateType.RUNNING, StateType.CANCELLING]
"""States of a served run that only a live serve moves on (its runner runs the flow's process)."""


def crash_runs_left_running(warehouse: str) -> list[str]:
    """Mark Crashed the runs of this warehouse's deployments that an earlier ``serve`` left pending
    or running (it was stopped or killed mid-run; the serve lock says none serves now), and return
    their names. Such a run stayed Running on the server for good, and the inbox never ran its clip
    again (a clip with an active run gets no new one): it now does on its next tick."""
    state = Crashed(message="the `cadestate serve` running it ended; a new serve found it left running")
    found: list = []
    with get_client(sync_client=True) as client:
        while True:  # all read first: each one crashed leaves the filter
            page = client.read_flow_runs(
                flow_run_filter=FlowRunFilter(state=FlowRunFilterState(type=FlowRunFilterStateType(any_=LEFT_RUNNING))),
                deployment_filter=DeploymentFilter(name=DeploymentFilterName(any_=list(DEPLOYMENTS))),
                sort=FlowRunSort.ID_DESC, limit=PAGE, offset=len(found))
            found += page
            if len(page) < PAGE:
                break
        mine = [run for run in found if run.parameters.get("warehouse") == warehouse]
        for run in mine:
            client.set_flow_run_state(run.id, state, force=True)
    return sorted(run.name for run in mine)


PAGE = 200
"""Flow runs per read (the most Prefect's API returns at once)."""


def start_clip_run(warehouse: str, config_path: str, source: ClipSource) -> str:
    """Create an annotate_clip run for ``source`` (it runs on the serving process); returns its id."""
    run = run_deployment(ANNOTATE, timeout=0, as_subflow=False, flow_run_name=f"annotate_clip/{source.clip}",
                         tags=run_tags(Path(warehouse), {source.clip: source.split}),
                         parameters={"warehouse": warehouse, "config_path": config_path, "clip": source.clip,
                                     "video": str(source.video), "cameras": str(source.cameras), "split": source.split})
    return str(run.id)


def start_clip_once(warehouse: str, config_path: str, source: ClipSource) -> bool:
    """:func:`start_clip_run` unless the clip has an active run; whether it started one. The check
    and the start hold the clip's ``_locks/_clip_start/<clip>.lock``: the inbox's and the labels
    inbox's ticks (two deployments, each one run at a time, but not one with the other) both
    checked, found none, and each started a run of one clip (its stages then ran twice over)."""
    with file_lock(Path(warehouse) / "_locks" / "_clip_start" / f"{check_name(source.clip)}.lock"):
        if active_clip_runs(source.clip, ACTIVE):
            return False
        start_clip_run(warehouse, config_path, source)
        return True


def resume_clips(clips: list[str]) -> list[str]:
    """Resume the suspended annotate_clip runs of ``clips`` (through the API); returns the clips
    resumed. The others have no suspended run (they run in ephemeral mode, or not at all yet), or
    one whose suspension ran out (the caller starts a run): that one raised and left the other
    clips of the tick neither resumed nor started. A run another process resumed meanwhile (a
    `labels ingest` beside the tick) counts as resumed."""
    resumed = []
    for clip in clips:
        runs = [r for r in active_clip_runs(clip, [StateType.PAUSED]) if r.state_name == "Suspended"]
        going = False
        for r in runs:
            try:
                resume_flow_run(r.id)
                going = True
            except NotPausedError:  # resumed by another process just now: it runs
                going = True
            except FlowPauseTimeout:  # its suspension ran out: not resumed
                continue
        if going:
            resumed.append(clip)
    return resumed


@flow(name="annotate_clip", flow_run_name="annotate_clip/{clip}", log_prints=True)
@config_errors_fail
def annotate_clip_served(warehouse: str, config_path: str, clip: str, video: str, cameras: str,
                         split: str = "train") -> list[StageReport] | State:
    """Run the stages of one clip; suspend while a human task waits (resumed by a label ingest).
    A clip with a failed stage ends Failed, its message naming the failed stages (the reports are
    in the ``runs`` table), not suspended: the inbox's next tick runs it again."""
    cfg = served_config(warehouse, config_path)
    root = str(Path(warehouse).resolve())
    state = _run(root, [ClipSource(clip, Path(video), Path(cameras), split)], cfg, False)
    if state.is_failed():  # its reports are in the runs table: Prefect takes a Failed state's data for an exception
        failed = [f"{r.stage}: {r.message}" for r in state.result(raise_on_failure=False) if r.state == "failed"]
        return Failed(message=one_line(f"{state.message}: {'; '.join(failed)}"))
    reports: list[StageReport] = state.result(raise_on_failure=False)
    waits = sorted(f"{r.stage}: {r.message}" for r in reports if r.state == "paused")
    if waits:
        get_run_logger().info("clip %s waits for people (%s); suspended until labels answer it", clip, "; ".join(waits))
        # A key of its own per suspension: a resumed run starts again from its (cached) stages, and
        # Prefect skips a suspend whose key it has seen, so a clip resumed while the same task still
        # waits (a label that answered another clip's task) would end Completed, not Suspended.
        suspend_flow_run(timeout=cfg.schedule.suspend_timeout_s, key=f"{digest(*waits)}:{uuid4().hex}")
    return reports


@flow(name="build_dataset_inbox", flow_run_name="build_dataset/inbox", log_prints=True)
@config_errors_fail
def build_dataset_inbox(warehouse: str, config_path: str = "") -> list[str]:
    """Start an annotate_clip run for every completely copied clip of ``[schedule] inbox`` that
    needs one (:func:`pairs_to_run`) and has no run under way; returns the clips started."""
    cfg = served_config(warehouse, config_path)
    inbox = Path(cfg.schedule.inbox)
    if not inbox.is_dir():
        no_folder("inbox", inbox)
    wh = Warehouse(warehouse)
    pairs = pairs_to_run(wh, official_names(ready_pairs(inbox, cfg.schedule.stable_s, cfg.schedule.inbox_split), wh=wh), cfg)
    started = [p.clip for p in pairs if start_clip_once(warehouse, config_path, p)]
    named = f": {', '.join(started)}" if started else ""
    get_run_logger().info("inbox %s: %d new clip(s) started%s", inbox, len(started), named)
    return started


def no_folder(key: str, path: Path) -> None:
    """Warn in the run's log that ``[schedule] <key>`` names no folder: nothing is taken from it
    (a typo, or a relative path taken from another folder than meant, watched nothing, unsaid)."""
    get_run_logger().warning("[schedule] %s: %s is no folder: nothing to take from it (a relative path is taken from "
                             "the folder `cadestate serve` runs in)", key, path.absolute())


@flow(name="ingest_labels", flow_run_name="ingest_labels/inbox", log_prints=True)
@config_errors_fail
def ingest_labels_inbox(warehouse: str, config_path: str = "") -> list[str]:
    """Ingest the label files of ``[schedule] labels_inbox`` (files ingested before are skipped) and
    resume the clips they answer: a suspended run is resumed, a clip with none gets a new run."""
    from tasks.video.ingest import registered_source
    from tasks.human.label_ingest import ingest_labels
    from tasks.status import clips_left_unrun

    cfg = served_config(warehouse, config_path)
    inbox = Path(cfg.schedule.labels_inbox)
    if not inbox.is_dir():
        no_folder("labels_inbox", inbox)
        return []
    wh = Warehouse(warehouse)
    report = ingest_labels(wh, inbox, coplanar_tol=cfg.pose.coplanar_tol)
    logger = get_run_logger()
    for e in report.errors:
        logger.warning("invalid label file: %s", e)
    for w in report.warnings:  # what `cadestate labels ingest` prints as warnings (an answer to a replaced task, ...)
        logger.warning("%s", w)
    # and the clips of files ingested before whose stages never took them in: an ingest_labels run
    # killed (a `server stop`) between its ingest and its resume left them suspended for good
    unrun = clips_left_unrun(wh, cfg, report.earlier_clips)
    for clip in unrun:
        logger.warning("clip %s: its labels were ingested but never run (an earlier ingest was stopped): resuming it", clip)
    todo = report.clips + unrun
    resumed = resume_clips(todo)
    for clip in sorted(set(todo) - set(resumed)):
        start_clip_once(warehouse, config_path, registered_source(wh, clip))
    return todo


@flow(name="dataset_report", flow_run_name="dataset_report", log_prints=True)
@config_errors_fail
def dataset_report(warehouse: str, config_path: str = "") -> str:
    """`cadestate compact`, then the dataset's statistics (`cadestate stats`) as ``stats.json`` and
    an HTML report in ``[schedule] report``; returns the report's path."""
    from tasks.dataset.stats import select_clips
    from tasks.dataset.stats_report import write_report
    from warehouse.catalog import compact_warehouse

    cfg = served_config(warehouse, config_path)
    wh = Warehouse(warehouse)
    done = compact_warehouse(wh)
    get_run_logger().info("compacted %d partition(s); snapshot of %d table(s)", len(done.compacted), len(done.snapshotted))
    choice = select_clips(wh)
    if choice.unfinished:
        get_run_logger().info("%s", choice.note(hint=""))
    out = Path(cfg.schedule.report)
    figures, index = write_report(wh, choice.chosen, out)
    atomic_write_bytes(out / "stats.json", json.dumps(figures, indent=1, default=str).encode())
    return str(index)


def deployments(config: Config, config_path: str) -> list:
    """The four deployments for this warehouse and config, with their schedules. Served runs use
    the local thread runner (the serving process imports the flows by module path)."""
    root = str(Path(config.warehouse.root).expanduser().resolve())
    params = {"warehouse": root, "config_path": str(Path(config_path).resolve()) if config_path else ""}
    module = EntrypointType.MODULE_PATH
    # One run of each scheduled flow at a time: after the server was down, its missed ticks came due
    # together, and two build_dataset runs at once each started a run of the same new clip.
    one = ConcurrencyLimitConfig(limit=1, collision_strategy=ConcurrencyLimitStrategy.CANCEL_NEW)
    # Clip runs: at most [schedule] clip_runs at once (a drop of 50 clips ran 5 at once, Prefect's
    # runner's own limit, on any machine); the server frees a run's slot when it is suspended.
    clips = ConcurrencyLimitConfig(limit=config.schedule.clip_runs, collision_strategy=ConcurrencyLimitStrategy.ENQUEUE)
    return [
        annotate_clip_served.to_deployment(
            name=ANNOTATE_DEPLOYMENT, concurrency_limit=clips, entrypoint_type=module, tags=["cadestate"],
            description="The stages of one clip; suspended while people answer its tasks."),
        build_dataset_inbox.to_deployment(
            name=INBOX_DEPLOYMENT, concurrency_limit=one, cron=config.schedule.inbox_cron, parameters=params, entrypoint_type=module,
            tags=["cadestate"], description=f"Annotate every new clip of {config.schedule.inbox}."),
        ingest_labels_inbox.to_deployment(
            name=LABELS_DEPLOYMENT, concurrency_limit=one, cron=config.schedule.labels_cron, parameters=params, entrypoint_type=module,
            tags=["cadestate"], description=f"Ingest the label files of {config.schedule.labels_inbox} and resume their clips."),
        dataset_report.to_deployment(
            name=REPORT_DEPLOYMENT, concurrency_limit=one, cron=config.schedule.report_cron, parameters=params, entrypoint_type=module,
            tags=["cadestate"], description=f"Write the dataset's statistics and HTML report to {config.schedule.report}."),
    ]
