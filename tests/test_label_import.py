"""Tool imports refuse bad CVAT and Label Studio files with one line naming the file and the
element or field (issue 13), instead of a traceback or a label that says nothing is missing."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest

from conftest import table_rows
from fuzz.harness import assert_clean_error, run_cli
from tasks.human.label_import import write_label
from tasks.human.label_import_labelstudio import import_labelstudio
from tasks.human.label_import_cvat import import_cvat
from tasks.human.labels import LabelError
from test_labels import CLIP, CVAT, H, STAMPS, W, base_wh, lwh, put  # noqa: F401  (fixtures)

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
    (CVAT.replace('label="chair"', 'label="Chair"'), r"/annotations/track\[0\]: class 'Chair' is not one of the task's: "
     r"chair, table \(is it 'chair'\? --map Chair=chair\)$"),
    (CVAT.replace('encoding="utf-8"', 'encoding="no-such-codec"'), r": not a readable XML file: unknown encoding"),
    (CVAT[:200], r": not well-formed XML"),
    (CVAT.replace('frame="0"', 'frame="90"').replace('frame="3"', 'frame="93"'), r": none of its 1 track\(s\) has a box on a frame"),
    # a track split and drawn again: named as the export's tracks, not as answers of a label in no file
    (CVAT.replace('</annotations>', '<track id="7" label="chair" source="manual"><box frame="0" xtl="33" ytl="19.2" xbr="160" '
                  'ybr="96" outside="0" occluded="0" keyframe="1"/></track></annotations>'),
     r"xml: /annotations/track\[2\] \(cvat:7\): the same object as /annotations/track\[0\] \(cvat:0\) \(class 'chair'"),
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
    (lambda d: d[0].pop("annotations"), r"\$\[0\]\.annotations: missing: not a Label Studio JSON export \(a JSON-MIN"),
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


# ------------------------------------------------------------------------------ what a review found (stop 70)

def _box(frame: int, x0: float = 32, x1: float = 160) -> str:
    return f'<box frame="{frame}" keyframe="1" outside="0" occluded="0" xtl="{x0}" ytl="19.2" xbr="{x1}" ybr="96"/>'


def _export(meta: str, tracks: str) -> str:
    return f'<?xml version="1.0" encoding="utf-8"?>\n<annotations><version>1.1</version><meta>{meta}</meta>{tracks}</annotations>'


def _stamps(doc: dict) -> list[list[int]]:
    return [[b["timestamp_us"] for b in a["boxes"]] for a in doc["answers"]]


def test_a_cvat_project_export_takes_off_the_frames_of_the_tasks_before_the_clips(lwh, tmp_path):
    """CVAT numbers a project's frames on from the tasks before in the subset (start_frame + step *
    size each): the clip's boxes landed 5 frames late when its task came second."""
    task = lambda i, name, size, subset="default": (f"<task><id>{i}</id><name>{name}</name><size>{size}</size><start_frame>0"
                                                    f"</start_frame><stop_frame>{size - 1}</stop_frame><frame_filter></frame_filter>"
                                                    f"<subset>{subset}</subset></task>")
    meta = f"<project><id>1</id><tasks>{task(3, 'attic', 7, 'Train')}{task(2, 'hall', 5)}{task(4, CLIP, 10)}</tasks></project>"
    tracks = (f'<track id="0" label="table" source="manual" task_id="2">{_box(1)}</track>'
              f'<track id="1" label="chair" source="manual" task_id="4">{_box(5)}{_box(11)}</track>')
    doc = import_cvat(lwh, put(tmp_path, "p.xml", _export(meta, tracks)), CLIP).document
    assert _stamps(doc) == [[0, 600_000]]  # hall's 5 frames taken off; attic's are of another subset (ordered by subset, id)
    early = tracks.replace(_box(5), _box(3))
    with pytest.raises(LabelError, match=r"track\[1\]/box\[0\]/@frame: 3 is before the frames of the clip's task"):
        import_cvat(lwh, put(tmp_path, "q.xml", _export(meta, early)), CLIP)


def test_cvat_job_exports_and_frame_steps_are_read_by_their_frame_span(lwh, tmp_path):
    """A job export states its own length as size (it was refused as 'made on the video'), its
    frame size outside meta/job (boxes were scaled by the clip's frames), and numbers its tracks
    from 0 as every job does (a second job's answer replaced the first without a warning)."""
    job = lambda i, start, stop: (f"<job><id>{i}</id><size>{stop - start + 1}</size><start_frame>{start}</start_frame>"
                                  f"<stop_frame>{stop}</stop_frame></job><original_size><width>{2 * W}</width>"
                                  f"<height>{2 * H}</height></original_size>")
    doc = import_cvat(lwh, put(tmp_path, "j.xml", _export(job(7, 5, 9), f'<track id="0" label="chair">{_box(5)}{_box(6)}</track>')),
                      CLIP).document
    assert _stamps(doc) == [[500_000, 600_000]] and doc["answers"][0]["source_id"] == "cvat:job7:0"
    assert doc["answers"][0]["boxes"][0]["box"] == pytest.approx([0.05, 0.05, 0.25, 0.25])  # of 640 x 384
    step = f"<task><id>4</id><name>{CLIP}</name><size>5</size><start_frame>0</start_frame><stop_frame>9</stop_frame>" \
           "<frame_filter>step=2</frame_filter></task>"
    assert _stamps(import_cvat(lwh, put(tmp_path, "s.xml", _export(step, f'<track id="0" label="chair">{_box(0)}{_box(4)}</track>')),
                               CLIP).document) == [[0, 400_000]]
    on_video = step.replace("<stop_frame>9", "<stop_frame>29")
    with pytest.raises(LabelError, match=r"meta/task/stop_frame: the tool showed 30 frames and clip 'c1' has 10: .*--frame-map video"):
        import_cvat(lwh, put(tmp_path, "v.xml", _export(on_video, f'<track id="0" label="chair">{_box(0)}</track>')), CLIP)


def test_an_import_keeps_the_not_an_object_statements_in_force_and_the_same_export_makes_the_same_file(lwh, tmp_path):
    """The import answers the task whole: it revoked the web app's 'track 0 is not an object'
    silently; and each import was dated now, so one export ingested twice was two answers."""
    from tasks.human.label_ingest import ingest_labels
    from tasks.tracking.relations import manual_answer_statements

    web = {"format": "cadestate-label/1", "kind": "manual_track", "task_id": "c1.mt", "clip": CLIP, "annotator": "a",
           "created_at": "2026-01-01T00:00:00+00:00", "not_objects": [0], "answers": []}
    assert ingest_labels(lwh, put(tmp_path / "web", "a.json", json.dumps(web))).ok
    xml = put(tmp_path, "a.xml", _export(f"<task><id>4</id><name>{CLIP}</name><size>10</size></task>"
                                         "<dumped>2026-03-01 10:00:00.5+01:00</dumped>",
                                         f'<track id="0" label="chair">{_box(0)}</track>'))
    first, again = import_cvat(lwh, xml, CLIP), import_cvat(lwh, xml, CLIP)
    assert first.document == again.document and first.document["created_at"] == "2026-03-01T09:00:00+00:00"
    assert first.document["not_objects"] == [0] and "keeps the answer in force's 'track N is not an object'" in first.warnings[0]
    out = write_label(first.document, tmp_path / "labels", "c1.a.cvat")
    assert len(ingest_labels(lwh, out).ingested) == 1 and manual_answer_statements(lwh, CLIP, "c1.mt")[0] == {0}
    assert ingest_labels(lwh, write_label(again.document, tmp_path / "labels2", "c1.a.cvat")).duplicates
    ls_doc = import_labelstudio(lwh, put(tmp_path, "ls.json", json.dumps(ls(lambda d: d[0]["annotations"][0].__setitem__(
        "updated_at", "2026-02-03T04:05:06.789Z")))), CLIP).document
    assert ls_doc["created_at"] == "2026-02-03T04:05:06+00:00"


def test_an_import_keeps_this_is_track_n_of_the_tool_tracks_drawn_before(lwh, tmp_path):
    """A person imported a CVAT track, then said in the app that it is track 0 (a fragment); the
    next export of the same task dropped that statement silently."""
    from tasks.human.label_ingest import ingest_labels
    from tasks.tracking.relations import manual_answer_statements

    meta = f"<task><id>4</id><name>{CLIP}</name><size>10</size></task>"
    first = import_cvat(lwh, put(tmp_path, "a.xml", _export(meta, f'<track id="0" label="chair">{_box(0)}</track>')), CLIP)
    assert ingest_labels(lwh, write_label(first.document, tmp_path / "l1", "c1.a.cvat")).ok
    web = {**first.document, "annotator": "a", "created_at": "2026-01-02T00:00:00+00:00"}
    web["answers"] = [{**first.document["answers"][0], "same_as_track": 0}]
    assert ingest_labels(lwh, put(tmp_path / "web", "w.json", json.dumps(web))).ok
    assert manual_answer_statements(lwh, CLIP, "c1.mt")[1] == {0: 0}
    tracks = f'<track id="0" label="chair">{_box(0)}{_box(3)}</track><track id="1" label="table">{_box(2)}</track>'
    again = import_cvat(lwh, put(tmp_path, "b.xml", _export(meta, tracks)), CLIP)
    assert [a.get("same_as_track") for a in again.document["answers"]] == [0, None]
    assert any("'this is track N': cvat:0 is track 0" in w for w in again.warnings), again.warnings
    assert ingest_labels(lwh, write_label(again.document, tmp_path / "l2", "c1.b.cvat")).ok
    assert manual_answer_statements(lwh, CLIP, "c1.mt")[1] == {0: 0}
    # CVAT numbers each export's tracks from 0: the chair deleted there, id 0 is the table now, and
    # kept by id the statement pinned "track 0 (a chair)" on it; elsewhere drawn, a chair is no more it either
    renumbered = f'<track id="0" label="table">{_box(2)}</track>'
    for tracks in (renumbered, f'<track id="0" label="chair">{_box(0, 200, 300)}</track>'):
        moved = import_cvat(lwh, put(tmp_path, "c.xml", _export(meta, tracks)), CLIP)
        assert [a.get("same_as_track") for a in moved.document["answers"]] == [None]
        assert any("leaves out the answer in force's 'this is track N' of cvat:0 (was track 0)" in w
                   for w in moved.warnings), moved.warnings


def test_exports_of_nothing_the_importer_reads_are_refused_not_nothing_missing(lwh, tmp_path):
    """An image export, polygons, or every track skipped made an empty answer: 'nothing is missing'."""
    rect = ls(lambda d: result(d).__setitem__("type", "rectanglelabels"))
    with pytest.raises(LabelError, match=r"result\[0\]\.type: 1 shape\(s\) on single images and no videorectangle"):
        import_labelstudio(lwh, put(tmp_path, "r.json", json.dumps(rect)), CLIP)
    polygons = '<annotations><image id="0" name="f0.jpg"><polygon label="chair" points="1,1;5,5;1,5"/></image></annotations>'
    with pytest.raises(LabelError, match=r"/annotations/image\[0\]/polygon\[0\]: a 'CVAT for images' export"):
        import_cvat(lwh, put(tmp_path, "i.xml", polygons), CLIP)
    only_file = CVAT.replace('source="manual"', 'source="file"')
    with pytest.raises(LabelError, match=r"each of its 2 track\(s\) has a --skip-source source \(file\)"):
        import_cvat(lwh, put(tmp_path, "f.xml", only_file), CLIP, skip_sources=("file",))


def test_clip_names_with_dashes_a_cvat_export_of_another_video_and_two_boxes_on_a_frame(lwh, tmp_path):
    from tasks.human.label_import import names_clip_exactly

    assert names_clip_exactly(["/data/upload/1/ab12cd34-c1.mp4"], CLIP) and not names_clip_exactly(["c1-2.mp4"], CLIP)
    two = [LS[0] | {"data": {"video": "/data/upload/1/ab12cd34-c1-2.mp4"}}, LS[0] | {"data": {"video": "/data/upload/1/ab12cd34-c1.mp4"}}]
    assert import_labelstudio(lwh, put(tmp_path, "two.json", json.dumps(two)), CLIP).warnings == []
    kitchen = _export(f"<task><id>4</id><name>kitchen</name><size>10</size><source>kitchen.mp4</source></task>",
                      f'<track id="0" label="chair">{_box(2)}{_box(2, 10, 100)}</track>')
    result_ = import_cvat(lwh, put(tmp_path, "k.xml", kitchen), CLIP)
    assert "its task (kitchen kitchen.mp4) names no clip 'c1'" in result_.warnings[0]
    assert result_.dropped == ["cvat:0: a second box on frame 200000 µs, left out"]


def test_boxes_off_the_clips_frames_are_left_out_in_one_line_per_track(lwh, tmp_path):
    """An export of every interpolated box of a video (--all-frames --frame-map video) leaves out
    the boxes between camera frames: one line per track says how many and on which frames, not one
    line per box (thousands on a long video, hiding the warnings)."""
    boxes = "".join(_box(f).replace('keyframe="1"', 'keyframe="0"') if f % 5 else _box(f) for f in range(25))
    export = put(tmp_path, "v.xml", _export("<task><id>4</id><name>c1</name></task>", f'<track id="0" label="chair">{boxes}</track>'))
    result_ = import_cvat(lwh, export, CLIP, frame_map="video", keyframes_only=False)
    assert [b["timestamp_us"] for b in result_.document["answers"][0]["boxes"]] == STAMPS
    assert result_.dropped == ["cvat:0: 15 box(es) on frames that are no camera frame of the clip: "
                               "frames 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, ... 24"]


def test_cli_import_prints_what_it_left_out_and_warns_of_one_line_each(lwh, tmp_path):
    """A track id or task name holding a line break (an XML ``&#10;``) stays on its line."""
    export = _export("<task><id>4</id><name>kitchen&#10;2nd floor</name><source>k.mp4</source></task>",
                     f'<track id="0&#10;a" label="chair">{_box(2)}{_box(40)}</track>')
    res = run_cli("-w", str(lwh.root), "labels", "import-cvat", str(put(tmp_path, "k.xml", export)), "--clip", CLIP,
                  "--out", str(tmp_path / "out"))
    assert res.code == 0 and [ln.split(": ")[0] for ln in res.stderr.splitlines()] == ["left out", "warning"], res.stderr
    assert "cvat:0\\na: 1 box(es)" in res.stderr and "kitchen\\n2nd floor" in res.stderr


def test_a_labelstudio_frame_count_off_the_clips_is_warned_of(lwh, tmp_path):
    """Label Studio numbers frames by time x the labelling config's <Video frameRate> (24 unless
    set): a count of frames other than the clip's (or, --frame-map video, its video's) says the
    frame numbers are not the clip's, and the boxes would land on other frames."""
    def export(count: int) -> Path:
        return put(tmp_path, f"ls{count}.json", json.dumps(ls(lambda d: result(d)["value"].__setitem__("framesCount", count))))

    assert import_labelstudio(lwh, export(10), CLIP).warnings == []
    warned = import_labelstudio(lwh, export(8), CLIP).warnings
    assert warned == [f"{tmp_path / 'ls8.json'}: $[0].annotations[0].result[0].value.framesCount: Label Studio counted 8 frames "
                      "and the clip has 10: its frame numbers are the clip's only if the labelling config's <Video "
                      "frameRate> is the rate of the video it showed"]
    lwh.write("clips", CLIP, table_rows("clips", [{"clip": CLIP, "fps": 10.0, "width": W, "height": H, "duration_us": 2_500_000}]))
    assert import_labelstudio(lwh, export(25), CLIP, frame_map="video").warnings == []
    assert "Label Studio counted 20 frames and the clip's video has 25 (2.5 s at 10 fps)" \
        in import_labelstudio(lwh, export(20), CLIP, frame_map="video").warnings[0]


def test_an_import_for_a_clip_without_a_manual_track_task_says_why_there_is_none(lwh, tmp_path):
    """A clip has no manual-track task when its split is not one of [manual_tracks] splits (or its
    manual_tracks stage has not run): giving a task id would not help."""
    lwh.write("frames", "c2", table_rows("frames", [{"clip": "c2", "timestamp_us": 0, "frame_index": 0, "width": W, "height": H}]))
    res = run_cli("-w", str(lwh.root), "labels", "import-cvat", str(put(tmp_path, "a.xml", CVAT)), "--clip", "c2",
                  "--out", str(tmp_path / "out"))
    assert assert_clean_error(res) == ("error: clip 'c2': no manual_track task to answer: a clip gets one when its split "
                                       "is one of [manual_tracks] splits (`cadestate ingest --split val`) and its "
                                       "manual_tracks stage has run")
    from tasks.human.shared import withdraw_task  # one it had is withdrawn (its split taken out, say): said so too

    assert withdraw_task(lwh, CLIP, "manual_track", "split 'train' is not one of [manual_tracks] splits (val, test)")
    res = run_cli("-w", str(lwh.root), "labels", "import-cvat", str(put(tmp_path, "a.xml", CVAT)), "--clip", CLIP,
                  "--out", str(tmp_path / "out"))
    assert assert_clean_error(res) == (f"error: clip '{CLIP}': its manual_track task was withdrawn: Nothing to answer: split "
                                       "'train' is not one of [manual_tracks] splits (val, test).")
