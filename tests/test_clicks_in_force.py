"""The rule of tasks.human.clicks_in_force on boxes, task versions and answers (the stage in a
warehouse: tests/test_human_tasks.py)."""

import datetime as dt

import pyarrow as pa
import pytest

from schemas.labels import KeyframeView
from tasks.human.clicks_in_force import (box_iou, held_clicks, holds, in_force_rows, item_key, match, seen_then, taken_answers,
                                         to_answer)
from schemas.dataclass_json import to_json

T = [dt.datetime(2026, 12, 1, h, tzinfo=dt.timezone.utc) for h in range(6)]
BOX = (0.1, 0.1, 0.5, 0.5)
PLACES = [(0.1 + 0.2 * (t % 4), 0.1 + 0.4 * (t // 4), 0.25 + 0.2 * (t % 4), 0.45 + 0.4 * (t // 4)) for t in range(8)]
"""Track t's box where each object stands (apart: IoU 0 with one another)."""
ELSEWHERE = (0.6, 0.6, 0.9, 0.9)


def _at(box: tuple) -> dict[int, list[tuple]]:
    """A track's boxes now: ``box`` on both key-frames of :func:`_task`."""
    return {10: [box], 20: [box]}


def test_box_iou_of_ymin_xmin_ymax_xmax_boxes():
    assert box_iou((0, 0, 1, 1), (0, 0, 1, 1)) == 1.0
    assert box_iou((0, 0, 0.5, 1), (0.25, 0, 0.75, 1)) == pytest.approx(1 / 3)  # half of each overlaps
    assert box_iou((0, 0, 0.2, 0.2), (0.5, 0.5, 0.7, 0.7)) == 0.0
    assert box_iou((0.3, 0.3, 0.3, 0.3), (0.3, 0.3, 0.3, 0.3)) == 0.0  # empty boxes overlap nothing


def test_an_answer_is_checked_against_the_task_version_it_saw():
    versions = [(T[0], {1: (0, 0, 1, 1)}), (T[2], {1: (0, 0, 0.5, 0.5)})]
    assert seen_then(versions, T[1]) == {1: (0, 0, 1, 1)}  # written before the second version
    assert seen_then(versions, T[3]) == {1: (0, 0, 0.5, 0.5)}
    assert seen_then(versions, T[0] - dt.timedelta(hours=1)) == {1: (0, 0, 1, 1)}  # none before: the oldest


def test_clicks_hold_where_every_clicked_box_overlaps_one_now():
    then = {10: BOX, 20: BOX}
    assert holds({10, 20}, then, {10: [BOX], 20: [(0.12, 0.1, 0.52, 0.5)]})
    assert not holds({10, 20}, then, {10: [BOX], 20: [(0.6, 0.6, 0.9, 0.9)]}), "one clicked frame shows another object"
    assert not holds({10, 20}, then, {10: [BOX]}), "the track has no box on a clicked frame any more"
    assert holds({10, 20}, then, {10: [BOX], 20: [(0.6, 0.6, 0.9, 0.9), BOX]}), "two boxes there: one overlaps"
    assert holds({10}, then, {10: [BOX]}), "frames not clicked do not count"
    assert holds({30}, then, {}), "a frame the task showed no box on says nothing"


def test_the_item_key_names_model_frames_and_boxes():
    view = KeyframeView(timestamp_us=10, frame_index=1, image_path="f.jpg", box=BOX)
    assert item_key(3, "lib.a", [view]) == "3:lib.a:10@0.1000,0.1000,0.5000,0.5000"
    assert item_key(3, "lib.a", [KeyframeView(timestamp_us=10, frame_index=1, image_path="f.jpg")]) == "3:lib.a:10@-"


def _rows(task: str, track: int, cad: str, at: dt.datetime, stamps=(10, 20), dx: float = 0.0) -> list[dict]:
    return [{"task_id": task, "track_id": track, "timestamp_us": ts, "point_index": k, "cad_id": cad,
             "point_2d": [0.2 + 0.05 * k + dx, 0.3], "point_3d": [0.1 * k, 0.0, 0.2], "is_mirrored": k == 9, "ingested_at": at}
            for ts in stamps for k in range(4)]


def _task(task: str, at: dt.datetime, boxes: dict[int, tuple]) -> dict:
    import json

    items = [{"track_id": t, "keyframes": [{"timestamp_us": ts, "box": list(b)} for ts in (10, 20)]} for t, b in boxes.items()]
    return {"task_id": task, "kind": "correspondences", "created_at": at, "document": json.dumps({"items": items})}


def test_the_answer_under_the_task_id_wins_else_the_newest_that_holds():
    answers = pa.Table.from_pylist(_rows("old1", 0, "a", T[1]) + _rows("old2", 0, "a", T[3], dx=0.1) + _rows("old3", 0, "b", T[4])
                                   + _rows("old1", 1, "a", T[1]) + _rows("now", 1, "a", T[5], dx=0.2)
                                   + _rows("old1", 2, "a", T[1]) + _rows("old2", 2, "a", T[3], dx=0.1))
    tasks = pa.Table.from_pylist([_task("old1", T[0], {t: PLACES[t] for t in range(3)}),
                                  _task("old2", T[2], {0: PLACES[0], 2: ELSEWHERE})])
    now = {t: _at(PLACES[t]) for t in (0, 1, 2)}
    held = held_clicks("now", {0: "a", 1: "a", 2: "a", 3: "a"}, now, answers, tasks)
    assert held[0].keyframes[0].points[0].x == pytest.approx(0.3), "the newest that holds (old3 used another model)"
    assert held[1].keyframes[0].points[0].x == pytest.approx(0.4), "the answer to this task"
    assert held[2].keyframes[0].points[0].x == pytest.approx(0.2), "old2 showed another object there: old1's"
    assert 3 not in held
    assert set(held_clicks("now", {0: "a"}, {}, answers, tasks)) == set(), "a track gone: nothing holds"
    # tracks remade and renumbered: clicks follow the object, whatever id its track has now
    moved = held_clicks("now", {5: "a", 6: "a", 7: "a"}, {5: _at(PLACES[2]), 6: _at(ELSEWHERE), 7: {10: [ELSEWHERE]}},
                        answers, tasks)
    assert moved[5].track_id == 5 and moved[5].keyframes[0].points[0].x == pytest.approx(0.2), "old1's track 2"
    assert moved[6].keyframes[0].points[0].x == pytest.approx(0.3), "old2's track 2, shown elsewhere"
    assert 7 not in moved, "no box now on a clicked frame"


def test_the_match_counts_frames_and_overlap():
    then = {10: BOX, 20: BOX}
    assert match([10, 20], then, {10: [BOX], 20: [BOX]}) == (2, 1.0)
    assert match([10], then, {10: [ELSEWHERE, (0.1, 0.1, 0.5, 0.4)]}) == (1, pytest.approx(0.75)), "the best box there"
    assert match([10, 20], then, {10: [BOX]}) is None, "no box now on a compared frame"
    assert match([], then, {}) == (0, 0.0)


def test_an_answer_goes_to_the_track_it_matches_best_and_the_newest_decides():
    earlier = [(T[2], 1, "x"), (T[2], 0, "y"), (T[1], 0, "z")]
    alike = lambda t, a: (1, 1.0)  # noqa: E731
    assert taken_answers(earlier, [0], alike) == {0: ["y", "x", "z"]}, "newest first; of one label file, the same id first"
    assert taken_answers(earlier, [0, 1], alike) == {1: ["x"], 0: ["y", "z"]}, "an answer speaks of one track"
    assert taken_answers(earlier, [5], alike) == {5: ["x", "y", "z"]}
    assert taken_answers(earlier, [6, 5], alike) == {5: ["x", "y", "z"]}, "equal matches, no same id: the smaller id"
    better = lambda t, a: (2, 0.9) if (t, a) == (0, "x") else (1, 1.0)  # noqa: E731
    assert taken_answers(earlier, [0, 1], better) == {0: ["y", "x", "z"]}, "more key-frames compared beats the same id"
    assert taken_answers(earlier, [0], lambda t, a: None if a == "z" else (1, 1.0)) == {0: ["y", "x"]}
    assert taken_answers(earlier, [0], lambda t, a: None) == {}


def test_carried_clicks_give_the_rows_they_came_from():
    rows = _rows("old", 4, "lib.a", T[0])
    doc = {"items": [{"track_id": 4, "previous": to_json(to_answer(4, rows))}, {"track_id": 5}]}
    got = in_force_rows("c", doc, pa.Table.from_pylist([], schema=pa.schema([("track_id", pa.int32())])))
    keep = ("timestamp_us", "point_index", "cad_id", "point_2d", "point_3d", "is_mirrored")
    assert [{k: r[k] for k in keep} for r in got] == [{k: r[k] for k in keep} for r in rows]
    assert {r["track_id"] for r in got} == {"4"}, "track 5 has no clicks"


def test_a_choice_holds_on_the_same_object_with_its_model_among_the_candidates():
    import json

    from tasks.human.choices_in_force import held_choices, same_object

    assert same_object({10: BOX, 20: BOX}, {10: [BOX]}), "a frame the track left says nothing"
    assert not same_object({10: BOX}, {20: [BOX]}), "no frame in common"
    assert not same_object({10: BOX, 20: BOX}, {10: [BOX], 20: [(0.6, 0.6, 0.9, 0.9)]})
    sel = lambda task, t, cad, at: {"task_id": task, "track_id": t, "cad_id": cad, "ingested_at": at}  # noqa: E731
    answers = pa.Table.from_pylist([sel("old", 0, "a", T[1]), sel("old", 1, "a", T[1]), sel("old", 2, None, T[1]),
                                    sel("old", 3, "a", T[1]), sel("old2", 3, "b", T[3]), sel("now", 4, "b", T[4]),
                                    sel("old", 4, "a", T[1])])
    items = [{"track_id": t, "keyframes": [{"timestamp_us": 10, "box": list(PLACES[t])}]} for t in range(5)]
    tasks = pa.Table.from_pylist([{"task_id": k, "kind": "cad_selection", "created_at": T[0], "document": json.dumps({"items": items})}
                                  for k in ("old", "old2")])
    now = {t: {10: [PLACES[t]]} for t in range(5)}
    held = held_choices("now", {0: {"a"}, 1: {"b"}, 2: {"a"}, 3: {"a"}, 4: {"a"}}, now, answers, tasks)
    assert held == {0: "a"}, "1: model gone; 2: none fits; 3: the newest said b, gone; 4: answered under the id"
    # tracks remade and renumbered: the choice follows the object
    assert held_choices("now", {7: {"a"}, 8: {"a"}}, {7: {10: [PLACES[0]]}, 8: {10: [ELSEWHERE]}}, answers, tasks) == {7: "a"}


def test_an_answer_on_another_object_that_overlaps_on_one_key_frame_stays_with_that_object():
    import json

    from tasks.human.choices_in_force import held_choices

    sel = lambda task, t, cad, at: {"task_id": task, "track_id": t, "cad_id": cad, "ingested_at": at}  # noqa: E731
    view = lambda ts, box: {"timestamp_us": ts, "box": list(box)}  # noqa: E731
    # t1 showed track 0 on object 0 (frames 10, 40, 50); t2 showed track 1 on object 1 (20, 30), whose box
    # jumped onto object 0 on frame 10
    shown = {"t1": [{"track_id": 0, "keyframes": [view(ts, PLACES[0]) for ts in (10, 40, 50)]}],
             "t2": [{"track_id": 1, "keyframes": [view(10, PLACES[0])] + [view(ts, PLACES[1]) for ts in (20, 30)]}]}
    tasks = pa.Table.from_pylist([{"task_id": k, "kind": "cad_selection", "created_at": T[0], "document": json.dumps({"items": v})}
                                  for k, v in shown.items()])
    answers = pa.Table.from_pylist([sel("t1", 0, "a", T[1]), sel("t2", 1, "b", T[3])])
    now = {0: {10: [PLACES[0]], 40: [PLACES[0]]}, 1: {20: [PLACES[1]], 30: [PLACES[1]]}}
    assert held_choices("now", {0: {"a", "b"}, 1: {"a", "b"}}, now, answers, tasks) == {0: "a", 1: "b"}
    assert held_choices("now", {0: {"a", "b"}}, now, answers, tasks) == {0: "a"}, "track 1 takes its answer, asked or not"


def test_clicks_go_to_one_track_where_two_now_hold_them():
    answers = pa.Table.from_pylist(_rows("old1", 0, "a", T[1]))
    tasks = pa.Table.from_pylist([_task("old1", T[0], {0: PLACES[0]})])
    assert set(held_clicks("now", {4: "a", 5: "a"}, {4: _at(PLACES[0]), 5: _at(PLACES[0])}, answers, tasks)) == {4}
    assert set(held_clicks("now", {0: "a", 5: "a"}, {5: _at(PLACES[0]), 0: _at(PLACES[0])}, answers, tasks)) == {0}
    near = (0.1, 0.13, 0.25, 0.48)  # IoU 0.84 with PLACES[0]
    assert held_clicks("now", {4: "a"}, {4: _at(near), 5: _at(PLACES[0])}, answers, tasks) == {}, \
        "track 5 matches best: the clicks are its object's, though it has no model chosen"
    assert set(held_clicks("now", {4: "a"}, {4: _at(near)}, answers, tasks)) == {4}


def test_a_drawn_fragment_of_a_track_does_not_take_its_earlier_answer():
    """A drawn object said to be track 7 (left out of the tasks) drawn tighter than 7's box matched
    7's earlier item better, took its answer, and 7 was asked again: a fragment's boxes are its track's."""
    import json

    from tasks.human.choices_in_force import held_choices
    from tasks.human.shared import boxes_now
    from tasks.tracking.clip_tracks import ClipTrack, TrackBox

    shown, shifted, stamps = (0.1, 0.1, 0.5, 0.5), (0.14, 0.14, 0.54, 0.54), (0, 100_000, 200_000)  # IoU 0.67
    item = {"track_id": 5, "keyframes": [{"timestamp_us": ts, "box": list(shown)} for ts in stamps]}
    tasks = pa.Table.from_pylist([{"task_id": "old", "kind": "cad_selection", "created_at": T[0],
                                   "document": json.dumps({"items": [item]})}])
    answers = pa.Table.from_pylist([{"task_id": "old", "track_id": 5, "cad_id": "a", "ingested_at": T[1]}])

    def track(t: int, box, manual: bool = False) -> ClipTrack:
        return ClipTrack(t, "chair", manual, tuple(TrackBox(i, ts, box, "chair") for i, ts in enumerate(stamps)))

    tracks = {7: track(7, shifted), 1_000_000: track(1_000_000, shown, manual=True)}  # the drawing: "is track 7"
    assert held_choices("now", {7: {"a", "b"}}, boxes_now(tracks), answers, tasks) == {}  # the fragment took it
    assert held_choices("now", {7: {"a", "b"}}, boxes_now(tracks, fragments={1_000_000: 7}), answers, tasks) == {7: "a"}
