"""An answer from a page in, a label file out, ingested: the same contract as ``cadestate labels ingest``.

:func:`submit` takes the JSON a page posts (a label document without ``format``/``created_at``;
``annotator`` is the app's), adds the header, validates it with :func:`tasks.human.labels.validate_label`
(the JSON Schema of its kind, then the warehouse rules), writes it atomically as
``<labels_dir>/<clip>/<task_id>.<UTC time>.<n>.json`` and ingests that file as validated
(:func:`tasks.human.label_ingest.ingest_validated`). A payload that fails validation raises
:class:`tasks.human.label_format.LabelError` naming the field, and nothing is written. The file is on
disk before ingest starts, so a crash mid-ingest loses nothing: :func:`ingest_pending` (run when the
app starts) ingests every file of the folder not ingested yet (ingest is idempotent by content), but
for one whose items were answered again later (:func:`set_aside_superseded`).

An answer to a task that a rerun replaced goes to the newest task of its kind where it fits it
(:class:`Conflict` otherwise), and a page says which answers it saw (``as_of``,
:func:`answers_as_of`): an item answered by someone else since then is a :class:`Conflict`, not a
silent replacement of their answer; the same answer by the same annotator (a page that sent it
again, the reply to the first lost) is said saved, and nothing is written. The check, the write and
the ingest hold the clip's :func:`answers_lock`, which every app over the warehouse takes. A
verdict or a "none of these" is moved to a replacing task only where the model, pose or candidates
it judged are the same there (:func:`_changed_under`).
"""

from __future__ import annotations

import contextlib
import datetime as dt
import hashlib
import json
import os
import threading
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from schemas.labels import LABEL_FORMAT
from tasks.human.label_format import MAX_LABEL_BYTES, LabelError, one_line
from tasks.human.label_ingest import DEFAULT_COPLANAR_TOL, IngestReport, ingest_labels, ingest_validated
from tasks.human.labels import ClipFacts, latest_tasks, utc_now, validate_label, withdrawn_why
from warehouse import Warehouse, atomic_write_bytes
from warehouse.store import check_name, file_lock

LABELS_DIR = "labels"
"""Folder of the app's label files under the warehouse root (one subfolder per clip)."""


class IngestFailed(RuntimeError):
    """A valid answer was written but not ingested (a failed warehouse write): it stays on disk and
    is ingested when the app starts next (or by ``cadestate labels ingest <warehouse>/labels``)."""


class Conflict(RuntimeError):
    """A valid answer that would silently undo another: to a task the pipeline has replaced, or to
    an item someone answered since the page loaded. Nothing is written."""


@dataclass
class Submitted:
    """What :func:`submit` did: the label file (relative to the warehouse root), its clip, and the
    ingest report's warnings and row counts."""

    path: str
    clip: str
    kind: str
    task_id: str
    warnings: list[str] = field(default_factory=list)
    rows: dict[str, int] = field(default_factory=dict)


def label_bytes(payload: Any, annotator: str | None) -> bytes:
    """The label file's bytes for a page's ``payload`` (a JSON object): ``format`` and ``created_at``
    (now, UTC) added, ``annotator`` set when the app has one. Raises LabelError for a non-object."""
    if not isinstance(payload, dict):
        raise LabelError(f"answer: $: expected a JSON object, not {type(payload).__name__}")
    doc = {"format": LABEL_FORMAT, **payload, "created_at": utc_now().isoformat()}
    if annotator:
        doc["annotator"] = annotator
    try:
        return (json.dumps(doc, indent=1, ensure_ascii=False, allow_nan=False) + "\n").encode()
    except ValueError as e:
        raise LabelError(f"answer: $: {e}") from None


def _free_path(folder: Path, task_id: str) -> Path:
    stamp = utc_now().strftime("%Y%m%dT%H%M%S%f")
    n = 0
    while (folder / f"{task_id}.{stamp}.{n}.json").exists():
        n += 1
    return folder / f"{task_id}.{stamp}.{n}.json"


def shown(wh: Warehouse, text: str) -> str:
    """``text`` for a page: paths in the warehouse relative to it (a page is no place for the
    server's folders)."""
    for root in dict.fromkeys((str(wh.root.resolve()), str(wh.root))):
        text = text.replace(root + os.sep, "")
    return text


def _not_ingested(wh: Warehouse, path: Path, errors: list[str]) -> str:
    """The one-line message of :class:`IngestFailed` for ``path``."""
    why = one_line("; ".join(errors) or "unknown reason")
    return shown(wh, f"{path}: written but not ingested ({why}); it is ingested when the app starts next")


def answers_as_of(wh: Warehouse, clip: str) -> str:
    """When the newest answer of ``clip`` was ingested (ISO 8601; '' when none): what a page that
    shows the clip's answers now has seen, and sends back with its own (:func:`submit`)."""
    if not wh.has_partition("label_files", clip):
        return ""
    times = wh.read("label_files", [clip], columns=["ingested_at"]).column("ingested_at").to_pylist()
    return max(times).isoformat() if times else ""


def _tracks(kind: str, answers: list) -> set[int]:
    """The items a label file answers: its tracks' ids, or -1 for a manual-track task (one item)."""
    if kind == "manual_track":
        return {-1}
    return {a["track_id"] if isinstance(a, dict) else a.track_id for a in answers
            if not isinstance(a, dict) or isinstance(a.get("track_id"), int)}


def _ingested(wh: Warehouse, clip: str) -> tuple[set[str], list[dict]]:
    """The SHA-256 of the label files ingested for ``clip``, and their rows (:func:`_answered_since`)."""
    if not wh.has_partition("label_files", clip):
        return set(), []
    rows = wh.read("label_files", [clip], columns=["label_sha256", "task_id", "kind", "ingested_at", "created_at",
                                                   "annotator", "document", "source_path"]).to_pylist()
    return {r["label_sha256"] for r in rows}, rows


def _answered_since(rows: list[dict], task_id: str, tracks: set[int], since: dt.datetime | None,
                    created_after: dt.datetime | None = None) -> dict | None:
    """The newest of the ``label_files`` ``rows`` of ``task_id`` answering one of ``tracks`` that was
    ingested after ``since`` (None: ever) and, with ``created_after``, whose answers were given after it."""
    for row in sorted(rows, key=lambda r: r["ingested_at"], reverse=True):
        if row["task_id"] != task_id:
            continue
        if since is not None and row["ingested_at"] <= since:
            break
        if created_after is not None and (row["created_at"] is None or row["created_at"] <= created_after):
            continue
        try:
            answers = json.loads(row["document"]).get("answers", [])
        except (ValueError, AttributeError):
            continue
        if _tracks(row["kind"], answers if isinstance(answers, list) else []) & tracks:
            return row
    return None


def _retargeted(payload: dict, annotator: str | None, newest: str, facts: ClipFacts, replaced: str) -> tuple[bytes, Any]:
    """The answer to task ``replaced`` given to ``newest``, the task of its kind that a rerun put in
    its place (a drawn object, a fragment or a duplicate changes the tracks asked about): its bytes
    and label file, where it fits that task (its tracks there, its model among their candidates);
    else :class:`Conflict`."""
    data = label_bytes({**payload, "task_id": newest}, annotator)
    try:
        lf = validate_label("answer", facts=facts, data=data, max_bytes=MAX_LABEL_BYTES)
        if (why := _changed_under(lf, facts.task(lf.clip, replaced), facts.task(lf.clip, newest))) is not None:
            raise LabelError(why)
    except LabelError as e:
        raise Conflict(f"task {replaced} was replaced by task {newest} (the pipeline ran again), which this answer "
                       f"does not fit ({e}): this answer was not saved; the queue opens task {newest} (reloading this page "
                       "opens the replaced task again)") from None
    return data, lf


def _changed_under(lf: Any, old: Any, new: Any) -> str | None:
    """Why an answer to task ``old`` that validates against ``new`` (its replacement) still does
    not hold there, or None: a verdict judged a model and pose (the answer names neither), and
    "none of these" judged a list of candidates; either changed under it is what nobody saw."""
    if old is None or new is None or lf.kind not in ("verification", "cad_selection"):
        return None
    before, after = ({it.track_id: it for it in t.items} for t in (old, new))
    for a in lf.label.answers:
        was, now = before.get(a.track_id), after.get(a.track_id)
        if was is None or now is None:
            continue
        if lf.kind == "verification" and (was.cad_id, was.mesh_path, was.pose) != (now.cad_id, now.mesh_path, now.pose):
            return f"track {a.track_id} is posed anew there ({now.cad_id}): the verdict was given on the pose shown before"
        if lf.kind == "cad_selection" and a.cad_id is None and \
                [c.cad_id for c in was.candidates] != [c.cad_id for c in now.candidates]:
            return f"track {a.track_id} has other candidates there: 'none of these' was said of those shown before"
    return None


def _essence(doc: Any) -> Any:
    """A label document less what a page counts or stamps anew when it sends the same answers again:
    its time, format and the seconds spent (on the task, and on each answer)."""
    if not isinstance(doc, dict):
        return doc
    answers = doc.get("answers")
    if isinstance(answers, list):
        doc = {**doc, "answers": [{k: v for k, v in x.items() if k != "seconds"} if isinstance(x, dict) else x for x in answers]}
    return {k: v for k, v in doc.items() if k not in ("seconds", "created_at", "format")}


def _repeat_of(row: dict, document: dict) -> bool:
    """Whether the ingested label ``row`` is ``document`` (the label file an answer would write) sent
    again: the same annotator, task and answers, because the reply to the first never came (the network)."""
    try:
        return _essence(json.loads(row["document"])) == _essence(document)
    except ValueError:
        return False


def _check_unseen(wh: Warehouse, lf: Any, task_ids: set[str], as_of: str, document: dict) -> dict | None:
    """Raise :class:`Conflict` when an item of ``lf`` was answered (under one of ``task_ids``) after
    ``as_of``, what the page had seen, unless that answer is ``document`` (this label file) sent
    again (:func:`_repeat_of`): its ``label_files`` row is returned then; None when nothing was answered since."""
    try:
        since = dt.datetime.fromisoformat(as_of) if as_of else None
    except ValueError:
        raise LabelError(f"as_of: {as_of!r} is not an ISO 8601 time") from None
    if since is not None and since.tzinfo is None:
        raise LabelError(f"as_of: {as_of!r} has no time zone")
    tracks = _tracks(lf.kind, list(lf.label.answers))
    ingested = _ingested(wh, lf.clip)[1]
    rows = [r for t in sorted(task_ids) if (r := _answered_since(ingested, t, tracks, since)) is not None]
    if rows:
        row = max(rows, key=lambda r: r["ingested_at"])
        if _repeat_of(row, document):
            return row
        who = f" by {row['annotator']}" if row["annotator"] else ""
        what = "this task" if lf.kind == "manual_track" else "this item"
        raise Conflict(f"{what} was answered{who} at {row['ingested_at']:%H:%M:%S} UTC since the page loaded: "
                       "reload the page to see that answer; yours was not saved")
    return None


def submit(wh: Warehouse, payload: Any, *, annotator: str | None, lock: threading.Lock, as_of: str | None = None,
           labels_dir: Path | None = None, coplanar_tol: float = DEFAULT_COPLANAR_TOL) -> Submitted:
    """Validate, write and ingest one answer (module docstring). An answer to a task a rerun has
    replaced goes to the newest task of its kind where it fits it (:func:`_retargeted`). ``as_of``:
    what the page had seen (:func:`answers_as_of`; None: no check of answers since). Raises
    LabelError (bad payload, nothing written), :class:`Conflict` (nothing written) or
    :class:`IngestFailed` (written, not ingested)."""
    data = label_bytes(payload, annotator)
    folder_root = labels_dir or wh.root / LABELS_DIR
    with lock:  # one writer: file names, ingest times and the answer tables stay consistent
        facts = ClipFacts(wh)
        lf = validate_label("answer", facts=facts, data=data, max_bytes=MAX_LABEL_BYTES)
        with answers_lock(wh, lf.clip):
            return _submit_clip(wh, payload, data, lf, facts, annotator, as_of, folder_root, coplanar_tol)


def answers_lock(wh: Warehouse, clip: str):
    """The lock (``_locks/_answers/<clip>.lock``) under which an app checks that no answer came
    since the page loaded, writes its answer and ingests it: every app over the warehouse takes it
    (one per annotator, on one shared warehouse), else two answers to one item both passed the
    check and the later silently replaced the other. Not the ingest's own :func:`labels_lock`,
    which it takes inside."""
    return file_lock(wh.root / "_locks" / "_answers" / f"{check_name(clip)}.lock")


def _submit_clip(wh: Warehouse, payload: Any, data: bytes, lf: Any, facts: ClipFacts, annotator: str | None,
                 as_of: str | None, folder_root: Path, coplanar_tol: float) -> Submitted:
    """:func:`submit` of a validated answer ``lf`` (its bytes ``data``), under the clip's :func:`answers_lock`."""
    asked, moved = lf.task_id, []
    newest = latest_tasks(wh, lf.clip).get(lf.kind)
    if newest is not None and newest["task_id"] != asked and (why := withdrawn_why(newest)) is not None:
        raise Conflict(f"task {asked} was withdrawn (the pipeline ran again and asks nothing of this kind now: "
                       f"{why}): this answer was not saved")
    if newest is not None and newest["task_id"] != asked:
        data, lf = _retargeted(payload, annotator, newest["task_id"], facts, asked)
        moved = [f"task {asked} was replaced by task {lf.task_id} (the pipeline ran again): the answer went to it"]
    if as_of is not None and (saved := _check_unseen(wh, lf, {asked, lf.task_id}, as_of, json.loads(data))) is not None:
        repeat = "this answer was saved already (sent again, the reply to it lost on the way): nothing written"
        path = saved["source_path"]
        with contextlib.suppress(ValueError):
            path = wh.relative(Path(path))
        return Submitted(path, lf.clip, lf.kind, lf.task_id, [*moved, repeat], {})
    path = _free_path(folder_root / lf.clip, lf.task_id)
    atomic_write_bytes(path, data)
    try:  # the file as validated (its bytes), not parsed again
        report = ingest_validated(wh, [replace(lf, path=path)], facts, coplanar_tol=coplanar_tol)
    except Exception as e:  # noqa: BLE001  (any failure past the write: the file waits for the next start)
        raise IngestFailed(_not_ingested(wh, path, [f"{type(e).__name__}: {e}"])) from e
    if not report.ingested:
        raise IngestFailed(_not_ingested(wh, path, report.errors))
    # committed, though a table kept from the answers may not have been updated (the clip's run rewrites it)
    return Submitted(wh.relative(path), lf.clip, lf.kind, lf.task_id, moved + list(report.warnings) + list(report.errors),
                     dict(report.rows))


def ingest_pending(wh: Warehouse, lock: threading.Lock, labels_dir: Path | None = None,
                   coplanar_tol: float = DEFAULT_COPLANAR_TOL) -> IngestReport | None:
    """Ingest the app's label files that are not ingested yet (after a crash); None when there is no folder."""
    folder = labels_dir or wh.root / LABELS_DIR
    if not folder.is_dir():
        return None
    with lock:
        set_aside = set_aside_superseded(wh, folder)
        report = ingest_labels(wh, folder, coplanar_tol=coplanar_tol)
    report.warnings[:0] = set_aside
    return report


SUPERSEDED = ".superseded"
"""Suffix of a left label file whose items were answered again later (:func:`set_aside_superseded`)."""


def set_aside_superseded(wh: Warehouse, folder: Path) -> list[str]:
    """Rename ``<file>.superseded`` each label file of ``folder`` not ingested yet (left by a failed
    ingest) one of whose items has an answer in the warehouse given after it: ingested now, it would
    come in force over that newer answer (the newest ingested is in force). Returns a warning each.
    The warehouse's label files are read once per clip."""
    notes, known = [], {}
    for path in sorted(folder.rglob("*.json")):
        try:
            data = path.read_bytes()
            doc = json.loads(data)
            clip, task_id, kind = doc["clip"], doc["task_id"], doc["kind"]
            created = dt.datetime.fromisoformat(doc["created_at"])
            tracks = _tracks(kind, doc.get("answers", []))
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            continue  # ingest reports what it cannot read
        if not isinstance(clip, str) or created.tzinfo is None:
            continue
        if clip not in known:
            known[clip] = _ingested(wh, clip)
        if hashlib.sha256(data).hexdigest() in known[clip][0]:
            continue
        newer = _answered_since(known[clip][1], str(task_id), tracks, None, created_after=created)
        if newer is not None:
            aside = path.with_name(path.name + SUPERSEDED)
            path.rename(aside)
            notes.append(f"{path}: not ingested, its items were answered again at {newer['created_at']:%Y-%m-%d %H:%M:%S} "
                         f"(kept as {aside.name})")
    return notes
