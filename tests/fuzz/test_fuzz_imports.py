"""Fuzz: CVAT video XML and Label Studio JSON exports, mutated into invalid ones, through
``labels import-cvat`` and ``labels import-labelstudio``.

Each case starts from a valid export (``tests/test_label_import.py``) and breaks it in one way the
importer must refuse: a number that is not one (text, NaN, infinite, huge, a fraction for a frame),
a missing attribute or field, a list or object of the wrong type, an empty, unknown or not-Unicode
label, no usable annotation, every box off the clip, a wrong root, truncation, a wrong or unknown
encoding, bad bytes, entity tricks, deep nesting. For each: a non-zero exit with one ``error:`` line
naming the file and no traceback, no label file written, and the warehouse unchanged.
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
from fuzz.json_mutations import BAD_BYTES, WRONG_TYPES, Raw, at, dumps, put_at
from test_label_import import LS
from test_labels import CLIP, CVAT, H, W, base_wh  # noqa: F401  (base_wh: the fixture)

CASES_PER_TOOL = 60
"""Generated cases per tool (each runs one command, about 0.05 s)."""

FUZZ = settings(max_examples=CASES_PER_TOOL, derandomize=True, database=None, deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

NOT_NUMBERS = ["abc", "", "nan", "inf", "-inf", "1e999", "0x10", "1,5", "--1"]
BAD_CLASSES = ["lamp", "Chair", "chair ", ""]
PARSED_BOXES = [(0, 0), (0, 2), (1, 0)]
"""(track, box) of the CVAT example's boxes that are read by default (key-frames, not outside)."""


# ------------------------------------------------------------------------------ CVAT: text -> bytes

def _box_attribute(text: str, track: int, box: int, attr: str, value: str | None) -> str:
    """``text`` with one attribute of one <box> set (None: removed)."""
    head, *tracks = text.split("<track ")
    boxes = tracks[track].split("<box ")
    before, after = boxes[box + 1].split(f'{attr}="', 1)
    rest = after.split('"', 1)[1]
    boxes[box + 1] = before + (f'{attr}="{value}"' if value is not None else "") + rest
    tracks[track] = "<box ".join(boxes)
    return "<track ".join([head, *tracks])


def cvat_box_number(data: st.DataObject) -> bytes:
    track, box = data.draw(st.sampled_from(PARSED_BOXES))
    attr = data.draw(st.sampled_from(["frame", "xtl", "ytl", "xbr", "ybr"]))
    bad = NOT_NUMBERS + [None] + (["-1", "0.5", "1e10", "1000000000"] if attr == "frame" else [])
    return _box_attribute(CVAT, track, box, attr, data.draw(st.sampled_from(bad))).encode()


def cvat_size(data: st.DataObject) -> bytes:
    tag, size = data.draw(st.sampled_from([("width", W), ("height", H)]))
    value = data.draw(st.sampled_from(NOT_NUMBERS + ["0", "-320", "1.5", "1e10"]))
    return CVAT.replace(f"<{tag}>{size}</{tag}>", f"<{tag}>{value}</{tag}>").encode()


def cvat_label(data: st.DataObject) -> bytes:
    track = data.draw(st.sampled_from(['label="chair"', 'label="table"']))
    bad = data.draw(st.sampled_from(BAD_CLASSES + [None]))
    return CVAT.replace(track, "" if bad is None else f'label="{bad}"').encode()


def cvat_off_the_clip(data: st.DataObject) -> bytes:
    text = CVAT
    for track, box in PARSED_BOXES:
        text = _box_attribute(text, track, box, "frame", str(data.draw(st.integers(10, 10**6))))
    return text.encode()


def cvat_structure(data: st.DataObject) -> bytes:
    end = CVAT.index("</annotations>") + len("</annotations>")
    return data.draw(st.sampled_from([
        CVAT[:data.draw(st.integers(0, end - 1))],
        CVAT.replace("<annotations>", "<annotation>").replace("</annotations>", "</annotation>"),
        CVAT.replace("</track>", "", 1),
        CVAT.replace('encoding="utf-8"', f'encoding="{data.draw(st.sampled_from(["no-such", "utf-16", "utf-32", "x"]))}"'),
        CVAT.replace("<annotations>", '<!DOCTYPE annotations [<!ENTITY e SYSTEM "file:///etc/hostname">]><annotations>&e;'),
        CVAT.replace("<version>", "<version>&undefined;"),
        "<annotations>" * data.draw(st.sampled_from([10, 10_000, 100_000])),
        "",
    ])).encode()


def cvat_bytes(data: st.DataObject) -> bytes:
    raw = CVAT.encode()
    how = data.draw(st.sampled_from(["utf-16", "latin-1", "bytes", "bomb"]))
    if how == "utf-16":
        return CVAT.encode("utf-16")  # says utf-8, is not
    if how == "latin-1":
        return CVAT.replace('label="chair"', 'label="chaise à porteurs"').encode("latin-1")
    if how == "bytes":
        return raw.replace(b'label="chair"', b'label="ch' + data.draw(st.sampled_from(BAD_BYTES)) + b'air"')
    ents = '<!ENTITY a0 "xxxxxxxxxx">' + "".join(f'<!ENTITY a{i} "' + f"&a{i - 1};" * 10 + '">' for i in range(1, 10))
    return CVAT.replace('<?xml version="1.0" encoding="utf-8"?>', f"<!DOCTYPE annotations [{ents}]>").replace(
        'label="chair"', 'label="&a9;"').encode()


CVAT_MUTATIONS: list[Callable[[st.DataObject], bytes]] = [cvat_box_number, cvat_size, cvat_label, cvat_off_the_clip,
                                                          cvat_structure, cvat_bytes]


# ------------------------------------------------------------------------------ Label Studio: doc -> bytes

RESULT = (0, "annotations", 0, "result", 0)
VALUE = (*RESULT, "value")
BOX = (*VALUE, "sequence", 0)

LS_TYPED = {(0, "annotations"): list, (0, "annotations", 0): dict, (0, "annotations", 0, "result"): list, RESULT: dict,
            VALUE: dict, (*VALUE, "labels"): list, (*VALUE, "labels", 0): str, (*VALUE, "sequence"): list, BOX: dict,
            (*BOX, "frame"): int, (*BOX, "x"): int, (*BOX, "y"): int, (*BOX, "width"): int, (*BOX, "height"): int}
"""Nodes of the example whose every wrong type is an error (an unused field, e.g. ``data`` or ``time``, may hold anything)."""


def _ls_doc() -> list:
    doc = copy.deepcopy(LS)
    doc[0]["annotations"][0]["result"][0]["value"]["sequence"].append(
        {"frame": 7, "x": 20, "y": 10, "width": 30, "height": 30, "rotation": 10, "time": 0.6})
    return doc


def ls_wrong_type(doc: list, data: st.DataObject) -> Any:
    path = data.draw(st.sampled_from(sorted(LS_TYPED, key=str)))
    return put_at(doc, path, data.draw(st.sampled_from(WRONG_TYPES[LS_TYPED[path]])))


def ls_number(doc: list, data: st.DataObject) -> Any:
    j = data.draw(st.integers(0, 1))
    field = data.draw(st.sampled_from(["frame", "x", "y", "width", "height", "rotation"]))
    bad = ["NaN", "Infinity", "-Infinity", "1" + "0" * 400, '"12"', "null" if field != "rotation" else '"x"']
    if field in ("frame", "x", "y", "width", "height"):
        bad += ["1e308", "-1e308"]
    if field == "frame":
        bad += ["0", "-3", "1.5", "1000000000"]
    return put_at(doc, (*VALUE, "sequence", j, field), Raw(data.draw(st.sampled_from(bad))))


def ls_missing(doc: list, data: st.DataObject) -> Any:
    path = data.draw(st.sampled_from([(*VALUE, "labels"), (*VALUE, "sequence"), (*RESULT, "value"),
                                      *[(*BOX, k) for k in ("frame", "x", "y", "width", "height")]]))
    del at(doc, path[:-1])[path[-1]]
    return doc


def ls_label(doc: list, data: st.DataObject) -> Any:
    lone = chr(data.draw(st.integers(0xD800, 0xDFFF)))
    bad = data.draw(st.sampled_from(BAD_CLASSES + [[], "chair" + lone, 7]))
    if bad == []:
        return put_at(doc, (*VALUE, "labels"), [])
    if data.draw(st.booleans()) and isinstance(bad, str) and bad.startswith("chair" + lone):
        return put_at(doc, (*RESULT, "id"), "r" + lone)
    return put_at(doc, (*VALUE, "labels", 0), bad)


def ls_annotations(doc: list, data: st.DataObject) -> Any:
    """No annotation left to use, several tasks for the clip, every box off the clip, or no task."""
    how = data.draw(st.sampled_from(["cancelled", "none", "two tasks", "off the clip", "no task", "id"]))
    if how == "cancelled":
        doc[0]["annotations"][0]["was_cancelled"] = data.draw(st.sampled_from([True, 1, "yes"]))
    elif how == "none":
        doc[0]["annotations"] = data.draw(st.sampled_from([[], [5], ["x"], [None]]))
    elif how == "two tasks":
        doc.append(copy.deepcopy(doc[0]))
    elif how == "off the clip":
        for j in (0, 1):
            at(doc, (*VALUE, "sequence", j))["frame"] = data.draw(st.integers(11, 10**6))
    elif how == "id":
        at(doc, RESULT)["id"] = data.draw(st.sampled_from([{"a": 1}, [1], 1.5, True, None]))
    else:
        return data.draw(st.sampled_from([[], 5, "x", None, [1, 2]]))
    return doc


def ls_text(doc: list, data: st.DataObject) -> bytes:
    """Truncated JSON, other encodings, bad bytes, deep nesting (bytes, not a document; a UTF-8
    byte-order mark is read, tests/test_labels.py)."""
    text = dumps(doc)
    how = data.draw(st.sampled_from(["truncated", "utf-16", "bytes", "deep"]))
    if how == "truncated":
        return text[:data.draw(st.integers(0, len(text) - 1))].encode()
    if how == "utf-16":
        return text.encode("utf-16")
    if how == "bytes":
        return text.encode().replace(b'"chair"', b'"ch' + data.draw(st.sampled_from(BAD_BYTES)) + b'air"')
    return ("[" * data.draw(st.sampled_from([10_000, 100_000]))).encode()


LS_MUTATIONS: list[Callable[[list, st.DataObject], Any]] = [ls_wrong_type, ls_number, ls_missing, ls_label, ls_annotations,
                                                            ls_text]


# ------------------------------------------------------------------------------ the suite

@pytest.fixture(scope="module")
def fuzz_root(base_wh, tmp_path_factory) -> Path:
    """A warehouse with a clip and its manual_track task (classes chair, table); no case may change it."""
    root = tmp_path_factory.mktemp("fuzz_imports") / "wh"
    shutil.copytree(base_wh, root)
    return root


def _check(root: Path, command: str, path: Path, data: bytes) -> None:
    before = warehouse_digest(root)
    path.write_bytes(data)
    count_case("imports")
    out = path.parent / "out"
    result = run_cli("-w", str(root), "labels", command, str(path), "--clip", CLIP, "--out", str(out))
    assert_clean_error(result, mentions=str(path))
    assert not out.exists() and warehouse_digest(root) == before


@FUZZ
@given(data=st.data())
def test_invalid_cvat_files_are_refused_cleanly(fuzz_root, tmp_path_factory, data):
    mutation = data.draw(st.sampled_from(CVAT_MUTATIONS), label="mutation")
    event(mutation.__name__)
    _check(fuzz_root, "import-cvat", tmp_path_factory.mktemp("case") / "annotations.xml", mutation(data))


@FUZZ
@given(data=st.data())
def test_invalid_labelstudio_files_are_refused_cleanly(fuzz_root, tmp_path_factory, data):
    mutation = data.draw(st.sampled_from(LS_MUTATIONS), label="mutation")
    event(mutation.__name__)
    made = mutation(_ls_doc(), data)
    _check(fuzz_root, "import-labelstudio", tmp_path_factory.mktemp("case") / "export.json",
           made if isinstance(made, bytes) else dumps(made).encode())
