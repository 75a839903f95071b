"""The annotation pages by real clicks in Chromium, on one task of each kind written straight into a
warehouse (no pipeline run, so each test takes seconds): the controls a person uses do what they say.

The app is the real one with its real background resume; the clip here has no video, so every resume
of it fails for real, which the page must say. tests/test_annotate_browser.py takes a rendered clip
through all four pages with the pipeline running between them.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
from pathlib import Path

import pytest

from browser import chromium_path, launch, served_app
from conftest import table_rows
from warehouse import Warehouse

pytestmark = pytest.mark.skipif(chromium_path() is None, reason="chromium not installed (make browser)")
playwright_api = pytest.importorskip("playwright.sync_api")

CLIP = "c1"
W, H = 640, 360
STAMPS = [i * 100_000 for i in range(10)]
NOW = "2026-01-01T00:00:00+00:00"
TRACKS = (0, 1, 2)
CUBE_POINTS = [(0.3, 0.5, 0.2), (0.5, 0.1, 0.3), (0.2, -0.3, 0.5), (-0.3, 0.2, 0.5)]
"""Points on the faces of a unit cube that the 3D view's first camera sees, not on one plane."""


def _build(root: Path) -> Warehouse:
    """Frames (grey pictures), six box models (unit cubes) with one render each, and a task of each kind for ``TRACKS``."""
    import trimesh
    from PIL import Image

    from schemas.labels import (CadCandidate, CadSelectionItem, CadSelectionTask, CorrespondenceAnswer, CorrespondenceItem,
                                CorrespondenceKeyframe, CorrespondencePoint, CorrespondenceTask, ExistingTrack,
                                KeyframeView, ManualTrackTask, Pose, TimedBox, VerificationItem, VerificationTask)
    from tasks.human.labels import write_task

    wh = Warehouse(root)
    wh.write("clips", CLIP, table_rows("clips", [{"clip": CLIP, "fps": 10.0, "width": W, "height": H}]))
    K = [W * 0.8, 0, W / 2, 0, W * 0.8, H / 2, 0, 0, 1]
    wh.write("frames", CLIP, table_rows("frames", [
        {"clip": CLIP, "timestamp_us": t, "frame_index": i, "video_time_us": t, "width": W, "height": H, "K": K,
         "world_to_camera_R": [1, 0, 0, 0, 1, 0, 0, 0, 1], "world_to_camera_t": [0, 0, 0]} for i, t in enumerate(STAMPS)]))
    for t in STAMPS:
        path = root / "media" / "frames" / CLIP / f"{t}.jpg"
        path.parent.mkdir(parents=True, exist_ok=True)
        Image.new("RGB", (W, H), (90, 110, 130)).save(path)
    for c in ("m0a", "m0b", "m1a", "m1b", "m2a", "m2b"):
        (root / "media" / "cad" / c).mkdir(parents=True, exist_ok=True)
        trimesh.creation.box(extents=(1, 1, 1)).export(root / "media" / "cad" / f"{c}.glb")
        Image.new("RGB", (64, 64), (200, 180, 160)).save(root / "media" / "cad" / c / "0.png")

    def kf(ts: int) -> KeyframeView:
        return KeyframeView(timestamp_us=ts, frame_index=ts // 100_000, image_path=f"media/frames/{CLIP}/{ts}.jpg",
                            box=(0.2, 0.2, 0.6, 0.6))

    head = dict(clip=CLIP, created_at=NOW, image_size=(H, W))
    write_task(wh, ManualTrackTask(task_id="c1.mt", **head, keyframes=tuple(kf(t) for t in STAMPS[::2]), classes=("chair", "table"),
                                   existing_tracks=tuple(ExistingTrack(track_id=k, label="chair", boxes=tuple(
                                       TimedBox(timestamp_us=t, box=(0.1, 0.1 + 0.2 * k, 0.3, 0.25 + 0.2 * k)) for t in STAMPS[::2]))
                                       for k in TRACKS)))
    # ten candidates a track, as retrieval gives: the first two models of their own, the others' views the second's
    write_task(wh, CadSelectionTask(task_id="c1.cs", **head, items=tuple(
        CadSelectionItem(track_id=t, label="chair", keyframes=(kf(0), kf(500_000)), candidates=tuple(
            CadCandidate(rank=r + 1, cad_id=f"m{t}{c}", library="lib", cad_class="chair", score=0.5,
                         mesh_path=f"media/cad/m{t}{min(c, 'b')}.glb", render_paths=(f"media/cad/m{t}{min(c, 'b')}/0.png",))
            for r, c in enumerate("abcdefghij")))
        for t in TRACKS)))

    def clicked(ts: int) -> CorrespondenceKeyframe:
        points = tuple(CorrespondencePoint(x=0.3 + 0.1 * k, y=0.4, xyz=xyz) for k, xyz in enumerate(CUBE_POINTS))
        return CorrespondenceKeyframe(timestamp_us=ts, points=points)

    # track 1 carries clicks of an earlier task: on key-frame 0, shown here, and on 600000, not shown
    write_task(wh, CorrespondenceTask(task_id="c1.co", **head, items=tuple(
        CorrespondenceItem(track_id=t, label="chair", cad_id=f"m{t}a", library="lib", mesh_path=f"media/cad/m{t}a.glb",
                           render_paths=(), symmetry=1, keyframes=(kf(0), kf(300_000)), previous=CorrespondenceAnswer(
                               track_id=t, cad_id=f"m{t}a", is_mirrored=False, keyframes=(clicked(0), clicked(600_000)))
                           if t == 1 else None) for t in TRACKS)))
    write_task(wh, VerificationTask(task_id="c1.ve", **head, items=tuple(
        VerificationItem(track_id=t, label="chair", cad_id=f"m{t}a", mesh_path=f"media/cad/m{t}a.glb",
                         pose=Pose(translation=(0, 0, 3), rotation=(1, 0, 0, 0), scale=(1, 1, 1), is_mirrored=False),
                         keyframes=(kf(0), kf(200_000))) for t in TRACKS)))
    return wh


@dataclasses.dataclass
class App:
    url: str
    wh: Warehouse
    page: object


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    from cadestate.config import Config, WarehouseConfig
    from cadestate.webapp.app import create_app

    wh = _build(tmp_path_factory.mktemp("pages") / "wh")
    config = Config(warehouse=WarehouseConfig(root=str(wh.root)))
    with served_app(create_app(config, annotator="pages-test")) as url, playwright_api.sync_playwright() as p:
        browser = launch(p)
        page = browser.new_page(viewport={"width": 1280, "height": 720})
        page.set_default_timeout(30_000)
        yield App(url, wh, page)
        browser.close()


def _answers(a: App, kind: str) -> list[list[dict]]:
    """The ``answers`` of every label file of ``kind`` the app wrote, oldest first."""
    files = sorted((a.wh.root / "labels" / CLIP).glob(f"{CLIP}.{ {'manual_track': 'mt', 'cad_selection': 'cs'}[kind]}.*.json"))
    return [json.loads(f.read_text())["answers"] for f in files]


def _drag(page, x0: float, y0: float, x1: float, y1: float, button: str = "left") -> None:
    r = page.locator("#draw").bounding_box()
    page.mouse.move(r["x"] + x0 * r["width"], r["y"] + y0 * r["height"])
    page.mouse.down(button=button)
    page.mouse.move(r["x"] + x1 * r["width"], r["y"] + y1 * r["height"], steps=4)
    page.mouse.up(button=button)


def _open_manual_tracks(a: App) -> None:
    a.page.goto(f"{a.url}/annotate/manual_track?clip={CLIP}&task=c1.mt")
    a.page.wait_for_function("() => document.querySelector('#draw') && document.querySelector('#draw').width > 0")


def test_a_second_browser_is_given_another_item_while_the_first_holds_one(app):
    """Two annotators (two browsers: each its own client id in its localStorage) were given the same
    next item, and the second met a 409 after the work: while one has the item open, the other's start
    page offers the next one and says the first is being done; opened all the same, the page says
    so; left, the item is offered again."""
    browser = app.page.context.browser
    first, second = (browser.new_context(viewport={"width": 1280, "height": 720}) for _ in range(2))
    a, b = first.new_page(), second.new_page()
    b.goto(app.url)
    b.wait_for_selector("#go:not([disabled])")
    offered = b.inner_text("#next")
    a.goto(app.url)
    a.wait_for_selector("#go:not([disabled])")
    assert a.inner_text("#next") == offered
    with a.expect_response("**/api/claims"):
        a.keyboard.press("Enter")  # a opens the next item
    url = a.url
    b.reload()
    b.wait_for_selector("#go:not([disabled])")
    assert b.inner_text("#next") != offered
    assert "(1 being done in another tab or browser)" in b.inner_text("#clips")
    b.goto(url)
    b.wait_for_selector("#held-elsewhere")
    assert "Another tab or browser opened this item" in b.inner_text("#held-elsewhere")
    a.goto("about:blank")  # a leaves the item: it is given back (not left held for HOLD_S)
    b.goto(app.url)
    b.wait_for_function("(offered) => document.querySelector('#next').textContent === offered", arg=offered, timeout=15_000)
    assert "being done" not in b.inner_text("#clips")
    first.close()
    second.close()


def _open_next(page, url: str) -> str:
    """Open the next item from the start page at ``url`` (once the page has claimed it); returns what
    the start page offered."""
    page.goto(url)
    page.wait_for_selector("#go:not([disabled])")
    offered = page.inner_text("#next")
    with page.expect_response("**/api/claims"):
        page.keyboard.press("Enter")
    return offered


def test_two_tabs_of_one_browser_are_given_different_items_and_a_reload_keeps_its_own(app):
    """One person opening a second tab to work on was given the item the first tab held (the client
    id was the browser's, shared by its tabs), and met a 409 after the work. Each tab has its own
    id now; a reload keeps the tab's (its page is not said to be open elsewhere)."""
    context = app.page.context.browser.new_context(viewport={"width": 1280, "height": 720})
    a, b = context.new_page(), context.new_page()
    offered = _open_next(a, app.url)
    with a.expect_response("**/api/claims"):
        a.reload()
    assert a.locator("#held-elsewhere").count() == 0
    b.goto(app.url)
    b.wait_for_selector("#go:not([disabled])")
    assert b.inner_text("#next") != offered and "(1 being done in another tab or browser)" in b.inner_text("#clips")
    assert a.evaluate("sessionStorage.getItem('cadestate-client')") != b.evaluate("sessionStorage.getItem('cadestate-client')")
    context.close()


def test_a_duplicated_tab_takes_an_id_of_its_own(app, tmp_path):
    """The browser's "Duplicate tab" copies sessionStorage, the client id with it: both tabs were
    one client, given one item with no word, and closing the copy gave back the first tab's claim
    (a second annotator was then given the item too). The copy takes a new id and another item.
    Playwright has no "duplicate": the second tab is given the first's sessionStorage, as Chrome does."""
    with _own_app(app, tmp_path / "wh") as own:
        context = own.page.context.browser.new_context(viewport={"width": 1280, "height": 720})
        first, copy = context.new_page(), context.new_page()
        link = f"{own.url}/annotate/cad_selection?clip={CLIP}&task=c1.cs"  # the start page's task link: no track
        with first.expect_response("**/api/claims"):
            first.goto(link)
        first.wait_for_selector(".cand")
        shared = first.evaluate("sessionStorage.getItem('cadestate-client')")
        copy.add_init_script(f"sessionStorage.setItem('cadestate-client', {json.dumps(shared)})")
        with copy.expect_response("**/api/claims"):
            copy.goto(link)
        copy.wait_for_selector(".cand")
        assert copy.evaluate("sessionStorage.getItem('cadestate-client')") not in (shared, None)
        assert copy.inner_text("#track-title") != first.inner_text("#track-title")
        held = lambda: {c["track_id"] for c in (json.loads(f.read_text()) for f in (own.wh.root / "_claims").glob("*.json"))}  # noqa: E731
        mine = int(first.inner_text("#track-title").split()[1])
        copy.close()
        first.wait_for_timeout(500)
        assert mine in held()  # the first tab's claim stays
        context.close()


def test_a_page_back_from_the_back_forward_cache_holds_its_item_again_at_once(app):
    """A page left gives its item back (pagehide); restored from the back-forward cache it is loaded
    again, and so holds its item again at once, not only at its next renewal a minute later.
    Chromium under automation keeps no page in that cache, so the page is sent the two events the
    browser sends it then."""
    context = app.page.context.browser.new_context(viewport={"width": 1280, "height": 720})
    a, other = context.new_page(), app.page.context.browser.new_context().new_page()
    offered = _open_next(a, app.url)
    with a.expect_response("**/api/claims/release"):
        a.evaluate("window.dispatchEvent(new PageTransitionEvent('pagehide', {persisted: true}))")
    other.goto(app.url)
    other.wait_for_selector("#go:not([disabled])")
    assert other.inner_text("#next") == offered  # given back
    with a.expect_response("**/api/claims"):
        a.evaluate("window.dispatchEvent(new PageTransitionEvent('pageshow', {persisted: true}))")
    # held again: the start page (refreshed every 5 s) offers another item well before the renewal
    other.wait_for_function("(offered) => document.querySelector('#next').textContent !== offered", arg=offered, timeout=15_000)
    context.close()
    other.context.close()


def test_the_start_page_asks_again_only_once_its_last_answer_came(app):
    """The start page asked every 5 s whether or not the last answer had come: an app reading
    thousands of clips for the first time took longer, and each tick sent another request to read
    them all again. The next request goes 5 s after the last answer."""
    page = app.page.context.browser.new_page(viewport={"width": 1280, "height": 720})
    held = []
    page.route("**/api/clips?**", lambda route: held.append(route))  # the answer takes long
    page.goto(f"{app.url}/")
    page.wait_for_timeout(6_500)
    assert len(held) == 1
    with page.expect_request("**/api/clips?**", timeout=15_000):  # and 5 s after its answer, the next
        held[0].continue_()
    page.close()


@contextlib.contextmanager
def _own_app(app: App, root: Path):
    """An app of its own over a fresh warehouse (``root``), with a new page of the module's browser:
    for a test whose page holds an item the module's other tests would then be kept from."""
    from cadestate.config import Config, WarehouseConfig
    from cadestate.webapp.app import create_app

    wh = _build(root)
    with served_app(create_app(Config(warehouse=WarehouseConfig(root=str(wh.root))), annotator="pages-test")) as url:
        page = app.page.context.browser.new_page(viewport={"width": 1280, "height": 720})
        page.set_default_timeout(30_000)
        try:
            yield App(url, wh, page)
        finally:
            page.close()


def test_manual_tracks_by_mouse_alone(app):
    """A click into an object's class field types there (the row was rebuilt under the click), and a
    class typed in another case is the task's (it was refused: "pick a class from the list"); deleting
    another object keeps the selected one selected; a right-button drag draws nothing; a page opened
    again before any resume shows the answer just saved (it showed none, and Enter saved that)."""
    page = app.page
    _open_manual_tracks(app)
    _drag(page, 0.6, 0.6, 0.8, 0.9, button="right")
    assert page.locator(".obj").count() == 0
    for k in range(3):  # three objects, one box each: a drag with none selected makes a new one
        page.evaluate("document.activeElement.blur()")
        page.click("#new")
        _drag(page, 0.1 + 0.25 * k, 0.6, 0.3 + 0.25 * k, 0.9)
    page.locator("input.cls").nth(1).click()
    page.keyboard.type("Table")  # another case: the task's own class
    page.locator("input.cls").nth(1).blur()
    assert [page.locator("input.cls").nth(i).input_value() for i in range(3)] == ["", "table", ""]
    page.locator(".obj").nth(2).locator("b").click()  # select the third, delete the first: the third stays selected
    page.locator(".obj").nth(0).locator("button.danger").click()
    assert page.inner_text(".obj.sel b") == "new 2"
    page.keyboard.press("ArrowRight")
    _drag(page, 0.4, 0.1, 0.6, 0.3)
    page.locator("select.same").nth(0).select_option("1")
    boxes = page.evaluate("[...document.querySelectorAll('.obj')].map(o => o.innerText.match(/(\\d+) box/)[1])")
    assert boxes == ["1", "2"], boxes
    for i in range(2):
        page.locator("input.cls").nth(i).fill(" CHAIR" if i else "table")
        page.locator("input.cls").nth(i).dispatch_event("change")
    page.evaluate("document.activeElement.blur()")
    page.keyboard.press("Enter")
    page.wait_for_selector("#pipeline")
    (saved,) = _answers(app, "manual_track")
    assert [(o["label"], len(o["boxes"]), o.get("same_as_track")) for o in saved] == [("table", 1, 1), ("chair", 2, None)]
    _open_manual_tracks(app)  # again at once: the answer in force, not the task file's "none drawn"
    assert page.locator(".obj").count() == 2 and page.locator("input.cls").nth(0).input_value() == "table"


def test_a_refused_manual_track_answer_names_the_objects_as_the_page_does(app):
    """Two drawings of one object: the refusal names them "new N", as the page does (it said
    answers[N-1], which the person never saw)."""
    page = app.page.context.browser.new_page(viewport={"width": 1280, "height": 720})
    page.goto(f"{app.url}/annotate/manual_track?clip={CLIP}&task=c1.mt")
    page.wait_for_function("() => document.querySelector('#draw') && document.querySelector('#draw').width > 0")
    drawn = page.locator(".obj").count()  # the answer in force: its objects come first
    for i in (drawn, drawn + 1):
        page.click("#new")
        _drag(page, 0.5, 0.5, 0.7, 0.8)
        page.locator("input.cls").nth(i).fill("table")
        page.locator("input.cls").nth(i).dispatch_event("change")
    page.evaluate("document.activeElement.blur()")
    page.keyboard.press("Enter")
    page.wait_for_selector("#status .toast.error")
    assert page.inner_text("#status .toast.error").startswith(f"answer: new {drawn + 2}: the same object as new {drawn + 1} (class 'table'")
    page.close()


def test_enter_in_a_class_field_confirms_it_and_a_box_drawn_in_a_small_window_stays_in_view(app):
    """Below 900 px the class field is under the frame: the focus it took after a box was drawn
    scrolled the frame away. Enter in the field did nothing; it now confirms the class (the keys go
    back to the page: a second Enter submits, as the button does); a class not of the task's is said."""
    page = app.page.context.browser.new_page(viewport={"width": 800, "height": 600})
    page.bring_to_front()  # the page that has the focus (a field of a page behind others takes none)
    page.goto(f"{app.url}/annotate/manual_track?clip={CLIP}&task=c1.mt")
    page.wait_for_function("() => document.querySelector('#draw') && document.querySelector('#draw').width > 0")
    page.wait_for_load_state("networkidle")  # the strip's images in, the page laid out as it stays
    drawn = page.locator(".obj").count()  # the answer in force: its objects come first
    _drag(page, 0.5, 0.5, 0.7, 0.8)  # none selected: a new object
    box = page.locator("#draw").bounding_box()
    focused = page.evaluate("document.activeElement.outerHTML.slice(0, 80)")
    assert 'class="cls"' in focused, focused  # the class is typed next
    assert page.evaluate("window.scrollY") == 0 and box["y"] >= 0 and box["y"] + box["height"] <= 600, box
    field = page.locator("input.cls").nth(drawn)
    page.keyboard.type("sofa")
    page.keyboard.press("Enter")
    assert "pick a class from the list (sofa)" in page.inner_text("#status")
    assert page.evaluate("document.activeElement.classList.contains('cls')")  # kept: the class is to be fixed
    field.fill("Table")
    page.keyboard.press("Enter")
    assert field.input_value() == "table" and not page.evaluate("document.activeElement.classList.contains('cls')")
    page.route("**/api/answers**", lambda route: route.abort())  # what was sent is enough: nothing saved
    try:
        with page.expect_request("**/api/answers**") as sent:
            page.keyboard.press("Enter")
    except playwright_api.TimeoutError:  # once in CI (not again in 8 runs): say what the page showed instead
        state = page.evaluate("({status: document.querySelector('#status').innerText, focused: document.activeElement.outerHTML"
                              ".slice(0, 80), submitDisabled: document.querySelector('#submit').disabled, framesMissing: "
                              "!!document.querySelector('#frames-missing')})")
        raise AssertionError(f"Enter sent no answer; the page: {state}") from None
    labels = [o["label"] for o in json.loads(sent.value.post_data)["answers"]]
    assert len(labels) == drawn + 1 and labels[-1] == "table"
    page.close()


def test_track_colours_stay_distinct_past_eight(app):
    """Eight colours in turn gave tracks 0 and 8 one colour: the first 20 tracks' colours differ in
    lightness or by 15 degrees of hue at least."""
    page = app.page
    page.goto(app.url)
    colours = page.evaluate("import('/static/common.js').then((m) => Array.from({length: 20}, (_, i) => m.trackColor(i)))")
    hsl = [tuple(float(v) for v in c[4:-1].replace("%", "").split(",")) for c in colours]
    for i, (h, _, light) in enumerate(hsl):
        for h2, _, light2 in hsl[i + 1:]:
            assert light != light2 or min(abs(h - h2), 360 - abs(h - h2)) >= 15, colours


def test_cad_selection_keys_after_tab(app):
    """Tab to the first candidate, press 2, Enter: the second is submitted (Enter chose the tabbed one
    again); the fragment list steps with the arrow keys and keeps the focus."""
    page = app.page
    page.goto(f"{app.url}/annotate/cad_selection?clip={CLIP}&task=c1.cs&track=0")
    page.wait_for_selector(".cand")
    page.locator("#same").focus()
    page.keyboard.press("ArrowDown")
    page.keyboard.press("ArrowDown")
    assert page.locator("#same").input_value() == "2" and page.evaluate("document.activeElement.id") == "same"
    page.keyboard.press("Escape")
    page.locator(".cand").nth(0).focus()
    page.keyboard.press("Tab")
    page.keyboard.press("Shift+Tab")
    assert page.evaluate("document.activeElement.dataset.cad") == "m0a"
    page.keyboard.press("2")
    assert page.locator(".cand.sel").get_attribute("aria-pressed") == "true"
    page.keyboard.press("Enter")
    page.wait_for_url("**track=1**")
    assert _answers(app, "cad_selection")[-1][0]["cad_id"] == "m0b"


def test_a_candidate_chosen_while_the_answer_is_on_its_way_does_not_replace_it(app, tmp_path):
    """On a slow link, 1 Enter then 3 Enter before the reply: choosing turned Submit on again, a second
    answer went out and was refused (409) while the first reply moved the page on, so the correction
    was dropped unseen. While an answer is on its way the choice stays, and nothing more is sent."""
    with _own_app(app, tmp_path / "wh") as own:
        _choice_while_sending(own)


def _choice_while_sending(app: App) -> None:
    page = app.page
    held, posts = [], []
    page.on("request", lambda r: posts.append(r) if r.method == "POST" and "/api/answers" in r.url else None)
    page.goto(f"{app.url}/annotate/cad_selection?clip={CLIP}&task=c1.cs&track=0")
    page.wait_for_selector(".cand")
    page.route("**/api/answers*", lambda route: held.append(route))  # the answer waits, as on a slow link
    with page.expect_request(lambda r: r.method == "POST" and "/api/answers" in r.url):
        page.keyboard.press("1")
        page.keyboard.press("Enter")
    page.keyboard.press("3")
    page.keyboard.press("Enter")
    page.wait_for_timeout(500)  # a second answer went out at once (before this page's change)
    assert page.locator(".cand.sel").get_attribute("data-cad") == "m0a" and page.locator("#submit").is_disabled()
    assert len(posts) == 1 and len(held) == 1
    held[0].continue_()
    page.wait_for_url(lambda url: "track=0" not in url)  # the page went on to the next item
    assert _answers(app, "cad_selection")[-1][0]["cad_id"] == "m0a" and len(posts) == 1


def test_a_claim_that_got_no_answer_is_made_again(app, tmp_path):
    """The first claim of a page failed (the app restarting, a network blip) and the page never
    claimed again: the item stayed free for others all the while it was open. It is claimed again."""
    with _own_app(app, tmp_path / "wh") as own:
        _claim_retried(own)


def _claim_retried(app: App) -> None:
    page = app.page
    tries = []

    def first_fails(route) -> None:
        tries.append(route.request.post_data_json)
        route.abort() if len(tries) == 1 else route.continue_()

    page.route("**/api/claims", first_fails)
    page.goto(f"{app.url}/annotate/cad_selection?clip={CLIP}&task=c1.cs&track=2")
    page.wait_for_selector(".cand")
    with page.expect_response("**/api/claims", timeout=30_000) as claimed:
        pass
    assert claimed.value.ok and len(tries) == 2 and tries[1] == {"clip": CLIP, "kind": "cad_selection", "track_id": 2}
    held = page.request.get(f"{app.url}/api/clips/{CLIP}").json()  # no client id: every claim is someone else's
    assert 2 in {t["kind"]: t for t in held["tasks"]}["cad_selection"]["held_tracks"]


def test_an_answered_item_is_given_back_at_once(app, tmp_path):
    """A page left open on "Task done" held the item it had answered for good (claimed again every
    minute): a rerun asking about the track again had it skipped for everyone else while that tab
    stayed open. The claim goes with the answer."""
    with _own_app(app, tmp_path / "wh") as own:
        page = own.page
        as_of = page.request.get(f"{own.url}/api/tasks/{CLIP}/c1.cs").json()["as_of"]
        others = [{"track_id": t, "cad_id": f"m{t}a"} for t in (0, 1)]  # every item but track 2 answered elsewhere
        assert page.request.post(f"{own.url}/api/answers?as_of={as_of}", data={"kind": "cad_selection", "clip": CLIP,
                                 "task_id": "c1.cs", "answers": others}).ok
        with page.expect_response("**/api/claims"):
            page.goto(f"{own.url}/annotate/cad_selection?clip={CLIP}&task=c1.cs&track=2")
        page.wait_for_selector(".cand")
        claims = lambda: [json.loads(f.read_text()) for f in (own.wh.root / "_claims").glob("*.json")]  # noqa: E731
        assert any(c["kind"] == "cad_selection" and c["track_id"] == 2 for c in claims())
        page.keyboard.press("1")
        page.keyboard.press("Enter")
        page.wait_for_selector("#pipeline")  # the task done: the page stays
        page.wait_for_timeout(500)
        assert not [c for c in claims() if c["kind"] == "cad_selection"], claims()


def test_two_pages_opened_on_one_task_link_at_once_are_given_two_items(app, tmp_path):
    """Two people open the start page's link of a task (no track): both read it with the first item
    free, the other's page claims it in between, and this one was given it too (a toast, then a
    409 after the work). The page goes on to the next free item it can claim."""
    with _own_app(app, tmp_path / "wh") as own:
        page = own.page

        def claimed_meanwhile(route) -> None:
            response = route.fetch()
            other = page.request.post(f"{own.url}/api/claims", data={"clip": CLIP, "kind": "cad_selection", "track_id": 0},
                                      headers={"X-Cadestate-Client": "the-other-page"})
            assert other.ok and not other.json()["held_by_other"]
            route.fulfill(response=response)

        page.route(f"**/api/tasks/{CLIP}/c1.cs", claimed_meanwhile)
        page.goto(f"{own.url}/annotate/cad_selection?clip={CLIP}&task=c1.cs")
        page.wait_for_selector(".cand")
        assert page.inner_text("#track-title").startswith("Track 1"), page.inner_text("#track-title")
        assert page.locator("#held-elsewhere").count() == 0


def test_cad_selection_keeps_the_key_frame_in_view_beside_the_candidates_in_a_small_window(app):
    """At 800 x 600 the key-frame stays in view while the person scrolls to the tenth candidate and
    clicks it (stacked, the candidates were below the frame, which left the window)."""
    page = app.page.context.browser.new_page(viewport={"width": 800, "height": 600})
    page.goto(f"{app.url}/annotate/cad_selection?clip={CLIP}&task=c1.cs&track=2")
    page.wait_for_selector(".cand")
    page.wait_for_load_state("networkidle")  # the candidates' views in: the tenth is below the window
    page.locator(".cand").nth(9).click()
    box = page.locator("#keyframe").bounding_box()
    assert page.inner_text("#choice") == "chosen: m2j" and page.evaluate("window.scrollY") > 0
    assert box["y"] >= 0 and box["y"] + box["height"] <= 600, box
    page.close()


def test_a_task_done_leaves_only_enter_for_the_next_task(app):
    """The task's own shortcuts stayed on once its page was replaced by "Task done": every key threw
    (n, arrows, o, x, /), and Enter ran the gone task's submit beside opening the next."""
    page = app.page.context.browser.new_page(viewport={"width": 1280, "height": 720})
    errors = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(f"{app.url}/annotate/manual_track?clip={CLIP}&task=c1.mt")
    page.wait_for_function("() => document.querySelector('#draw') && document.querySelector('#draw').width > 0")
    page.keyboard.press("Enter")  # nothing is missing
    page.wait_for_selector("#next-link", timeout=30_000)
    for key in ("n", "ArrowRight", "ArrowLeft", "o", "x", "/"):
        page.keyboard.press(key)
    page.wait_for_timeout(300)
    assert errors == [], errors
    with page.expect_navigation():
        page.keyboard.press("Enter")
    assert "/annotate/" in page.url and "manual_track" not in page.url and errors == [], (page.url, errors)
    page.close()


PHONE_PAGES = [("/", "#clips tbody tr"), (f"/annotate/manual_track?clip={CLIP}&task=c1.mt", "#keyframe"),
               (f"/annotate/cad_selection?clip={CLIP}&task=c1.cs", ".cand"),
               (f"/annotate/correspondences?clip={CLIP}&task=c1.co", "#keyframe"),
               (f"/annotate/verification?clip={CLIP}&task=c1.ve", "#stack[data-ready]")]


def test_no_page_is_wider_than_a_phone(app):
    """At 375 x 667 the candidates were five a row (the fifth cut off) and the header ran 90 px
    past the window's edge: every page fits the width, the candidates two a row."""
    page = app.page.context.browser.new_page(viewport={"width": 375, "height": 667})
    for path, ready in PHONE_PAGES:
        page.goto(app.url + path)
        page.wait_for_selector(ready)
        wide = page.evaluate("() => [document.documentElement.scrollWidth, Math.max(...[...document.querySelectorAll("
                             "'header *')].map(e => e.getBoundingClientRect().right))]")
        assert wide[0] <= 375 and wide[1] <= 375, (path, wide)
        if ".cand" in ready:
            assert len(page.evaluate("getComputedStyle(document.querySelector('.grid')).gridTemplateColumns").split()) == 2
    page.close()


def test_correspondences_click_pairs_without_scrolling_in_a_small_window(app):
    """At 800 x 600 the model and the image stay side by side: each pair (a click on the model, then
    one on the image) is clicked where the page shows them (stacked, the model was below the window
    and every pair took two scrolls)."""
    page = app.page.context.browser.new_page(viewport={"width": 800, "height": 600})
    page.goto(f"{app.url}/annotate/correspondences?clip={CLIP}&task=c1.co&track=0")
    page.wait_for_selector("#viewer[data-ready='1']")
    page.wait_for_function("() => document.querySelector('#image-canvas').width > 0")
    for k, xyz in enumerate(CUBE_POINTS):
        page.mouse.click(*page.evaluate(f"window.viewer.screenOf({list(xyz)})"))
        r = page.locator("#image-canvas").bounding_box()
        page.mouse.click(r["x"] + (0.3 + 0.1 * k) * r["width"], r["y"] + 0.4 * r["height"])
    assert page.inner_text("#count") == "(4; 4-6)" and page.evaluate("window.scrollY") == 0
    page.close()


def test_a_mirror_toggled_alone_is_work_the_page_asks_before_dropping(app):
    """m alone, then the queue link: the browser asks first (the mirror was not counted as work)."""
    page = app.page
    page.goto(f"{app.url}/annotate/correspondences?clip={CLIP}&task=c1.co&track=1")  # (2's model is not cached: it goes later)
    page.wait_for_selector("#viewer[data-ready='1']")
    page.keyboard.press("m")
    asked = []
    page.once("dialog", lambda d: (asked.append(d.type), d.dismiss()))
    page.click("header a", no_wait_after=True)
    page.wait_for_timeout(300)
    assert asked == ["beforeunload"] and "/annotate/correspondences" in page.url, (asked, page.url)
    page.keyboard.press("m")  # back as it was: nothing to lose
    page.click("header a")
    page.wait_for_selector("#clips")


def test_clicks_carried_on_a_key_frame_not_shown_go_back_with_the_answer(app):
    """Track 1's clicks of an earlier task are on key-frames 0 (shown) and 600000 (not shown): one pair
    on 0 clicked again, the answer keeps 600000's clicks (they were dropped without a word, and the
    newest answer of a track is its whole answer), unless the page's "drop" is pressed."""
    page = app.page
    page.goto(f"{app.url}/annotate/correspondences?clip={CLIP}&task=c1.co&track=1")
    page.wait_for_selector("#viewer[data-ready='1']")
    page.wait_for_function("() => document.querySelector('#image-canvas').width > 0")
    assert page.inner_text("#count") == "(4; 4-6)"
    said = page.inner_text("#summary")
    page.locator("#pairs li[data-index='3'] button").click()
    page.mouse.click(*page.evaluate(f"window.viewer.screenOf({list(CUBE_POINTS[3])})"))
    r = page.locator("#image-canvas").bounding_box()
    page.mouse.click(r["x"] + 0.65 * r["width"], r["y"] + 0.5 * r["height"])
    page.click("#submit")
    page.wait_for_url("**track=0**")  # the next item waiting
    (path,) = (app.wh.root / "labels" / CLIP).glob(f"{CLIP}.co.*.json")
    (answer,) = json.loads(path.read_text())["answers"]
    assert [k["timestamp_us"] for k in answer["keyframes"]] == [0, 600_000]
    assert [p["x"] for p in answer["keyframes"][0]["points"]] == pytest.approx([0.3, 0.4, 0.5, 0.65], abs=0.01)
    assert [tuple(p["xyz"]) for p in answer["keyframes"][1]["points"]] == CUBE_POINTS
    assert "1 clicked before on key-frames not shown here, kept" in said
    page.goto(f"{app.url}/annotate/correspondences?clip={CLIP}&task=c1.co&track=1")
    page.wait_for_selector("#viewer[data-ready='1']")
    page.click("#drop-unshown")  # key-frame 0 alone is left: one view gives no depth, so no answer yet
    assert page.locator("#submit").is_disabled() and "annotate 2 key-frames at least" in page.inner_text("#summary")
    page.keyboard.press("ArrowRight")  # key-frame 300000: four pairs
    page.wait_for_function("() => document.querySelector('#image-canvas').width > 0")
    for k, xyz in enumerate(CUBE_POINTS):
        page.mouse.click(*page.evaluate(f"window.viewer.screenOf({list(xyz)})"))
        r = page.locator("#image-canvas").bounding_box()
        page.mouse.click(r["x"] + (0.3 + 0.1 * k) * r["width"], r["y"] + 0.4 * r["height"])
    page.click("#submit")
    page.wait_for_selector("#next-item")  # with ingest's warning: the answer leaves out a key-frame its earlier one clicked
    newest = max((app.wh.root / "labels" / CLIP).glob(f"{CLIP}.co.*.json"))
    assert [k["timestamp_us"] for k in json.loads(newest.read_text())["answers"][0]["keyframes"]] == [0, 300_000]


def test_an_answer_saved_when_its_task_cannot_be_read_again_is_not_said_failed(app):
    """The answer is saved, then reading its task again fails (the network, the app restarting): the
    page goes on to the clip's next item; it said the error with Submit on again, and pressed again
    the same answer met a 409 against itself."""
    page = app.page.context.browser.new_page(viewport={"width": 1280, "height": 720})
    page.goto(f"{app.url}/annotate/cad_selection?clip={CLIP}&task=c1.cs&track=1")
    page.wait_for_selector(".cand")
    page.route("**/api/tasks/**", lambda route: route.abort())
    page.keyboard.press("2")
    page.keyboard.press("Enter")
    page.wait_for_selector("#pipeline")
    assert "the answer is saved, but the task cannot be read again" in page.inner_text("#status")
    (saved,) = _answers(app, "cad_selection")[-1]
    assert (saved["track_id"], saved["cad_id"]) == (1, "m1b")
    page.close()


def test_the_page_says_a_failed_resume_and_a_task_that_cannot_load(app):
    """The clip has no video: the real resume after an answer fails, and the panel says so (it was
    overwritten by "next task ready"). A stale link says it cannot load, with no Submit to press."""
    page = app.page
    other = page.request.post(f"{app.url}/api/answers", data={"kind": "cad_selection", "task_id": "c1.cs", "clip": CLIP,
                                                             "answers": [{"track_id": t, "cad_id": None} for t in (0, 1)]})
    assert other.ok, other.text()  # the other items answered: the page's is the last, the panel follows it
    page.goto(f"{app.url}/annotate/cad_selection?clip={CLIP}&task=c1.cs&track=2")
    page.wait_for_selector(".cand")
    page.keyboard.press("1")
    page.keyboard.press("Enter")
    page.wait_for_selector("#resume-failed", timeout=120_000)
    assert page.inner_text("#resume-failed").startswith("The resume failed: ")
    page.goto(f"{app.url}/annotate/verification?clip={CLIP}&task=c1.gone")
    page.wait_for_selector("#load-error")
    assert "no task 'c1.gone'" in page.inner_text("#load-error") and page.locator("#accept").count() == 0
    page.goto(f"{app.url}/annotate/verification?clip={CLIP}&task=c1.cs")  # a link to a task of another kind: was a blank page
    page.wait_for_selector("#load-error")
    assert "This is not a verification task: c1.cs is a cad_selection task" in page.inner_text("#load-error")
    assert page.locator("#accept").count() == 0


def test_a_verdict_given_before_is_shown(app):
    """Reject track 2, open it again: the title says it was rejected (its comment was shown, the
    verdict itself was not, and a person checking their answer could not tell)."""
    page = app.page
    page.goto(f"{app.url}/annotate/verification?clip={CLIP}&task=c1.ve&track=2")
    page.wait_for_selector("#stack[data-ready='1']")
    page.click("#comment")
    page.keyboard.type("off by a hand")
    page.keyboard.press("Escape")
    page.keyboard.press("r")
    page.wait_for_url("**track=0**")  # (1's layers stay unrendered: its model goes later)
    page.goto(f"{app.url}/annotate/verification?clip={CLIP}&task=c1.ve&track=2")
    page.wait_for_selector("#stack[data-ready='1']")
    assert page.inner_text("#track-title").endswith("(answered before: rejected)")
    assert page.input_value("#comment") == "off by a hand"


def test_no_verdict_on_a_model_that_cannot_be_shown(app):
    """The posed model's mesh is gone and the key-frames have no overlay: the page says so and keeps
    Accept and Reject off (pressing a accepted a pose nobody saw)."""
    page = app.page
    verdicts = lambda: list((app.wh.root / "labels" / CLIP).glob(f"{CLIP}.ve.*.json"))  # noqa: E731
    before = verdicts()
    (app.wh.root / "media" / "cad" / "m1a.glb").unlink()
    page.goto(f"{app.url}/annotate/verification?clip={CLIP}&task=c1.ve&track=1")
    page.wait_for_selector("#stack[data-ready='1']")
    assert "no verdict without it" in page.inner_text("#loading")
    page.keyboard.press("a")
    page.wait_for_timeout(300)
    assert page.locator("#accept").is_disabled() and verdicts() == before


def test_no_verdict_on_overlays_that_cannot_be_shown(app, tmp_path):
    """The model's layers cannot be rendered (its mesh gone), so the page shows the stage's overlays
    (the model blended in): those missing too, the key-frame was a broken image with no word, and
    pressing a saved an accept of a pose nobody saw."""
    import datetime as dt

    from schemas.labels import KeyframeView, Pose, VerificationItem, VerificationTask
    from tasks.human.labels import write_task

    with _own_app(app, tmp_path / "wh") as own:
        kf = [KeyframeView(timestamp_us=ts, frame_index=ts // 100_000, image_path=f"media/frames/{CLIP}/{ts}.jpg",
                           box=(0.2, 0.2, 0.6, 0.6), overlay_path=f"media/verification/{CLIP}/overlays/7_{ts}.jpg")
              for ts in (0, 200_000)]  # frames of the clip; no such overlays
        write_task(own.wh, VerificationTask(task_id=f"{CLIP}.ve7", clip=CLIP, created_at=dt.datetime.now(dt.timezone.utc).isoformat(),
                                            image_size=(H, W), items=(VerificationItem(
                                                track_id=7, label="chair", cad_id="gone", mesh_path="media/cad/gone.glb",
                                                pose=Pose(translation=(0, 0, 3), rotation=(1, 0, 0, 0), scale=(1, 1, 1), is_mirrored=False),
                                                keyframes=tuple(kf)),)))
        page = own.page
        page.goto(f"{own.url}/annotate/verification?clip={CLIP}&task={CLIP}.ve7&track=7")
        page.wait_for_selector("#stack[data-ready='1']")
        assert "overlays cannot be loaded" in page.inner_text("#frames-missing")
        page.keyboard.press("a")
        page.wait_for_timeout(300)
        assert page.locator("#accept").is_disabled() and not list((own.wh.root / "labels").rglob(f"{CLIP}.ve7.*.json"))


def test_a_page_without_its_task_says_so_and_caps_lock_keeps_the_keys(app):
    """/annotate/verification alone said "no task 'undefined' for clip 'undefined'"; with Caps Lock on
    no letter key did anything (the keys are lower case)."""
    page = app.page.context.browser.new_page(viewport={"width": 1280, "height": 720})
    page.goto(f"{app.url}/annotate/verification")
    assert "No task named" in page.inner_text("#load-error") and "undefined" not in page.inner_text("main")
    page.goto(f"{app.url}/annotate/verification?clip={CLIP}&task=c1.ve&track=0")
    page.wait_for_selector("#stack[data-ready='1']")
    assert "on" not in (page.get_attribute("#outline", "class") or "")
    page.evaluate("document.dispatchEvent(new KeyboardEvent('keydown', {key: 'O', modifierCapsLock: true, bubbles: true}))")
    assert "on" in page.get_attribute("#outline", "class").split()
    page.close()


def test_no_answer_on_a_key_frame_that_cannot_be_shown(app):
    """A key-frame image gone from the media: the page says which, for as long as it is open, and
    sends no answer (the verification page said nothing and Accept went; the manual-track page's
    toast went after 12 s and Enter said nothing was missing on frames nobody saw)."""
    page = app.page.context.browser.new_page(viewport={"width": 1280, "height": 720})  # no image cached
    (app.wh.root / "media" / "frames" / CLIP / "200000.jpg").unlink()  # a key-frame of the manual-track and verification tasks
    files = lambda: sorted((app.wh.root / "labels" / CLIP).glob("*.json"))  # noqa: E731
    before = files()
    page.goto(f"{app.url}/annotate/verification?clip={CLIP}&task=c1.ve&track=0")
    page.wait_for_selector("#stack[data-ready='1']")
    page.keyboard.press("a")
    page.wait_for_timeout(500)
    assert files() == before and page.locator("#accept").is_disabled()
    assert f"media/frames/{CLIP}/200000.jpg" in page.inner_text("#frames-missing")
    page.goto(f"{app.url}/annotate/manual_track?clip={CLIP}&task=c1.mt")
    page.wait_for_selector("#frames-missing")
    gone = page.locator("#strip .thumb").nth(1)  # a dashed box: its alt text was written over its number
    assert "missing" in gone.get_attribute("class") and gone.locator("img").is_hidden() and gone.inner_text() == "2"
    page.evaluate("document.activeElement.blur()")
    page.keyboard.press("Enter")
    page.wait_for_timeout(500)
    assert "no answer without it" in page.inner_text("#status") and files() == before
    page.close()


def test_no_none_of_these_on_candidates_whose_views_cannot_be_shown(app, tmp_path):
    """A candidate's view gone from the media: "none of these" was taken with its picture broken,
    unseen. The page names it and sends no answer."""
    with _own_app(app, tmp_path / "wh") as own:
        (own.wh.root / "media" / "cad" / "m0b" / "0.png").unlink()  # the views of candidates 2-10 of track 0
        page = own.page
        page.goto(f"{own.url}/annotate/cad_selection?clip={CLIP}&task=c1.cs&track=0")
        page.wait_for_selector("#frames-missing")
        assert "key-frame images and candidate views cannot be loaded (media/cad/m0b/0.png)" in page.inner_text("#frames-missing")
        page.keyboard.press("n")
        page.keyboard.press("Enter")
        page.wait_for_timeout(500)
        assert "no answer without it" in page.inner_text("#status")
        assert not (own.wh.root / "labels").exists() or not list((own.wh.root / "labels").rglob("*.json"))


def test_a_model_that_cannot_be_loaded_is_said_where_it_is_clicked(app):
    """The chosen model's mesh is gone: the correspondences page says so under the empty 3D view for
    as long as it is open (a toast said it for 12 s, then the hint asked for a click on the model)."""
    page = app.page
    (app.wh.root / "media" / "cad" / "m2a.glb").unlink()
    page.goto(f"{app.url}/annotate/correspondences?clip={CLIP}&task=c1.co&track=2")
    page.wait_for_selector("#status .toast.error")
    assert page.inner_text("#hint").startswith("⚠ cannot load the model media/cad/m2a.glb")
    assert page.locator("#submit").is_disabled()


def test_the_correspondences_page_says_when_the_3d_view_cannot_load(app, monkeypatch, tmp_path):
    """An app started without three.js (no `make web-vendor`): the correspondences page says so
    (it was blank, without its header; the warning went to the terminal of whoever started the app)."""
    from cadestate.config import Config, WarehouseConfig
    from cadestate.webapp.app import create_app

    monkeypatch.setenv("CADESTATE_WEB_VENDOR", str(tmp_path))
    with served_app(create_app(Config(warehouse=WarehouseConfig(root=str(app.wh.root))), annotator="pages-test")) as url:
        page = app.page
        page.goto(f"{url}/annotate/correspondences?clip={CLIP}&task=c1.co&track=0")
        page.wait_for_selector("#load-error")
        assert page.inner_text("#load-error").startswith("The 3D view cannot be loaded: ")
        assert "make web-vendor" in page.inner_text("#load-error") and page.inner_text("header h1") == "Correspondences"


def test_a_page_of_a_task_a_rerun_withdrew_says_so_with_nothing_to_submit(app, tmp_path):
    """A verification page opened from a link kept after a rerun solved no pose: the task is
    withdrawn (the newest of its kind asks nothing), so the page says why and offers nothing to
    submit; the start page no longer lists it."""
    from cadestate.config import Config, WarehouseConfig
    from cadestate.webapp.app import create_app
    from tasks.human.shared import withdraw_task

    wh = _build(tmp_path / "wh")
    assert withdraw_task(wh, CLIP, "verification", "no solved pose") == "; task c1.ve withdrawn"
    with served_app(create_app(Config(warehouse=WarehouseConfig(root=str(wh.root))), annotator="pages-test")) as url:
        page = app.page
        page.goto(f"{url}/")
        page.wait_for_selector(f"a[href*='task=c1.mt']")
        assert page.locator("a[href*='task=c1.cs']").count() == 1 and page.locator("a[href*='verification']").count() == 0
        page.goto(f"{url}/annotate/verification?clip={CLIP}&task=c1.ve&track=0")
        page.wait_for_selector("#load-error")
        assert page.inner_text("#load-error") == "A rerun withdrew this task: Nothing to answer: no solved pose. back to the queue"
        assert page.locator("#accept").count() == 0
