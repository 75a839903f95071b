"""Ingest label files into the warehouse (``cadestate labels ingest DIR``).

:func:`ingest_labels` validates every ``*.json`` under a folder (:func:`tasks.labels.validate_label`)
and appends the valid ones to the answer tables (``manual_track_labels``, ``cad_selection_labels``,
``correspondence_labels``, ``verification_labels``) and then to ``label_files``, which is the
commit record: answer rows whose file has no ``label_files`` row (a crash between the two writes)
are ignored, and the file is ingested again on the next run. Rules:

- idempotent: a file whose bytes (SHA-256) were ingested before adds nothing, whatever its name;
- invalid files are reported (file and field) and skipped; the others are ingested; nothing
  ingested before is touched (every label table is an append-only history);
- partial labels are fine: a label may answer some of its task's tracks;
- supersession, computed on read (:func:`current_answers`): per (task, track), the answer of the
  newest file wins, older ones stay in the history; a manual-track label replaces the whole answer
  of its task. "Newer" is ingested later; files ingested together are ordered by their
  ``created_at`` (else their modification time), then by path;
- co-planarity of the 3D points of each key-frame (and of each track's answer) is detected at
  ingest with the pose solver's own test (:func:`tasks.pose_checks.coplanar_axis`) and stored;
- the newest correspondences of every track of a touched clip are written to the
  ``correspondences`` table (the pose stage's input) when they changed.
"""

from __future__ import annotations

import datetime as dt
import hashlib
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from cadestate.lineage import digest, table_digest
from schemas.labels import ANSWER_TABLES, KINDS
from schemas.pose import CORRESPONDENCES
from tasks.labels import ClipFacts, LabelError, LabelFile, utc_now, validate_label
from tasks.pose_checks import coplanar_axis
from warehouse import Warehouse

DEFAULT_COPLANAR_TOL = 0.02
"""As ``[pose] coplanar_tol``: co-planar when the smallest singular value of the centred points is
below this fraction of the largest."""


@dataclass
class IngestReport:
    """What :func:`ingest_labels` did. ``clips``: clips with new labels (the ones to resume)."""

    ingested: list[str] = field(default_factory=list)
    duplicates: list[str] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    clips: list[str] = field(default_factory=list)
    rows: dict[str, int] = field(default_factory=dict)
    coplanar_keyframes: int = 0

    @property
    def ok(self) -> bool:
        return not self.errors


def label_paths(source: str | Path | Sequence[str | Path]) -> list[Path]:
    """The label files of ``source``: the file itself, every ``*.json`` below the folder (hidden
    files and folders skipped), or the files of a list; sorted."""
    if isinstance(source, (list, tuple)):
        return sorted(p for item in source for p in label_paths(item))
    source = Path(source)
    if source.is_file():
        return [source]
    if not source.is_dir():
        raise FileNotFoundError(f"{source}: no such label file or folder")
    return sorted(p for p in source.rglob("*.json")
                  if p.is_file() and not any(part.startswith(".") for part in p.relative_to(source).parts))


# ------------------------------------------------------------------------------ rows

def _manual_rows(lf: LabelFile, facts: ClipFacts, tol: float) -> list[dict]:
    return [{"object_index": i, "label": a.label, "source_id": a.source_id, "timestamp_us": b.timestamp_us, "box": list(b.box)}
            for i, a in enumerate(lf.label.answers) for b in a.boxes]


def _cad_selection_rows(lf: LabelFile, facts: ClipFacts, tol: float) -> list[dict]:
    items = {it.track_id: it for it in facts.task(lf.clip, lf.task_id).items}
    rows = []
    for a in lf.label.answers:
        ranks = {c.cad_id: c.rank for c in items[a.track_id].candidates}
        rows.append({"track_id": a.track_id, "cad_id": a.cad_id, "rank": ranks.get(a.cad_id)})
    return rows


def keyframe_coplanar_axis(xyz: np.ndarray, tol: float) -> int:
    """CAD axis nearest the normal of one key-frame's 3D points if they are co-planar, else -1."""
    return coplanar_axis(xyz, np.zeros(len(xyz), np.int64), 1, tol)


def _correspondence_rows(lf: LabelFile, facts: ClipFacts, tol: float) -> list[dict]:
    items = {it.track_id: it for it in facts.task(lf.clip, lf.task_id).items}
    rows = []
    for a in lf.label.answers:
        xyz = np.array([p.xyz for kf in a.keyframes for p in kf.points], np.float64)
        kf_index = np.array([j for j, kf in enumerate(a.keyframes) for _ in kf.points], np.int64)
        track_axis = coplanar_axis(xyz, kf_index, items[a.track_id].symmetry, tol)
        for kf in a.keyframes:
            axis = keyframe_coplanar_axis(np.array([p.xyz for p in kf.points], np.float64), tol)
            rows += [{"track_id": a.track_id, "timestamp_us": kf.timestamp_us, "point_index": k, "cad_id": a.cad_id,
                      "point_2d": [p.x, p.y], "point_3d": list(p.xyz), "is_mirrored": a.is_mirrored,
                      "keyframe_coplanar": axis >= 0, "keyframe_coplanar_axis": axis, "track_coplanar_axis": track_axis}
                     for k, p in enumerate(kf.points)]
    return rows


def _verification_rows(lf: LabelFile, facts: ClipFacts, tol: float) -> list[dict]:
    items = {it.track_id: it for it in facts.task(lf.clip, lf.task_id).items}
    return [{"track_id": a.track_id, "cad_id": items[a.track_id].cad_id, "accepted": a.verdict == "accept",
             "comment": a.comment} for a in lf.label.answers]


ROWS = {"manual_track": _manual_rows, "cad_selection": _cad_selection_rows,
        "correspondences": _correspondence_rows, "verification": _verification_rows}


def answer_rows(lf: LabelFile, facts: ClipFacts, ingested_at: dt.datetime, tol: float = DEFAULT_COPLANAR_TOL) -> list[dict]:
    """Rows of the kind's answer table for one validated label file."""
    head = {"clip": lf.clip, "label_sha256": lf.sha256, "ingested_at": ingested_at, "task_id": lf.task_id}
    return [{**head, **r} for r in ROWS[lf.kind](lf, facts, tol)]


def file_row(lf: LabelFile, ingested_at: dt.datetime) -> dict:
    """The ``label_files`` row of one label file."""
    created = lf.label.created_at
    created_at = None if created is None else _utc(dt.datetime.fromisoformat(created))
    return {"clip": lf.clip, "label_sha256": lf.sha256, "ingested_at": ingested_at, "task_id": lf.task_id, "kind": lf.kind,
            "source_path": str(lf.path), "annotator": lf.label.annotator, "created_at": created_at,
            "num_answers": len(lf.label.answers), "document": lf.document}


def _utc(t: dt.datetime) -> dt.datetime:
    return t.replace(tzinfo=dt.timezone.utc) if t.tzinfo is None else t.astimezone(dt.timezone.utc)


# ------------------------------------------------------------------------------ ingest

def _order(lf: LabelFile) -> tuple:
    if lf.label.created_at is not None:
        when = _utc(dt.datetime.fromisoformat(lf.label.created_at))
    else:
        when = dt.datetime.fromtimestamp(lf.path.stat().st_mtime, dt.timezone.utc) if lf.path.exists() else utc_now()
    return when, str(lf.path)


def _ingest_times(wh: Warehouse, n: int, now: dt.datetime | None) -> list[dt.datetime]:
    """``n`` strictly increasing times, all after every ``label_files.ingested_at`` so far."""
    start = now or utc_now()
    seen = wh.read("label_files", columns=["ingested_at"]).column("ingested_at").to_pylist()
    if seen and max(seen) >= start:
        start = max(seen) + dt.timedelta(microseconds=1)
    return [start + dt.timedelta(microseconds=i) for i in range(n)]


def ingest_labels(wh: Warehouse, source: str | Path | Sequence[str | Path], *, coplanar_tol: float = DEFAULT_COPLANAR_TOL,
                  now: dt.datetime | None = None) -> IngestReport:
    """Validate and ingest the label files of ``source`` (a folder, one file or a list of them); see the module doc."""
    report = IngestReport()
    known = set(wh.read("label_files", columns=["label_sha256"]).column("label_sha256").to_pylist())
    facts = ClipFacts(wh)
    accepted: list[LabelFile] = []
    for path in label_paths(source):
        try:
            data = path.read_bytes()
        except OSError as e:
            report.errors.append(f"{path}: $: cannot read: {e.strerror or e}")
            continue
        if hashlib.sha256(data).hexdigest() in known:
            report.duplicates.append(str(path))
            continue
        try:
            lf = validate_label(path, facts=facts, data=data)
        except LabelError as e:
            report.errors.append(str(e))
            continue
        known.add(lf.sha256)
        accepted.append(lf)
    accepted.sort(key=_order)
    times = dict(zip((lf.sha256 for lf in accepted), _ingest_times(wh, len(accepted), now)))
    by_clip: dict[str, list[LabelFile]] = defaultdict(list)
    for lf in accepted:
        by_clip[lf.clip].append(lf)
    for clip, files in sorted(by_clip.items()):
        _ingest_clip(wh, clip, files, times, facts, coplanar_tol, report)
        report.ingested += [str(lf.path) for lf in files]
    report.clips = sorted(by_clip)
    return report


def _ingest_clip(wh: Warehouse, clip: str, files: list[LabelFile], times: dict[str, dt.datetime], facts: ClipFacts,
                 tol: float, report: IngestReport) -> None:
    """Answers first, then ``label_files`` (the commit record), then ``correspondences``."""
    for kind in KINDS:
        rows = [r for lf in files if lf.kind == kind for r in answer_rows(lf, facts, times[lf.sha256], tol)]
        if not rows:
            continue
        spec = ANSWER_TABLES[kind]
        report.rows[spec.name] = report.rows.get(spec.name, 0) + wh.write(spec.name, clip, pa.Table.from_pylist(rows, schema=spec.schema))
        if kind == "correspondences":
            report.coplanar_keyframes += len({(r["label_sha256"], r["track_id"], r["timestamp_us"]) for r in rows if r["keyframe_coplanar"]})
    rows = [file_row(lf, times[lf.sha256]) for lf in files]
    report.rows["label_files"] = report.rows.get("label_files", 0) + wh.write("label_files", clip, pa.Table.from_pylist(rows))
    if any(lf.kind == "correspondences" for lf in files):
        report.rows["correspondences"] = report.rows.get("correspondences", 0) + sync_correspondences(wh, clip)


# ------------------------------------------------------------------------------ reading

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
    clips = None if clips is None else [c for c in clips if c in wh.partitions(spec.name)]
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
    """The clip's ``correspondences`` from its labels: per track, the newest answer over all tasks."""
    rows = current_answers(wh, "correspondences", [clip])
    newest = _newest([(t,) for t in rows.column("track_id").to_pylist()], rows.column("ingested_at").to_pylist())
    rows = rows.filter(pa.array(newest, pa.bool_())).to_pylist()
    out = [{"clip": clip, "track_id": str(r["track_id"]), "timestamp_us": r["timestamp_us"], "point_index": r["point_index"],
            "cad_id": r["cad_id"], "point_2d": r["point_2d"], "point_3d": r["point_3d"], "is_mirrored": r["is_mirrored"]}
           for r in rows]
    table = pa.Table.from_pylist(out, schema=CORRESPONDENCES.schema)
    return table.sort_by([(k, "ascending") for k in CORRESPONDENCES.key])


def sync_correspondences(wh: Warehouse, clip: str) -> int:
    """Rewrite the clip's ``correspondences`` partition from its labels if it changed; returns rows written."""
    table = correspondence_table(wh, clip)
    if table_digest(table) == table_digest(wh.read("correspondences", [clip])):
        return 0
    return wh.write("correspondences", clip, table)


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
