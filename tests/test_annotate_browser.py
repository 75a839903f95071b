"""A fresh benchmark clip from ingest to verified poses, answered only in the browser (issue 15).

The annotation app (``cadestate annotate``) serves a warehouse whose val clip (a rendered
walkthrough, real small CAD library) has just paused at its manual-track task. Debian's Chromium,
driven by Playwright, answers the four pages in pipeline order by clicking and typing; what it
enters comes from the benchmark's simulated annotators (``bench.simulated_labels.answer_tasks``:
ground truth plus their noise), so the clicks on the 3D model and the image are at positions
computed from the ground truth. Each test checks that the label file the app wrote validates, is
ingested, and that the background resume took the clip to its next stage; each saves a screenshot
(``$CADESTATE_SCREENSHOTS``, else the test's temporary folder). The tests run in order and share
the clip: a later one skips when an earlier one failed.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
from pathlib import Path

import numpy as np
import pytest

from bench.benchmark import clip_sources, generate
from bench.simulated_labels import answer_tasks
from bench.walkthrough import WalkthroughSpec
from browser import chromium_path, launch, served_app
from conftest import warehouse_copy
from tasks.human.labels import validate_label
from tasks.tracking.relations import verification_statements
from warehouse import Warehouse

pytestmark = [pytest.mark.slow, pytest.mark.skipif(chromium_path() is None, reason="chromium not installed (make browser)")]
playwright_api = pytest.importorskip("playwright.sync_api")

SPEC = WalkthroughSpec(width=480, height=270, num_video_frames=60, sample_every=2, alone_scale=0.5)
SEED = 3
RESUME_S = 400  # a resume runs the clip's flow on 2 shared cores (Prefect's local API starts first)


@dataclasses.dataclass
class Served:
    wh: Warehouse
    bench: Path
    clip: str
    url: str
    page: object
    shots: Path
    failed: list = dataclasses.field(default_factory=list)


@pytest.fixture(scope="module")
def served(small_library_warehouse, tmp_path_factory):
    from cadestate.webapp.app import create_app
    from flows.annotate_clip import run_clips

    tmp = tmp_path_factory.mktemp("annotate")
    folder = tmp / "bench"
    manifest, _ = generate(folder, SEED, 1, Warehouse(small_library_warehouse.warehouse.root), SPEC, show_progress=False)
    clip, source = manifest.clips[0], dataclasses.replace(clip_sources(folder)[0], split="val")
    config = warehouse_copy(small_library_warehouse, tmp / "wh")
    # every pair of poses flagged as maybe one object, so the verification page shows its flag on this small clip
    config = dataclasses.replace(config, verification=dataclasses.replace(config.verification, duplicate_overlap=0.0))
    reports = run_clips([source], config, show_progress=False)
    assert {r.stage for r in reports if r.state == "paused"} == {"manual_tracks"}

    shots = Path(os.environ.get("CADESTATE_SCREENSHOTS") or tmp / "screens")
    shots.mkdir(parents=True, exist_ok=True)
    with served_app(create_app(config, annotator="browser-test")) as url, playwright_api.sync_playwright() as p:
        browser = launch(p)
        page = browser.new_page(viewport={"width": 1400, "height": 860})
        page.set_default_timeout(30_000)
        yield Served(Warehouse(config.warehouse.root), folder, clip, url, page, shots)
        browser.close()


SCREENSHOT_TIMEOUT_MS = 120_000
"""A screenshot of a page with a WebGL view (SwiftShader) on a loaded 2-core machine took over 30 s
(the page's default) in one fresh-clone run; the page itself had answered within its waits."""


@pytest.fixture
def s(served, request):
    """The shared clip; skips when an earlier page failed (the clip did not reach this task)."""
    if served.failed:
        pytest.skip(f"an earlier page failed: {served.failed[0]}")
    failed_before = request.session.testsfailed
    yield served
    if request.session.testsfailed > failed_before:  # the call phase is reported before teardown
        served.failed.append(request.node.name)


def simulated(s: Served, kind: str) -> dict:
    """The simulated annotators' answers to the clip's open ``kind`` task (their files removed: the
    browser is the only way in)."""
    docs = []
    for path in answer_tasks(s.bench, s.wh, s.clip):
        docs.append(json.loads(path.read_text()))
        path.unlink()
    found = [d for d in docs if d["kind"] == kind]
    assert found, f"no open {kind} task (open: {[d['kind'] for d in docs]})"
    return found[0]


def open_next(s: Served, kind: str) -> dict:
    """Open the clip's next waiting item (of ``kind``); returns the queue's entry for it."""
    nxt = json.loads(s.page.context.request.get(f"{s.url}/api/next?clip={s.clip}").text())
    assert nxt and nxt["kind"] == kind, nxt
    s.page.goto(s.url + nxt["url"])
    return nxt


def wait_for_pipeline(s: Served) -> str:
    """Wait for the page's 'next task ready' line (after the last item of a task); returns it."""
    s.page.wait_for_selector("#next-ready", timeout=RESUME_S * 1000)
    return s.page.inner_text("#next-ready")


def track_shown(s: Served) -> int:
    return int(re.match(r"Track (\d+)", s.page.inner_text("#track-title")).group(1))


def new_label_files(s: Served, kind: str, seen: set) -> list:
    """The app's label files of ``kind`` not seen before, each validated against the warehouse and ingested."""
    ingested = set(s.wh.read("label_files").column("label_sha256").to_pylist())
    out = []
    for path in sorted((s.wh.root / "labels" / s.clip).glob("*.json")):
        if path in seen:
            continue
        seen.add(path)
        lf = validate_label(path, s.wh)
        if lf.kind == kind:
            assert lf.sha256 in ingested and lf.label.annotator == "browser-test"
            out.append(lf)
    return out


def relations(s: Served, kind: str) -> set[tuple]:
    """The clip's ``track_relations`` rows of ``kind``: (relation, track_id, other_track_id, object_index)."""
    rows = s.wh.read("track_relations", [s.clip]).to_pylist() if s.clip in s.wh.partitions("track_relations") else []
    return {(r["relation"], r["track_id"], r["other_track_id"], r["object_index"]) for r in rows if r["kind"] == kind}


SEEN: set = set()


def test_manual_tracks_page(s):
    answer = simulated(s, "manual_track")
    opened = open_next(s, "manual_track")
    page = s.page
    task = page.evaluate("""async () => { const p = new URLSearchParams(location.search);
        const r = await fetch(`/api/tasks/${p.get('clip')}/${p.get('task')}`); return (await r.json()).task; }""")
    stamps = [int(k["timestamp_us"]) for k in task["keyframes"]]
    existing = [t["track_id"] for t in task["existing_tracks"]]
    assert answer["answers"] and all(o["boxes"] for o in answer["answers"]), "the simulated annotators drew no object"
    assert len(existing) >= 2, f"the clip has tracks {existing}: too few to relate the drawn objects to"
    for i, obj in enumerate(answer["answers"]):
        page.keyboard.press("n")
        page.locator("input.cls").nth(i).fill(obj["label"])
        page.locator("input.cls").nth(i).dispatch_event("change")
        page.locator("input.cls").nth(i).blur()
        for b in obj["boxes"]:
            page.locator("#strip .thumb").nth(stamps.index(b["timestamp_us"])).click()
            page.wait_for_function("() => document.querySelector('#draw') && document.querySelector('#draw').width > 0")
            r = page.locator("#draw").bounding_box()
            y0, x0, y1, x1 = b["box"]
            page.mouse.move(r["x"] + x0 * r["width"], r["y"] + y0 * r["height"])
            page.mouse.down()
            page.mouse.move(r["x"] + x1 * r["width"], r["y"] + y1 * r["height"], steps=4)
            page.mouse.up()
    # "this is track N" on the first object and "track M is not an object". The clip's third track (a chair
    # seen in 4 frames at detector scores near the threshold) is not always found; with two tracks the drawn
    # object stays its own, so that the CAD-selection task still has two items (a fragment needs another track).
    same = existing[0] if len(existing) >= 3 else None
    not_object = existing[-1]
    if same is not None:
        page.locator("select.same").nth(0).select_option(str(same))
    page.locator(f'input.not-object[data-track="{not_object}"]').check()
    page.screenshot(path=s.shots / "manual_track.png", timeout=SCREENSHOT_TIMEOUT_MS)
    asked = []  # leaving for the queue with objects drawn and not submitted: the browser asks first
    page.once("dialog", lambda d: (asked.append(d.type), d.dismiss()))
    page.click("header a", no_wait_after=True)
    page.wait_for_timeout(300)
    assert asked == ["beforeunload"] and "/annotate/manual_track" in page.url, (asked, page.url)
    page.evaluate("document.activeElement.blur()")  # Enter below is the page's, not the link's
    page.keyboard.press("Enter")
    page.keyboard.press("Enter")  # a second press while the answer is on its way sends nothing
    ready = wait_for_pipeline(s)
    (lf,) = new_label_files(s, "manual_track", SEEN)
    drawn, expected = lf.label.answers, answer["answers"]
    assert [a.label for a in drawn] == [o["label"] for o in expected]
    for a, o in zip(drawn, expected):
        assert [b.timestamp_us for b in a.boxes] == [b["timestamp_us"] for b in o["boxes"]]
        assert np.allclose([b.box for b in a.boxes], [b["box"] for b in o["boxes"]], atol=0.01)
    assert lf.label.seconds is not None and lf.label.seconds > 0
    assert [a.same_as_track for a in drawn] == [same] + [None] * (len(drawn) - 1) and list(lf.label.not_objects) == [not_object]
    assert relations(s, "manual_track") == ({("same_object", same, None, 0)} if same is not None else set()) | {
        ("not_object", not_object, None, None)}
    assert "cad_selection" in ready, ready
    page.goto(s.url + opened["url"])  # reopened, the task shows its whole answer: submitting it again loses nothing
    page.wait_for_selector("select.same")
    assert page.locator(f'input.not-object[data-track="{not_object}"]').is_checked()
    assert page.locator("select.same").nth(0).input_value() == ("" if same is None else str(same))


def test_cad_selection_page(s):
    answer = {a["track_id"]: a["cad_id"] for a in simulated(s, "cad_selection")["answers"]}
    nxt = open_next(s, "cad_selection")
    page, done = s.page, []
    page.wait_for_selector("#track-title:not(:empty)")
    first = track_shown(s)
    other = next((t for t in answer if t != first), None)
    assert other is not None, f"a one-item task ({first}): no track to call it a fragment of"
    page.select_option("#same", str(other))  # "same object as track N" (a fragment), then answered again for real
    page.keyboard.press("f")  # the drop-down let go of the keys once chosen in
    assert page.inner_text("#choice") == f"fragment of track {other}"
    page.click("#submit")
    page.wait_for_url(re.compile(rf"track=(?!{first}\b)\d+"))
    page.goto(f"{s.url}/annotate/cad_selection?clip={s.clip}&task={nxt['task_id']}&track={first}")
    while True:
        page.wait_for_selector("#track-title:not(:empty)")
        track = track_shown(s)
        choice = answer[track]
        page.click(f'.cand[data-cad="{choice}"]' if choice else "#none")
        if not done:  # Enter on a button reached by keyboard presses it: it had submitted the choice made before instead
            page.focus("#none")
            page.keyboard.press("Shift+Tab")
            page.keyboard.press("Tab")  # keyboard focus (:focus-visible), not a click's
            assert page.evaluate("document.activeElement.id") == "none"
            page.keyboard.press("Enter")
            page.wait_for_timeout(300)
            assert page.inner_text("#choice") == "none of these" and f"track={track}" in page.url, page.url
            page.click(f'.cand[data-cad="{choice}"]' if choice else "#none")
            page.screenshot(path=s.shots / "cad_selection.png", timeout=SCREENSHOT_TIMEOUT_MS)
        if len(done) == 1:
            page.keyboard.press("Enter")  # the card or button clicked has the focus, a mouse's: Enter is the page's, submit
        else:
            page.click("#submit")
        done.append(track)
        if len(done) == len(answer):
            break
        page.wait_for_url(re.compile(rf"track=(?!{track}\b)\d+"))
    ready = wait_for_pipeline(s)
    files = new_label_files(s, "cad_selection", SEEN)
    assert len(files) == len(answer) + 1, [lf.path.name for lf in files]
    fragment = files[0].label.answers  # the files sort by time: the fragment answer came first
    assert [(a.track_id, a.cad_id, a.same_as_track) for a in fragment] == [(first, None, other)]
    got = {a.track_id: a.cad_id for lf in files[1:] for a in lf.label.answers}
    assert got == answer and sorted(done) == sorted(answer)
    assert relations(s, "cad_selection") == {("same_object", first, other, None)}
    assert "correspondences" in ready, ready
    assert all(a.seconds is not None for lf in files for a in lf.label.answers)


VIEWS = [(0.6, 0.5, 0.8), (-0.6, 0.5, 0.8), (0.6, 0.5, -0.8), (-0.6, 0.5, -0.8), (0, 1, 0.05), (0, 0.3, 1), (0, 0.3, -1),
         (1, 0.3, 0), (-1, 0.3, 0), (0.7, -0.3, 0.7), (-0.7, -0.3, 0.7), (0.7, -0.3, -0.7), (-0.7, -0.3, -0.7), (0, -1, 0.05)]
"""Camera directions (world, from the model's centre) the test orbits through to see a point."""


def _click_pairs(s: Served, kf_index: int, points: list[dict], where: list | None = None) -> int:
    """Click the pairs ``points`` on key-frame ``kf_index``; ``where`` collects each clicked pair's
    view direction and screen position on the model."""
    page = s.page
    page.locator("#strip .thumb").nth(kf_index).click()
    page.wait_for_function("() => document.querySelector('#image-canvas') && document.querySelector('#image-canvas').width > 0")
    clicked = 0
    for q in points:
        for d in VIEWS:  # orbit until the point is in sight, as a person would
            page.evaluate("dir => viewer.viewDirection(dir)", d)
            sx, sy = page.evaluate("xyz => viewer.screenOf(xyz)", q["xyz"])
            hit = page.evaluate("([x, y]) => viewer.pick(x, y)", [sx, sy])
            if hit is not None and np.linalg.norm(np.subtract(hit, q["xyz"])) < 0.01:
                break
        else:
            continue  # hidden from every side: a person would click another point
        page.mouse.click(sx, sy)
        if where is not None:
            where.append((d, sx, sy))
        r = page.locator("#image-canvas").bounding_box()
        page.mouse.click(r["x"] + q["x"] * r["width"], r["y"] + q["y"] * r["height"])
        clicked += 1
    return clicked


def _assert_a_paired_model_point_is_refused(s: Served, direction, sx: float, sy: float) -> None:
    """Clicking the model point of the key-frame's first pair again (the same view, the same spot)
    is refused on the page, naming the pair (the label format would refuse it at submit), and no
    pair is started."""
    page = s.page
    page.evaluate("dir => viewer.viewDirection(dir)", direction)
    page.mouse.click(sx, sy)
    assert "the model point of pair 1" in page.locator(".toast.error").last.inner_text()
    assert "now click it in the image" not in page.inner_text("#pairs")


def _assert_narrow_warning(s: Served, task: dict, cad_id: str) -> None:
    """The page warns of a model axis the track's clicks hardly span exactly when the solver ties
    its scale (:func:`tasks.pose.checks.unobserved_axes` with the served ``[pose] min_axis_span``),
    naming the same axes; the model size the page measures is the one the solver reads
    (``cad_models.extent``), and the page's rule is the solver's on random points too."""
    from tasks.pose.checks import unobserved_axes

    page, span = s.page, task["pose"]["min_axis_span"]
    [extent] = [r["extent"] for r in s.wh.read("cad_models", columns=["cad_id", "extent"]).to_pylist() if r["cad_id"] == cad_id]
    assert np.allclose(page.evaluate("() => viewer.size"), extent, rtol=1e-3, atol=1e-4)
    points = np.array(page.evaluate("() => pairs.flat().map((q) => q.xyz)"))
    want = ", ".join("xyz"[a] for a in np.flatnonzero(unobserved_axes(points, np.array(extent), span))) if len(points) >= 4 else ""
    shown = page.inner_text("#narrow") if page.is_visible("#narrow") else ""
    assert bool(shown) == bool(want) and (not want or f"along {want}:" in shown), (want, shown)
    rng = np.random.default_rng(0)
    cases = [(rng.uniform(-0.5, 0.5, (6, 3)) * rng.uniform(0.01, 1, 3), rng.uniform(0.2, 2, 3), span) for _ in range(20)]
    edge = np.array([[0.0, 0.0, 0.0], [0.5, 0.1, 0.0]])
    cases += [(edge, np.array([2.5, 2.5, 0.0]), 0.2),  # x spans exactly 20 %: observed; z: a flat model, never tied
              (edge, np.ones(3), 0.0), (np.zeros((0, 3)), np.ones(3), 0.2)]  # the rule off; no points
    for pts, size, m in cases:
        js = page.evaluate("async ([p, z, m]) => (await import('/static/viewer.js')).narrowAxes(p, z, m)", [pts.tolist(), size.tolist(), m])
        assert js == ["xyz"[a] for a in np.flatnonzero(unobserved_axes(pts, size, m))], (pts, size, m)


def test_correspondences_page(s):
    sim = simulated(s, "correspondences")
    answer = {a["track_id"]: a for a in sim["answers"]}
    open_next(s, "correspondences")
    page, done = s.page, []
    served = json.loads(page.context.request.get(f"{s.url}/api/tasks/{s.clip}/{sim['task_id']}").text())
    task = served["task"]
    assert set(answer) == {it["track_id"] for it in task["items"]}, "the simulated annotators gave up on no track"
    while True:
        page.wait_for_selector("#viewer[data-ready='1']", timeout=60_000)
        track = track_shown(s)
        a = answer[track]
        stamps = [k["timestamp_us"] for k in next(it for it in task["items"] if it["track_id"] == track)["keyframes"]]
        if a["is_mirrored"]:
            page.keyboard.press("m")
        ready = 0
        for kf in a["keyframes"]:
            where = []
            n = _click_pairs(s, stamps.index(kf["timestamp_us"]), kf["points"], where)
            if n >= 4 and not done:
                _assert_a_paired_model_point_is_refused(s, *where[0])
            ready += n >= 4
            if ready == 1 and n >= 4 and not done:  # one view gives no depth: one key-frame is not an answer
                assert not page.is_enabled("#submit") and "annotate 2 key-frames at least" in page.inner_text("#summary")
            if 0 < n < 4:
                for _ in range(n):
                    page.keyboard.press("u")  # undo: too few visible points on this key-frame
        if not done:
            page.screenshot(path=s.shots / "correspondences.png", timeout=SCREENSHOT_TIMEOUT_MS)
        _assert_narrow_warning(s, served, next(it for it in task["items"] if it["track_id"] == track)["cad_id"])
        assert page.is_enabled("#submit"), page.inner_text("#summary")
        page.click("#submit")
        done.append(track)
        if len(done) == len(answer):
            break
        page.wait_for_url(re.compile(rf"track=(?!{track}\b)\d+"))
    ready = wait_for_pipeline(s)
    files = new_label_files(s, "correspondences", SEEN)
    assert files and sorted(a.track_id for lf in files for a in lf.label.answers) == sorted(done)
    for lf in files:
        for got in lf.label.answers:
            want = {k["timestamp_us"]: k for k in answer[got.track_id]["keyframes"]}
            assert got.is_mirrored == answer[got.track_id]["is_mirrored"]
            for kf in got.keyframes:
                assert 4 <= len(kf.points) <= 6
                for p in kf.points:  # each pair is one of the ground-truth pairs, as clicked
                    d = [np.linalg.norm(np.subtract(p.xyz, q["xyz"])) + abs(p.x - q["x"]) + abs(p.y - q["y"]) for q in want[kf.timestamp_us]["points"]]
                    assert min(d) < 0.03, (got.track_id, kf.timestamp_us, min(d))
    assert s.wh.read("poses", [s.clip]).num_rows >= 1, "the resume solved poses"
    assert "verification" in ready, ready


COUNT_OPAQUE = """async () => { const img = document.querySelector('#model-layer'); await img.decode();
    const c = document.createElement('canvas'); c.width = img.naturalWidth; c.height = img.naturalHeight;
    const ctx = c.getContext('2d'); ctx.drawImage(img, 0, 0); const d = ctx.getImageData(0, 0, c.width, c.height).data;
    let n = 0; for (let i = 3; i < d.length; i += 4) if (d[i] > 0) n++; return n; }"""
"""Opaque pixels of the model layer shown (the posed model's RGBA render)."""


def _stack_pixels(s: Served) -> np.ndarray:
    from io import BytesIO

    from PIL import Image

    shot = s.page.locator("#stack").screenshot(timeout=SCREENSHOT_TIMEOUT_MS)
    return np.asarray(Image.open(BytesIO(shot)).convert("RGB"), dtype=np.int16)


def _assert_model_drawn(s: Served, track: int) -> None:
    """On the first key-frame where the model layer has opaque pixels: the page with the layer
    differs from the bare frame (b). Fails when no key-frame of the track shows the model."""
    page = s.page
    for i in range(page.locator("#strip .thumb").count()):
        page.locator("#strip .thumb").nth(i).click()
        if page.evaluate(COUNT_OPAQUE) > 0:
            break
    else:
        raise AssertionError(f"track {track}: the model layer is empty on every key-frame")
    assert float(page.evaluate("getComputedStyle(document.querySelector('#model-layer')).opacity")) > 0
    if page.locator("#outline-layer").is_visible():
        page.keyboard.press("o")  # the outline off: only the model layer tells the two apart
    shown = _stack_pixels(s)
    page.keyboard.press("b")
    bare = _stack_pixels(s)
    page.keyboard.press("b")
    assert shown.shape == bare.shape and np.abs(shown - bare).max() > 30, f"track {track}: the model layer changes no pixel"


def test_verification_page(s):
    sim = simulated(s, "verification")["answers"]
    answer = {a["track_id"]: a["verdict"] for a in sim}
    same = {a["track_id"]: a["same_as_track"] for a in sim if "same_as_track" in a}
    nxt = open_next(s, "verification")
    page, done = s.page, []
    page.wait_for_selector("#stack[data-ready='1']", timeout=60_000)
    first = track_shown(s)
    others = sorted(t for t in answer if t != first)
    assert others, f"a one-item task ({first}): no pose to call it a duplicate of"
    # the flag names every other track (duplicate_overlap 0); s picks the first, sent as same_as_track with the verdict
    assert page.locator("#dup").is_visible() and page.inner_text("#dup-tracks").startswith(f"track {others[0]} (")
    assert page.locator("#dup-tracks a").count() == len(others)
    page.keyboard.press("s")
    assert page.input_value("#same") == str(others[0])
    page.click("#accept" if answer[first] == "accept" else "#reject")
    page.wait_for_url(re.compile(rf"track=(?!{first}\b)\d+"))
    page.goto(f"{s.url}/annotate/verification?clip={s.clip}&task={nxt['task_id']}&track={first}")
    while True:  # every track answered as simulated, the first one again: its newer answer is in force
        page.wait_for_selector("#stack[data-ready='1']", timeout=60_000)
        track = track_shown(s)
        page.keyboard.press("o")  # outline
        page.keyboard.press("-")
        assert page.locator("#outline-layer").is_visible()
        page.keyboard.press("b")  # bare frame, and back
        assert not page.locator("#outline-layer").is_visible()
        page.keyboard.press("b")
        _assert_model_drawn(s, track)
        if not done:
            page.screenshot(path=s.shots / "verification.png", timeout=SCREENSHOT_TIMEOUT_MS)
        page.select_option("#same", str(same.get(track, "")))  # after the keys: the select keeps the focus
        page.click("#accept" if answer[track] == "accept" else "#reject")
        done.append(track)
        if len(done) == len(answer):
            break
        page.wait_for_url(re.compile(rf"track=(?!{track}\b)\d+"))
    ready = wait_for_pipeline(s)
    files = new_label_files(s, "verification", SEEN)
    assert len(files) == len(answer) + 1, [lf.path.name for lf in files]
    assert [(a.track_id, a.same_as_track) for a in files[0].label.answers] == [(first, others[0])]  # the files sort by time
    assert {a.track_id: a.verdict for lf in files[1:] for a in lf.label.answers} == answer
    assert {a.track_id: a.same_as_track for lf in files[1:] for a in lf.label.answers if a.same_as_track is not None} == same
    assert ("same_object", first, others[0], None) in relations(s, "verification")
    assert verification_statements(s.wh, s.clip) == same  # the newer answer for the first track is in force
    verified = s.wh.read("verified_poses", [s.clip]).to_pylist()
    assert {int(v["track_id"]): v["accepted"] for v in verified} == {t: v == "accept" for t, v in answer.items()}
    assert "nothing waits" in ready, ready
    page.goto(s.url + "/")
    page.wait_for_selector("tr[data-clip] td")
    page.screenshot(path=s.shots / "start.png", timeout=SCREENSHOT_TIMEOUT_MS)
    effort = s.wh.read("label_effort", [s.clip]).column("kind").to_pylist()
    assert {"manual_track", "cad_selection", "correspondences", "verification"} <= set(effort)
