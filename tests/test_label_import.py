"""Tool imports refuse bad CVAT and Label Studio files with one line naming the file and the
element or field (issue 13), instead of a traceback or a label that says nothing is missing."""

from __future__ import annotations

import copy
import json

import pytest

from fuzz.harness import assert_clean_error, run_cli
from tasks.human.label_import import import_cvat, import_labelstudio
from tasks.human.labels import LabelError
from test_labels import CLIP, CVAT, base_wh, lwh, put  # noqa: F401  (fixtures)

LS = [{"id": 1, "data": {"video": f"/data/upload/{CLIP}.mp4"}, "annotations": [
    {"id": 3, "was_cancelled": False, "result": [
        {"id": "r1", "type": "videorectangle", "value": {"labels": ["chair"], "sequence": [
            {"frame": 1, "x": 10, "y": 10, "width": 40, "height": 40, "rotation": 0, "time": 0.0}]}}]}]}]


def ls(edit) -> list:
    doc = copy.deepcopy(LS)
    edit(doc)
    return doc


def result(doc: list) -> dict:
    return doc[0]["annotations"][0]["result"][0]


CVAT_CASES = [
    (CVAT.replace(f"<width>{320}</width>", "<width>abc</width>"),
     r"/annotations/meta/task/original_size/width: must be a number, not 'abc'"),
    (CVAT.replace(f"<height>{192}</height>", "<height>0</height>"), r"original_size/height: .*whole number from 1"),
    (CVAT.replace('frame="0"', 'frame="0.5"', 1), r"/annotations/track\[0\]/box\[0\]/@frame: must be a whole number"),
    (CVAT.replace('ybr="96"', 'ybr="nan"', 1), r"track\[0\]/box\[0\]/@ybr: must be a finite number"),
    (CVAT.replace('frame="0" ', "", 1), r"track\[0\]/box\[0\]/@frame: must be a number, not None"),
    (CVAT.replace(' label="chair"', ""), r"/annotations/track\[0\]/@label: must be a non-empty string"),
    (CVAT.replace('label="chair"', 'label="lamp"'), r"/annotations/track\[0\]: class 'lamp' is not one of the task's"),
    (CVAT.replace('encoding="utf-8"', 'encoding="no-such-codec"'), r": not a readable XML file: unknown encoding"),
    (CVAT[:200], r": not well-formed XML"),
    (CVAT.replace('frame="0"', 'frame="90"').replace('frame="3"', 'frame="93"'), r": none of its 1 track\(s\) has a box on a frame"),
]


@pytest.mark.parametrize("text, message", CVAT_CASES)
def test_bad_cvat_files_give_one_line_naming_the_element(lwh, tmp_path, text, message):
    path = put(tmp_path, "annotations.xml", text)
    with pytest.raises(LabelError, match=message) as e:
        import_cvat(lwh, path, CLIP, skip_sources=("file",))
    assert str(e.value).startswith(f"{path}: ")


LS_CASES = [
    (lambda d: result(d).__setitem__("value", [1]), r"\$\[0\]\.annotations\[0\]\.result\[0\]\.value: expected an object, not list"),
    (lambda d: result(d)["value"].__setitem__("labels", 5), r"result\[0\]\.value\.labels: expected a list, not int"),
    (lambda d: result(d)["value"].__setitem__("labels", [7]), r"value\.labels\[0\]: must be a non-empty string, not 7"),
    (lambda d: result(d)["value"].__setitem__("labels", ["ch\ud800"]), r"value\.labels\[0\]: not valid Unicode"),
    (lambda d: result(d)["value"]["sequence"][0].__setitem__("x", "abc"), r"sequence\[0\]\.x: must be a number, not 'abc'"),
    (lambda d: result(d)["value"]["sequence"][0].__setitem__("x", True), r"sequence\[0\]\.x: must be a number, not True"),
    (lambda d: result(d)["value"]["sequence"][0].__setitem__("width", 10**400), r"sequence\[0\]\.width: must be a number"),
    (lambda d: result(d)["value"]["sequence"][0].__setitem__("y", 1e308), r"sequence\[0\]: x, y, width and height are percent"),
    (lambda d: result(d)["value"]["sequence"][0].__setitem__("frame", 0), r"sequence\[0\]\.frame: must be a whole number from 1"),
    (lambda d: result(d)["value"].__setitem__("sequence", [3]), r"sequence\[0\]: expected an object, not int"),
    (lambda d: d[0].__setitem__("annotations", 5), r"\$\[0\]\.annotations: expected a list, not int"),
    (lambda d: d[0]["annotations"][0].__setitem__("was_cancelled", True), r"\$\[0\]\.annotations: no annotation that was not"),
    (lambda d: d[0]["annotations"][0].__setitem__("result", {"a": 1}), r"annotations\[0\]\.result: expected a list, not dict"),
    (lambda d: d[0]["annotations"][0]["result"].__setitem__(0, "x"), r"annotations\[0\]\.result\[0\]: expected an object, not str"),
    (lambda d: result(d).__setitem__("id", {"a": 1}), r"result\[0\]\.id: must be a string or an integer"),
    (lambda d: d.append(copy.deepcopy(d[0])), r"\$: expected one Label Studio task \(for clip 'c1'\), found 2"),
]


@pytest.mark.parametrize("edit, message", LS_CASES)
def test_bad_labelstudio_files_give_one_line_naming_the_field(lwh, tmp_path, edit, message):
    path = put(tmp_path, "ls.json", json.dumps(ls(edit)))
    with pytest.raises(LabelError, match=message) as e:
        import_labelstudio(lwh, path, CLIP)
    assert str(e.value).startswith(f"{path}: ") and len(str(e.value).splitlines()) == 1


def test_the_unchanged_examples_import(lwh, tmp_path):
    assert len(import_labelstudio(lwh, put(tmp_path, "ls.json", json.dumps(LS)), CLIP).document["answers"]) == 1
    assert len(import_cvat(lwh, put(tmp_path, "a.xml", CVAT), CLIP, skip_sources=("file",)).document["answers"]) == 1


@pytest.mark.parametrize("command, name, text", [
    ("import-cvat", "annotations.xml", CVAT.replace(f"<width>{320}</width>", "<width>abc</width>")),
    ("import-labelstudio", "ls.json", json.dumps(ls(lambda d: result(d)["value"].__setitem__("labels", 5)))),
    ("import-labelstudio", "ls.json", '[{"id": 1, "annotations": [{"result": [{"type": "videorectangle", "value": [1]}]}]}]'),
    ("import-cvat", "annotations.xml", "<annotations>" * 100_000),
    ("import-labelstudio", "ls.json", "[" * 100_000),
])
def test_cli_imports_refuse_with_one_error_line(lwh, tmp_path, command, name, text):
    path = put(tmp_path, name, text)
    res = run_cli("-w", str(lwh.root), "labels", command, str(path), "--clip", CLIP, "--out", str(tmp_path / "out"))
    assert_clean_error(res, mentions=str(path))
    assert not (tmp_path / "out").exists()


def test_cli_import_into_an_unwritable_folder(lwh, tmp_path):
    blocker = put(tmp_path, "file", "x")
    res = run_cli("-w", str(lwh.root), "labels", "import-cvat", str(put(tmp_path, "a.xml", CVAT)), "--clip", CLIP,
                  "--skip-source", "file", "--out", str(blocker / "sub"))
    assert_clean_error(res, mentions=f"{blocker / 'sub'}: cannot write the label file there")
