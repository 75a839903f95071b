"""Fuzz: label files of the four kinds, mutated into invalid ones, through ``labels validate`` and
``labels ingest --no-resume``.

Every case starts from a valid label file (``tests/test_labels.py``'s ``good(kind)``) and makes it
invalid in one way: a wrong type, a whole number written as ``0.0``, a non-finite or huge number, a
bad or out-of-range date, a lone surrogate in a value or key, an unknown clip/task/track/frame/model/
class, a duplicate key, a missing required or an unknown field, a broken structure (too few or too
many clicks, repeated points, key-frames, tracks or boxes, empty answers, not an object), deep
nesting, truncation, a wrong encoding or bad bytes, or a size over the limit. Only invalid cases are
generated (a valid one would rightly change the warehouse). For each: both commands exit non-zero
with one ``error:`` line naming the file and no traceback, and the warehouse is unchanged.
Hypothesis runs derandomized (a fixed sequence of cases), without its example database or deadline.
"""

from __future__ import annotations

import copy
import shutil
from pathlib import Path
from typing import Any, Callable

import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from fuzz.harness import assert_clean_error, count_case, run_cli, warehouse_digest
from fuzz.json_mutations import BAD_BYTES, WRONG_TYPES, Dup, Raw, at, dumps, nodes, put_at
from schemas.labels import KINDS
from tasks.human.label_format import MAX_LABEL_BYTES
from test_labels import STAMPS, base_wh, good  # noqa: F401  (base_wh: the fixture)

CASES_PER_KIND = 50
"""Generated cases per label kind (each runs two commands, about 0.1 s in all)."""

FUZZ = settings(max_examples=CASES_PER_KIND, derandomize=True, database=None, deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

TASK_TRACKS = {"cad_selection": {0, 1, 2}, "correspondences": {0, 1}, "verification": {0, 1}}
REQUIRED = {"format", "kind", "task_id", "clip", "answers", "track_id", "cad_id", "verdict", "label", "boxes",
            "timestamp_us", "box", "points", "x", "y", "xyz", "keyframes", "is_mirrored"}
BAD_DATES = ["0001-01-01T00:00:00+14:00", "9999-12-31T23:59:59-14:00", "yesterday", "2026-13-01", "", "2026-02-30",
             "2026-01-01T25:00:00", "2026-01-01T00:00:00+25:00"]


def _pick(data: st.DataObject, candidates: list, what: str) -> Any:
    assert candidates, f"no {what} to mutate"
    return data.draw(st.sampled_from(candidates), label=what)


def _numbers(doc: dict) -> list[tuple[tuple, Any]]:
    return [(p, v) for p, v in nodes(doc) if isinstance(v, (int, float)) and not isinstance(v, bool)]


# ------------------------------------------------------------------------------ mutations: doc -> bytes

Mutation = Callable[[dict, str, st.DataObject], bytes]


def wrong_type(doc: dict, kind: str, data: st.DataObject) -> bytes:
    path, value = _pick(data, nodes(doc), "node")
    return dumps(put_at(doc, path, data.draw(st.sampled_from(WRONG_TYPES[type(value)])))).encode()


def float_for_integer(doc: dict, kind: str, data: st.DataObject) -> bytes:
    path, value = _pick(data, [(p, v) for p, v in nodes(doc) if p[-1] in ("track_id", "timestamp_us")], "integer")
    written = data.draw(st.sampled_from([f"{value}.0", f"{value}e0", f"{value}.000"]))
    return dumps(put_at(doc, path, Raw(written))).encode()


def non_finite(doc: dict, kind: str, data: st.DataObject) -> bytes:
    path, _ = _pick(data, _numbers(doc), "number")
    written = data.draw(st.sampled_from(["NaN", "Infinity", "-Infinity", "1e999", "-1e999"]))
    return dumps(put_at(doc, path, Raw(written))).encode()


def huge(doc: dict, kind: str, data: st.DataObject) -> bytes:
    """Every number of a label is bounded (unit box and image coordinates, 100 m CAD points,
    int32 track ids) or must be a frame of the clip."""
    path, _ = _pick(data, _numbers(doc), "number")
    value = data.draw(st.sampled_from(["1e308", "-1e308", "1" + "0" * 30, str(2**63), str(-2**63), str(2**31)]))
    return dumps(put_at(doc, path, Raw(value))).encode()


@st.composite
def _before_year_one(draw: st.DrawFn) -> str:
    """0001-01-01 at hh:mm with a UTC offset larger than that: before year 1 in UTC."""
    hour = draw(st.integers(0, 22))
    return f"0001-01-01T{hour:02d}:00:00+{draw(st.integers(hour + 1, 23)):02d}:00"


def bad_date(doc: dict, kind: str, data: st.DataObject) -> bytes:
    doc["created_at"] = data.draw(st.one_of(st.sampled_from(BAD_DATES), _before_year_one()))
    return dumps(doc).encode()


def surrogate(doc: dict, kind: str, data: st.DataObject) -> bytes:
    lone = chr(data.draw(st.integers(0xD800, 0xDFFF), label="surrogate"))
    if data.draw(st.booleans(), label="in a key"):
        path, obj = _pick(data, [(p, v) for p, v in [((), doc), *nodes(doc)] if isinstance(v, dict) and v], "object")
        key = data.draw(st.sampled_from(sorted(obj)))
        return dumps(put_at(doc, path, {(k[:1] + lone + k[1:] if k == key else k): v for k, v in obj.items()})).encode()
    path, text = _pick(data, [(p, v) for p, v in nodes(doc) if isinstance(v, str)], "string")
    i = data.draw(st.integers(0, len(text)))
    return dumps(put_at(doc, path, text[:i] + lone + text[i:])).encode()


def unknown_reference(doc: dict, kind: str, data: st.DataObject) -> bytes:
    """A clip, task, track, frame, model or class that the warehouse or the task does not have."""
    options = [(("clip",), st.sampled_from(["c2", "nope", "C1", "c1.x"])), (("task_id",), st.sampled_from(["c1.zz", "c2.mt", "x"]))]
    for path, value in nodes(doc):
        if path[-1] == "track_id":
            options.append((path, st.integers(3, 2**31 - 1).filter(lambda t: t not in TASK_TRACKS[kind])))
        elif path[-1] == "timestamp_us":
            options.append((path, st.integers(0, 10**12).filter(lambda t: t not in STAMPS)))
        elif path[-1] == "cad_id" and value is not None:
            options.append((path, st.sampled_from(["m9z", "m2a", "M0A"])))
        elif path[-1] == "label":
            options.append((path, st.sampled_from(["lamp", "Chair", "chair "])))
    path, values = _pick(data, options, "reference")
    return dumps(put_at(doc, path, data.draw(values))).encode()


def duplicate_key(doc: dict, kind: str, data: st.DataObject) -> bytes:
    path, obj = _pick(data, [(p, v) for p, v in [((), doc), *nodes(doc)] if isinstance(v, dict) and v], "object")
    pairs = list(obj.items())
    i, j = data.draw(st.integers(0, len(pairs) - 1)), data.draw(st.integers(0, len(pairs)))
    pairs.insert(j, (pairs[i][0], data.draw(st.sampled_from([pairs[i][1], 1, "x"]))))
    return dumps(put_at(doc, path, Dup(tuple(pairs)))).encode()


def missing_field(doc: dict, kind: str, data: st.DataObject) -> bytes:
    path = _pick(data, [(*p, k) for p, v in [((), doc), *nodes(doc)] if isinstance(v, dict) for k in v if k in REQUIRED],
                 "required field")
    del at(doc, path[:-1])[path[-1]]
    return dumps(doc).encode()


def unknown_field(doc: dict, kind: str, data: st.DataObject) -> bytes:
    path, obj = _pick(data, [(p, v) for p, v in [((), doc), *nodes(doc)] if isinstance(v, dict)], "object")
    obj["x_" + data.draw(st.text("abcdefghij_", max_size=8))] = data.draw(st.sampled_from([1, "v", None, []]))
    return dumps(doc).encode()


def _structures(doc: dict, kind: str) -> list[Callable[[dict], Any]]:
    """Edits that break a rule of the kind beyond types (counts, repeats, empties, the wrong kind)."""
    other = next(k for k in KINDS if k != kind)
    edits: list[Callable[[dict], Any]] = [
        lambda d: d.__setitem__("kind", other), lambda d: d.__setitem__("format", "cadestate-task/1"),
        lambda d: d.__setitem__("format", "cadestate-label/2")]
    if kind == "manual_track":
        boxes = lambda d: d["answers"][0]["boxes"]  # noqa: E731
        edits += [lambda d: boxes(d).clear(), lambda d: boxes(d)[0].__setitem__("box", [0.5, 0.5, 0.5, 0.8]),
                  lambda d: boxes(d)[1].__setitem__("box", [0.5, 0.7, 0.9, 0.3]),
                  lambda d: boxes(d).append({**boxes(d)[0], "box": [0.1, 0.1, 0.2, 0.2]})]
    else:
        edits += [lambda d: d["answers"].clear(), lambda d: d["answers"].append(copy.deepcopy(d["answers"][0]))]
    if kind == "correspondences":
        kf = lambda d: d["answers"][0]["keyframes"]  # noqa: E731
        edits += [lambda d: kf(d)[1]["points"].pop(),  # 3 clicks (key-frame 0 has 5)
                  lambda d: kf(d)[0]["points"].extend([{"x": 0.9, "y": 0.9, "xyz": [0.1, 0.2, 0.3]},
                                                       {"x": 0.8, "y": 0.9, "xyz": [0.2, 0.2, 0.3]}]),
                  lambda d: kf(d)[1].__setitem__("points", [kf(d)[1]["points"][0]] * 4),
                  lambda d: kf(d)[0]["points"][3].__setitem__("xyz", list(kf(d)[0]["points"][1]["xyz"])),
                  lambda d: kf(d).append(copy.deepcopy(kf(d)[0])), lambda d: kf(d).clear()]
    return edits


def broken_structure(doc: dict, kind: str, data: st.DataObject) -> bytes:
    _pick(data, _structures(doc, kind), "structure")(doc)
    return dumps(doc).encode()


def not_an_object(doc: dict, kind: str, data: st.DataObject) -> bytes:
    return dumps(data.draw(st.sampled_from([[doc], [], "x", None, 3, True]))).encode()


def deep_nesting(doc: dict, kind: str, data: st.DataObject) -> bytes:
    n = data.draw(st.sampled_from([100, 1_000, 5_000, 100_000]))
    text = data.draw(st.sampled_from(["[" * n, "[" * n + "]" * n, '{"a": ' * n + "1" + "}" * n]))
    return text.encode()


def truncated(doc: dict, kind: str, data: st.DataObject) -> bytes:
    text = dumps(doc)
    return text[:data.draw(st.integers(0, len(text) - 1))].encode()


def bad_encoding(doc: dict, kind: str, data: st.DataObject) -> bytes:
    """UTF-16/32, or bytes that are not UTF-8 inside a string (the annotator's; a UTF-8 byte-order mark is read)."""
    text = dumps(doc)
    how = data.draw(st.sampled_from(["utf-16", "utf-32", "utf-16-le", "bytes"]))
    if how == "bytes":
        return text.encode().replace(b'"ann"', b'"a' + data.draw(st.sampled_from(BAD_BYTES)) + b'n"')
    return text.encode(how)


def oversize(doc: dict, kind: str, data: st.DataObject) -> bytes:
    text = dumps(doc).encode()
    return text + b" " * (MAX_LABEL_BYTES - len(text) + 1 + data.draw(st.integers(0, 100)))


MUTATIONS: list[Mutation] = [wrong_type, float_for_integer, non_finite, huge, bad_date, surrogate, unknown_reference,
                             duplicate_key, missing_field, unknown_field, broken_structure, not_an_object, deep_nesting, truncated,
                             bad_encoding, oversize]


# ------------------------------------------------------------------------------ the suite

@pytest.fixture(scope="module")
def fuzz_root(base_wh, tmp_path_factory) -> Path:
    """A warehouse with a clip and one task of each kind; no case may change it."""
    root = tmp_path_factory.mktemp("fuzz_labels") / "wh"
    shutil.copytree(base_wh, root)
    return root


@pytest.mark.parametrize("kind", KINDS)
@FUZZ
@given(data=st.data())
def test_invalid_label_files_are_refused_cleanly(fuzz_root, tmp_path_factory, kind, data):
    before = warehouse_digest(fuzz_root)
    mutation = data.draw(st.sampled_from(MUTATIONS), label="mutation")
    event(mutation.__name__)  # --hypothesis-show-statistics: cases per mutation
    path = tmp_path_factory.mktemp("case") / f"{kind}.json"
    path.write_bytes(mutation(good(kind), kind, data))
    count_case("labels")
    for command in (["validate"], ["ingest", "--no-resume"]):
        result = run_cli("-w", str(fuzz_root), "labels", *command, str(path))
        assert_clean_error(result, mentions=str(path))
    assert warehouse_digest(fuzz_root) == before
    path.unlink()
