"""Where each clip stands: the last run of every stage, and why it is stale if it is.

A stage is stale when the stage chain would run it (:func:`cached_run`, the cache rule: no
completed or paused run with its config section, code and inputs, its upstream stages' latest
outputs, whose output its tables still hold, no run of it having failed or been killed since), the reasons told against its last such run; or when
an upstream stage is stale (it will rerun and may change them). Read from the ``runs`` table and
the markers of runs in progress (:mod:`tasks.stage`): a stage whose process is running shows
``running``, one whose process ended mid-run (killed) ``interrupted``. :func:`clip_notes` adds
what a user should know about a clip's results (nothing detected, so every later stage ran on
nothing).
"""

from __future__ import annotations

import datetime as dt
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from cadestate.config import Config
from tasks.inputs_memo import InputsMemo
from tasks.registry import config_hash, stages_of, upstream_inputs_hash
from tasks.stage import RUNNING_DIR, RunMarker, StageRun, run_markers
from warehouse import Warehouse, check_name
from warehouse.store import is_name

SOURCE_FILE_STAGES = ("cameras", "ingest")
"""Clip stages that read the clip's input files themselves (their inputs digest is taken from the
files as they run, which status does not hash: it compares their sizes and times instead)."""
from warehouse.kept import kept_read

RUN_COLUMNS = ("clip", "run_id", "stage", "status", "config_hash", "inputs_hash", "output_hash", "code_hash",
               "started_at", "rows_written", "duration_s", "message")
"""The columns of ``runs`` that the status and the stage chain's cache (:mod:`tasks.stage_chain`) read."""


@dataclass(frozen=True)
class Signature:
    """What a stage run depends on: its config section's digest, its code's digest, and the digest of
    its inputs (upstream output digests, then the digests of what else it reads)."""

    config_hash: str
    code_hash: str
    inputs_hash: str


def cached_run(runs: list[dict[str, Any]], unit: str, stage: str, signature: Signature) -> StageRun | None:
    """The recorded run that makes running ``stage`` of ``unit`` with ``signature`` again needless,
    or None.

    ``runs``: the unit's ``runs`` rows (:func:`read_runs`), oldest first. A completed or paused
    run with the same signature counts while the stage's latest completed or paused run has its
    output and no run failed or was interrupted after it: then the tables hold what a run with
    this signature writes. (Each table is swapped whole, but a stage writes its tables one after
    another: one that failed or was killed between two of them, or after its first, left them
    holding part of its own output.)"""
    mine = [r for r in runs if r["stage"] == stage]  # recorded runs end completed, paused, failed or interrupted
    if not mine or mine[-1]["status"] in ("failed", "interrupted"):
        return None
    ok = [r for r in mine if r["status"] in ("completed", "paused")]
    key = (signature.config_hash, signature.code_hash, signature.inputs_hash)
    same = [r for r in ok if (r["config_hash"], r["code_hash"], r["inputs_hash"]) == key]
    if not same or same[-1]["output_hash"] != ok[-1]["output_hash"]:
        return None
    r = same[-1]
    return StageRun(clip=unit, stage=stage, run_id=r["run_id"], status=r["status"],
                    config_hash=signature.config_hash, inputs_hash=signature.inputs_hash, output_hash=r["output_hash"],
                    code_hash=signature.code_hash, rows_written=int(r["rows_written"] or 0),
                    duration_s=float(r["duration_s"] or 0.0), message=r["message"] or "")


@dataclass(frozen=True)
class StageStatus:
    clip: str  # or library
    stage: str
    status: str  # completed | failed | paused | interrupted | running | never run
    last_run_at: str
    rows_written: int
    stale_reasons: tuple[str, ...]
    message: str = ""  # the last run's message (for a paused run: the task file and what it waits for)


def read_runs(wh: Warehouse, names: Sequence[str] | None = None, keep: bool = False) -> list[dict]:
    """The :data:`RUN_COLUMNS` of the runs of ``names`` (clips or libraries; default: all), oldest
    first. ``keep``: from, or into, the rows kept with the state of the run files
    (:func:`warehouse.kept.kept_read`), as ``cadestate status`` reads them: DuckDB is imported
    and the files read only when a run file came or went since."""
    if wh.reads_cached:  # a long-lived process (the app's resumes): files read before come from its cache
        rows = wh.read("runs", names, columns=RUN_COLUMNS).to_pylist()
    elif keep:  # kept per clip or library named (one file each, as the input digests), else once for all
        rows = [r for name in (sorted(set(names)) if names else [None]) for r in _kept_runs(wh, name)]
    else:
        rows = _runs(wh, names)
    return sorted(rows, key=lambda r: r["started_at"])  # stable: runs of one start stay in key order


def _runs(wh: Warehouse, names: Sequence[str] | None) -> list[dict]:
    from warehouse.query import read_rows  # here: DuckDB costs `status` ~0.1 s, paid only when runs changed

    return read_rows(wh, "runs", RUN_COLUMNS, names, timestamps=("started_at",))


def _kept_runs(wh: Warehouse, name: str | None) -> list[dict]:
    """:func:`_runs` of clip or library ``name`` (None: of all), kept in ``_cache/reads/runs/<name>.json``
    (``runs.json``) while no run file of it came or went; times kept as ISO 8601 with their UTC offset."""
    parts = None if name is None else [check_name(name)]

    def as_json() -> list[dict]:
        return [{**r, "started_at": r["started_at"] and r["started_at"].isoformat()} for r in _runs(wh, parts)]

    kept = kept_read(wh, "runs" if name is None else f"runs/{name}", [("files", "runs", name or "*")], as_json)
    return [{**r, "started_at": r["started_at"] and dt.datetime.fromisoformat(r["started_at"])} for r in kept]


def _registered(wh: Warehouse, table: str, names: Sequence[str] | None) -> set[str]:
    """The partitions of ``table`` that have data: all, or those among ``names`` (looked up one by
    one: listing 10,000 clips' partitions costs about 0.3 s)."""
    if not names:
        return set(wh.partitions(table))
    return {n for n in names if wh.has_partition(table, n)}


def _markers(wh: Warehouse, names: Sequence[str] | None) -> dict[str, list[RunMarker]]:
    """The run markers (:func:`tasks.stage.run_markers`) of the clips and libraries (all, or those
    among ``names``) that have any: runs in progress, or killed, which may have been the unit's
    first (a library's ``cad_ingest``, a clip's ``cameras`` by SfM) and then left no row anywhere else."""
    if names:
        found = [n for n in names if is_name(n)]
    else:
        try:
            found = [n for n in os.listdir(wh.root / RUNNING_DIR) if is_name(n)]
        except OSError:  # no run yet
            return {}
    return {n: markers for n in found if (markers := run_markers(wh, n))}


def pipeline_status(wh: Warehouse, config: Config, names: Sequence[str] | None = None,
                    scope: str = "clip", runs: list[dict] | None = None) -> list[StageStatus]:
    """One :class:`StageStatus` per (clip or library, stage), names sorted, stages in pipeline order;
    ``runs``: :func:`read_runs` of ``names``, when the caller has read them already."""
    stages = stages_of(scope)
    runs = [r for r in (read_runs(wh, names) if runs is None else runs) if r["stage"] in {s.name for s in stages}]
    markers = _markers(wh, names)
    known = (_registered(wh, "clips" if scope == "clip" else "cad_models", names) | {r["clip"] for r in runs}
             | {n for n, found in markers.items() if any(m.stage in {s.name for s in stages} for m in found)})
    names = sorted(known & set(names) if names else known)  # a name of the other scope is not listed here
    last: dict[tuple[str, str], dict] = {}
    last_ok: dict[tuple[str, str], dict] = {}
    by_unit: dict[str, list[dict]] = {}
    for r in runs:
        by_unit.setdefault(r["clip"], []).append(r)
        last[(r["clip"], r["stage"])] = r
        if r["status"] in ("completed", "paused"):  # a paused run's output is valid (what is answered)
            last_ok[(r["clip"], r["stage"])] = r
    result = []
    for clip in names:
        stale_stages: set[str] = set()
        memo = InputsMemo(wh, clip)
        recorded_ids = {(r["stage"], r["run_id"]) for r in by_unit.get(clip, [])}
        for m in markers.get(clip, []):  # runs not recorded yet: in progress, or their process was killed
            if (m.stage, m.run_id) in recorded_ids:
                continue  # recorded, its process killed before it took its marker away (as settle_interrupted finds)
            if (recorded := last.get((clip, m.stage))) is not None and recorded["started_at"] > m.started_at:
                continue  # a later run of the stage was recorded (a Dask retry on another worker): this one is over
            last[(clip, m.stage)] = {"status": "running" if m.alive else "interrupted", "started_at": m.started_at,
                                     "message": f"process {m.pid} on {m.host}" + ("" if m.alive else
                                                " ended before the run finished (killed or crashed)")}
        for stage in stages:
            latest, ok = last.get((clip, stage.name)), last_ok.get((clip, stage.name))
            reasons = []
            if ok is None:
                reasons.append("never completed")
            else:
                ups = [last_ok.get((clip, u)) for u in stage.upstream]
                inputs = ok["inputs_hash"]  # no upstream (its source is digested as it runs), or one never completed
                if stage.upstream and all(ups):
                    inputs = upstream_inputs_hash([u["output_hash"] for u in ups] + stage.config_inputs(config)
                                                  + memo.clip_inputs(stage))
                signature = Signature(config_hash(stage.name, config), stage.code_hash, inputs)
                if cached_run(by_unit.get(clip, []), clip, stage.name, signature) is None:  # as the chain finds it
                    differs = (("config changed", ok["config_hash"] != signature.config_hash),
                               ("code changed", ok["code_hash"] != signature.code_hash),
                               ("inputs changed", ok["inputs_hash"] != inputs))
                    reasons += [why for why, changed in differs if changed]
                if latest["status"] in ("failed", "interrupted"):  # a killed run's marker too: the next run redoes it
                    reasons.append(f"last run {latest['status']}")
                if stage.name in SOURCE_FILE_STAGES and (edited := _edited_inputs(wh, clip)):
                    reasons.append(f"inputs changed ({', '.join(edited)} of inputs/{clip}/ edited since ingest)")
                if any(u in stale_stages for u in stage.upstream + stage.after):  # after: it reads what that one writes
                    reasons.append("upstream stale")
            if reasons:
                stale_stages.add(stage.name)
            result.append(StageStatus(
                clip, stage.name,
                latest["status"] if latest else "never run",
                latest["started_at"].strftime("%Y-%m-%d %H:%M") if latest else "",
                ok["rows_written"] if ok else 0,
                tuple(reasons),
                latest["message"] if latest else "",
            ))
        memo.save()
    return result


def _edited_inputs(wh: Warehouse, clip: str) -> list[str]:
    """:func:`tasks.video.placed.edited_inputs`, imported here: a library's status imports no clip module."""
    from tasks.video.placed import edited_inputs

    return edited_inputs(wh, clip)


def stale_libraries(wh: Warehouse, config: Config) -> dict[str, list[str]]:
    """The CAD libraries (partitions of ``cad_models``) with a stage that ``config`` makes stale
    (:func:`pipeline_status`: its config, code or inputs changed since it ran): library -> one
    ``'stage: reasons'`` per such stage. Retrieval reads a library as its stages last left it, so a
    stale one is ranked with descriptors the current configuration no longer makes (a warehouse
    copied from one built with another ``[cad_embed] whitening``, a descriptor retrained since)."""
    libraries = wh.partitions("cad_models")
    out: dict[str, list[str]] = {}
    for s in pipeline_status(wh, config, libraries, scope="library") if libraries else []:
        if s.stale_reasons:
            out.setdefault(s.clip, []).append(f"{s.stage}: {', '.join(s.stale_reasons)}")
    return out


DROPPED_TRACK_NOTES = (
    ("thin", "tracks too thin to annotate were dropped (fewer than [tracking] thin_detections detections, none on "
             "a manual-track key-frame)"),
    ("shadow", "shadow tracks were dropped (their boxes on a stronger track's boxes: one object tracked twice; "
               "[tracking] shadow_iou)"),
    ("weak", "weak tracks were dropped (their detections' mean score below [tracking] min_track_score)"),
)
"""The tracks the tracking stage drops, as its message counts them ("N <kind> tracks dropped"), and
what :func:`clip_notes` says of them."""


def clip_notes(rows: Sequence[StageStatus]) -> list[str]:
    """What a user should know about each clip beyond its stages' states, one line per note:
    a clip whose detection found nothing (a dark or empty video, or too strict a ``[detect]``
    threshold or class filter) runs every later stage on nothing; a clip whose world up was
    estimated unreliably (:mod:`tasks.video.world_up`) may have every object pulled the wrong way; the
    tracks too thin to annotate (:mod:`tasks.tracking.merge`), the shadow tracks
    (:mod:`tasks.tracking.shadow`) and the weak tracks that tracking dropped are counted, and a clip
    whose detections made no track at all is named."""
    notes = []
    for r in rows:
        if r.stage == "ingest" and r.status == "completed" and "world up: " in r.message:
            up = r.message[r.message.index("world up: ") + len("world up: "):]
            notes.append(f"{r.clip}: world up unreliable: {up}")
        if r.stage == "tracking" and r.status == "completed":
            if (none := re.match(r"0 tracks from (\d+) detections", r.message)) and none.group(1) != "0":
                notes.append(f"{r.clip}: tracking kept no track of its {none.group(1)} detections (no object boxed on "
                             "[tracking] min_detections frames, or every track dropped as counted here), so every "
                             "later stage ran on nothing")
            for kind, note in DROPPED_TRACK_NOTES:
                found = re.search(rf"(\d+) {kind} tracks dropped", r.message)
                if found and found.group(1) != "0":
                    notes.append(f"{r.clip}: {found.group(1)} {note}")
        if r.stage == "detect" and r.status == "completed" and r.rows_written == 0:
            notes.append(f"{r.clip}: no object detected in any frame, so every later stage ran on nothing "
                         "(a dark or empty video? else lower [detect] score_threshold or widen [detect] classes)")
    return notes


def clips_left_unrun(wh: Warehouse, config: Config, clips: Sequence[str]) -> list[str]:
    """The ``clips`` (those of label files ingested before, in their order) whose stages have not
    taken in their labels: answered since their last stage run started (:func:`answered_since_run`:
    a label ingest was killed after its ingest and before its resume), or with a stage whose last
    run was interrupted (killed while it resumed the clip); ingesting the folder again resumes them.
    Not a clip whose stages are stale for another reason: a changed detector or CAD library made
    every labelled clip "never run" and ran it again. Nor one answered since with no stage's inputs
    changed (a file of the answers in force again, or one ingested while the clip was running): its
    run would be all cached and record nothing, so it stayed "answered since" and was resumed on
    every labels tick, ingest and app start (a clip with no run at all has its first). One status read
    for all."""
    if not clips:
        return []
    clips = list(dict.fromkeys(clips))
    rows = pipeline_status(wh, config, clips)
    interrupted = {r.clip for r in rows if r.status == "interrupted"}
    ran = {r.clip for r in rows if r.status != "never run"}
    moved = {r.clip for r in rows if "inputs changed" in r.stale_reasons} | (set(clips) - ran)
    answered = set(answered_since_run(wh, clips)) & moved
    return [c for c in clips if c in interrupted or c in answered]


def answered_since_run(wh: Warehouse, clips: Sequence[str] | None = None) -> list[str]:
    """The clips (of ``clips``; None: all) whose newest answer was ingested after their last stage
    run started: a label ingest killed before its resume, an annotation app stopped before its
    resume worker took them (its queue is in memory), answers ``labels ingest --no-resume`` took."""
    answered = _newest(wh, "label_files", "ingested_at", clips)
    ran = _newest(wh, "runs", "started_at", list(answered))
    return sorted(clip for clip, at in answered.items() if clip not in ran or ran[clip] < at)


def _newest(wh: Warehouse, table: str, column: str, clips: Sequence[str] | None = None) -> dict:
    """{clip: the newest ``column`` (a time) of its rows in ``table``} (of ``clips``; None: every clip's)."""
    clips = [c for c in (wh.partitions(table) if clips is None else clips) if wh.has_partition(table, c)]
    if not clips:
        return {}
    rows = wh.read(table, clips, columns=["clip", column]).group_by("clip").aggregate([(column, "max")]).to_pylist()
    return {r["clip"]: r[f"{column}_max"] for r in rows}


@dataclass(frozen=True)
class ClipSummary:
    """One clip's stages in a line (`cadestate status` beyond a few clips): where it stands (the first
    stage, in pipeline order, running, failed, interrupted, paused or never run, else 'completed'),
    its newest run, how many of its stages are completed, of how many, and its stale stages."""

    clip: str
    stands: str
    last_run_at: str
    done: int
    stages: int
    stale: tuple[str, ...]


STANDS_ORDER = ("running", "failed", "interrupted", "paused", "never run")
"""What a clip's line says first, when one of its stages is so (a running stage before a failed one, ...)."""


def clip_summaries(rows: Sequence[StageStatus]) -> list[ClipSummary]:
    """:class:`ClipSummary` of each clip of ``rows`` (:func:`pipeline_status`: stages in pipeline order)."""
    by_clip: dict[str, list[StageStatus]] = {}
    for r in rows:
        by_clip.setdefault(r.clip, []).append(r)
    out = []
    for clip, stages in by_clip.items():
        first = next(((s, r.stage) for s in STANDS_ORDER for r in stages if r.status == s), None)
        stands = "completed" if first is None else f"{'waits' if first[0] == 'paused' else first[0]} at {first[1]}"
        out.append(ClipSummary(clip, stands,
                               max((r.last_run_at for r in stages), default=""),
                               sum(r.status == "completed" for r in stages), len(stages),
                               tuple(r.stage for r in stages if r.stale_reasons)))
    return out
