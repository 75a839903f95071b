"""Ingest label files into the warehouse (``cadestate labels ingest DIR``).

:func:`ingest_labels` validates every ``*.json`` under a folder (:func:`tasks.human.labels.validate_label`)
and commits each valid file all or nothing: its rows are built and conformed to their tables in
memory first (:func:`prepare_file`), then appended to its answer table (``manual_track_labels``,
``cad_selection_labels``, ``correspondence_labels``, ``verification_labels``), to ``label_effort``
(the ``seconds`` given per item) and ``track_relations`` (``not_objects``, every kind's ``same_as_track``), and then to
``label_files``, which is the commit record: answer rows whose file has no ``label_files`` row (a
crash or a failed write between the two) are ignored, the file is ingested again on the next run,
and the clip's next ingest removes them (:func:`drop_uncommitted`: SQL over the tables counts them
till then). Rules:

- idempotent: a file whose bytes (SHA-256) were ingested before adds nothing, whatever its name;
- every file's outcome is reported: ingested, already ingested, or its error (one line naming the
  file and field); a file that is invalid, or whose write fails, stops none of the others; nothing
  ingested before is touched (every label table is an append-only history);
- partial labels are fine: a label may answer some of its task's tracks;
- supersession, computed on read (:func:`tasks.human.answers_in_force.current_answers`): per (task, track), the answer of the
  newest file wins, older ones stay in the history; a manual-track label replaces the whole answer
  of its task. "Newer" is ingested later; files ingested together are ordered by their
  ``created_at`` (else their modification time), then by path;
- co-planarity of the 3D points of each key-frame (and of each track's answer) is detected at
  ingest with the pose solver's own test (:func:`tasks.pose.checks.coplanar_axis`) and stored;
- the clicks that answer the items of a touched clip's newest correspondences task
  (:mod:`tasks.human.clicks_in_force`) are written to the ``correspondences`` table (the pose
  stage's input) when they changed.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import hashlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa

from schemas.label_tables import ANSWER_TABLES, LABEL_EFFORT, LABEL_FILES, SIDE_TABLES, TRACK_RELATIONS
from schemas.labels import KINDS
from tasks.human.answers_in_force import labels_lock, sync_correspondences
from tasks.human.label_format import MAX_LABEL_BYTES, LabelError, one_line, read_limited
from tasks.human.label_warnings import LabelWarnings
from tasks.human.labels import ClipFacts, LabelFile, check_label, utc_now, validate_label
from tasks.pose.checks import coplanar_axis
from warehouse import Warehouse

DEFAULT_COPLANAR_TOL = 0.02
"""As ``[pose] coplanar_tol``: co-planar when the smallest singular value of the centred points is
below this fraction of the largest."""


@dataclass
class IngestReport:
    """What :func:`ingest_labels` did, file by file: ``ingested`` and ``duplicates`` (paths),
    ``errors`` (one line each, naming the file), ``warnings`` (on files ingested or not);
    ``clips``: clips with new labels (the ones to resume); ``duplicate_clips``: the clips of the
    ``duplicates``, in their order (a run killed after their ingest may have left them unrun)."""

    ingested: list[str] = field(default_factory=list)
    duplicates: list[str] = field(default_factory=list)
    duplicate_clips: list[str] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    clips: list[str] = field(default_factory=list)
    rows: dict[str, int] = field(default_factory=dict)
    coplanar_keyframes: int = 0

    @property
    def ok(self) -> bool:
        return not self.errors

    @property
    def earlier_clips(self) -> list[str]:
        """The clips of the ``duplicates`` with no new labels, once each: those a killed ingest
        may have left unrun (:func:`tasks.status.clips_left_unrun` tells)."""
        return [c for c in dict.fromkeys(self.duplicate_clips) if c not in self.clips]


def label_paths(source: str | Path | Sequence[str | Path]) -> list[Path]:
    """The label files of ``source``: the file itself, every ``*.json`` below the folder (hidden
    files and folders skipped; a link to nothing is one, whose reading then fails), or the files of a
    list; sorted."""
    if isinstance(source, (list, tuple)):
        return sorted(p for item in source for p in label_paths(item))
    source = Path(source)
    if source.is_file():
        return [source]
    if not source.is_dir():
        raise FileNotFoundError(f"{source}: no such label file or folder")
    return sorted(p for p in source.rglob("*.json")
                  if (p.is_file() or (p.is_symlink() and not p.exists())) and not any(part.startswith(".") for part in p.relative_to(source).parts))


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
             "comment": a.comment, "same_as_track": a.same_as_track} for a in lf.label.answers]


ROWS = {"manual_track": _manual_rows, "cad_selection": _cad_selection_rows,
        "correspondences": _correspondence_rows, "verification": _verification_rows}


def answer_rows(lf: LabelFile, facts: ClipFacts, ingested_at: dt.datetime, tol: float = DEFAULT_COPLANAR_TOL) -> list[dict]:
    """Rows of the kind's answer table for one validated label file."""
    head = {"clip": lf.clip, "label_sha256": lf.sha256, "ingested_at": ingested_at, "task_id": lf.task_id}
    return [{**head, **r} for r in ROWS[lf.kind](lf, facts, tol)]


def effort_rows(lf: LabelFile, ingested_at: dt.datetime) -> list[dict]:
    """``label_effort`` rows: the seconds given per item (a manual_track label is one item, track -1)."""
    head = {"clip": lf.clip, "label_sha256": lf.sha256, "ingested_at": ingested_at, "task_id": lf.task_id, "kind": lf.kind,
            "annotator": lf.label.annotator}
    if lf.kind == "manual_track":
        return [] if lf.label.seconds is None else [{**head, "track_id": -1, "seconds": lf.label.seconds}]
    return [{**head, "track_id": a.track_id, "seconds": a.seconds} for a in lf.label.answers if a.seconds is not None]


def relation_rows(lf: LabelFile, ingested_at: dt.datetime) -> list[dict]:
    """``track_relations`` rows: "track N is not an object", "this is track N", "same object as track N"."""
    said: list[dict] = []
    if lf.kind == "manual_track":
        said += [{"relation": "not_object", "track_id": t, "other_track_id": None, "object_index": None}
                 for t in lf.label.not_objects]
        said += [{"relation": "same_object", "track_id": a.same_as_track, "other_track_id": None, "object_index": i}
                 for i, a in enumerate(lf.label.answers) if a.same_as_track is not None]
    elif lf.kind in ("cad_selection", "verification"):
        said += [{"relation": "same_object", "track_id": a.track_id, "other_track_id": a.same_as_track, "object_index": None}
                 for a in lf.label.answers if a.same_as_track is not None]
    head = {"clip": lf.clip, "label_sha256": lf.sha256, "ingested_at": ingested_at, "task_id": lf.task_id, "kind": lf.kind}
    return [{**head, "statement_index": k, **r} for k, r in enumerate(said)]


def file_row(lf: LabelFile, ingested_at: dt.datetime) -> dict:
    """The ``label_files`` row of one label file (a path that is not UTF-8 is kept with its odd
    bytes escaped, as printed)."""
    return {"clip": lf.clip, "label_sha256": lf.sha256, "ingested_at": ingested_at, "task_id": lf.task_id, "kind": lf.kind,
            "source_path": one_line(str(lf.path)), "annotator": lf.label.annotator, "created_at": lf.created_at,
            "num_answers": len(lf.label.answers), "document": lf.document}


# ------------------------------------------------------------------------------ ingest

def _order(lf: LabelFile) -> tuple:
    if lf.created_at is not None:
        when = lf.created_at
    else:
        try:
            when = dt.datetime.fromtimestamp(lf.path.stat().st_mtime, dt.timezone.utc)
        except OSError:
            when = utc_now()
    return when, str(lf.path)


def _ingest_times(wh: Warehouse, n: int, now: dt.datetime | None, clips: list[str]) -> list[dt.datetime]:
    """``n`` strictly increasing times, all after every ``label_files.ingested_at`` of ``clips`` so
    far (answers are ordered within their clip: every answer table's key starts with the clip)."""
    start = now or utc_now()
    seen = wh.read("label_files", clips, columns=["ingested_at"]).column("ingested_at").to_pylist()
    if seen and max(seen) >= start:
        start = max(seen) + dt.timedelta(microseconds=1)
    return [start + dt.timedelta(microseconds=i) for i in range(n)]


WRITE_ERRORS = (OSError, ValueError, pa.ArrowException)
"""What a failed write raises (the disk; data that does not fit its table): reported per file."""


@dataclass(frozen=True)
class PreparedFile:
    """One label file's rows, conformed to their tables and ready to write: ``answers`` (rows of
    its kind's answer table), ``sides`` (rows of ``label_effort`` and ``track_relations``, by table
    name) and ``record`` (its ``label_files`` row, the commit record)."""

    lf: LabelFile
    answers: pa.Table
    record: pa.Table
    sides: dict[str, pa.Table] = field(default_factory=dict)


def prepare_file(wh: Warehouse, lf: LabelFile, ingested_at: dt.datetime, facts: ClipFacts,
                 tol: float = DEFAULT_COPLANAR_TOL) -> PreparedFile:
    """Build and conform a file's rows in memory: data that does not fit fails here, before anything is written."""
    spec = ANSWER_TABLES[lf.kind]
    answers = pa.Table.from_pylist(answer_rows(lf, facts, ingested_at, tol), schema=spec.schema)
    record = pa.Table.from_pylist([file_row(lf, ingested_at)], schema=LABEL_FILES.schema)
    sides = {}
    for side, rows in ((LABEL_EFFORT, effort_rows(lf, ingested_at)), (TRACK_RELATIONS, relation_rows(lf, ingested_at))):
        if rows:
            sides[side.name] = wh.conform(side.name, lf.clip, pa.Table.from_pylist(rows, schema=side.schema))
    return PreparedFile(lf, wh.conform(spec.name, lf.clip, answers), wh.conform(LABEL_FILES.name, lf.clip, record), sides)


def ingested_sha256(wh: Warehouse, clips: list[str] | None = None) -> dict[str, str]:
    """The SHA-256 of every label file ingested before (for ``clips``: of theirs), each with its clip
    (a file names its clip, so the same bytes were ingested for the same clip)."""
    files = wh.read("label_files", clips, columns=["label_sha256", "clip"])
    return dict(zip(files.column("label_sha256").to_pylist(), files.column("clip").to_pylist()))


@dataclass(frozen=True)
class CheckedFile:
    """One label file as ingest checks it: ``lf`` when it is valid and new; ``error`` (one line
    naming the file) when it is not valid; ``ingested_for`` (its clip) when the same bytes were
    ingested before (``in_batch``: came earlier in the same batch): ingest skips it."""

    path: Path
    lf: LabelFile | None = None
    error: str | None = None
    ingested_for: str | None = None
    in_batch: bool = False


def check_files(paths: Sequence[Path], facts: ClipFacts | None, known: dict[str, str],
                max_bytes: int = MAX_LABEL_BYTES) -> list[CheckedFile]:
    """Check ``paths`` as ingest does, one :class:`CheckedFile` each, in their order: the bytes'
    SHA-256 against ``known`` (SHA-256 to clip, as :func:`ingested_sha256`; the new files are
    added to it) first, then the format; then, with ``facts``, each file against the warehouse in
    the order ingest applies them (:func:`_order`, the newest answer in force), its links going
    into ``facts`` for the files after it (a ring across files is seen as it would stand)."""
    checked: list[CheckedFile] = []
    batch: dict[str, int] = {}  # the batch's new bytes: the file that has them first
    copies: list[tuple[int, str]] = []
    for path in paths:
        try:
            data = read_limited(path, max_bytes)
            if (clip := known.get(sha := hashlib.sha256(data).hexdigest())) is not None:
                if sha in batch:
                    copies.append((len(checked), sha))
                checked.append(CheckedFile(path, ingested_for=clip, in_batch=sha in batch))
                continue
            lf = validate_label(path, data=data, max_bytes=max_bytes)  # the format alone
        except LabelError as e:
            checked.append(CheckedFile(path, error=str(e)))
            continue
        known[sha] = lf.clip
        batch[sha] = len(checked)
        checked.append(CheckedFile(path, lf=lf))
    if facts is None:
        return checked
    for i in sorted((i for i, c in enumerate(checked) if c.lf is not None), key=lambda i: _order(checked[i].lf)):
        lf = checked[i].lf
        try:
            warnings = check_label(lf.label, facts, str(checked[i].path))
        except LabelError as e:
            checked[i] = CheckedFile(checked[i].path, error=str(e))
            continue
        if warnings:
            checked[i] = CheckedFile(checked[i].path, lf=dataclasses.replace(lf, warnings=lf.warnings + tuple(warnings)))
        facts.take(lf.label)
    for i, sha in copies:  # a copy of a file refused here is not "already ingested": those bytes never were
        if (original := checked[batch[sha]]).error is not None:
            checked[i] = CheckedFile(checked[i].path, error=f"{checked[i].path}: the same bytes as {original.path}, "
                                                           "not ingested either (its error above)")
    return checked


def _accepted(wh: Warehouse, files: Sequence[CheckedFile], report: IngestReport) -> list[LabelFile]:
    """The valid new files of ``files``; the errors and duplicates go to ``report``, with the
    warnings of the valid ones (:func:`order_warnings` too)."""
    accepted: list[LabelFile] = []
    for checked in files:
        if checked.error is not None:
            report.errors.append(checked.error)
        elif checked.ingested_for is not None:
            report.duplicates.append(str(checked.path))
            report.duplicate_clips.append(checked.ingested_for)
        else:
            report.warnings += checked.lf.warnings
            accepted.append(checked.lf)
    report.warnings += order_warnings(wh, accepted)
    return accepted


def order_warnings(wh: Warehouse, files: Sequence[LabelFile]) -> list[str]:
    """The warnings of :mod:`tasks.human.label_warnings` on valid label files, each compared with
    the answers ingested before and with the files before it in the order they are applied (the
    newest answer is the one in force)."""
    warn = LabelWarnings(wh)
    return [w for lf in sorted(files, key=_order) for w in warn.check(lf)]


def _failed(report: IngestReport, lf: LabelFile, e: Exception) -> None:
    report.errors.append(one_line(f"{lf.path}: $: not ingested, writing failed: {getattr(e, 'strerror', None) or e}"))


def _write_each(wh: Warehouse, table: str, clip: str, parts: list[tuple[PreparedFile, pa.Table]],
                report: IngestReport) -> list[PreparedFile]:
    """Append the rows of several files to ``table`` in one write; if that fails, one write per
    file, so that a file whose write fails stops none of the others. Returns the files written."""
    try:
        if parts:
            wh.write(table, clip, pa.concat_tables([t for _, t in parts]))
        return [f for f, _ in parts]
    except WRITE_ERRORS as e:
        if len(parts) == 1:
            _failed(report, parts[0][0].lf, e)
            return []
    written = []
    for f, t in parts:
        try:
            wh.write(table, clip, t)
            written.append(f)
        except WRITE_ERRORS as e:
            _failed(report, f.lf, e)
    return written


def _commit_clip(wh: Warehouse, clip: str, files: list[PreparedFile], report: IngestReport) -> list[PreparedFile]:
    """Commit the files of one clip: their answers (one write per answer table), then the
    ``label_files`` rows of the files whose answers were written. Returns the files committed."""
    answered = [f for f in files if not f.answers.num_rows]
    for kind in KINDS:
        parts = [(f, f.answers) for f in files if f.lf.kind == kind and f.answers.num_rows]
        answered += _write_each(wh, ANSWER_TABLES[kind].name, clip, parts, report)
    answered.sort(key=files.index)
    for side in SIDE_TABLES:  # effort and relations: a file whose rows fail here is not committed either
        parts = [(f, f.sides[side.name]) for f in answered if side.name in f.sides]
        written = _write_each(wh, side.name, clip, parts, report)
        answered = [f for f in answered if side.name not in f.sides or f in written]
    return _write_each(wh, LABEL_FILES.name, clip, [(f, f.record) for f in answered], report)


def _count(report: IngestReport, f: PreparedFile) -> None:
    """Add one committed file to ``report``: its path, rows and co-planar key-frames."""
    report.ingested.append(str(f.lf.path))
    for name, table in ((ANSWER_TABLES[f.lf.kind].name, f.answers), *f.sides.items(), (LABEL_FILES.name, f.record)):
        if table.num_rows:
            report.rows[name] = report.rows.get(name, 0) + table.num_rows
    if f.lf.kind == "correspondences":
        flags = f.answers.select(["track_id", "timestamp_us", "keyframe_coplanar"]).to_pylist()
        report.coplanar_keyframes += len({(r["track_id"], r["timestamp_us"]) for r in flags if r["keyframe_coplanar"]})


def ingest_labels(wh: Warehouse, source: str | Path | Sequence[str | Path], *, coplanar_tol: float = DEFAULT_COPLANAR_TOL,
                  now: dt.datetime | None = None, max_bytes: int = MAX_LABEL_BYTES) -> IngestReport:
    """Validate and ingest the label files of ``source`` (a folder, one file or a list of them),
    each file all or nothing; see the module doc. Writes are batched per clip and table (each
    write rebuilds the catalog), falling back to one write per file when a batch fails."""
    report = IngestReport()
    facts = ClipFacts(wh)
    accepted = _accepted(wh, check_files(label_paths(source), facts, ingested_sha256(wh), max_bytes), report)
    return _ingest(wh, accepted, facts, report, coplanar_tol, now)


def ingest_validated(wh: Warehouse, files: Sequence[LabelFile], facts: ClipFacts, *,
                     coplanar_tol: float = DEFAULT_COPLANAR_TOL) -> IngestReport:
    """:func:`ingest_labels` of label files validated already against this warehouse (``facts``:
    the :class:`ClipFacts` they were validated with; the app validates an answer before it writes
    its file, and need not parse it again). A file whose bytes were ingested before is a duplicate.
    The warnings are those :func:`ingest_labels` gives (:mod:`tasks.human.label_warnings` too)."""
    report = IngestReport()
    known = ingested_sha256(wh, sorted({lf.clip for lf in files}))
    checked = []
    for lf in files:
        earlier = known.get(lf.sha256)
        checked.append(CheckedFile(lf.path, lf=lf) if earlier is None else CheckedFile(lf.path, ingested_for=earlier))
        known.setdefault(lf.sha256, lf.clip)
    return _ingest(wh, _accepted(wh, checked, report), facts, report, coplanar_tol, None)


def drop_uncommitted(wh: Warehouse, clip: str) -> int:
    """Remove the clip's rows of answer, ``label_effort`` and ``track_relations`` tables that no
    ``label_files`` row commits (a process killed, or a write failed, before its file's commit
    record); call it under :func:`labels_lock`, which every commit holds. Returns the rows removed."""
    files = wh.read(LABEL_FILES.name, [clip], columns=["label_sha256", "ingested_at"])
    committed = set(zip(files.column("label_sha256").to_pylist(), files.column("ingested_at").to_pylist()))

    def uncommitted(rows: pa.Table) -> list[bool]:
        return [k not in committed for k in zip(rows.column("label_sha256").to_pylist(), rows.column("ingested_at").to_pylist())]

    removed = 0
    for spec in (*ANSWER_TABLES.values(), *SIDE_TABLES):
        keys = wh.read(spec.name, [clip], columns=["label_sha256", "ingested_at"])
        if any(uncommitted(keys)):  # the partition is read whole only then
            removed += wh.drop_rows(spec.name, clip, uncommitted)
    return removed


def _ingest(wh: Warehouse, accepted: list[LabelFile], facts: ClipFacts, report: IngestReport, coplanar_tol: float,
            now: dt.datetime | None) -> IngestReport:
    """Ingest the ``accepted`` files (valid, new) into ``report``: batched per clip and table."""
    by_clip: dict[str, list[LabelFile]] = {}
    for lf in sorted(accepted, key=_order):
        by_clip.setdefault(lf.clip, []).append(lf)
    for clip, lfs in sorted(by_clip.items()):
        # another ingest of the same files commits them once: checked again here; and the times are
        # taken here, after every answer another process committed (taken before, a file committed
        # last could carry an older time than one committed meanwhile, and never come in force)
        with labels_lock(wh, clip):
            files = []
            for lf, at in zip(lfs, _ingest_times(wh, len(lfs), now, [clip])):
                try:
                    files.append(prepare_file(wh, lf, at, facts, coplanar_tol))
                except WRITE_ERRORS as e:
                    _failed(report, lf, e)
            try:
                if removed := drop_uncommitted(wh, clip):
                    report.warnings.append(f"clip {clip}: removed {removed} label row(s) that an earlier ingest wrote "
                                           "but never committed (stopped or failed before their label_files row)")
            except WRITE_ERRORS as e:
                report.warnings.append(one_line(f"clip {clip}: uncommitted label rows not removed: {e}"))
            known = ingested_sha256(wh, [clip])
            report.duplicates += [str(f.lf.path) for f in files if f.lf.sha256 in known]
            report.duplicate_clips += [clip for f in files if f.lf.sha256 in known]
            committed = _commit_clip(wh, clip, [f for f in files if f.lf.sha256 not in known], report)
        for f in committed:
            _count(report, f)
        report.clips += [clip] if committed else []
        if any(f.lf.kind == "correspondences" for f in committed):
            try:
                report.rows["correspondences"] = report.rows.get("correspondences", 0) + sync_correspondences(wh, clip)[1]
            except WRITE_ERRORS as e:
                report.errors.append(one_line(f"clip {clip}: the correspondences table was not updated: {e}"))
    return report


# ------------------------------------------------------------------------------ reading
