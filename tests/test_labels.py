"""Task and label files of the human tasks: schemas, validation (with fuzzing), ingest, supersession, tool imports."""

from __future__ import annotations

import copy
import dataclasses
import datetime as dt
import json
import random
import shutil
import subprocess
import sys
from pathlib import Path

import jsonschema
import pyarrow as pa
import pytest
from typer.testing import CliRunner

from cadestate.cli import app
from conftest import table_rows
from schemas import TABLES
from schemas.labels import (KINDS, CadCandidate, CadSelectionItem, CadSelectionTask, CorrespondenceItem, CorrespondenceTask,
                            ExistingTrack, KeyframeView, ManualTrackTask, Pose, TimedBox, VerificationItem, VerificationTask,
                            json_schema, schema_file_name)
from tasks.human.label_import import write_label
from tasks.human.label_import_labelstudio import import_labelstudio
from tasks.human.label_import_cvat import import_cvat, read_cvat
from tasks.human.label_format import parse_task
from tasks.human.answers_in_force import answers_digest, current_answers, label_history
from tasks.human.label_ingest import ingest_labels, ingest_validated
from tasks.tracking.relations import same_as_statements
from tasks.human.labels import ClipFacts, LabelError, latest_task, new_task_id, validate_label, write_task
from warehouse import Warehouse

CLIP = "c1"
W, H = 320, 192
STAMPS = [i * 100_000 for i in range(10)]  # 10 frames, 10 fps
NOW = "2026-01-01T00:00:00+00:00"
CUBE = [[-0.5, -0.5, -0.5], [0.5, -0.5, -0.5], [0.5, 0.5, -0.5], [-0.5, 0.5, 0.5], [0.5, 0.5, 0.5]]
TOP = [[-0.4, 0.5, -0.3], [0.4, 0.5, -0.3], [0.4, 0.5, 0.3], [-0.4, 0.5, 0.3]]  # y = 0.5: co-planar, normal +Y


def _kf(ts: int, box=(0.2, 0.2, 0.6, 0.6)) -> KeyframeView:
    return KeyframeView(timestamp_us=ts, frame_index=ts // 100_000, image_path=f"media/frames/{CLIP}/v/{ts}.jpg", box=box)


def _candidates(ids: list[str]) -> tuple[CadCandidate, ...]:
    return tuple(CadCandidate(rank=i + 1, cad_id=c, library="lib", cad_class="chair", score=0.5, mesh_path=f"media/cad/{c}.glb",
                              render_paths=(f"media/cad_views/{c}/0.png",)) for i, c in enumerate(ids))


def _tasks() -> list:
    head = dict(clip=CLIP, created_at=NOW, image_size=(H, W))
    return [
        ManualTrackTask(task_id="c1.mt", **head, keyframes=tuple(_kf(t) for t in STAMPS[::2]), classes=("chair", "table"),
                        existing_tracks=(ExistingTrack(track_id=0, label="chair", boxes=(TimedBox(timestamp_us=0, box=(0.1, 0.1, 0.3, 0.3)),)),)),
        CadSelectionTask(task_id="c1.cs", **head, items=tuple(
            CadSelectionItem(track_id=t, label="chair", keyframes=(_kf(0), _kf(500_000)), candidates=_candidates([f"m{t}a", f"m{t}b"]))
            for t in (0, 1, 2))),
        CorrespondenceTask(task_id="c1.co", **head, items=tuple(
            CorrespondenceItem(track_id=t, label="chair", cad_id=f"m{t}a", library="lib", mesh_path=f"media/cad/m{t}a.glb",
                               render_paths=(), symmetry=1, keyframes=(_kf(0), _kf(300_000), _kf(600_000))) for t in (0, 1))),
        VerificationTask(task_id="c1.ve", **head, items=tuple(
            VerificationItem(track_id=t, label="chair", cad_id=f"m{t}a", mesh_path="m.glb",
                             pose=Pose(translation=(0, 0, 2), rotation=(1, 0, 0, 0), scale=(1, 1, 1), is_mirrored=False),
                             keyframes=(_kf(0),)) for t in (0, 1))),
    ]


@pytest.fixture(scope="module")
def base_wh(tmp_path_factory) -> Path:
    wh = Warehouse(tmp_path_factory.mktemp("labels") / "wh")
    wh.write("clips", CLIP, table_rows("clips", [{"clip": CLIP, "fps": 10.0, "width": W, "height": H, "duration_us": 1_000_000}]))
    wh.write("frames", CLIP, table_rows("frames", [{"clip": CLIP, "timestamp_us": t, "frame_index": i, "video_time_us": t + 1000,
                                               "width": W, "height": H} for i, t in enumerate(STAMPS)]))
    for task in _tasks():
        write_task(wh, task)
    return wh.root


@pytest.fixture
def lwh(base_wh, tmp_path) -> Warehouse:
    shutil.copytree(base_wh, tmp_path / "wh")
    return Warehouse(tmp_path / "wh")


def good(kind: str) -> dict:
    return copy.deepcopy(_good(kind))


def _good(kind: str) -> dict:
    head = {"format": "cadestate-label/1", "kind": kind, "clip": CLIP, "annotator": "ann", "created_at": NOW}
    if kind == "manual_track":
        return {**head, "task_id": "c1.mt", "answers": [{"label": "table", "boxes": [
            {"timestamp_us": 0, "box": [0.5, 0.5, 0.9, 0.8]}, {"timestamp_us": 400_000, "box": [0.5, 0.4, 0.9, 0.7]}]}]}
    if kind == "cad_selection":
        return {**head, "task_id": "c1.cs", "answers": [{"track_id": 0, "cad_id": "m0b"}, {"track_id": 1, "cad_id": None}]}
    if kind == "correspondences":
        pts = lambda xyz: [{"x": 0.1 + 0.1 * i, "y": 0.2 + 0.05 * i, "xyz": p} for i, p in enumerate(xyz)]  # noqa: E731
        return {**head, "task_id": "c1.co", "answers": [{"track_id": 0, "cad_id": "m0a", "is_mirrored": True, "keyframes": [
            {"timestamp_us": 0, "points": pts(CUBE)}, {"timestamp_us": 300_000, "points": pts(TOP)}]}]}
    return {**head, "task_id": "c1.ve", "answers": [{"track_id": 0, "verdict": "accept"}, {"track_id": 1, "verdict": "reject",
                                                                                             "comment": "off by a lot"}]}


def put(folder: Path, name: str, doc) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    path.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return path


# ------------------------------------------------------------------------------ schemas

@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("which", ["task", "label"])
def test_schemas_are_valid_and_published(kind, which):
    schema = json_schema(kind, which)
    jsonschema.Draft202012Validator.check_schema(schema)
    published = Path(__file__).parent.parent / "schemas" / "json" / schema_file_name(kind, which)
    assert json.loads(published.read_text()) == schema, "run `cadestate labels schema --write schemas/json`"


def test_good_labels_and_tasks(lwh, tmp_path):
    for kind in KINDS:
        lf = validate_label(put(tmp_path, f"{kind}.json", good(kind)), lwh)
        assert lf.kind == kind and lf.clip == CLIP and len(lf.sha256) == 64
        jsonschema.validate(good(kind), json_schema(kind, "label"))
    assert lwh.read("label_tasks").num_rows == 4
    write_task(lwh, _tasks()[1])  # the same task again: nothing new
    assert lwh.read("label_tasks").num_rows == 4
    task_file = lwh.root / lwh.read("label_tasks").to_pylist()[0]["path"]
    jsonschema.validate(json.loads(task_file.read_text()), json_schema(json.loads(task_file.read_text())["kind"], "task"))
    assert new_task_id("cad_selection", CLIP, "a") == new_task_id("cad_selection", CLIP, "a") != new_task_id("cad_selection", CLIP, "b")


def test_write_task_rejects_a_bad_task(lwh):
    bad = ManualTrackTask(task_id="c1.bad", clip=CLIP, created_at=NOW, image_size=(H, W), keyframes=(_kf(0, box=(0.1, 0.1, 1.5, 0.5)),),
                          existing_tracks=(), classes=())
    with pytest.raises(LabelError, match=r"\$\.keyframes\[0\]\.box\[2\]"):
        write_task(lwh, bad)


def _edit(kind, fn):
    doc = good(kind)
    fn(doc)
    return doc


def _third_keyframe(d: dict) -> None:
    """Answer 0 clicked on key-frame 600000 too (so that one left out leaves two: an answer on one
    key-frame is refused, one view gives no depth)."""
    d["answers"][0]["keyframes"].append({"timestamp_us": 600_000, "points": copy.deepcopy(d["answers"][0]["keyframes"][0]["points"])})


def _third_keyframe_then_first_left_out(d: dict) -> None:
    _third_keyframe(d)
    d["answers"][0]["keyframes"].pop(0)


def _many_then_one_again(d: dict) -> None:
    """600 chairs, one box each at its own place on one of the clip's frames, then answers[5]
    drawn again: a box shifted by a pixel on its frame, and one on a frame it has no box on."""
    d["answers"] = [{"label": "chair", "boxes": [{"timestamp_us": STAMPS[i % 10],
                                                  "box": [(i // 10) % 30 / 32, i // 300 / 4, (i // 10) % 30 / 32 + 0.03, i // 300 / 4 + 0.2]}]}
                    for i in range(600)]
    again = copy.deepcopy(d["answers"][5])
    again["boxes"][0]["box"][1] += 1 / W
    again["boxes"].append({"timestamp_us": STAMPS[9], "box": [0.9, 0.9, 0.95, 0.95]})
    d["answers"].append(again)


MALFORMED = [
    ("manual_track", _many_then_one_again, r"\$\.answers\[600\]: the same object as answers\[5\] \(class 'chair'"),
    ("correspondences", lambda d: d["answers"][0]["keyframes"][0]["points"][3].__setitem__("x", float("nan")),
     r"\$\.answers\[0\]\.keyframes\[0\]\.points\[3\]\.x: not a finite number"),
    ("correspondences", lambda d: d["answers"][0]["keyframes"][0]["points"][1].__setitem__("y", 1.2),
     r"\$\.answers\[0\]\.keyframes\[0\]\.points\[1\]\.y: 1.2 is greater than the maximum of 1"),
    ("correspondences", lambda d: d["answers"][0]["keyframes"][1]["points"][0]["xyz"].__setitem__(2, float("inf")),
     r"\$\.answers\[0\]\.keyframes\[1\]\.points\[0\]\.xyz\[2\]: not a finite number"),
    ("correspondences", lambda d: d["answers"][0]["keyframes"][1]["points"].pop(),
     r"\$\.answers\[0\]\.keyframes\[1\]\.points: 3 item\(s\), at least 4 needed: 4-6 correspondences\.$"),
    # clicks on one key-frame can never give a pose (pose's single_keyframe): refused, the item waits
    ("correspondences", lambda d: d["answers"][0]["keyframes"].pop(),
     r"\$\.answers\[0\]\.keyframes: 1 item\(s\), at least 2 needed: .*one view gives no depth\.$"),
    ("correspondences", lambda d: d["answers"][0]["keyframes"][1].__setitem__("timestamp_us", 123),
     r"\$\.answers\[0\]\.keyframes\[1\]\.timestamp_us: 123 is not a frame of the clip"),
    ("correspondences", lambda d: d["answers"][0]["keyframes"][1].__setitem__("timestamp_us", 0),
     r"\$\.answers\[0\]\.keyframes\[1\]\.timestamp_us: key-frame 0 is answered twice"),
    ("correspondences", lambda d: d["answers"][0]["keyframes"][1].__setitem__("timestamp_us", 900_000),
     r"\$\.answers\[0\]\.keyframes\[1\]\.timestamp_us: 900000 is not a key-frame of track 0 in task c1\.co "
     r"\(its key-frames: 0, 300000, 600000\)"),
    ("manual_track", lambda d: d["answers"].append(copy.deepcopy(d["answers"][0])),
     r"\$\.answers\[1\]: the same object as answers\[0\] \(class 'table', boxes overlapping by IoU >= 0\.9"),
    ("manual_track", lambda d: d["answers"].extend([{**d["answers"][0], "label": "chair", "source_id": "cvat:1"}] * 2),
     r"\$\.answers\[2\]\.source_id: 'cvat:1' is also answers\[1\]'s"),
    ("manual_track", lambda d: [d["answers"].append({"label": c, "boxes": [{"timestamp_us": 200_000, "box": [0.1, 0.1, 0.3, 0.3]}],
                                                     "same_as_track": 0}) for c in ("chair", "table")],
     r"\$\.answers\[2\]\.same_as_track: answers\[1\] is track 0 too: one drawn object per track"),
    ("correspondences", lambda d: d["answers"][0].__setitem__("cad_id", "m0b"), r"\$\.answers\[0\]\.cad_id: 'm0b' is not the task's model"),
    ("correspondences", lambda d: d["answers"][0].__setitem__("track_id", 7), r"\$\.answers\[0\]\.track_id: unknown track 7"),
    ("cad_selection", lambda d: d["answers"][0].__setitem__("cad_id", "m1a"), r"\$\.answers\[0\]\.cad_id: 'm1a' is not a candidate of track 0"),
    ("cad_selection", lambda d: d["answers"][1].__setitem__("track_id", 0), r"\$\.answers\[1\]\.track_id: track 0 is answered twice"),
    ("cad_selection", lambda d: d["answers"][0].__setitem__("track_id", "0"), r"\$\.answers\[0\]\.track_id: '0' is not of type 'integer'"),
    ("cad_selection", lambda d: d.__setitem__("clip", "nope"), r"\$\.clip: unknown clip 'nope'"),
    ("cad_selection", lambda d: d.__setitem__("task_id", "c1.zz"), r"\$\.task_id: unknown task 'c1.zz'"),
    ("cad_selection", lambda d: d.__setitem__("task_id", "c1.ve"), r"\$\.kind: task c1.ve is a verification task"),
    ("cad_selection", lambda d: d.__setitem__("kind", "cad"), r"\$\.kind: must be one of"),
    ("cad_selection", lambda d: d.pop("answers"), r"\$: 'answers' is missing"),
    ("cad_selection", lambda d: d.__setitem__("extra", 1), r"\$: unknown field\(s\) 'extra'"),
    ("cad_selection", lambda d: d.__setitem__("created_at", "yesterday"), r"\$\.created_at: not an ISO 8601"),
    ("verification", lambda d: d["answers"][0].__setitem__("verdict", "maybe"), r"\$\.answers\[0\]\.verdict: 'maybe' is not one of"),
    ("manual_track", lambda d: d["answers"][0]["boxes"][0].__setitem__("box", [0.5, 0.5, 0.4, 0.8]),
     r"\$\.answers\[0\]\.boxes\[0\]\.box: empty box"),
    ("manual_track", lambda d: d["answers"][0]["boxes"][1].__setitem__("box", [0.5, 0.5, 0.9, -0.1]),
     r"\$\.answers\[0\]\.boxes\[1\]\.box\[3\]: -0.1 is less than the minimum of 0"),
    ("manual_track", lambda d: d["answers"][0].__setitem__("label", "lamp"), r"\$\.answers\[0\]\.label: class 'lamp' is not one of"),
    # issue 13: values that crashed validation, or passed it and failed (or misled) later
    ("cad_selection", lambda d: d.__setitem__("created_at", "0001-01-01T00:00:00+14:00"),
     r"\$\.created_at: '0001-01-01T00:00:00\+14:00' is out of range in UTC"),
    ("verification", lambda d: d["answers"][1].__setitem__("comment", "a\ud800b"), r"\$\.answers\[1\]\.comment: not valid Unicode"),
    ("verification", lambda d: d.__setitem__("x\udc00", 1), r"\$\.x\\udc00: not valid Unicode"),
    ("cad_selection", lambda d: d["answers"][0].__setitem__("track_id", 0.0), r"\$\.answers\[0\]\.track_id: 0\.0 is not of type 'integer'"),
    ("correspondences", lambda d: d["answers"][0]["keyframes"][1]["points"][2]["xyz"].__setitem__(0, 1e308),
     r"\$\.answers\[0\]\.keyframes\[1\]\.points\[2\]\.xyz\[0\]: 1e\+308 is greater than the maximum of 100"),
    ("correspondences", lambda d: d["answers"][0]["keyframes"][1].__setitem__("points", [d["answers"][0]["keyframes"][1]["points"][0]] * 4),
     r"\$\.answers\[0\]\.keyframes\[1\]\.points\[1\]\.xyz: the same 3D point as points\[0\]"),
    # a track said to be the same object as itself: that, not a ring of one
    ("verification", lambda d: d["answers"][0].__setitem__("same_as_track", 0),
     r"\$\.answers\[0\]\.same_as_track: track 0 is not another track of task c1\.ve"),
    ("cad_selection", lambda d: d["answers"][1].update(same_as_track=1),
     r"\$\.answers\[1\]\.same_as_track: track 1 is not another track of task c1\.cs"),
]


@pytest.mark.parametrize("kind, edit, message", MALFORMED)
def test_malformed_labels_name_file_and_field(lwh, tmp_path, kind, edit, message):
    path = put(tmp_path / "labels", "x.json", json.dumps(_edit(kind, edit)))
    with pytest.raises(LabelError) as e:
        validate_label(path, lwh)
    assert str(e.value).startswith(f"{path}: ")
    assert __import__("re").search(message, str(e.value)), str(e.value)


@pytest.mark.parametrize("text, message", [
    ('{"a": 1, "a": 2}', "duplicate key 'a'"), ("{", "not valid JSON"), ("[1, 2]", "expected a JSON object"),
    (b"\xff\xfe", "not UTF-8"), ("", "not valid JSON"),
    ('{"clip_name": "c", "noise": {}}', r'\$\.format: missing: not a label file \(one starts with "format": "cadestate-label/1"\)'),
])
def test_unreadable_documents(tmp_path, text, message):
    path = tmp_path / "bad.json"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(LabelError, match=message):
        validate_label(path)


def test_size_limit_is_checked_before_reading(tmp_path):
    from tasks.human.label_format import MAX_LABEL_BYTES

    text = json.dumps(good("verification"))
    path = put(tmp_path, "big.json", text + " " * (MAX_LABEL_BYTES - len(text) + 1))
    with pytest.raises(LabelError, match=r"big\.json: \$: larger than the limit of 20 MB for label files"):
        validate_label(path)
    with pytest.raises(LabelError, match="limit of 0.0001 MB"):
        validate_label(put(tmp_path, "small.json", text), max_bytes=100)


def test_same_image_point_for_two_model_points_is_a_warning(lwh, tmp_path):
    doc = _edit("correspondences", lambda d: d["answers"][0]["keyframes"][0]["points"][2].update(x=0.1, y=0.2))
    lf = validate_label(put(tmp_path, "co.json", doc), lwh)
    assert lf.warnings == (f"{tmp_path / 'co.json'}: $.answers[0].keyframes[0].points[2]: the same image point as points[0] "
                           "for another 3D point (two model points on one viewing ray?)",)
    assert validate_label(put(tmp_path, "ok.json", good("correspondences")), lwh).warnings == ()


def test_errors_stay_on_one_line(tmp_path):
    path = put(tmp_path, "a\nb.json", _edit("verification", lambda d: d.__setitem__("kind", "x\u2028y")))
    with pytest.raises(LabelError) as e:
        validate_label(path)
    assert len(str(e.value).splitlines()) == 1 and "a\\nb.json" in str(e.value)


# ------------------------------------------------------------------------------ fuzzing

def _paths(doc, path=()):
    items = doc.items() if isinstance(doc, dict) else enumerate(doc) if isinstance(doc, list) else ()
    for k, v in items:
        yield (*path, k), v
        yield from _paths(v, (*path, k))


def _set(doc, path, value):
    for k in path[:-1]:
        doc = doc[k]
    if value is _DELETE:
        del doc[path[-1]]
    else:
        doc[path[-1]] = value


_DELETE = object()


def mutations(doc: dict, rng: random.Random, n: int):
    """(mutated text, must_fail) pairs: deletions, type changes, NaN, out-of-range values, truncation, byte flips."""
    text = json.dumps(doc)
    nodes = list(_paths(doc))
    for _ in range(n):
        path, value = rng.choice(nodes)
        d = copy.deepcopy(doc)
        op = rng.randrange(8)
        if op == 0:
            _set(d, path, _DELETE)
            yield json.dumps(d), False
        elif op == 1:
            _set(d, path, {"junk": 1})  # no field of any label accepts this object
            yield json.dumps(d), True
        elif op == 2 and isinstance(value, (int, float)) and not isinstance(value, bool):
            _set(d, path, rng.choice([float("nan"), float("inf"), -float("inf")]))
            yield json.dumps(d), True
        elif op == 3 and isinstance(value, (int, float)) and not isinstance(value, bool):
            _set(d, path, str(value))
            yield json.dumps(d), True
        elif op == 4 and isinstance(value, str):
            _set(d, path, 7)
            yield json.dumps(d), True
        elif op == 5 and isinstance(value, (int, float)) and not isinstance(value, bool):
            _set(d, path, rng.choice([-1, 2, 1e12, -0.5, 1.5]))
            yield json.dumps(d), False
        elif op == 6:
            yield text[:rng.randrange(len(text))], True
        else:
            i = rng.randrange(len(text))
            yield text[:i] + rng.choice('{}[]",:0a-') + text[i + 1:], False


@pytest.mark.parametrize("kind", KINDS)
def test_fuzzed_labels_raise_label_error_naming_the_file(lwh, tmp_path, kind):
    rng = random.Random(f"fuzz-{kind}")
    facts = ClipFacts(lwh)
    failed = 0
    for i, (text, must_fail) in enumerate(mutations(good(kind), rng, 60)):
        path = put(tmp_path, f"{kind}-{i}.json", text)
        try:
            validate_label(path, facts=facts)
        except LabelError as e:
            failed += 1
            assert str(e).startswith(f"{path}: $"), str(e)
        else:
            assert not must_fail, f"accepted: {text}"
    assert failed >= 30


# ------------------------------------------------------------------------------ ingest

def test_ingest_a_list_of_files_reads_only_those(lwh, tmp_path):
    d = tmp_path / "labels"
    chosen = [put(d, "sel.json", good("cad_selection")), put(d, "mt.json", good("manual_track"))]
    put(d, "bad.json", "not json")  # in the folder, not in the list
    report = ingest_labels(lwh, chosen)
    assert report.ok and sorted(report.ingested) == sorted(map(str, chosen))

def test_a_label_file_that_is_a_broken_link_is_reported_not_skipped(lwh, tmp_path):
    """A *.json of the folder that links to nothing (a synced folder's placeholder, a file moved
    away) was skipped in silence: the person's answers seemed ingested."""
    d = tmp_path / "labels"
    put(d, "sel.json", good("cad_selection"))
    (d / "gone.json").symlink_to(tmp_path / "elsewhere" / "mt.json")
    report = ingest_labels(lwh, d)
    assert report.ingested == [str(d / "sel.json")]
    assert report.errors == [f"{d / 'gone.json'}: $: cannot read: No such file or directory"]


def test_ingest_is_idempotent_and_reports_bad_files(lwh, tmp_path):
    d = tmp_path / "labels"
    for kind in KINDS:
        put(d, f"{kind}.json", good(kind))
    put(d, "bad.json", _edit("verification", lambda x: x["answers"][0].__setitem__("track_id", 9)))
    put(d / ".hidden", "skip.json", "not json")
    first = ingest_labels(lwh, d)
    assert len(first.ingested) == 4 and first.clips == [CLIP]
    assert first.errors == [f"{d / 'bad.json'}: $.answers[0].track_id: unknown track 9 (task c1.ve has tracks 0, 1)"]
    counts = {t: lwh.read(t).num_rows for t in ("label_files", "manual_track_labels", "cad_selection_labels",
                                                "correspondence_labels", "verification_labels", "correspondences")}
    assert counts == {"label_files": 4, "manual_track_labels": 2, "cad_selection_labels": 2, "correspondence_labels": 9,
                      "verification_labels": 2, "correspondences": 9}
    shutil.copy(d / "verification.json", d / "copy.json")
    again = ingest_labels(lwh, d)
    assert again.ingested == [] and len(again.duplicates) == 5 and again.clips == []
    assert {t: lwh.read(t).num_rows for t in counts} == counts
    corr = lwh.read("correspondences").to_pylist()
    assert {r["track_id"] for r in corr} == {"0"} and all(r["is_mirrored"] for r in corr)
    rows = lwh.read("correspondence_labels").to_pylist()
    assert {r["timestamp_us"]: (r["keyframe_coplanar"], r["keyframe_coplanar_axis"]) for r in rows} == {0: (False, -1), 300_000: (True, 1)}
    assert {r["track_coplanar_axis"] for r in rows} == {-1} and first.coplanar_keyframes == 1
    sel = lwh.read("cad_selection_labels").to_pylist()
    assert [(r["track_id"], r["cad_id"], r["rank"]) for r in sel] == [(0, "m0b", 2), (1, None, None)]


def test_ingest_validated_ingests_what_was_validated_once(lwh, tmp_path):
    """The app's path (cadestate.webapp.answers.submit): files validated once, then ingested as
    they are; the same rows as ingest_labels, and bytes ingested before are duplicates."""
    d = tmp_path / "labels"
    facts = ClipFacts(lwh)
    files = [validate_label(put(d, f"{kind}.json", good(kind)), facts=facts) for kind in KINDS]
    report = ingest_validated(lwh, files, facts)
    assert sorted(report.ingested) == sorted(str(f.path) for f in files) and report.clips == [CLIP]
    assert report.rows["correspondences"] == 9 and lwh.read("label_files").num_rows == 4
    again = ingest_validated(lwh, files[:1], ClipFacts(lwh))
    assert again.ingested == [] and again.duplicates == [str(files[0].path)]
    assert ingest_labels(lwh, d).duplicates == sorted(str(f.path) for f in files)
    # The app's answers get the warnings a file's ingest gives (a second session's clicks leaving out a key-frame).
    second = _edit("correspondences", lambda d: (d.__setitem__("created_at", "2026-01-02T00:00:00+00:00"),
                                                 _third_keyframe_then_first_left_out(d)))
    fewer = validate_label(put(d, "fewer.json", second), facts=ClipFacts(lwh))
    assert [w.split(": ", 1)[1][:40] for w in ingest_validated(lwh, [fewer], ClipFacts(lwh)).warnings] == [
        "its clicks for track 0 replace those of "]


def test_a_parsed_task_is_kept_and_a_bad_one_fails_every_time(lwh):
    text = lwh.read("label_tasks").to_pylist()[0]["path"]
    doc = (lwh.root / text).read_text()
    assert parse_task(doc, "task a") is parse_task(doc, "task a")
    bad = doc.replace('"format": "cadestate-task/1"', '"format": "cadestate-task/0"')
    assert bad != doc
    for _ in range(2):
        with pytest.raises(LabelError, match=r"task a: \$\.format: must be 'cadestate-task/1'"):
            parse_task(bad, "task a")


LABEL_TABLES = ("label_files", "manual_track_labels", "cad_selection_labels", "correspondence_labels", "verification_labels")


def test_one_bad_file_does_not_abort_the_batch(lwh, tmp_path):
    """Issue 13: a created_at out of range raised OverflowError and stopped the batch; a lone
    surrogate passed validation and failed at write time after the answers were written."""
    d = tmp_path / "labels"
    put(d, "a.json", _edit("cad_selection", lambda x: x.__setitem__("created_at", "0001-01-01T00:00:00+14:00")))
    put(d, "b.json", good("verification"))
    put(d, "c.json", _edit("manual_track", lambda x: x.__setitem__("annotator", "\ud800")))
    report = ingest_labels(lwh, d)
    assert report.ingested == [str(d / "b.json")] and report.clips == [CLIP]
    assert [e.split(": ")[:2] for e in report.errors] == [[str(d / "a.json"), "$.created_at"], [str(d / "c.json"), "$.annotator"]]
    assert {t: lwh.read(t).num_rows for t in LABEL_TABLES} == {"label_files": 1, "manual_track_labels": 0,
                                                              "cad_selection_labels": 0, "correspondence_labels": 0,
                                                              "verification_labels": 2}


@pytest.mark.parametrize("failing", ["cad_selection_labels", "label_files"])
def test_a_failed_write_stops_no_other_file(lwh, tmp_path, monkeypatch, failing):
    d = tmp_path / "labels"
    for name, kind in (("a", "cad_selection"), ("b", "verification")):
        put(d, f"{name}.json", good(kind))
    put(d, "c.json", _edit("cad_selection", lambda x: x.__setitem__("answers", x["answers"][1:])))
    doomed = validate_label(d / "a.json").sha256
    real = Warehouse.write

    def write(self, table, part, data):
        if table == failing and doomed in data.column("label_sha256").to_pylist():
            raise OSError(28, "No space left on device")
        return real(self, table, part, data)

    monkeypatch.setattr(Warehouse, "write", write)
    report = ingest_labels(lwh, d)
    assert report.errors == [f"{d / 'a.json'}: $: not ingested, writing failed: No space left on device"]
    assert sorted(report.ingested) == [str(d / "b.json"), str(d / "c.json")] and report.rows["label_files"] == 2
    assert doomed not in lwh.read("label_files").column("label_sha256").to_pylist()
    assert current_answers(lwh, "cad_selection", [CLIP]).to_pylist()[0]["track_id"] == 1  # c.json's only answer
    assert current_answers(lwh, "cad_selection", [CLIP]).num_rows == 1 and current_answers(lwh, "verification", [CLIP]).num_rows == 2


def test_supersession_keeps_history(lwh, tmp_path):
    ingest_labels(lwh, put(tmp_path / "a", "sel.json", good("cad_selection")))
    newer = _edit("cad_selection", lambda d: d.__setitem__("answers", [{"track_id": 0, "cad_id": "m0a"}]))  # partial: track 0 only
    ingest_labels(lwh, put(tmp_path / "b", "sel.json", newer))
    now = {r["track_id"]: r["cad_id"] for r in current_answers(lwh, "cad_selection", [CLIP]).to_pylist()}
    assert now == {0: "m0a", 1: None}
    assert lwh.read("cad_selection_labels").num_rows == 3  # both files stay in the history
    hist = label_history(lwh).to_pylist()
    assert [h["superseded"] for h in hist] == [False, False]  # the first still answers track 1
    ingest_labels(lwh, put(tmp_path / "c", "sel.json", _edit("cad_selection", lambda d: d["answers"].reverse())))
    assert [h["superseded"] for h in label_history(lwh).to_pylist()] == [True, True, False]
    # manual tracks: the newer label replaces the whole answer, even an empty one (nothing missing)
    ingest_labels(lwh, put(tmp_path / "d", "mt.json", good("manual_track")))
    ingest_labels(lwh, put(tmp_path / "e", "mt.json", _edit("manual_track", lambda d: d.__setitem__("answers", []))))
    assert current_answers(lwh, "manual_track", [CLIP]).num_rows == 0 and lwh.read("manual_track_labels").num_rows == 2
    # correspondences: the newest answer to the task, track by track, is what the pose stage reads
    ingest_labels(lwh, put(tmp_path / "f", "co.json", good("correspondences")))
    flipped = _edit("correspondences", lambda d: (d["answers"][0].__setitem__("is_mirrored", False),
                                                  d["answers"][0]["keyframes"][0]["points"].pop()))
    ingest_labels(lwh, put(tmp_path / "g", "co.json", flipped))
    corr = lwh.read("correspondences").to_pylist()
    assert len(corr) == 8 and not any(r["is_mirrored"] for r in corr)
    assert lwh.read("correspondence_labels").num_rows == 17


def test_answers_digest_follows_the_answers_not_the_files(lwh, tmp_path):
    before = answers_digest(lwh, "verification", CLIP)
    ingest_labels(lwh, put(tmp_path / "a", "v.json", good("verification")))
    first = answers_digest(lwh, "verification", CLIP, "c1.ve")
    ingest_labels(lwh, put(tmp_path / "b", "v.json", _edit("verification", lambda d: d.__setitem__("annotator", "other"))))
    assert answers_digest(lwh, "verification", CLIP, "c1.ve") == first != before
    ingest_labels(lwh, put(tmp_path / "c", "v.json", _edit("verification", lambda d: d["answers"][0].__setitem__("verdict", "reject"))))
    assert answers_digest(lwh, "verification", CLIP, "c1.ve") != first


def test_same_batch_is_ordered_by_created_at(lwh, tmp_path):
    d = tmp_path / "labels"
    put(d, "a.json", _edit("verification", lambda x: (x.__setitem__("created_at", "2026-03-02T00:00:00Z"), x["answers"].pop())))
    put(d, "b.json", _edit("verification", lambda x: (x.__setitem__("created_at", "2026-03-01T00:00:00Z"),
                                                        x["answers"][0].__setitem__("verdict", "reject"), x["answers"].pop())))
    ingest_labels(lwh, d)
    assert [r["accepted"] for r in current_answers(lwh, "verification", [CLIP], task_id="c1.ve").to_pylist()] == [True]


def test_answers_without_a_commit_record_are_ignored(lwh, tmp_path):
    path = put(tmp_path, "v.json", good("verification"))
    lf = validate_label(path, lwh)
    from tasks.human.label_ingest import answer_rows

    orphan = answer_rows(lf, ClipFacts(lwh), dt.datetime(2026, 1, 1, tzinfo=dt.timezone.utc))  # a crash before label_files
    lwh.write("verification_labels", CLIP, pa.Table.from_pylist(orphan, schema=TABLES["verification_labels"].schema))
    assert current_answers(lwh, "verification", [CLIP]).num_rows == 0
    assert len(ingest_labels(lwh, path).ingested) == 1
    assert current_answers(lwh, "verification", [CLIP]).num_rows == 2


def test_answers_left_without_a_commit_record_are_removed_by_the_next_ingest(lwh, tmp_path):
    """An ingest whose ``label_files`` write fails (as one killed before it) leaves the answers,
    effort and relations it wrote; they were ignored in force but seen by SQL, for ever. The clip's
    next ingest removes them: the tables, and the views over them, hold committed rows only."""
    from warehouse.catalog import connect

    doc = good("verification")
    doc["answers"][0].update(seconds=4.0, same_as_track=1)
    path = put(tmp_path / "in", "v.json", doc)
    block = lwh.partition_dir("label_files", CLIP)
    block.parent.mkdir(parents=True, exist_ok=True)
    block.write_text("")  # the commit record's folder cannot be made: the write fails after the answers' writes
    report = ingest_labels(lwh, path)
    assert report.ingested == [] and "writing failed" in report.errors[0]
    uncommitted = {t: lwh.read(t, [CLIP]).num_rows for t in ("verification_labels", "label_effort", "track_relations")}
    assert uncommitted == {"verification_labels": 2, "label_effort": 1, "track_relations": 1}
    block.unlink()
    report = ingest_labels(lwh, path)
    assert report.ingested == [str(path)] and "removed 4 label row(s)" in report.warnings[0]
    con = connect(lwh)
    for table in uncommitted:
        assert lwh.read(table, [CLIP]).num_rows == uncommitted[table]
        assert con.execute(f"SELECT count(*) FROM {table}").fetchone()[0] == uncommitted[table]
    assert ingest_labels(lwh, path).warnings == []


# ------------------------------------------------------------------------------ tool imports

CVAT = f"""<?xml version="1.0" encoding="utf-8"?>
<annotations>
  <version>1.1</version>
  <meta><task><id>4</id><name>c1</name><size>10</size><mode>interpolation</mode>
    <original_size><width>{W}</width><height>{H}</height></original_size></task></meta>
  <track id="0" label="chair" source="manual">
    <box frame="0" xtl="32" ytl="19.2" xbr="160" ybr="96" outside="0" occluded="0" keyframe="1" z_order="0"></box>
    <box frame="1" xtl="33" ytl="19.2" xbr="161" ybr="96" outside="0" occluded="0" keyframe="0" z_order="0"></box>
    <box frame="3" xtl="-2" ytl="0" xbr="64" ybr="96" outside="0" occluded="1" keyframe="1" z_order="0"></box>
    <box frame="5" xtl="32" ytl="19.2" xbr="160" ybr="96" outside="1" occluded="0" keyframe="1" z_order="0"></box>
  </track>
  <track id="1" label="table" source="file">
    <box frame="2" xtl="0" ytl="0" xbr="10" ybr="10" outside="0" occluded="0" keyframe="1" z_order="0"></box>
  </track>
</annotations>
"""


def test_cvat_import(lwh, tmp_path):
    xml = put(tmp_path, "annotations.xml", CVAT)
    result = import_cvat(lwh, xml, CLIP, skip_sources=("file",))
    doc = result.document
    assert doc["task_id"] == "c1.mt" and doc["kind"] == "manual_track" and len(doc["answers"]) == 1
    a = doc["answers"][0]
    assert a["label"] == "chair" and a["source_id"] == "cvat:0"
    assert [b["timestamp_us"] for b in a["boxes"]] == [0, 300_000]
    assert a["boxes"][0]["box"] == pytest.approx([0.1, 0.1, 0.5, 0.5]) and a["boxes"][1]["box"] == pytest.approx([0.0, 0.0, 0.5, 0.2])
    assert len(import_cvat(lwh, xml, CLIP, keyframes_only=False).document["answers"][0]["boxes"]) == 3
    out = write_label(doc, tmp_path / "labels", "c1.cvat")
    report = ingest_labels(lwh, out.parent)
    assert report.ok and lwh.read("manual_track_labels").num_rows == 2
    with pytest.raises(LabelError, match="not a CVAT annotations file"):
        import_cvat(lwh, put(tmp_path, "x.xml", "<root/>"), CLIP)
    with pytest.raises(LabelError, match=r"box\[0\]/@xtl: must be a number"):
        import_cvat(lwh, put(tmp_path, "y.xml", CVAT.replace('xtl="32"', 'xtl="abc"', 1)), CLIP)


def test_labelstudio_import(lwh, tmp_path):
    seq = [{"frame": 1, "enabled": True, "rotation": 0, "x": 10, "y": 10, "width": 40, "height": 40, "time": 0.0},
           {"frame": 4, "enabled": False, "rotation": 90, "x": 50, "y": 10, "width": 10, "height": 20, "time": 0.3}]
    export = [{"id": 1, "data": {"video": f"/data/upload/{CLIP}.mp4"}, "annotations": [
        {"id": 2, "was_cancelled": True, "result": []},
        {"id": 3, "was_cancelled": False, "updated_at": "2026-01-02", "result": [
            {"id": "r1", "type": "videorectangle", "from_name": "box", "to_name": "video",
             "value": {"framesCount": 10, "duration": 1.0, "sequence": seq, "labels": ["desk"]}},
            {"id": "r2", "type": "labels", "value": {}}]}]},
        {"id": 9, "data": {"video": "/data/upload/other.mp4"}, "annotations": []}]
    path = put(tmp_path, "ls.json", export)
    for mode in ("frames", "video"):
        doc = import_labelstudio(lwh, path, CLIP, "c1.mt", frame_map=mode, label_map={"desk": "table"}).document
        (a,) = doc["answers"]
        assert a["label"] == "table" and a["source_id"] == "labelstudio:r1"
        assert [b["timestamp_us"] for b in a["boxes"]] == [0, 300_000]
        assert a["boxes"][0]["box"] == pytest.approx([0.1, 0.1, 0.5, 0.5])
        # rotated 90 deg about its top-left corner (160, 19.2) px: 32 x 38.4 px -> x in [121.6, 160], y in [19.2, 51.2]
        assert a["boxes"][1]["box"] == pytest.approx([19.2 / H, 121.6 / W, 51.2 / H, 0.5])
    with pytest.raises(LabelError, match="class 'desk' is not one of"):
        import_labelstudio(lwh, path, CLIP)


def test_cvat_exports_of_the_wrong_kind_or_task_are_refused_and_rotated_boxes_bounded(lwh, tmp_path):
    images = put(tmp_path, "img.xml", '<annotations><version>1.1</version><image id="0" name="f0.jpg" width="320" '
                 'height="192"><box label="chair" xtl="1" ytl="1" xbr="9" ybr="9"/></image></annotations>')
    with pytest.raises(LabelError, match=r"img.xml: /annotations/image\[0\]/box\[0\]: a 'CVAT for images' export"):
        import_cvat(lwh, images, CLIP)
    video = put(tmp_path, "video.xml", CVAT.replace("<size>10</size>", "<size>30</size>"))  # the task was made on the video
    with pytest.raises(LabelError, match=r"video.xml: /annotations/meta/task/size: the tool showed 30 frames and clip 'c1' "
                                         r"has 10: was the task made on the video\? \(--frame-map video\)"):
        import_cvat(lwh, video, CLIP, skip_sources=("file",))
    assert import_cvat(lwh, video, CLIP, skip_sources=("file",), frame_map="video").document["answers"]
    turned = put(tmp_path, "rot.xml", CVAT.replace('xtl="32" ytl="19.2" xbr="160" ybr="96"',
                                                     'xtl="32" ytl="19.2" xbr="160" ybr="96" rotation="90"', 1))
    box = import_cvat(lwh, turned, CLIP, skip_sources=("file",)).document["answers"][0]["boxes"][0]["box"]
    # 128 x 76.8 px about its centre (96, 57.6), turned a quarter: 76.8 x 128 px
    assert box == pytest.approx([max(0.0, (57.6 - 64) / H), (96 - 38.4) / W, (57.6 + 64) / H, (96 + 38.4) / W])
    project = CVAT.replace("<meta><task><id>4</id><name>c1</name><size>10</size>",
                           "<meta><project><tasks><task><id>4</id><name>c1</name><size>10</size></task>"
                           "<task><id>8</id><name>c10</name><size>10</size></task></tasks></project><task><id>4</id><name>c1</name><size>10</size>")
    project = project.replace('<track id="0" label="chair" source="manual">', '<track id="0" label="chair" source="manual" task_id="4">')
    project = project.replace('<track id="1" label="table" source="file">', '<track id="1" label="table" source="manual" task_id="8">')
    doc = import_cvat(lwh, put(tmp_path, "project.xml", project), CLIP).document
    assert [a["source_id"] for a in doc["answers"]] == ["cvat:0"]  # c10's track left out, c1 not taken for c10
    with pytest.raises(LabelError, match=r"a project export of 2 tasks \('c1', 'c10'\), none of which names clip 'c2'"):
        read_cvat(tmp_path / "project.xml", (W, H), clip="c2")


def test_labelstudio_frames_not_times_and_the_clip_it_names(lwh, tmp_path):
    """Label Studio writes a 1-based frame f at time f / fps: the frame is read, the time is not."""
    seq = [{"frame": 1, "x": 10, "y": 10, "width": 40, "height": 40, "time": 0.1},
           {"frame": 4, "x": 10, "y": 10, "width": 40, "height": 40, "time": 0.4}]
    task = {"id": 1, "data": {"video": "/data/upload/3/1f2e-kitchen.mp4"}, "annotations": [{"id": 3, "result": [
        {"id": "r1", "type": "videorectangle", "value": {"framesCount": 10, "sequence": seq, "labels": ["chair"]}}]}]}
    path = put(tmp_path, "ls.json", [task])
    result = import_labelstudio(lwh, path, CLIP, frame_map="video")
    assert [b["timestamp_us"] for b in result.document["answers"][0]["boxes"]] == [0, 300_000]
    assert result.warnings == [f"{path}: $[0].data: names no clip 'c1' ({{\"video\": \"/data/upload/3/1f2e-kitchen.mp4\"}}): "
                               "is this the clip's export?"]
    two = put(tmp_path, "two.json", [task | {"data": {"video": "/data/upload/c1.mp4"}}, task | {"id": 2, "data": {"video": "c10.mp4"}}])
    assert import_labelstudio(lwh, two, CLIP).warnings == []  # c1, not c10
    longer = put(tmp_path, "long.json", [task | {"data": {"video": "c1.mp4"}, "annotations": [{"id": 3, "result": [
        {"id": "r1", "type": "videorectangle", "value": {"framesCount": 30, "sequence": seq, "labels": ["chair"]}}]}]}])
    with pytest.raises(LabelError, match=r"long.json: \$\[0\].annotations\[0\].result\[0\].value.framesCount: the tool "
                                         "showed 30 frames"):
        import_labelstudio(lwh, longer, CLIP)
    bom = tmp_path / "bom.json"
    bom.write_bytes(b"\xef\xbb\xbf" + two.read_bytes())
    assert import_labelstudio(lwh, bom, CLIP).document["answers"]
    with pytest.raises(LabelError, match=r"^\S+nothing.json: \$: expected one Label Studio task \(for clip 'c1'\), found 0$"):
        import_labelstudio(lwh, put(tmp_path, "nothing.json", []), CLIP)


def test_a_label_file_with_a_bom_is_read_and_answers_naming_each_other_are_refused(lwh, tmp_path):
    path = tmp_path / "v.json"
    path.write_bytes(b"\xef\xbb\xbf" + json.dumps(good("verification")).encode())
    lf = validate_label(path, lwh)
    assert lf.kind == "verification" and json.loads(lf.document) == good("verification")  # the document kept is JSON
    ring = _edit("cad_selection", lambda x: x.__setitem__("answers", [
        {"track_id": 0, "cad_id": None, "same_as_track": 1}, {"track_id": 1, "cad_id": None, "same_as_track": 2},
        {"track_id": 2, "cad_id": None, "same_as_track": 0}]))
    with pytest.raises(LabelError, match=r"\$.answers\[0\].same_as_track: tracks 0 -> 1 -> 2 -> 0 each name the next as "
                                         "the same object"):
        validate_label(put(tmp_path, "ring.json", ring), lwh)


# ------------------------------------------------------------------------------ command line

def test_cli_schema_validate_ingest(lwh, tmp_path):
    runner = CliRunner()
    w = ["-w", str(lwh.root)]
    result = runner.invoke(app, ["labels", "schema", "correspondences"])
    assert result.exit_code == 0 and json.loads(result.output) == json_schema("correspondences", "label")
    result = runner.invoke(app, ["labels", "schema", "--file", "task"])
    assert result.exit_code == 0 and set(json.loads(result.output)) == {f"{k}.task" for k in KINDS}
    d = tmp_path / "labels"
    put(d, "ok.json", good("verification"))
    bad = put(d, "bad.json", _edit("verification", lambda x: x["answers"][0].__setitem__("verdict", 1)))
    result = runner.invoke(app, [*w, "labels", "validate", str(d / "ok.json"), str(bad)])
    assert result.exit_code == 1 and "ok (verification" in result.output
    for args in (["validate"], ["ingest", "--no-resume"], ["validate", str(d / "ok.json")]):  # as the shell sees it
        done = subprocess.run([sys.executable, "-m", "cadestate", *w, "labels", *args, str(d / "nothing.json")],
                              capture_output=True, text=True)
        assert done.returncode == 2 and "nothing.json: no such label file or folder" in done.stderr, (args, done.stderr)
        assert ("ok (verification" in done.stdout) == (len(args) == 2 and args[0] == "validate"), done.stdout  # others checked
    result = runner.invoke(app, [*w, "labels", "ingest", "--no-resume", str(d)])
    assert result.exit_code == 1 and "1 label file(s) ingested" in result.output and "clips with new labels: c1" in result.output
    xml = put(tmp_path, "annotations.xml", CVAT)
    result = runner.invoke(app, [*w, "labels", "import-cvat", str(xml), "--clip", CLIP, "--out", str(d), "--skip-source", "file"])
    assert result.exit_code == 0, result.output
    from cadestate.lineage import file_sha256

    written = d / f"c1.annotations.{file_sha256(xml)[:8]}.cvat.json"  # two CVAT exports, both annotations.xml, both kept
    assert validate_label(written, lwh).kind == "manual_track"


def test_cli_ingest_reports_every_file_on_one_line_each(lwh, tmp_path):
    from fuzz.harness import run_cli

    d = tmp_path / "labels"
    put(d, "a.json", _edit("cad_selection", lambda x: x.__setitem__("created_at", "0001-01-01T00:00:00+14:00")))
    put(d, "b.json", good("verification"))
    put(d, "c\nd.json", _edit("manual_track", lambda x: x.__setitem__("annotator", "\ud800")))
    put(d, "e.json", _edit("correspondences", lambda x: x["answers"][0]["keyframes"][0]["points"][2].update(x=0.1, y=0.2)))
    result = run_cli("-w", str(lwh.root), "labels", "ingest", "--no-resume", str(d))
    assert result.code == 1
    lines = result.stderr.splitlines()
    assert [ln.split(": ", 2)[:2] for ln in lines] == [["warning", str(d / "e.json")], ["error", str(d / "a.json")],
                                                        ["error", f"{d}/c\\nd.json"]]
    assert {f"{d / 'b.json'}: ingested", f"{d / 'e.json'}: ingested"} <= set(result.stdout.splitlines())
    again = run_cli("-w", str(lwh.root), "labels", "ingest", "--no-resume", str(d / "b.json"))
    assert again.code == 0 and f"{d / 'b.json'}: already ingested" in again.stdout.splitlines()
    both = run_cli("-w", str(lwh.root), "labels", "ingest", "--no-resume", str(d / "b.json"), str(d / "e.json"))  # as validate takes them
    assert both.code == 0 and both.stdout.splitlines()[:2] == [f"{d / 'b.json'}: already ingested", f"{d / 'e.json'}: already ingested"]
    gone = run_cli("-w", str(lwh.root), "labels", "ingest", "--no-resume", str(d / "b.json"), str(d / "gone.json"))
    assert gone.code == 2 and "gone.json: no such label file or folder" in gone.stderr and gone.stdout == "", gone
    (tmp_path / "none").mkdir()
    nothing = run_cli("-w", str(lwh.root), "labels", "ingest", "--no-resume", str(tmp_path / "none"))
    assert nothing.code == 0 and nothing.stderr.startswith(f"warning: no label file (*.json) in {tmp_path / 'none'}: ")
    small = run_cli("-w", str(lwh.root), "labels", "validate", "--max-mb", "0.0001", str(d / "b.json"))
    assert small.code == 1 and small.stderr.startswith(f"error: {d / 'b.json'}: $: larger than the limit of 0.0001 MB")


def test_cli_size_limit_default_is_the_named_constant():
    from cadestate.cli.labels import DEFAULT_MAX_MB
    from tasks.human.label_format import MAX_LABEL_BYTES

    assert DEFAULT_MAX_MB * 1e6 == MAX_LABEL_BYTES


def test_the_newest_task_of_each_kind_from_one_read(lwh):
    """tasks.human.labels.latest_tasks: per kind, the row a filtered read's max by created_at gives."""
    from schemas.labels import KINDS
    from tasks.human.labels import latest_tasks

    newest = latest_tasks(lwh, CLIP)
    assert newest and set(newest) <= set(KINDS)
    for kind in KINDS:
        rows = lwh.read("label_tasks", [CLIP], filters=[("kind", "=", kind)]).to_pylist()
        assert newest.get(kind) == (max(rows, key=lambda r: r["created_at"]) if rows else None)
    assert latest_tasks(lwh, "no-such-clip") == {}


def test_the_newest_version_of_a_task_is_found_among_many(tmp_path):
    """A task rewritten after answers has a row per version; the newest (the first of equal times)
    is the one labels are checked against, whatever order the rows were written in."""
    wh = Warehouse(tmp_path / "w")
    t0 = dt.datetime(2026, 1, 1, tzinfo=dt.timezone.utc)
    versions = [("t", 1, "a"), ("other", 9, "x"), ("t", 3, "b"), ("t", 2, "c"), ("t", 3, "d")]
    for task_id, minute, sha in versions:
        wh.write("label_tasks", "c", table_rows("label_tasks", [{"clip": "c", "task_id": task_id, "kind": "manual_track",
                                                                   "task_sha256": sha, "created_at": t0 + dt.timedelta(minutes=minute)}]))
    assert latest_task(wh, "c", "t")["task_sha256"] == "b"
    assert latest_task(wh, "c", "other")["task_sha256"] == "x"
    assert latest_task(wh, "c", "missing") is None and latest_task(wh, "no_clip", "t") is None


def test_clip_facts_look_at_one_clip_folder_and_know_no_clip_of_an_impossible_name(tmp_path):
    wh = Warehouse(tmp_path / "w")
    wh.write("clips", "c", table_rows("clips", [{"clip": "c"}]))
    facts = ClipFacts(wh)
    assert facts.has_clip("c") and not facts.has_clip("d")
    assert not any(facts.has_clip(name) for name in ("../c", "", "a/b", ".c"))


def test_a_manual_track_answer_that_leaves_out_objects_of_the_one_it_replaces_is_warned_of(lwh, tmp_path):
    """Two CVAT jobs exported for one task: the second answer replaces the first whole."""
    first = _edit("manual_track", lambda x: [a.__setitem__("source_id", f"cvat:{i}") for i, a in enumerate(x["answers"])])
    report = ingest_labels(lwh, put(tmp_path / "a", "job1.json", first))
    assert report.ok and report.warnings == []
    second = _edit("manual_track", lambda x: (x.__setitem__("created_at", "2026-01-02T00:00:00+00:00"),
                                               x["answers"][0].__setitem__("source_id", "cvat:9")))
    report = ingest_labels(lwh, put(tmp_path / "b", "job2.json", second))
    assert report.ok and report.warnings == [f"{tmp_path / 'b' / 'job2.json'}: its answer replaces that of "
                                             f"{tmp_path / 'a' / 'job1.json'} for task c1.mt and leaves out 1 of its object(s): "
                                             "the newest manual-track answer is the whole answer, so put every object drawn in one file"]
    whole = _edit("manual_track", lambda x: (x.__setitem__("created_at", "2026-01-03T00:00:00+00:00"),
                                              x["answers"][0].__setitem__("source_id", "cvat:9"),
                                              x["answers"][0].__setitem__("boxes", x["answers"][0]["boxes"][:1])))
    assert ingest_labels(lwh, put(tmp_path / "c", "all.json", whole)).warnings == []  # the same objects, answered again


def test_a_fragment_answer_closing_a_ring_with_the_answers_in_force_is_refused(lwh, tmp_path):
    """Track 0 said to be a fragment of 1 (one file), then 1 of 0 (another): both would leave the
    dataset; the second is refused naming the earlier link. Answering 0 anew (a model) frees 1."""
    first = _edit("cad_selection", lambda d: d.__setitem__("answers", [{"track_id": 0, "cad_id": None, "same_as_track": 1}]))
    assert ingest_labels(lwh, put(tmp_path / "a", "one.json", first)).ok
    ring = _edit("cad_selection", lambda d: (d.__setitem__("created_at", "2026-01-02T00:00:00+00:00"),
                                             d.__setitem__("answers", [{"track_id": 1, "cad_id": None, "same_as_track": 0}])))
    report = ingest_labels(lwh, put(tmp_path / "b", "two.json", ring))
    assert report.errors == [f"{tmp_path / 'b' / 'two.json'}: $.answers[0].same_as_track: tracks 1 -> 0 -> 1 each name the "
                             "next as the same object (0 -> 1 answered before): one of them must be the object (its own answer)"]
    ring["answers"].append({"track_id": 0, "cad_id": "m0a"})
    assert ingest_labels(lwh, put(tmp_path / "c", "three.json", ring)).ok


def test_a_ring_closed_by_two_files_of_one_ingest_is_refused(lwh, tmp_path):
    """Both files are validated before either is written: the second is checked against the first."""
    a = _edit("cad_selection", lambda d: d.__setitem__("answers", [{"track_id": 0, "cad_id": None, "same_as_track": 1}]))
    b = _edit("cad_selection", lambda d: (d.__setitem__("created_at", "2026-01-02T00:00:00+00:00"),
                                          d.__setitem__("answers", [{"track_id": 1, "cad_id": None, "same_as_track": 0}])))
    put(tmp_path / "in", "a.json", a)
    put(tmp_path / "in", "b.json", b)
    report = ingest_labels(lwh, tmp_path / "in")
    assert len(report.ingested) == 1 and len(report.errors) == 1 and "b.json: $.answers[0].same_as_track: tracks 1 -> 0 -> 1" \
        in report.errors[0], report.errors


def test_a_ring_is_checked_in_the_order_the_files_apply_not_by_name(lwh, tmp_path):
    """a.json (newest: 0 -> 1), b.json (oldest: 0 is the object), c.json (between: 1 -> 0): checked
    by name, b's answer seemed to free 0 and all three passed, leaving the ring 0 -> 1 -> 0 in force
    (a's answer is the newest for 0). Checked as they apply (b, c, a), a closes the ring: refused."""
    def links(created, answers):
        return _edit("cad_selection", lambda d: (d.__setitem__("created_at", created), d.__setitem__("answers", answers)))
    put(tmp_path / "in", "a.json", links("2026-01-03T00:00:00+00:00", [{"track_id": 0, "cad_id": None, "same_as_track": 1}]))
    put(tmp_path / "in", "b.json", links("2026-01-01T00:00:00+00:00", [{"track_id": 0, "cad_id": "m0a"}]))
    put(tmp_path / "in", "c.json", links("2026-01-02T00:00:00+00:00", [{"track_id": 1, "cad_id": None, "same_as_track": 0}]))
    report = ingest_labels(lwh, tmp_path / "in")
    assert len(report.errors) == 1 and f"{tmp_path / 'in' / 'a.json'}: $.answers[0].same_as_track: tracks 0 -> 1 -> 0" \
        in report.errors[0], report.errors
    assert same_as_statements(lwh, CLIP, "cad_selection", "c1.cs") == {1: 0}


@pytest.mark.parametrize("newest_drops", [False, True])
def test_the_key_frame_warning_follows_the_order_answers_are_applied_in(lwh, tmp_path, newest_drops):
    """Files of one ingest apply by created_at, not by name: the warning is the newest answer's."""
    def clicks(created, drop_first):
        return _edit("correspondences", lambda d: (d.__setitem__("created_at", created),
                                                   (_third_keyframe_then_first_left_out if drop_first else _third_keyframe)(d)))
    put(tmp_path / "in", "a.json", clicks("2026-01-03T00:00:00+00:00", newest_drops))  # the newer, in force
    put(tmp_path / "in", "b.json", clicks("2026-01-02T00:00:00+00:00", not newest_drops))
    warnings = ingest_labels(lwh, tmp_path / "in").warnings
    assert [w.split(":")[0] for w in warnings] == ([str(tmp_path / "in" / "a.json")] if newest_drops else []), warnings


def test_clicked_points_lie_within_the_models_box(lwh, tmp_path):
    """A unit error (centimetres for metres) is refused, naming the point; points on the box's faces pass."""
    lwh.write("cad_models", "lib", table_rows("cad_models", [{"cad_id": "m0a", "library": "lib", "extent": [1.0, 1.0, 1.0]}]))
    assert validate_label(put(tmp_path, "m.json", good("correspondences")), lwh).kind == "correspondences"
    cm = _edit("correspondences", lambda d: [q.__setitem__("xyz", [v * 100 for v in q["xyz"]])
                                             for q in d["answers"][0]["keyframes"][1]["points"]])
    with pytest.raises(LabelError, match=r"cm\.json: \$\.answers\[0\]\.keyframes\[1\]\.points\[0\]\.xyz: \[-40\.0, 50\.0, -30\.0\] "
                                         r"is outside the model's bounding box \(extent \[1\.0, 1\.0, 1\.0\] m, centred on 0\): metres expected"):
        validate_label(put(tmp_path, "cm.json", cm), lwh)


def test_answers_to_a_replaced_task_and_clicks_leaving_out_key_frames_are_warned_of(lwh, tmp_path):
    """Two sessions of clicks for one track: the second replaces the first whole. An answer to a
    task that a newer one replaced counts only where it still holds."""
    first = _edit("correspondences", _third_keyframe)
    assert ingest_labels(lwh, put(tmp_path / "a", "s1.json", first)).warnings == []
    second = _edit("correspondences", lambda d: (d.__setitem__("created_at", "2026-01-02T00:00:00+00:00"),
                                                 _third_keyframe_then_first_left_out(d)))
    report = ingest_labels(lwh, put(tmp_path / "b", "s2.json", second))
    assert report.ok and report.warnings == [f"{tmp_path / 'b' / 's2.json'}: its clicks for track 0 replace those of "
                                             f"{tmp_path / 'a' / 's1.json'} and leave out 1 of its key-frame(s): the newest "
                                             "answer of a track is its whole answer, so give every key-frame's clicks in one file"]
    newer = next(t for t in _tasks() if t.kind == "correspondences")
    write_task(lwh, dataclasses.replace(newer, task_id="c1.co2", created_at="2026-01-05T00:00:00+00:00"))
    third = _edit("correspondences", lambda d: (d.__setitem__("created_at", "2026-01-03T00:00:00+00:00"), _third_keyframe(d)))
    report = ingest_labels(lwh, put(tmp_path / "c", "s3.json", third))
    assert report.ok and report.warnings == [f"{tmp_path / 'c' / 's3.json'}: answers task c1.co, which a rerun replaced with "
                                             "c1.co2: its answers count only where they still hold on the newest task "
                                             "(`cadestate status` says what waits)"]


def test_a_task_written_on_a_clock_behind_still_comes_in_force(lwh):
    """A rerun's task written by a process whose clock is behind (another machine's, a clock set
    back) was older than the task it replaced, which stayed in force: people answered the new one
    and their answers never reached the data. It is dated a microsecond after the newest of its kind."""
    from tasks.human.labels import latest_task_of_kind

    before = next(t for t in _tasks() if t.kind == "correspondences")
    assert latest_task_of_kind(lwh, CLIP, "correspondences")["task_id"] == before.task_id
    path = write_task(lwh, dataclasses.replace(before, task_id="c1.co2", created_at="2020-01-01T00:00:00+00:00"))
    newest = latest_task_of_kind(lwh, CLIP, "correspondences")
    assert newest["task_id"] == "c1.co2"
    written = json.loads(path.read_text())["created_at"]
    assert dt.datetime.fromisoformat(written) == dt.datetime.fromisoformat(NOW) + dt.timedelta(microseconds=1)
    assert json.loads(newest["document"])["created_at"] == written
    write_task(lwh, dataclasses.replace(before, task_id="c1.co2", created_at=written))  # written again: nothing new
    assert lwh.read("label_tasks", [CLIP], filters=[("task_id", "=", "c1.co2")]).num_rows == 1


def test_two_ingests_of_the_same_files_at_once_commit_each_file_once(lwh, tmp_path):
    """Two processes (here threads) ingesting one folder: the duplicate check and the commit hold
    the clip's labels lock, so each file is committed once and reported a duplicate by the other."""
    import threading

    d = tmp_path / "labels"
    for kind in ("verification", "cad_selection"):
        put(d, f"{kind}.json", good(kind))
    start, reports = threading.Barrier(2), []

    def ingest():
        start.wait()
        reports.append(ingest_labels(lwh, d))

    threads = [threading.Thread(target=ingest) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted((len(r.ingested), len(r.duplicates)) for r in reports) == [(0, 2), (2, 0)]
    assert lwh.read("label_files").num_rows == 2 and lwh.read("verification_labels").num_rows == 2


def test_an_answer_given_before_the_one_it_replaces_is_warned_of(lwh, tmp_path):
    """A folder synced late: Alice's 09:00 "accept" ingested after Bob's 11:00 "reject" came in
    force over it without a word (the answer ingested last is in force, whenever it was given)."""
    bob = _edit("verification", lambda x: x.update(annotator="bob", created_at="2026-01-01T11:00:00+00:00",
                                                    answers=[{"track_id": 0, "verdict": "reject"}]))
    alice = _edit("verification", lambda x: x.update(annotator="alice", created_at="2026-01-01T09:00:00+00:00",
                                                      answers=[{"track_id": 0, "verdict": "accept"}, {"track_id": 1, "verdict": "accept"}]))
    first = put(tmp_path / "b", "bob.json", bob)
    assert ingest_labels(lwh, first).warnings == []
    report = ingest_labels(lwh, put(tmp_path / "a", "alice.json", alice))
    assert report.ingested and report.warnings == [
        f"{tmp_path / 'a' / 'alice.json'}: its answer for track 0 was given at 2026-01-01 09:00:00 UTC, before the one it "
        f"replaces ({first}, given at 2026-01-01 11:00:00 UTC): the answer ingested last is in force, whenever it was given"]
    later = _edit("verification", lambda x: x.update(created_at="2026-01-01T12:00:00+00:00"))
    assert ingest_labels(lwh, put(tmp_path / "c", "carol.json", later)).warnings == []


def test_a_copy_of_a_file_refused_is_refused_too_not_already_ingested(lwh, tmp_path):
    """Two copies of one file that fails the warehouse's checks: the second was "already
    ingested", though those bytes never were (and its clip counted as one whose answers are in)."""
    bad = _edit("cad_selection", lambda x: x["answers"][0].__setitem__("track_id", 5))
    d = tmp_path / "in"
    put(d, "a.json", bad), put(d, "b.json", bad)
    report = ingest_labels(lwh, d)
    assert report.duplicates == [] and report.duplicate_clips == [] and not report.ingested
    assert len(report.errors) == 2 and "unknown track 5" in report.errors[0], report.errors
    assert report.errors[1] == f"{d / 'b.json'}: the same bytes as {d / 'a.json'}, not ingested either (its error above)"


def test_an_answer_committed_while_another_ingest_waits_for_the_clip_comes_before_it(lwh, tmp_path):
    """The answer times were taken before the clip's lock: an ingest that waited for it while
    another committed wrote an older time than that other's, so the file committed last never came
    in force (and two ingests in one clock tick put two answers in force). Here the main thread
    holds the lock and commits bob's answer as an ingest does, while alice's ingest waits."""
    import threading
    import time

    from tasks.human.answers_in_force import labels_lock
    from tasks.human.label_ingest import _commit_clip, _ingest_times, prepare_file, IngestReport

    alice = _edit("cad_selection", lambda x: x.update(annotator="alice", answers=[{"track_id": 0, "cad_id": "m0b"}]))
    bob = _edit("cad_selection", lambda x: x.update(annotator="bob", answers=[{"track_id": 0, "cad_id": "m0a"}]))
    reports = []
    waiting = threading.Thread(target=lambda: reports.append(ingest_labels(lwh, put(tmp_path / "a", "a.json", alice))))
    with labels_lock(lwh, CLIP):
        waiting.start()
        time.sleep(0.5)  # alice's ingest is at the lock
        lf = validate_label(put(tmp_path / "b", "b.json", bob), lwh)
        (at,) = _ingest_times(lwh, 1, None, [CLIP])
        assert _commit_clip(lwh, CLIP, [prepare_file(lwh, lf, at, ClipFacts(lwh))], IngestReport())
    waiting.join(30)
    assert reports and reports[0].ingested, reports
    times = {r["annotator"]: r["ingested_at"] for r in lwh.read("label_files").to_pylist()}
    assert times["alice"] > times["bob"], times
    assert [r["cad_id"] for r in current_answers(lwh, "cad_selection", [CLIP]).to_pylist() if r["track_id"] == 0] == ["m0b"]


def test_validate_checks_a_folder_as_ingest_reads_it(lwh, tmp_path):
    """`labels validate` of a folder refuses what `labels ingest` of it refuses (a ring closed by
    two of its files) and gives the warnings ingest gives (an answer to a task a rerun replaced)."""
    from fuzz.harness import run_cli

    d = tmp_path / "in"
    put(d, "a.json", _edit("cad_selection", lambda x: x.__setitem__("answers", [{"track_id": 0, "cad_id": None, "same_as_track": 1}])))
    put(d, "b.json", _edit("cad_selection", lambda x: x.__setitem__("answers", [{"track_id": 1, "cad_id": None, "same_as_track": 0}])))
    newer = next(t for t in _tasks() if t.kind == "cad_selection")
    write_task(lwh, dataclasses.replace(newer, task_id="c1.cs2", created_at="2026-01-05T00:00:00+00:00"))
    checked = run_cli("-w", str(lwh.root), "labels", "validate", str(d))
    report = ingest_labels(lwh, d)
    assert len(report.errors) == 1 and "b.json: $.answers[0].same_as_track: tracks 1 -> 0 -> 1" in report.errors[0]
    assert len(report.warnings) == 1 and "a.json: answers task c1.cs, which a rerun replaced with c1.cs2" in report.warnings[0]
    assert checked.code == 1 and checked.stdout.splitlines() == [f"{d / 'a.json'}: ok (cad_selection, task c1.cs, 1 answer(s))"]
    assert checked.stderr.splitlines() == [f"error: {report.errors[0]}", f"warning: {report.warnings[0]}"]
    # a.json is ingested now: checked again, it is said so, with no warning (ingest skips it)
    again = run_cli("-w", str(lwh.root), "labels", "validate", str(d / "a.json"))
    assert again.code == 0 and again.stderr == "", again.stderr
    assert again.stdout.splitlines() == [f"{d / 'a.json'}: ok, its bytes were ingested before (clip {CLIP}): `labels ingest` skips it"]
    # two copies of one new file: ingest takes the first and skips the second; validate says so
    e = tmp_path / "copies"
    for name in ("c.json", "d.json"):
        put(e, name, good("verification"))
    twice = run_cli("-w", str(lwh.root), "labels", "validate", str(e))
    assert twice.code == 0 and twice.stdout.splitlines()[1] == f"{e / 'd.json'}: ok, its bytes are an earlier file's of these: `labels ingest` skips it"
    assert ingest_labels(lwh, e).duplicates == [str(e / "d.json")]


def test_a_manual_track_answer_to_a_replaced_task_is_said_to_leave_the_new_one_waiting(lwh, tmp_path):
    """A manual-track answer answers its own task only (nothing of it carries to a newer task, which
    shows it as 'previous'): the warning says the new task still waits, not that it counts where it holds."""
    newer = next(t for t in _tasks() if t.kind == "manual_track")
    write_task(lwh, dataclasses.replace(newer, task_id="c1.mt2", created_at="2026-01-05T00:00:00+00:00"))
    report = ingest_labels(lwh, put(tmp_path / "in", "m.json", good("manual_track")))
    assert report.ok and report.warnings == [f"{tmp_path / 'in' / 'm.json'}: answers task c1.mt, which a rerun replaced with "
                                             "c1.mt2: a manual-track answer answers its own task only, so c1.mt2 still "
                                             "waits for one (an import made again answers the newest task)"]


def test_an_answer_to_a_withdrawn_task_is_refused(lwh, tmp_path):
    """A rerun withdrew the clip's manual-track task (a task with nothing to answer took its place):
    an answer to that task passed (boxes only need clip frames, there are no tracks to check), was
    ingested and counted as answering it. Refused, naming the task id."""
    from tasks.human.labels import new_task_id
    from tasks.human.shared import withdraw_task

    assert withdraw_task(lwh, CLIP, "manual_track", "split 'train' is not one of [manual_tracks] splits (val, test)")
    doc = {**good("manual_track"), "task_id": new_task_id("manual_track", CLIP, "withdrawn")}
    path = put(tmp_path / "labels", "x.json", json.dumps(doc))
    with pytest.raises(LabelError, match=r"\$\.task_id: task c1\.manual_track\.\w+ asks nothing \(a rerun withdrew the "
                                         r"kind's task: Nothing to answer: split 'train'"):
        validate_label(path, lwh)


def test_a_drawn_object_over_an_existing_track_is_warned_of(lwh, tmp_path):
    """A "new" object drawn where track 0 is (IoU 1 on the key-frame both have), not said to be
    track 0, was taken without a word: it became a second track of the chair, asked about in CAD
    selection, correspondences and verification twice. Warned of (and ingested); said to be track 0,
    or drawn elsewhere, it is not."""
    over = {"label": "chair", "boxes": [{"timestamp_us": 0, "box": [0.1, 0.1, 0.3, 0.31]},
                                        {"timestamp_us": 400_000, "box": [0.5, 0.4, 0.9, 0.7]}]}  # no box of track 0 there
    doc = _edit("manual_track", lambda d: d["answers"].append(over))
    lf = validate_label(put(tmp_path, "mt.json", doc), lwh)
    assert list(lf.warnings) == [f"{tmp_path / 'mt.json'}: $.answers[1]: its boxes overlap track 0's on every key-frame both "
                                 "have (IoU >= 0.5): if it is that object, say \"same_as_track\": 0 (or leave it out: it is "
                                 "tracked), else it becomes a second track of it"]
    assert ingest_labels(lwh, put(tmp_path / "in", "mt.json", doc)).warnings == [
        w.replace(str(tmp_path / "mt.json"), str(tmp_path / "in" / "mt.json")) for w in lf.warnings]
    said = _edit("manual_track", lambda d: d["answers"].append({**over, "same_as_track": 0}))
    beside = _edit("manual_track", lambda d: d["answers"].append({**over, "boxes": [{"timestamp_us": 0, "box": [0.3, 0.1, 0.5, 0.3]}]}))
    assert validate_label(put(tmp_path, "said.json", said), lwh).warnings == ()
    assert validate_label(put(tmp_path, "beside.json", beside), lwh).warnings == ()
