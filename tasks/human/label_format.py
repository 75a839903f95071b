"""Label and task documents: the format checks, no warehouse involved (:mod:`tasks.human.labels` adds those).

A document is checked in this order: at most :data:`MAX_LABEL_BYTES` (label files), UTF-8 JSON
without duplicate keys, every number finite and every string and key valid Unicode (no lone
surrogate: no table could store it), the kind's JSON Schema with integers written as integers
(``0``, not ``0.0``), a ``created_at`` that is a date-time in UTC's range, and, for
correspondences, the clicks of each key-frame on different 3D points (:func:`check_clicks`).
Every failure is a :class:`LabelError`: one line naming the file and the field as a JSON path,
e.g. ``labels/c1.json: $.answers[2].keyframes[0].points[3].x: not a finite number``.
"""

from __future__ import annotations

import datetime as dt
import functools
import json
import math
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import jsonschema
import numpy as np
import pyarrow as pa

from schemas.core import UTC_TS
from schemas.dataclass_json import from_json
from schemas.labels import (KINDS, LABEL_CLASSES, LABEL_FORMAT, TASK_CLASSES, TASK_FORMAT, CorrespondenceLabel, Label, Task,
                            json_schema)

MAX_LABEL_BYTES = 20_000_000
"""Largest label file accepted (20 MB; ``cadestate labels ingest/validate --max-mb``). A label
answers one task of one clip: a few kB, a few MB for the longest clips. Bigger files are refused
before they are read (a 200 MB file took 4 minutes and 2.8 GB of memory to ingest)."""

LABEL_FILES_WHAT = "label files (--max-mb raises it)"
"""What :data:`MAX_LABEL_BYTES` limits, as its error says."""

SAME_POINT_M = 1e-3
"""Two clicks of one key-frame whose 3D points are closer than this (1 mm) click the same model point."""

SAME_IMAGE_POINT = 1e-4
"""Two clicks of one key-frame whose image points are closer than this (normalised) click the same pixel."""

_UNPRINTABLE = re.compile(r"[\x00-\x1f\x7f-\x9f\u2028\u2029\ud800-\udfff]")


def one_line(text: str) -> str:
    """``text`` with control characters, line separators and lone surrogates escaped (``\\n``,
    ``\\ud800``): it prints as one line on any terminal."""
    return _UNPRINTABLE.sub(lambda m: m.group().encode("unicode_escape").decode("ascii"), text)


class LabelError(ValueError):
    """A task or label file that does not fit its format or the warehouse: one line naming the file
    and field (whatever the file's names and values hold)."""

    def __init__(self, message: str):
        super().__init__(one_line(message))


def json_path(parts: Iterator[Any] | list[Any]) -> str:
    """``$.answers[2].x`` from path elements (strings are keys, integers are indices)."""
    out = "$"
    for p in parts:
        out += f"[{p}]" if isinstance(p, int) else f".{p}"
    return out


def field_error(name: str, path: list, message: str) -> LabelError:
    """The error of file ``name`` at the field ``path`` (JSON path elements): one line naming both."""
    return LabelError(f"{name}: {json_path(path)}: {message}")


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict:
    keys = [k for k, _ in pairs]
    dup = sorted({k for k in keys if keys.count(k) > 1})
    if dup:
        raise ValueError(f"duplicate key {dup[0]!r}")
    return dict(pairs)


def read_limited(path: Path, max_bytes: int = MAX_LABEL_BYTES, what: str = LABEL_FILES_WHAT, root: str = "$") -> bytes:
    """The bytes of the file at ``path``, refused (without reading on) when over ``max_bytes``;
    errors name the file and its ``root`` (``$`` for JSON, ``/`` for XML)."""
    try:
        with open(path, "rb") as f:
            data = f.read(max_bytes + 1)
    except OSError as e:
        raise LabelError(f"{path}: {root}: cannot read: {e.strerror or e}") from None
    check_size(data, str(path), max_bytes, what, root)
    return data


def check_size(data: bytes, name: str, max_bytes: int = MAX_LABEL_BYTES, what: str = LABEL_FILES_WHAT, root: str = "$") -> None:
    """Refuse a document over ``max_bytes`` (the limit is stated, in MB, with ``what`` it is for)."""
    if len(data) > max_bytes:
        raise LabelError(f"{name}: {root}: larger than the limit of {max_bytes / 1e6:g} MB for {what}")


def parse_json(data: bytes, name: str) -> Any:
    """Parse bytes as UTF-8 JSON (a leading byte-order mark, as Windows editors write, dropped);
    errors name the file and line/column."""
    try:
        text = data.removeprefix(b"\xef\xbb\xbf").decode("utf-8")
    except UnicodeDecodeError as e:
        raise LabelError(f"{name}: $: not UTF-8 text (byte {e.start})") from None
    try:
        return json.loads(text, object_pairs_hook=_no_duplicates)
    except json.JSONDecodeError as e:
        raise LabelError(f"{name}: $: not valid JSON: {e.msg} (line {e.lineno}, column {e.colno})") from None
    except (ValueError, RecursionError) as e:
        raise LabelError(f"{name}: $: not valid JSON: {e}") from None


def _unicode_ok(text: str) -> bool:
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def unstorable(doc: Any, path: tuple = ()) -> tuple[tuple, str] | None:
    """Path and reason of the first value in ``doc`` that no table can store, else None: a NaN or
    infinite number (JSON allows neither; Python's parser reads them), or a key or string with a
    lone surrogate (a ``\\ud800`` escape: not Unicode text, so not UTF-8 either)."""
    if isinstance(doc, float) and not math.isfinite(doc):
        return path, "not a finite number"
    if isinstance(doc, str) and not _unicode_ok(doc):
        return path, "not valid Unicode (a lone surrogate such as \\ud800)"
    items = doc.items() if isinstance(doc, dict) else enumerate(doc) if isinstance(doc, list) else ()
    for k, v in items:
        if isinstance(k, str) and not _unicode_ok(k):
            return (*path, k), "not valid Unicode (a lone surrogate such as \\ud800) in a key"
        if (found := unstorable(v, (*path, k))) is not None:
            return found
    return None


def _strict_integer(checker: Any, instance: Any) -> bool:
    """JSON Schema's ``integer`` accepts ``0.0``; ids and timestamps must be written as integers."""
    return isinstance(instance, int) and not isinstance(instance, bool)


_StrictValidator = jsonschema.validators.extend(
    jsonschema.Draft202012Validator,
    type_checker=jsonschema.Draft202012Validator.TYPE_CHECKER.redefine("integer", _strict_integer))


@functools.cache
def _validator(kind: str, which: str) -> jsonschema.Draft202012Validator:
    return _StrictValidator(json_schema(kind, which))


def _schema_error(e: jsonschema.ValidationError) -> str:
    if e.validator == "additionalProperties":
        extra = sorted(set(e.instance) - set(e.schema.get("properties", {})))
        return f"unknown field(s) {', '.join(map(repr, extra))}"
    if e.validator == "required":
        return e.message.replace("is a required property", "is missing")
    if e.validator == "const":
        return f"must be {e.validator_value!r}, not {e.instance!r}"
    if e.validator == "anyOf":  # a nullable field: say which types fit
        kinds = [repr(b["type"]) if "type" in b else b.get("$ref", "?").rsplit("/", 1)[-1] for b in e.validator_value]
        return f"{e.instance!r} is not of type {' or '.join(kinds)}"[:200]
    if e.validator in ("minItems", "maxItems") and isinstance(e.instance, list):  # not the whole list's repr
        bound = "at least {} needed" if e.validator == "minItems" else "at most {} allowed"
        return f"{len(e.instance)} item(s), {bound.format(e.validator_value)}: {e.schema.get('description', '')}".rstrip(": ")
    message = e.message
    return message if len(message) <= 200 else message[:197] + "..."


def check_document(doc: Any, which: str, name: str) -> str:
    """Check ``doc`` against the JSON Schema of its kind; returns the kind."""
    if not isinstance(doc, dict):
        raise LabelError(f"{name}: $: expected a JSON object, not {type(doc).__name__}")
    try:
        bad = unstorable(doc)
    except RecursionError:
        raise LabelError(f"{name}: $: nested too deeply") from None
    if bad is not None:
        raise LabelError(f"{name}: {json_path(bad[0])}: {bad[1]}")
    expected = LABEL_FORMAT if which == "label" else TASK_FORMAT
    fmt = doc.get("format")
    if "format" not in doc:
        raise LabelError(f"{name}: $.format: missing: not a {which} file (one starts with \"format\": \"{expected}\")")
    if fmt != expected:
        other = {LABEL_FORMAT: " (a label file)", TASK_FORMAT: " (a task file)"}.get(fmt, "") if isinstance(fmt, str) else ""
        raise LabelError(f"{name}: $.format: must be {expected!r}, not {repr(fmt)[:60]}{other}")
    kind = doc.get("kind")
    if kind not in KINDS:
        raise LabelError(f"{name}: $.kind: must be one of {', '.join(KINDS)}, not {kind!r}")
    errors = list(_validator(kind, which).iter_errors(doc))
    if errors:
        e = jsonschema.exceptions.best_match(errors)
        more = f" (and {len(errors) - 1} more error(s))" if len(errors) > 1 else ""
        raise LabelError(f"{name}: {json_path(e.absolute_path)}: {_schema_error(e)}{more}")
    return kind


def check_time(value: str | None, field: str, name: str) -> dt.datetime | None:
    """An ISO 8601 date-time in UTC (naive: taken as UTC) that a ``timestamp[us, UTC]`` column can
    hold; None for None."""
    if value is None:
        return None
    try:
        t = dt.datetime.fromisoformat(value)
    except ValueError:
        raise LabelError(f"{name}: $.{field}: not an ISO 8601 date-time: {value[:60]!r}") from None
    try:
        utc = t.replace(tzinfo=dt.timezone.utc) if t.tzinfo is None else t.astimezone(dt.timezone.utc)
        pa.scalar(utc, UTC_TS)
    except (OverflowError, pa.ArrowException):
        raise LabelError(f"{name}: $.{field}: {value!r} is out of range in UTC (years 1 to 9999)") from None
    return utc


def parse_label(data: bytes, name: str) -> tuple[Label, dt.datetime | None]:
    """A label document's content and its ``created_at`` (UTC) after the format checks (no
    warehouse involved)."""
    doc = parse_json(data, name)
    kind = check_document(doc, "label", name)
    created_at = check_time(doc.get("created_at"), "created_at", name)
    return from_json(LABEL_CLASSES[kind], doc), created_at


def check_clicks(label: Label, name: str) -> list[str]:
    """The clicks of a correspondences label, key-frame by key-frame; returns warnings.

    Error: two clicks of one key-frame on the same 3D point (within :data:`SAME_POINT_M`). A model
    point has one image point, so the repeat is a slip or contradicts the first click, and the
    key-frame is left with fewer than the 4 different points the task asks for (four copies of one
    point pin a pose no more than one point does). The solver cannot tell such a key-frame from a
    good one, so it is refused here rather than solved into a wrong pose.

    Warning: two clicks at the same image point (within :data:`SAME_IMAGE_POINT`) on different 3D
    points. That is legal (two model points on one viewing ray, a near and a far corner lined up)
    but is most often a slip, so it is reported and kept."""
    if not isinstance(label, CorrespondenceLabel):
        return []
    warnings = []
    for i, a in enumerate(label.answers):
        for j, kf in enumerate(a.keyframes):
            xyz = np.array([p.xyz for p in kf.points], np.float64)
            xy = np.array([(p.x, p.y) for p in kf.points], np.float64)
            for k in range(1, len(xyz)):
                where = ["answers", i, "keyframes", j, "points", k]
                same = np.flatnonzero(np.linalg.norm(xyz[:k] - xyz[k], axis=1) < SAME_POINT_M)
                if same.size:
                    raise LabelError(f"{name}: {json_path([*where, 'xyz'])}: the same 3D point as points[{same[0]}]: "
                                     "each click of a key-frame must be a different point of the model")
                pixel = np.flatnonzero(np.linalg.norm(xy[:k] - xy[k], axis=1) < SAME_IMAGE_POINT)
                if pixel.size:
                    warnings.append(f"{name}: {json_path(where)}: the same image point as points[{pixel[0]}] for another "
                                    "3D point (two model points on one viewing ray?)")
    return warnings


@functools.lru_cache(maxsize=64)
def parse_task(data: bytes | str, name: str) -> Task:
    """A task document's content after the format checks. The result (frozen, of tuples) is kept
    for the latest documents: a label's checks, its ingest and the stage that reads its answers all
    parse the same task, and a large one takes tens of milliseconds to check. A document that fails
    raises each time."""
    doc = parse_json(data.encode() if isinstance(data, str) else data, name)
    kind = check_document(doc, "task", name)
    return from_json(TASK_CLASSES[kind], doc)
