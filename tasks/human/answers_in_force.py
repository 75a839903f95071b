"""The answers in force, read from the label tables that :mod:`tasks.human.label_ingest` fills.

Supersession is computed on read (:func:`current_answers`): per (clip, task, track) the answer of
the newest label file that answers it; for ``manual_track``, per (clip, task) the newest file's.
"Newer" is ingested later (files ingested together are ordered at ingest). Everything here reads
only: the stages, the web app's queue, the simulated annotators and ``cadestate status`` (through
:mod:`tasks.human.inputs`) count answers through these functions. The one write,
:func:`sync_correspondences`, keeps the ``correspondences`` table (the pose stage's input) equal to
the clicks in force (:mod:`tasks.human.clicks_in_force`).
"""

from __future__ import annotations

import json

import pyarrow as pa
import pyarrow.compute as pc

from cadestate.lineage import digest, table_digest
from schemas.label_tables import ANSWER_TABLES
from schemas.labels import KINDS
from schemas.pose import CORRESPONDENCES
from tasks.human.clicks_in_force import in_force_rows
from tasks.human.labels import latest_task_of_kind
from warehouse import Warehouse


def _newest(keys: list[tuple], times: list) -> list[bool]:
    """For each row, whether its time is the newest among the rows with the same key."""
    best: dict[tuple, object] = {}
    for k, t in zip(keys, times):
        if k not in best or t > best[k]:
            best[k] = t
    return [best[k] == t for k, t in zip(keys, times)]


def _committed_files(wh: Warehouse, kind: str, clips: list[str] | None) -> pa.Table:
    files = wh.read("label_files", clips, columns=["clip", "label_sha256", "ingested_at", "task_id", "kind"])
    return files.filter(pc.equal(files.column("kind"), kind))


def current_answers(wh: Warehouse, kind: str, clips: list[str] | None = None, task_id: str | None = None) -> pa.Table:
    """The answers in force (rows of the kind's answer table): per (clip, task, track) those of the
    newest label file that answers it; for ``manual_track``, per (clip, task) the newest file's."""
    spec = ANSWER_TABLES[kind]
    clips = None if clips is None else [c for c in clips if wh.has_partition(spec.name, c)]
    if clips == []:
        return spec.schema.empty_table()
    files = _committed_files(wh, kind, clips).to_pylist()
    rows = wh.read(spec.name, clips)
    committed = {(f["label_sha256"], f["ingested_at"]) for f in files}
    if kind == "manual_track":
        newest = _newest([(f["clip"], f["task_id"]) for f in files], [f["ingested_at"] for f in files])
        committed = {(f["label_sha256"], f["ingested_at"]) for f, keep in zip(files, newest) if keep}
    key = list(zip(rows.column("label_sha256").to_pylist(), rows.column("ingested_at").to_pylist()))
    rows = rows.filter(pa.array([k in committed for k in key], pa.bool_()))
    if kind != "manual_track":
        units = list(zip(*(rows.column(c).to_pylist() for c in ("clip", "task_id", "track_id"))))
        rows = rows.filter(pa.array(_newest(units, rows.column("ingested_at").to_pylist()), pa.bool_()))
    if task_id is not None:
        rows = rows.filter(pc.equal(rows.column("task_id"), task_id))
    return rows


def answered_tasks(wh: Warehouse, kind: str, clip: str) -> set[str]:
    """Ids of the clip's tasks of ``kind`` that some ingested label file answers (for
    ``manual_track`` an empty answer, "nothing is missing", answers its task too)."""
    return set(_committed_files(wh, kind, [clip]).column("task_id").to_pylist())


def answered_items(wh: Warehouse, clip: str, doc: dict) -> set[int]:
    """The items of a task (its document) that are answered, as the stages count them: those with
    an answer in force under the task's id, and those carrying a ``previous`` answer (for
    correspondences, clicks given on an earlier task that still hold:
    :mod:`tasks.human.clicks_in_force`; for the other kinds it is an answer under the id). A
    manual-track task is one item, ``-1``, answered whole."""
    if doc["kind"] == "manual_track":
        return {-1} if doc["task_id"] in answered_tasks(wh, "manual_track", clip) else set()
    done = set(current_answers(wh, doc["kind"], [clip], doc["task_id"]).column("track_id").to_pylist())
    return done | {int(it["track_id"]) for it in doc["items"] if it.get("previous") is not None}


def answers_digest(wh: Warehouse, kind: str, clip: str, task_id: str | None = None) -> str:
    """Digest of the answers in force (without where they came from): part of the inputs hash of a
    stage that consumes labels, so it reruns when its answers change and stays cached otherwise.
    For ``manual_track`` the answered tasks count too (an empty answer has no rows)."""
    rows = current_answers(wh, kind, [clip], task_id).drop_columns(["label_sha256", "ingested_at"])
    keys = ["task_id"] + [k for k in ANSWER_TABLES[kind].key if k in rows.column_names]
    rows_digest = table_digest(rows.sort_by([(k, "ascending") for k in keys]))
    if kind != "manual_track":
        return rows_digest
    answered = sorted(t for t in answered_tasks(wh, kind, clip) if task_id is None or t == task_id)
    return digest(rows_digest, *answered)


def correspondence_table(wh: Warehouse, clip: str) -> pa.Table:
    """The clip's ``correspondences`` from its labels: the clicks that answer the items of its newest
    correspondences task (:func:`tasks.human.clicks_in_force.in_force_rows`); empty without one."""
    row = latest_task_of_kind(wh, clip, "correspondences")
    rows = [] if row is None else in_force_rows(clip, json.loads(row["document"]),
                                                current_answers(wh, "correspondences", [clip], row["task_id"]))
    table = pa.Table.from_pylist(rows, schema=CORRESPONDENCES.schema)
    return table.sort_by([(k, "ascending") for k in CORRESPONDENCES.key])


def labels_lock(wh: Warehouse, clip: str):
    """The lock of a clip's answers (``_locks/_labels/<clip>.lock``): held while label files of the
    clip are checked for duplicates and committed, and while its ``correspondences`` are rewritten
    from them, so that two ingests (or an ingest and the clip's run) never both commit one file nor
    write a table from answers one of them has not seen."""
    from warehouse.store import check_name, file_lock

    return file_lock(wh.root / "_locks" / "_labels" / f"{check_name(clip)}.lock")


def sync_correspondences(wh: Warehouse, clip: str) -> tuple[pa.Table, int]:
    """Rewrite the clip's ``correspondences`` partition from its labels (:func:`correspondence_table`)
    if it changed, under :func:`labels_lock`; returns the table and the rows written (0: unchanged)."""
    with labels_lock(wh, clip):
        table = correspondence_table(wh, clip)
        if table_digest(table) == table_digest(wh.read("correspondences", [clip])):
            return table, 0
        return table, wh.write("correspondences", clip, table)


def label_history(wh: Warehouse, clips: list[str] | None = None) -> pa.Table:
    """``label_files`` (without the documents) with ``superseded``: none of the file's answers is in force."""
    files = wh.read("label_files", clips).drop_columns(["document"])
    in_force: set[str] = set()
    for kind in KINDS:
        if kind == "manual_track":
            f = _committed_files(wh, kind, clips).to_pylist()
            newest = _newest([(r["clip"], r["task_id"]) for r in f], [r["ingested_at"] for r in f])
            in_force |= {r["label_sha256"] for r, keep in zip(f, newest) if keep}
        else:
            in_force |= set(current_answers(wh, kind, clips).column("label_sha256").to_pylist())
    superseded = [sha not in in_force for sha in files.column("label_sha256").to_pylist()]
    return files.append_column("superseded", pa.array(superseded, pa.bool_()))
