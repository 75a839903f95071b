"""The annotation app's API (``cadestate annotate``, :mod:`cadestate.webapp`): answers in, label files out.

On the synthetic tasks of tests/test_labels.py: bad payloads get a 4xx naming the field and write
nothing; a good one is written as a label file that validates, ingested (with its seconds and
track relations) and its clip queued for resume; concurrent answers to one task all land, the
newest in force; a file a crash left un-ingested is ingested when the app starts.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import pytest
from fastapi.testclient import TestClient

from cadestate.config import Config, WarehouseConfig
from cadestate.webapp.app import create_app
from cadestate.webapp.resume import Resumer
from tasks.human.answers_in_force import current_answers
from tasks.human.labels import validate_label, write_task
from test_labels import CLIP, base_wh, good, lwh  # noqa: F401  (fixtures)
from warehouse import Warehouse


class Requests:
    """A resume that records the clips asked for instead of running them."""

    def __init__(self):
        self.clips: list[str] = []
        self.lock = threading.Lock()

    def __call__(self, clip: str) -> str:
        with self.lock:
            self.clips.append(clip)
        return "ok"


def _client(wh: Warehouse, runs: Requests) -> TestClient:
    config = Config(warehouse=WarehouseConfig(root=str(wh.root)))
    return TestClient(create_app(config, annotator="tester", resumer=Resumer(config, run=runs)))


def payload(kind: str) -> dict:
    doc = good(kind)
    for k in ("format", "created_at", "annotator"):
        doc.pop(k)
    return doc


def _ran(wh: Warehouse) -> None:
    """Record a stage run of the clip started now, as a resume does (:class:`Requests` runs nothing):
    an app starting later finds no answer newer than the clip's last run to resume."""
    import datetime as dt

    from conftest import table_rows

    wh.write("runs", CLIP, table_rows("runs", [{"clip": CLIP, "run_id": f"r-{time.time_ns()}", "stage": "verification",
                                                 "status": "paused", "started_at": dt.datetime.now(dt.timezone.utc)}]))


def _label_files(wh: Warehouse) -> list:
    return sorted((wh.root / "labels").rglob("*.json")) if (wh.root / "labels").exists() else []


BAD = [  # (kind, change, the field the error names)
    ("cad_selection", lambda d: d["answers"][0].update(track_id=7), "$.answers[0].track_id"),
    ("cad_selection", lambda d: d["answers"][0].update(cad_id="nope"), "$.answers[0].cad_id"),
    ("cad_selection", lambda d: d["answers"][0].update(seconds=-1), "$.answers[0].seconds"),
    ("cad_selection", lambda d: d["answers"][0].update(same_as_track=1), "$.answers[0].cad_id"),
    ("cad_selection", lambda d: d["answers"][1].update(same_as_track=9), "$.answers[1].same_as_track"),
    ("cad_selection", lambda d: d.update(task_id="c1.nope"), "$.task_id"),
    ("cad_selection", lambda d: d.update(extra=1), "$"),
    ("manual_track", lambda d: d["answers"][0]["boxes"][0].update(box=[0.5, 0.5, 0.4, 0.8]), "$.answers[0].boxes[0].box"),
    ("manual_track", lambda d: d["answers"][0].update(label="giraffe"), "$.answers[0].label"),
    ("manual_track", lambda d: d.update(not_objects=[5]), "$.not_objects[0]"),
    ("manual_track", lambda d: d["answers"][0].update(same_as_track=3), "$.answers[0].same_as_track"),
    ("correspondences", lambda d: d["answers"][0]["keyframes"][0]["points"][0].update(x=1.5), "$.answers[0].keyframes[0].points[0].x"),
    ("verification", lambda d: d["answers"][0].update(verdict="maybe"), "$.answers[0].verdict"),
    ("verification", lambda d: d["answers"][1].update(same_as_track=1), "$.answers[1].same_as_track"),  # itself
    ("verification", lambda d: d["answers"][0].update(same_as_track=9), "$.answers[0].same_as_track"),  # not the task's
    ("verification", lambda d: d.pop("answers"), "$"),
]


@pytest.mark.parametrize("kind,change,field", BAD, ids=[f"{k}:{f}" for k, _, f in BAD])
def test_bad_payload_is_refused_naming_the_field_and_nothing_is_written(lwh, kind, change, field):
    runs = Requests()
    doc = payload(kind)
    change(doc)
    with _client(lwh, runs) as client:
        r = client.post("/api/answers", json=doc)
    assert r.status_code == 422, r.text
    assert r.json()["detail"].startswith(f"answer: {field}"), r.json()["detail"]
    assert _label_files(lwh) == [] and lwh.read("label_files").num_rows == 0 and runs.clips == []


def test_not_an_object_is_refused(lwh):
    with _client(lwh, Requests()) as client:
        assert client.post("/api/answers", json=[1, 2]).status_code == 422
        assert client.post("/api/answers", content=b"{not json", headers={"Content-Type": "application/json"}).status_code == 422
    assert _label_files(lwh) == []


def test_an_answer_is_written_validated_ingested_and_its_clip_resumed(lwh):
    runs = Requests()
    doc = payload("cad_selection")
    doc["answers"][0]["seconds"] = 12.5
    with _client(lwh, runs) as client:
        r = client.post("/api/answers", json=doc)
        assert r.status_code == 200, r.text
        assert client.app.state.resumer.wait_idle(CLIP, 10)
        state = client.get(f"/api/clips/{CLIP}").json()
    path = lwh.root / r.json()["path"]
    lf = validate_label(path, lwh)  # the file is a valid label file of the existing format
    assert lf.label.annotator == "tester" and lf.kind == "cad_selection"
    assert lwh.read("label_files").column("label_sha256").to_pylist() == [lf.sha256]
    assert {a["track_id"]: a["cad_id"] for a in current_answers(lwh, "cad_selection", [CLIP]).to_pylist()} == {0: "m0b", 1: None}
    effort = lwh.read("label_effort").to_pylist()
    assert [(e["track_id"], e["seconds"], e["annotator"]) for e in effort] == [(0, 12.5, "tester")]
    assert runs.clips == [CLIP] and state["resume"]["state"] == "idle" and state["resume"]["runs"] == 1
    waiting = {t["kind"]: t["waiting"] for t in state["tasks"]}
    assert waiting["cad_selection"] == 1  # track 2 still waits


def test_relations_and_the_task_seconds_of_a_manual_track_answer_are_kept(lwh):
    said_none = {**payload("manual_track"), "not_objects": [0], "seconds": 40.0}
    said_same = {**payload("manual_track"), "seconds": 5.0}
    said_same["answers"] = [*said_same["answers"],
                            {"label": "chair", "boxes": [{"timestamp_us": 200_000, "box": [0.1, 0.1, 0.3, 0.3]}], "same_as_track": 0}]
    with _client(lwh, Requests()) as client:
        both = client.post("/api/answers", json={**said_same, "not_objects": [0]})  # track 0 is no object and is object 2?
        assert both.status_code == 422 and "$.answers[1].same_as_track" in both.text and "also said to be no object" in both.text
        assert client.post("/api/answers", json=said_none).status_code == 200
        assert client.post("/api/answers", json=said_same).status_code == 200
    rel = sorted((r["relation"], r["track_id"], r["object_index"]) for r in lwh.read("track_relations").to_pylist())
    assert rel == [("not_object", 0, None), ("same_object", 0, 1)]
    assert sorted((e["track_id"], e["seconds"]) for e in lwh.read("label_effort").to_pylist()) == [(-1, 5.0), (-1, 40.0)]


def test_concurrent_answers_to_one_task_all_land_and_the_newest_is_in_force(lwh):
    runs = Requests()
    choices = ["m0a", "m0b", None] * 3
    with _client(lwh, runs) as client:
        def send(cad_id):
            return client.post("/api/answers", json={**payload("cad_selection"), "answers": [{"track_id": 0, "cad_id": cad_id}]})

        with ThreadPoolExecutor(6) as pool:
            replies = list(pool.map(send, choices))
        assert [r.status_code for r in replies] == [200] * len(choices), [r.text for r in replies]
        assert client.app.state.resumer.wait_idle(CLIP, 20)
    files = lwh.read("label_files").to_pylist()
    assert len(_label_files(lwh)) == len(files) == len(choices) and len({f["ingested_at"] for f in files}) == len(choices)
    newest = max(files, key=lambda f: f["ingested_at"])
    in_force = current_answers(lwh, "cad_selection", [CLIP]).to_pylist()
    assert [(a["track_id"], a["cad_id"], a["label_sha256"]) for a in in_force] == \
        [(0, json.loads(newest["document"])["answers"][0]["cad_id"], newest["label_sha256"])]
    assert 1 <= len(runs.clips) <= len(choices)  # requests while queued coalesce


def test_a_file_left_by_a_crash_is_ingested_when_the_app_starts(lwh):
    folder = lwh.root / "labels" / CLIP
    folder.mkdir(parents=True)
    (folder / "c1.ve.left.json").write_text(json.dumps(good("verification")))
    runs = Requests()
    with _client(lwh, runs) as client:
        assert client.app.state.resumer.wait_idle(CLIP, 10)
    assert lwh.read("label_files").num_rows == 1 and runs.clips == [CLIP]


def test_a_left_file_that_fails_again_at_start_is_reported_not_dropped(lwh, capsys):
    folder = lwh.root / "labels" / CLIP
    folder.mkdir(parents=True)
    (folder / "c1.ve.left.json").write_text("{")  # cut off by the crash
    with _client(lwh, Requests()) as client:
        errors = client.get("/api/clips").json()["label_errors"]
    assert len(errors) == 1 and "c1.ve.left.json" in errors[0]
    assert f"error: {errors[0]}" in capsys.readouterr().err
    assert not lwh.has_partition("label_files", CLIP)


def test_start_page_data_and_next_item(lwh):
    with _client(lwh, Requests()) as client:
        clips = client.get("/api/clips").json()
        assert clips["annotator"] == "tester"
        (c,) = clips["clips"]
        assert [(t["kind"], t["items"], t["waiting"]) for t in c["tasks"]] == [
            ("manual_track", 1, 1), ("cad_selection", 3, 3), ("correspondences", 2, 2), ("verification", 2, 2)]
        assert clips["next"]["kind"] == "manual_track" and client.get("/api/next").json() == clips["next"]
        task = client.get(f"/api/tasks/{CLIP}/c1.cs").json()
        assert task["task"]["kind"] == "cad_selection" and task["answered"] == []
        assert client.get(f"/api/tasks/{CLIP}/nope").status_code == 404
        assert client.get("/media/../catalog.duckdb").status_code == 404
        for page in ("/", "/annotate/manual_track", "/annotate/cad_selection", "/annotate/correspondences", "/annotate/verification"):
            assert client.get(page).status_code == 200, page


def test_the_start_page_reads_a_clip_again_only_when_its_files_changed(lwh):
    """Every 5 s the start page asked for every clip's tasks, each worked out again (~22 ms a clip:
    minutes at thousands of clips): an unchanged clip is served as kept, and read again the moment
    an answer is ingested, a resume writes a new task, or another process writes a run."""
    from cadestate.webapp.queue import ClipState
    from conftest import table_rows
    from test_labels import _tasks
    from warehouse.kept import SETTLE_NS

    def settle():  # the folders written just now are not trusted for SETTLE_NS (warehouse/kept.py)
        time.sleep(SETTLE_NS / 1e9 + 0.02)

    def waiting(client) -> dict:
        (c,) = client.get("/api/clips").json()["clips"]
        return {t["kind"]: (t["items"], t["waiting"]) for t in c["tasks"]} | {"runs": len(c["runs"])}

    def new_task(clip: str) -> str:  # a resume whose rerun asks about a third track
        older = _tasks()[3]
        write_task(lwh, dataclasses.replace(older, task_id="c1.ve2", created_at="2026-01-01T00:01:00+00:00",
                                            items=(*older.items, dataclasses.replace(older.items[0], track_id=2))))
        return "ok"

    config = Config(warehouse=WarehouseConfig(root=str(lwh.root)))
    with TestClient(create_app(config, annotator="tester", resumer=Resumer(config, run=new_task))) as client:
        settle()
        before = waiting(client)
        assert before == {"manual_track": (1, 1), "cad_selection": (3, 3), "correspondences": (2, 2), "verification": (2, 2), "runs": 0}
        kept = client.app.state.queue.state(CLIP)
        assert client.app.state.queue.state(CLIP) is kept and waiting(client) == before  # not worked out again
        assert client.post("/api/answers", json=payload("cad_selection")).status_code == 200
        assert waiting(client)["cad_selection"] == (3, 1)  # at once, as after every answer
        assert client.app.state.resumer.wait_idle(CLIP, 10)
        assert waiting(client)["verification"] == (3, 3)
        settle()
        lwh.write("runs", CLIP, table_rows("runs", [{"clip": CLIP, "run_id": "r1", "stage": "pose", "status": "failed"}]))
        assert waiting(client)["runs"] == 1
        settle()
        assert client.app.state.queue.state(CLIP) is client.app.state.queue.state(CLIP)
        after = waiting(client)
    # the app started again: the clip's state kept on disk is served, not worked out again (an app
    # over 1,000 finished clips read them all for 43 s when it started)
    copy = lwh.root / "_cache" / "reads" / "queue" / f"{CLIP}.json"
    doc = json.loads(copy.read_text())
    assert ClipState.from_json(doc["value"]).runs[0]["stage"] == "pose"
    doc["value"]["runs"][0]["message"] = "marked in the copy"  # what the next app serves shows where it came from
    copy.write_text(json.dumps(doc))
    with TestClient(create_app(config, annotator="tester", resumer=Resumer(config, run=new_task))) as client:
        assert waiting(client) == after
        assert client.get(f"/api/clips/{CLIP}").json()["runs"][0]["message"] == "marked in the copy"


def test_two_browsers_are_given_different_items_while_a_page_holds_one(lwh):
    """Two annotators on one app were given the same next item, and the second met a 409 after doing
    the work: an item a page opened is held for its browser, and the queue (/api/next, the start
    page's next item, a page's next after an answer) gives other browsers other items until the page
    gives it back or stops renewing it."""
    from cadestate.webapp.claims import HOLD_S

    a, b = {"X-Cadestate-Client": "browser-a"}, {"X-Cadestate-Client": "browser-b"}
    mt = {"clip": CLIP, "kind": "manual_track", "track_id": -1}
    with _client(lwh, Requests()) as client:
        first = client.get("/api/next", headers=a).json()
        assert first["kind"] == "manual_track" and client.get("/api/next", headers=b).json() == first  # nobody holds it yet
        assert client.post("/api/claims", json=mt, headers=a).json() == {"held_by_other": False, "age_s": None, "hold_s": HOLD_S}
        assert client.get("/api/next", headers=a).json() == first  # a's own
        other = client.get("/api/next", headers=b).json()
        assert (other["kind"], other["track_id"]) == ("cad_selection", 0)
        assert client.get("/api/next").json() == other  # no client id: every claim is someone else's
        start = client.get("/api/clips", headers=b).json()
        assert start["next"] == other and start["clips"][0]["next"] == other
        tasks = {t["kind"]: t for t in start["clips"][0]["tasks"]}
        assert tasks["manual_track"]["held_tracks"] == [-1] and tasks["cad_selection"]["held_tracks"] == []
        assert client.get(f"/api/clips/{CLIP}", headers=a).json()["tasks"][0]["held_tracks"] == []
        claimed = client.post("/api/claims", json=mt, headers=b).json()  # b opens it all the same: said, not taken
        assert claimed["held_by_other"] is True and claimed["age_s"] >= 0
        cs0 = {"clip": CLIP, "kind": "cad_selection", "track_id": 0}
        assert client.post("/api/claims", json=cs0, headers=b).json()["held_by_other"] is False
        assert client.get(f"/api/tasks/{CLIP}/c1.cs", headers=a).json()["held"] == [0]  # a's page goes on to track 1
        assert client.get("/api/next", headers=a).json()["kind"] == "manual_track"
        client.post("/api/claims/release", json=mt, headers=b)  # not b's: nothing given back
        assert client.get("/api/next", headers=b).json() == other  # its own claim is no bar to it
        assert client.post("/api/claims/release", json=mt, headers=a).status_code == 200  # a left the page
        assert client.get("/api/next", headers=b).json() == first
        lapsed = client.app.state.claims
        lapsed.claim("browser-a", (CLIP, "manual_track", -1))
        lapsed.hold_s = 0.0  # renewed no more: lapsed
        lapsed.claim("browser-a", (CLIP, "manual_track", -1))
        assert client.get("/api/next", headers=b).json() == first
        bad = [({**mt, "kind": "nope"}, a, "claim: $.kind: one of manual_track"), ({**mt, "track_id": "0"}, a, "claim: $.track_id"),
               ({"clip": CLIP}, a, "claim: $: an object with clip, kind and track_id"), (mt, {}, "header X-Cadestate-Client: missing"),
               (mt, {"X-Cadestate-Client": "x" * 65}, "header X-Cadestate-Client: a client id of 1 to 64 characters, not 65")]
        for body, headers, said in bad:
            r = client.post("/api/claims", json=body, headers=headers)
            assert r.status_code == 422 and r.json()["detail"].startswith(said), r.text
        before = client.app.state.claims.all()
        r = client.post("/api/claims", json={**mt, "clip": "no-such-clip"}, headers=a)  # was held, in memory, for nothing
        assert r.status_code == 404 and r.json()["detail"] == "unknown clip 'no-such-clip'", r.text
        assert client.app.state.claims.all() == before


def test_every_app_over_one_warehouse_sees_the_claims_and_a_restart_keeps_them(lwh):
    """Claims lived in one app's memory: two annotators each running ``cadestate annotate`` over one
    warehouse were both given the same item, and a restarted app had forgotten every claim."""
    a, b = {"X-Cadestate-Client": "browser-a"}, {"X-Cadestate-Client": "browser-b"}
    mt = {"clip": CLIP, "kind": "manual_track", "track_id": -1}
    with _client(lwh, Requests()) as one, _client(lwh, Requests()) as two:
        first = one.get("/api/next", headers=a).json()
        assert two.get("/api/next", headers=b).json() == first
        assert one.post("/api/claims", json=mt, headers=a).json()["held_by_other"] is False
        other = two.get("/api/next", headers=b).json()
        assert other != first and (other["kind"], other["track_id"]) == ("cad_selection", 0)
        assert two.post("/api/claims", json=mt, headers=b).json()["held_by_other"] is True
        assert two.get("/api/clips", headers=b).json()["held"] == 1
    with _client(lwh, Requests()) as restarted:
        assert restarted.get("/api/next", headers=b).json() == other
        restarted.post("/api/claims/release", json=mt, headers=a)  # a's page, left, tells the app it reaches
        assert restarted.get("/api/next", headers=b).json() == first


def _claim_at_once(root: str, client: str, start: float) -> bool:
    from cadestate.webapp.claims import Claims

    time.sleep(max(0.0, start - time.time()))
    return Claims(root).claim(client, ("c", "cad_selection", 3)) is None


def test_claims_of_processes_at_once_give_an_item_to_one_and_lapse_on_time(tmp_path):
    import multiprocessing

    from cadestate.webapp.claims import Claims

    start = time.time() + 2.0  # every process imported and waiting when the claims are made
    with multiprocessing.get_context("spawn").Pool(4) as pool:
        won = pool.starmap(_claim_at_once, [(str(tmp_path), f"tab-{i}", start) for i in range(4)])
    assert sum(won) == 1
    now = [time.time()]
    claims = Claims(tmp_path, clock=lambda: now[0])
    (item, held), = claims.all().items()
    assert item == ("c", "cad_selection", 3) and held.client == f"tab-{won.index(True)}"
    assert claims.claim(held.client, item) is None and claims.all()[item].since == held.since  # renewed, not restarted
    now[0] += claims.hold_s + 1  # renewed no more: lapsed, and another tab may take it
    assert claims.all() == {} and claims.held_by_others(None) == set()
    assert claims.claim("tab-new", item) is None and len(list((tmp_path / "_claims").glob("*.json"))) == 1
    claims.release("tab-other", item)  # not its claim: kept
    assert set(claims.all()) == {item}
    claims.release("tab-new", item)
    assert claims.all() == {} and list((tmp_path / "_claims").glob("*.json")) == []
    (tmp_path / "_claims" / "edited.json").write_text("{not json")  # a file that is no claim is no bar
    assert claims.all() == {} and claims.claim("tab-new", item) is None


def test_the_start_page_counts_only_waiting_items_as_being_done_elsewhere(lwh):
    """A page stays open after its answer (the panel of what comes next), renewing its claim: the
    other browser's start page said 'nothing else waits: 1 item(s) being done by someone else' for
    as long as it stayed open; ``held`` counts the held items that still wait."""
    a, b = {"X-Cadestate-Client": "browser-a"}, {"X-Cadestate-Client": "browser-b"}
    with _client(lwh, Requests()) as client:
        for track in (0, 99):  # an item of the task, and none (a page of an older task, say)
            client.post("/api/claims", json={"clip": CLIP, "kind": "cad_selection", "track_id": track}, headers=a)
        client.app.state.claims.claim("browser-a", ("gone", "cad_selection", 0))  # a clip removed since its claim
        assert client.get("/api/clips", headers=b).json()["held"] == 1
        assert client.post("/api/answers", json=payload("cad_selection")).status_code == 200  # answers track 0
        assert client.get("/api/clips", headers=b).json()["held"] == 0


def test_the_start_page_asks_for_a_page_of_clips_and_the_next_item_of_all(lwh):
    """A warehouse of thousands of clips was one table of all, every 5 s: a page of ``limit`` clips
    from ``offset`` (with the total) comes back, and the next item is the first of all clips,
    on that page or not."""
    from conftest import table_rows

    for name in ("c2", "c3"):  # clips with no task yet
        lwh.write("clips", name, table_rows("clips", [{"clip": name, "fps": 10.0, "width": 320, "height": 192}]))
    with _client(lwh, Requests()) as client:
        every = client.get("/api/clips").json()
        assert [c["clip"] for c in every["clips"]] == [CLIP, "c2", "c3"] and every["total"] == 3
        page = client.get("/api/clips", params={"offset": 1, "limit": 1}).json()
        assert [c["clip"] for c in page["clips"]] == ["c2"] and (page["total"], page["offset"]) == (3, 1)
        assert page["next"] == every["next"] and page["next"]["clip"] == CLIP  # not on this page
        assert client.get("/api/clips", params={"offset": 5, "limit": 2}).json()["clips"] == []
        assert client.get("/api/clips", params={"limit": 0}).status_code == 422


def test_a_bad_query_or_path_parameter_is_a_one_line_422_naming_it(lwh):
    """FastAPI's own refusal of a parameter was a 422 whose detail was a JSON list of objects (the
    pages showed it as it is); now one line naming the parameter, what is wrong and what was sent,
    as the app's other errors are."""
    with _client(lwh, Requests()) as client:
        for url, said in (("/api/clips?offset=-1", "query parameter offset: input should be greater than or equal to 0 (got '-1')"),
                          ("/api/clips?limit=abc", "query parameter limit: input should be a valid integer"),
                          (f"/api/clips/{CLIP}?wait=soon", "query parameter wait: input should be a valid number"),
                          (f"/api/clips/{CLIP}?wait=-5", "query parameter wait: input should be greater than or equal to 0"),
                          (f"/api/verification_layers/{CLIP}/t/abc", "path parameter track_id: input should be a valid integer")):
            r = client.get(url)
            detail = r.json()["detail"]
            assert r.status_code == 422 and isinstance(detail, str) and detail.startswith(said), r.text
            assert "\n" not in detail and url.split("=")[-1].split("/")[-1] in detail, detail
        both = client.get("/api/clips", params={"offset": -1, "limit": "x"}).json()["detail"]
        assert both.startswith("query parameter offset: ") and "; query parameter limit: " in both, both
        r = client.post("/api/answers", content=b"{not json", headers={"Content-Type": "application/json"})
        assert r.status_code == 422 and r.json()["detail"].startswith("body: not JSON: "), r.text


FAULTS = [("write", "cad_selection_labels"), ("write", "label_effort"), ("write", "label_files"), ("read", "label_files")]


@pytest.mark.parametrize("method,table", FAULTS, ids=[f"{m}:{t}" for m, t in FAULTS])
def test_a_warehouse_failing_mid_ingest_answers_5xx_keeps_the_file_and_the_next_start_ingests_it(lwh, monkeypatch, method, table):
    """Fault injection: the warehouse's own ``write`` (or ``read``) raises OSError for one table during the POST."""
    real = getattr(Warehouse, method)

    def failing(self, name, *args, **kwargs):
        if name == table:
            raise OSError(28, "No space left on device")
        return real(self, name, *args, **kwargs)

    doc = payload("cad_selection")
    doc["answers"][0]["seconds"] = 3.0  # a label_effort row too
    runs = Requests()
    monkeypatch.setattr(Warehouse, method, failing)
    with _client(lwh, runs) as client:
        r = client.post("/api/answers", json=doc)
    monkeypatch.setattr(Warehouse, method, real)  # the disk is back
    assert 500 <= r.status_code < 600, r.text
    detail = r.json()["detail"]
    assert "\n" not in detail and "written but not ingested" in detail and "No space left on device" in detail, detail
    (path,) = _label_files(lwh)
    assert str(lwh.relative(path)) in detail and str(lwh.root) not in detail  # a page is no place for the server's folders
    assert validate_label(path, lwh).kind == "cad_selection"
    assert lwh.read("label_files").num_rows == 0 and current_answers(lwh, "cad_selection", [CLIP]).num_rows == 0
    assert runs.clips == []

    with _client(lwh, runs) as client:
        assert client.app.state.resumer.wait_idle(CLIP, 10)
    assert lwh.read("label_files").column("label_sha256").to_pylist() == [validate_label(path, lwh).sha256]
    assert {a["track_id"]: a["cad_id"] for a in current_answers(lwh, "cad_selection", [CLIP]).to_pylist()} == {0: "m0b", 1: None}
    committed = {(f["label_sha256"], f["ingested_at"]) for f in lwh.read("label_files").to_pylist()}
    effort = [e["seconds"] for e in lwh.read("label_effort").to_pylist() if (e["label_sha256"], e["ingested_at"]) in committed]
    assert effort == [3.0] and runs.clips == [CLIP]  # rows of the failed attempt have no commit record


class Held(Requests):
    """A resume that runs until the test lets it end."""

    def __init__(self):
        super().__init__()
        self.go = threading.Event()

    def __call__(self, clip: str) -> str:
        self.go.wait(30)
        return super().__call__(clip)


def test_a_page_waiting_for_the_next_task_is_answered_when_the_resume_ends(lwh):
    held = Held()
    with _client(lwh, held) as client:
        assert client.post("/api/answers", json=payload("cad_selection")).status_code == 200
        t0 = time.monotonic()
        busy = client.get(f"/api/clips/{CLIP}?wait=0.3").json()  # the resume is still running: answered after 0.3 s
        assert busy["resume"]["state"] in ("queued", "running") and time.monotonic() - t0 >= 0.3
        threading.Timer(0.5, held.go.set).start()
        t0 = time.monotonic()
        done = client.get(f"/api/clips/{CLIP}?wait=20").json()  # answered as the resume ends, not after 20 s
        waited = time.monotonic() - t0
    assert done["resume"]["state"] == "idle" and done["resume"]["runs"] == 1 and held.clips == [CLIP]
    assert 0.3 < waited < 10


def test_a_page_is_answered_when_the_stages_ran_not_when_prefect_has_recorded_them(lwh):
    """The resume's two phases (cadestate.webapp.resume): a page waits for the stages only; an answer
    that comes while the clip is recorded in Prefect queues it at once and runs after the record;
    a record that fails leaves the clip ready, its error kept."""
    runs, record = Requests(), Held()
    config = Config(warehouse=WarehouseConfig(root=str(lwh.root)))
    resumer = Resumer(config, run=runs, record=record, record_delay_s=0)
    with TestClient(create_app(config, annotator="tester", resumer=resumer)) as client:
        assert client.post("/api/answers", json=payload("cad_selection")).status_code == 200
        t0 = time.monotonic()
        ready = client.get(f"/api/clips/{CLIP}?wait=20").json()
        assert time.monotonic() - t0 < 10 and runs.clips == [CLIP] and record.clips == []
        assert ready["resume"]["state"] == "recording" and ready["resume"]["runs"] == 1
        assert client.post("/api/answers", json=payload("cad_selection")).status_code == 200  # during the record
        assert client.get(f"/api/clips/{CLIP}").json()["resume"]["state"] == "queued"  # a page waits again
        record.go.set()
        assert resumer.wait_idle(CLIP, 20, settled=True)
        assert runs.clips == [CLIP, CLIP] and record.clips == [CLIP, CLIP]
        assert client.get(f"/api/clips/{CLIP}").json()["resume"] == {
            "state": "idle", "runs": 2, "message": "ok", "finished_at": resumer.status(CLIP)["finished_at"], "failed": False,
            "prefect": "ok"}

    def broken(clip: str) -> str:
        raise RuntimeError("Prefect's API did not start\nsecond line")

    resumer = Resumer(config, run=runs, record=broken, record_delay_s=0)
    with TestClient(create_app(config, annotator="tester", resumer=resumer)) as client:
        assert client.post("/api/answers", json=payload("cad_selection")).status_code == 200
        assert resumer.wait_idle(CLIP, 20, settled=True)
        resume = client.get(f"/api/clips/{CLIP}").json()["resume"]
    assert resume["state"] == "idle" and resume["message"] == "ok"
    assert resume["prefect"] == "RuntimeError: Prefect's API did not start"


def test_a_clip_answered_again_soon_is_recorded_in_prefect_once_after_its_last_run(lwh):
    """The record waits RECORD_DELAY_S: answers that come meanwhile run the stages again at once,
    and only the last run is recorded (the page loads its next task beside no flow run)."""
    runs, recorded = Requests(), Requests()
    config = Config(warehouse=WarehouseConfig(root=str(lwh.root)))
    resumer = Resumer(config, run=runs, record=recorded, record_delay_s=1.5)
    with TestClient(create_app(config, annotator="tester", resumer=resumer)) as client:
        for _ in range(3):
            assert client.post("/api/answers", json=payload("cad_selection")).status_code == 200
            assert client.get(f"/api/clips/{CLIP}?wait=20").json()["resume"]["state"] == "recording"
        assert recorded.clips == [] and runs.clips == [CLIP] * 3
        assert resumer.wait_idle(CLIP, 20, settled=True)
    assert recorded.clips == [CLIP] and resumer.status(CLIP)["runs"] == 3


def test_another_clips_page_does_not_wait_for_a_record_in_prefect(tmp_path):
    """One worker took clips and records in one line: a clip answered while another's record waited
    (or ran: a whole local flow run) waited for it before its stages ran. Queued clips go first."""
    order, lock = [], threading.Lock()

    def step(what: str):
        def call(clip: str) -> str:
            with lock:
                order.append(f"{what} {clip}")
            return "ok"
        return call

    resumer = Resumer(Config(warehouse=WarehouseConfig(root=str(tmp_path))), run=step("run"), record=step("record"),
                      record_delay_s=1.0).start()
    try:
        resumer.request("a")
        assert resumer.wait_idle("a", 10)
        t0 = time.monotonic()
        resumer.request("b")  # within a's record delay
        assert resumer.wait_idle("b", 10) and time.monotonic() - t0 < 0.9
        assert resumer.wait_idle("a", 10, settled=True) and resumer.wait_idle("b", 10, settled=True)
        assert order == ["run a", "run b", "record a", "record b"]
        assert resumer.status("a")["state"] == resumer.status("b")["state"] == "idle"
        resumer.request("c")  # stopping while its record waits: dropped, and the clip is not left "recording"
        assert resumer.wait_idle("c", 10)
    finally:
        resumer.stop()
    assert not resumer.alive() and resumer.status("c")["state"] == "idle" and order[-1] == "run c"


def test_the_worker_warms_up_before_its_first_resume_and_goes_on_if_that_fails(lwh):
    """An answer that comes while the app warms up (cadestate.webapp.resume.warm_up) is queued and
    runs once the warm-up is over; a warm-up that fails keeps its error and stops nothing."""
    runs, warm = Requests(), Held()
    config = Config(warehouse=WarehouseConfig(root=str(lwh.root)))
    resumer = Resumer(config, run=runs, warm=lambda: warm("warm-up"))
    with TestClient(create_app(config, annotator="tester", resumer=resumer)) as client:
        assert client.post("/api/answers", json=payload("cad_selection")).status_code == 200
        time.sleep(0.3)
        assert not resumer.warmed.is_set() and runs.clips == []
        assert client.get(f"/api/clips/{CLIP}").json()["resume"]["state"] == "queued"
        warm.go.set()
        assert client.get(f"/api/clips/{CLIP}?wait=20").json()["resume"]["state"] == "idle"
    assert warm.clips == ["warm-up"] and runs.clips == [CLIP] and resumer.warm_message == "ok"

    def broken() -> str:
        raise ImportError("no module named torch")

    _ran(lwh)  # what a real resume records: else the next start resumes the clip answered above
    runs = Requests()
    resumer = Resumer(config, run=runs, warm=broken)
    with TestClient(create_app(config, annotator="tester", resumer=resumer)) as client:
        assert resumer.warmed.wait(20) and resumer.warm_message == "ImportError: no module named torch"
        assert client.post("/api/answers", json=payload("cad_selection")).status_code == 200
        assert client.get(f"/api/clips/{CLIP}?wait=20").json()["resume"]["state"] == "idle"
    assert runs.clips == [CLIP]


def test_the_real_warm_up_imports_what_an_answer_runs(lwh):
    from cadestate.webapp.resume import warm_up

    config = Config(warehouse=WarehouseConfig(root=str(lwh.root)))
    assert warm_up(config) == "6 stages imported, the catalog checked"
    assert {"tasks.pose.pose", "tasks.human.verification", "tasks.retrieval.retrieval"} <= set(sys.modules)
    assert (lwh.root / "catalog.duckdb").is_file()


def test_the_warm_up_reads_ahead_what_the_first_resume_of_a_waiting_clip_reads(lwh, monkeypatch):
    """With the app's read cache, the first answer's resume opens no file its digests read."""
    import pyarrow.parquet as pq

    from cadestate.webapp.resume import warm_up
    from tasks.inputs_memo import InputsMemo
    from tasks.registry import stages_of
    from tasks.status import read_runs
    from warehouse.read_cache import ReadCache

    config, cache = Config(warehouse=WarehouseConfig(root=str(lwh.root))), ReadCache()
    assert warm_up(config, cache).endswith(", 1 clip(s) with items waiting read")
    opened: list[str] = []
    real = pq.ParquetFile
    monkeypatch.setattr(pq, "ParquetFile", lambda f, *a, **k: opened.append(str(f)) or real(f, *a, **k))
    wh = Warehouse(lwh.root).cache_reads(cache=cache)  # what tasks.stage_chain.run_unit reads before its stages
    memo = InputsMemo(wh, CLIP)
    digests = [memo.clip_inputs(s, fresh=True) for s in stages_of("clip") if not s.has("source_inputs")]
    read_runs(wh, [CLIP])
    assert any(digests) and opened == []
    assert digests == [InputsMemo(Warehouse(lwh.root), CLIP).clip_inputs(s, fresh=True)
                       for s in stages_of("clip") if not s.has("source_inputs")]  # the same digests as uncached


def _one(track: int, cad_id: str | None) -> dict:
    """A CAD-selection answer to one track of task c1.cs."""
    return {**payload("cad_selection"), "answers": [{"track_id": track, "cad_id": cad_id}]}


def test_an_item_answered_since_the_page_loaded_is_a_409_not_a_silent_replacement(lwh):
    """Two tabs (or annotators) on one item: the second to answer is told, and nothing of theirs is
    written; another item of the same task, or the item once reloaded, is answered as usual."""
    with _client(lwh, Requests()) as client:
        tab_a = client.get(f"/api/tasks/{CLIP}/c1.cs").json()["as_of"]
        tab_b = client.get(f"/api/tasks/{CLIP}/c1.cs").json()["as_of"]
        assert tab_a == tab_b == ""  # nothing answered yet
        assert client.post("/api/answers", json=_one(0, "m0a"), params={"as_of": tab_b}).status_code == 200
        late = client.post("/api/answers", json=_one(0, "m0b"), params={"as_of": tab_a})
        assert late.status_code == 409 and "this item was answered by tester at " in late.json()["detail"], late.text
        assert " UTC since the page loaded" in late.json()["detail"]  # the time is the warehouse's (UTC), not the reader's clock
        assert client.post("/api/answers", json=_one(2, "m2b"), params={"as_of": tab_a}).status_code == 200  # another item
        reloaded = client.get(f"/api/tasks/{CLIP}/c1.cs").json()
        assert reloaded["answered"] == [0, 2] and reloaded["as_of"] > tab_a
        assert client.post("/api/answers", json=_one(0, "m0b"), params={"as_of": reloaded["as_of"]}).status_code == 200
        bad = client.post("/api/answers", json=_one(1, None), params={"as_of": "yesterday"})
        assert bad.status_code == 422 and "as_of: 'yesterday' is not an ISO 8601 time" in bad.json()["detail"]
    assert len(_label_files(lwh)) == 3
    assert {a["track_id"]: a["cad_id"] for a in current_answers(lwh, "cad_selection", [CLIP]).to_pylist()} == {0: "m0b", 2: "m2b"}


def test_an_answer_sent_again_after_its_reply_was_lost_is_said_saved(lwh):
    """The answer was saved but its reply lost (the network): the page said the error, and the same
    answer sent again met a 409 naming its own annotator, "yours was not saved". The same answers
    (but the seconds, counted anew) by the same annotator are that answer: said saved, nothing written."""
    runs = Requests()
    with _client(lwh, runs) as client:
        first = client.post("/api/answers", json=_one(0, "m0a") | {"answers": [{"track_id": 0, "cad_id": "m0a", "seconds": 4.0}]},
                            params={"as_of": ""})
        assert first.status_code == 200, first.text
        assert client.app.state.resumer.wait_idle(CLIP, 10)
        again = client.post("/api/answers", json=_one(0, "m0a") | {"answers": [{"track_id": 0, "cad_id": "m0a", "seconds": 9.5}]},
                            params={"as_of": ""})
        assert again.status_code == 200 and again.json()["path"] == first.json()["path"], again.text
        assert again.json()["warnings"] == ["this answer was saved already (sent again, the reply to it lost on the way): "
                                            "nothing written"]
        assert client.app.state.resumer.wait_idle(CLIP, 10) and runs.clips == [CLIP]  # nothing new: no resume
        other = client.post("/api/answers", json=_one(0, "m0b"), params={"as_of": ""})  # another answer: refused as before
        assert other.status_code == 409 and "yours was not saved" in other.json()["detail"]
        drawn = {**payload("manual_track"), "seconds": 30.0}
        assert client.post("/api/answers", json=drawn, params={"as_of": ""}).status_code == 200
        assert client.post("/api/answers", json={**drawn, "seconds": 41.0}, params={"as_of": ""}).json()["warnings"][-1] \
            .startswith("this answer was saved already")
        changed = client.post("/api/answers", json={**drawn, "not_objects": [0]}, params={"as_of": ""})  # one more thing said
        assert changed.status_code == 409, changed.text
    assert len(_label_files(lwh)) == 2


@pytest.mark.parametrize("kind", ["manual_track", "cad_selection", "correspondences", "verification"])
def test_a_task_served_after_an_answer_shows_that_answer_before_any_resume(lwh, kind):
    """The task file holds an answer only once the clip's resume has rerun its stage: a page opened
    before that (Back, a 409's reload, a resume that failed) showed the answer as it was when the
    task was written (an empty manual-track answer that Enter saved over the objects drawn). The
    served task's items carry the answer in force now."""
    task_id = payload(kind)["task_id"]
    with _client(lwh, Requests()) as client:
        before = client.get(f"/api/tasks/{CLIP}/{task_id}").json()["task"]
        first = payload(kind)
        if kind == "manual_track":
            first = {**first, "not_objects": [0]}
        if kind == "cad_selection":
            first["answers"][1] = {"track_id": 1, "cad_id": None, "same_as_track": 0}
        if kind == "verification":
            first["answers"][0]["same_as_track"] = 1
        assert client.post("/api/answers", json=first).status_code == 200
        served = client.get(f"/api/tasks/{CLIP}/{task_id}").json()["task"]
    strip = lambda a: {k: v for k, v in a.items() if k != "seconds" and v is not None}  # noqa: E731
    if kind == "manual_track":
        assert before.get("previous", []) == []
        assert [strip(a) for a in served["previous"]] == [strip(a) for a in first["answers"]]
        assert served["previous_not_objects"] == [0]
        return
    shown = {it["track_id"]: strip(it["previous"]) for it in served["items"] if it.get("previous")}
    assert shown == {a["track_id"]: strip(a) for a in first["answers"]}
    assert all(not it.get("previous") for it in before["items"])
    assert [it["track_id"] for it in served["items"]] == [it["track_id"] for it in before["items"]]


def test_a_correspondences_item_whose_clicks_gave_no_pose_says_why(lwh):
    """The pose stage runs after the correspondences task: a pose the solver could not make from a
    person's clicks was lost without a word. The item, served again, carries the status, message and
    per-key-frame errors of the pose solved from the answer in force, and nothing for an answer newer
    than the last pose run (not solved yet) or for a pose that is ok."""
    import datetime as dt

    from conftest import table_rows

    with _client(lwh, Requests()) as client:
        assert client.post("/api/answers", json=payload("correspondences")).status_code == 200
        answered = max(lwh.read("label_files").column("ingested_at").to_pylist())
        later = answered + dt.timedelta(microseconds=1)  # the pose run after that answer
        lwh.write("runs", CLIP, table_rows("runs", [{"clip": CLIP, "run_id": "r-pose", "stage": "pose", "status": "completed",
                                                      "started_at": later}]))
        bad = {"clip": CLIP, "track_id": "0", "status": "high_residual", "message": "mean reprojection error 31.0 px > 20.0 px",
               "keyframe_timestamps_us": [0, 300_000], "keyframe_error_px": [2.0, 60.0]}
        lwh.write("poses", CLIP, table_rows("poses", [bad, {**bad, "track_id": "1", "status": "ok"}]))
        items = {it["track_id"]: it for it in client.get(f"/api/tasks/{CLIP}/c1.co").json()["task"]["items"]}
        assert items[0]["pose_failed"] == {"status": "high_residual", "message": "mean reprojection error 31.0 px > 20.0 px",
                                           "keyframe_error_px": {"0": 2.0, "300000": 60.0}}
        assert "pose_failed" not in items[1]  # no answer of its own here, and its pose is ok
        (co,) = [t for t in client.get("/api/clips").json()["clips"][0]["tasks"] if t["kind"] == "correspondences"]
        assert co["pose_failed"] == [0]  # the start page links to it
        assert client.post("/api/answers", json=payload("correspondences")).status_code == 200  # answered again after the run
        items = {it["track_id"]: it for it in client.get(f"/api/tasks/{CLIP}/c1.co").json()["task"]["items"]}
        assert "pose_failed" not in items[0]


def test_an_answer_to_a_task_the_pipeline_replaced_goes_to_the_new_task_where_it_fits(lwh):
    """A page left open on a task that a rerun replaced (a fragment or a drawn object changes the
    tracks asked about): the answer is saved to the newest task when it fits it (there, "none of these"
    and fragments were lost: only chosen models were carried over); one that does not fit (its track
    is no item there) is a 409, nothing written."""
    from test_labels import _tasks

    older = _tasks()[1]
    write_task(lwh, dataclasses.replace(older, task_id="c1.cs2", created_at="2026-01-01T00:01:00+00:00",
                                        items=older.items[:2]))  # track 2 is no longer asked about
    with _client(lwh, Requests()) as client:
        assert client.get(f"/api/tasks/{CLIP}/c1.cs").json()["current"] is False
        assert client.get(f"/api/tasks/{CLIP}/c1.cs2").json()["current"] is True
        moved = client.post("/api/answers", json=_one(0, None), params={"as_of": ""})
        assert moved.status_code == 200 and moved.json()["task_id"] == "c1.cs2", moved.text
        assert "task c1.cs was replaced by task c1.cs2" in moved.json()["warnings"][0]
        gone = client.post("/api/answers", json=_one(2, "m2a"))
        assert gone.status_code == 409 and "task c1.cs was replaced by task c1.cs2 (the pipeline ran again), which " \
            "this answer does not fit (answer: $.answers[0].track_id: unknown track 2" in gone.json()["detail"], gone.text
        assert "the queue opens task c1.cs2" in gone.json()["detail"]  # not "reload the page", which opens c1.cs again
        again = client.post("/api/answers", json=_one(0, "m0a"), params={"as_of": ""})  # the page saw no answer
        assert again.status_code == 409 and "this item was answered by tester" in again.json()["detail"], again.text
    assert len(_label_files(lwh)) == 1
    assert [(a["task_id"], a["track_id"], a["cad_id"]) for a in current_answers(lwh, "cad_selection", [CLIP]).to_pylist()] \
        == [("c1.cs2", 0, None)]


def test_a_left_answer_answered_again_since_is_set_aside_not_put_in_force(lwh, monkeypatch, capsys):
    """An answer written but not ingested (the warehouse failed), then answered again once the
    warehouse was back: at the next start the left file is set aside, since ingested then it would
    come in force over the newer answer."""
    real = Warehouse.write

    def failing(self, name, *args, **kwargs):
        if name == "label_files":
            raise OSError(28, "No space left on device")
        return real(self, name, *args, **kwargs)

    with _client(lwh, Requests()) as client:
        monkeypatch.setattr(Warehouse, "write", failing)
        assert client.post("/api/answers", json=_one(0, "m0a")).status_code == 500
        monkeypatch.setattr(Warehouse, "write", real)
        assert client.post("/api/answers", json=_one(0, None)).status_code == 200
    (left,) = [p for p in _label_files(lwh) if validate_label(p, lwh).label.answers[0].cad_id == "m0a"]
    with _client(lwh, Requests()):
        pass
    assert not left.exists() and left.with_name(left.name + ".superseded").is_file()
    assert f"warning: {left}: not ingested, its items were answered again at " in capsys.readouterr().err
    assert {a["track_id"]: a["cad_id"] for a in current_answers(lwh, "cad_selection", [CLIP]).to_pylist()} == {0: None}
    assert lwh.read("label_files").num_rows == 1


def test_layers_that_cannot_be_rendered_are_a_one_line_503_and_odd_media_names_a_404(lwh):
    with _client(lwh, Requests()) as client:
        r = client.get(f"/api/verification_layers/{CLIP}/c1.ve/0")  # its mesh m.glb is nowhere
        assert r.status_code == 503 and r.json()["detail"].startswith("cannot render track 0's posed model: ") and \
            "\n" not in r.json()["detail"] and str(lwh.root) not in r.json()["detail"], r.text
        assert client.get("/media/" + "x" * 300).status_code == 404
        assert client.get("/media/a%00b").status_code == 404
        assert client.get("/api/next", params={"clip": "nope"}).status_code == 404


def test_a_verdict_or_none_of_these_is_not_moved_onto_a_pose_or_candidates_nobody_saw(lwh):
    """A verification answer names no model nor pose, and "none of these" no candidate: each
    validated against any task that replaced its own, so an Accept given to track 0 posed as m0a
    was recorded against a rerun's m0b, posed elsewhere, mirrored. Unchanged items still move."""
    from schemas.labels import Pose
    from test_labels import _tasks

    cs, ve = _tasks()[1], _tasks()[3]
    moved_pose = Pose(translation=(1.5, 0.0, 4.0), rotation=(0.0, 1.0, 0.0, 0.0), scale=(2.0, 2.0, 2.0), is_mirrored=True)
    write_task(lwh, dataclasses.replace(ve, task_id="c1.ve2", created_at="2026-01-01T00:05:00+00:00",
                                        items=(dataclasses.replace(ve.items[0], cad_id="m0b", pose=moved_pose), *ve.items[1:])))
    write_task(lwh, dataclasses.replace(cs, task_id="c1.cs2", created_at="2026-01-01T00:05:00+00:00", items=(
        dataclasses.replace(cs.items[0], candidates=cs.items[0].candidates[::-1]), *cs.items[1:])))
    verdict = lambda t: {"kind": "verification", "clip": CLIP, "task_id": "c1.ve",  # noqa: E731
                         "answers": [{"track_id": t, "verdict": "accept"}]}
    with _client(lwh, Requests()) as client:
        posed_anew = client.post("/api/answers", json=verdict(0))
        assert posed_anew.status_code == 409 and "track 0 is posed anew there (m0b)" in posed_anew.json()["detail"], posed_anew.text
        same = client.post("/api/answers", json=verdict(1))
        assert same.status_code == 200 and same.json()["task_id"] == "c1.ve2", same.text
        none_of_others = client.post("/api/answers", json=_one(0, None))
        assert none_of_others.status_code == 409 and "track 0 has other candidates there" in none_of_others.json()["detail"]
        assert client.post("/api/answers", json=_one(0, "m0a")).status_code == 200  # a model chosen: still one of them
        assert client.post("/api/answers", json=_one(1, None)).status_code == 200  # the same candidates: moved
    assert len(_label_files(lwh)) == 3


def test_two_apps_on_one_warehouse_do_not_both_take_an_answer_to_one_item(lwh):
    """Each annotator may run their own app on a shared warehouse: the check that nothing was
    answered since the page loaded, the write and the ingest were one step within an app only, so
    two answers to one item at once were both taken and the later silently replaced the other."""
    with _client(lwh, Requests()) as first, _client(lwh, Requests()) as second:
        for track in (0, 1, 2):
            as_of = first.get(f"/api/tasks/{CLIP}/c1.cs").json()["as_of"]
            go = threading.Barrier(2)

            def send(client, cad_id):
                go.wait()
                return client.post("/api/answers", json=_one(track, cad_id), params={"as_of": as_of}).status_code

            with ThreadPoolExecutor(2) as pool:
                codes = sorted(pool.map(send, (first, second), (f"m{track}a", f"m{track}b")))
            assert codes == [200, 409], (track, codes)
    assert len(_label_files(lwh)) == 3


def test_an_answer_committed_whose_clicks_table_failed_to_update_is_saved_and_its_clip_resumed(lwh, monkeypatch):
    """Fault injection: the warehouse's ``write`` of ``correspondences`` raises OSError after the
    answer was committed. It was a 500 "written but not ingested", though in force: the page's
    second try met a 409 against its own answer, and the clip (whose run rewrites the table) was
    never resumed."""
    real = Warehouse.write

    def failing(self, name, *args, **kwargs):
        if name == "correspondences":
            raise OSError(28, "No space left on device")
        return real(self, name, *args, **kwargs)

    runs = Requests()
    monkeypatch.setattr(Warehouse, "write", failing)
    with _client(lwh, runs) as client:
        r = client.post("/api/answers", json=payload("correspondences"), params={"as_of": ""})
        assert client.app.state.resumer.wait_idle(CLIP, 10)
    assert r.status_code == 200, r.text
    assert any("the correspondences table was not updated" in w and "No space left" in w for w in r.json()["warnings"])
    assert runs.clips == [CLIP] and current_answers(lwh, "correspondences", [CLIP]).num_rows > 0


def test_a_clip_answered_since_its_last_run_is_resumed_when_the_app_starts(lwh, tmp_path):
    """The resume queue is in memory: an answer taken while the worker was busy (another clip, the
    warm-up) was never resumed once the app stopped, nor by the next start, though the app said
    "a clip it ran resumes on the next start". Answers ingested by `cadestate labels ingest` with no
    run since are resumed too; a clip whose run started after its newest answer is not."""
    from tasks.human.label_ingest import ingest_labels

    doc = {**good("verification")}
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "v.json").write_text(json.dumps(doc))
    assert ingest_labels(lwh, tmp_path / "in").ok
    runs = Requests()
    with _client(lwh, runs) as client:
        assert client.app.state.resumer.wait_idle(CLIP, 10)
    assert runs.clips == [CLIP]
    _ran(lwh)
    again = Requests()
    with _client(lwh, again) as client:
        assert client.app.state.resumer.wait_idle(CLIP, 10)
    assert again.clips == []


def test_a_body_larger_than_an_answer_may_be_is_refused_before_it_is_read(lwh):
    """FastAPI read and parsed a body of any size before the answer's check refused it (24 MB: 7 s
    and 250 MB of memory), for anyone who could reach the app."""
    from tasks.human.label_format import MAX_LABEL_BYTES

    big = b'{"kind": "cad_selection", "pad": "' + b"x" * MAX_LABEL_BYTES + b'"}'
    with _client(lwh, Requests()) as client:
        r = client.post("/api/answers", content=big, headers={"Content-Type": "application/json"})
        assert r.status_code == 413 and r.json()["detail"].startswith("the request's body is 20.0 MB, more than an answer"), r.text
        # sent in chunks, with no length: it was read whole, then refused naming `labels ingest`'s --max-mb
        chunked = client.post("/api/answers", content=iter([big[:1000], big[1000:]]), headers={"Content-Type": "application/json"})
        assert chunked.status_code == 411 and "needs a Content-Length" in chunked.json()["detail"], chunked.text
        assert client.post("/api/answers", json=payload("cad_selection")).status_code == 200
    assert len(_label_files(lwh)) == 1


def test_claims_are_kept_in_the_warehouse_a_tilde_root_names(tmp_path, monkeypatch):
    """A root given as ~/wh: the tables went to $HOME/wh but the claims to ./~/wh/_claims, so two
    apps started from other folders did not see each other's claims (both gave one item)."""
    from cadestate.webapp.claims import CLAIMS_DIR

    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.chdir(tmp_path)
    config = Config(warehouse=WarehouseConfig(root="~/wh"))
    app = create_app(config, annotator="tester", resumer=Resumer(config, run=Requests()))
    assert app.state.claims.folder == tmp_path / "home" / "wh" / CLAIMS_DIR
