"""An answer from a page in, a label file out, ingested: the same contract as ``cadestate labels ingest``.

:func:`submit` takes the JSON a page posts (a label document without ``format``/``created_at``;
``annotator`` is the app's), adds the header, validates it with :func:`tasks.human.labels.validate_label`
(the JSON Schema of its kind, then the warehouse rules), writes it atomically as
``<labels_dir>/<clip>/<task_id>.<UTC time>.<n>.json`` and ingests that file as validated
(:func:`tasks.human.label_ingest.ingest_validated`). A payload that fails validation raises
:class:`tasks.human.label_format.LabelError` naming the field, and nothing is written. The file is on
disk before ingest starts, so a crash mid-ingest loses nothing: :func:`ingest_pending` (run when the
app starts) ingests every file of the folder not ingested yet (ingest is idempotent by content).
"""

from __future__ import annotations

import json
import threading
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from schemas.labels import LABEL_FORMAT
from tasks.human.label_format import MAX_LABEL_BYTES, LabelError, one_line
from tasks.human.label_ingest import DEFAULT_COPLANAR_TOL, IngestReport, ingest_labels, ingest_validated
from tasks.human.labels import ClipFacts, utc_now, validate_label
from warehouse import Warehouse, atomic_write_bytes

LABELS_DIR = "labels"
"""Folder of the app's label files under the warehouse root (one subfolder per clip)."""


class IngestFailed(RuntimeError):
    """A valid answer was written but not ingested (a failed warehouse write): it stays on disk and
    is ingested when the app starts next (or by ``cadestate labels ingest <warehouse>/labels``)."""


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


def _not_ingested(path: Path, errors: list[str]) -> str:
    """The one-line message of :class:`IngestFailed` for ``path``."""
    why = one_line("; ".join(errors) or "unknown reason")
    return f"{path}: written but not ingested ({why}); it is ingested when the app starts next"


def submit(wh: Warehouse, payload: Any, *, annotator: str | None, lock: threading.Lock,
           labels_dir: Path | None = None, coplanar_tol: float = DEFAULT_COPLANAR_TOL) -> Submitted:
    """Validate, write and ingest one answer (module docstring). Raises LabelError (bad payload,
    nothing written) or :class:`IngestFailed` (written, not ingested)."""
    data = label_bytes(payload, annotator)
    folder_root = labels_dir or wh.root / LABELS_DIR
    with lock:  # one writer: file names, ingest times and the answer tables stay consistent
        facts = ClipFacts(wh)
        lf = validate_label("answer", facts=facts, data=data, max_bytes=MAX_LABEL_BYTES)
        path = _free_path(folder_root / lf.clip, lf.task_id)
        atomic_write_bytes(path, data)
        try:  # the file as validated (its bytes), not parsed again
            report = ingest_validated(wh, [replace(lf, path=path)], facts, coplanar_tol=coplanar_tol)
        except Exception as e:  # noqa: BLE001  (any failure past the write: the file waits for the next start)
            raise IngestFailed(_not_ingested(path, [f"{type(e).__name__}: {e}"])) from e
    if report.errors or not report.ingested:
        raise IngestFailed(_not_ingested(path, report.errors))
    return Submitted(wh.relative(path), lf.clip, lf.kind, lf.task_id, list(lf.warnings), dict(report.rows))


def ingest_pending(wh: Warehouse, lock: threading.Lock, labels_dir: Path | None = None,
                   coplanar_tol: float = DEFAULT_COPLANAR_TOL) -> IngestReport | None:
    """Ingest the app's label files that are not ingested yet (after a crash); None when there is no folder."""
    folder = labels_dir or wh.root / LABELS_DIR
    if not folder.is_dir():
        return None
    with lock:
        return ingest_labels(wh, folder, coplanar_tol=coplanar_tol)
