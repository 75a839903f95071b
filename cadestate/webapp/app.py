"""The HTTP side of ``cadestate annotate``: pages, the warehouse's media, and a small JSON API.

Pages (``static/``): ``/`` (clips, their waiting tasks, the next-item queue) and
``/annotate/<kind>?clip=C&task=T[&track=N]`` for the four kinds. API (JSON):

- ``GET /api/clips[?offset=N&limit=M]``: every clip (``limit`` of them from the ``offset``-th;
  ``total``: how many there are) with its tasks (items, waiting, ``held_tracks``: waiting items
  another client holds), its last stage runs, its resume state, its next item; the next item of
  all clips; how many waiting items other clients hold (``held``); and the label files left un-ingested
  that failed again at this start (``label_errors``, one line each);
- ``GET /api/clips/<clip>[?wait=S]``: one clip so; with ``wait``, answered once the clip's resume is
  over or after S seconds (at most :data:`MAX_WAIT_S`), whichever comes first: a page waiting for
  the clip's next task learns it the moment the resume ends, without polling;
- ``GET /api/next[?clip=C]``: the next waiting item no other client holds (null: none);
- ``GET /api/tasks/<clip>/<task_id>``: the task document, the tracks answered, those another client
  holds (``held``), the clip's resume state, whether it is the newest task of its kind (``current``),
  why a rerun withdrew the kind's tasks (``withdrawn``: the newest asks nothing; else null) and
  ``as_of``, what answers it saw;
- ``POST /api/claims``, ``POST /api/claims/release``: ``{clip, kind, track_id}``, the item a page
  opened, held for its client or given back (:mod:`cadestate.webapp.claims`); the claim answers
  ``held_by_other`` (and ``age_s``) when another client holds it, and ``hold_s``; a clip the
  warehouse does not hold is a 404.
- ``GET /api/verification_layers/<clip>/<task_id>/<track_id>``: the posed model's image layers
  (503, one line, when they cannot be rendered);
- ``POST /api/answers[?as_of=T]``: a label document without ``format``/``created_at`` (see
  :mod:`cadestate.webapp.answers`): 200 with the label file written and ingested and the clip
  queued for resume (an answer to a task a rerun replaced goes to the newer task where it fits); 422
  naming the field when it does not validate, 409 when it does not fit the newer task or answers an
  item answered since ``as_of`` (nothing written either way); 500 when it was written but not
  ingested (it is ingested at the next start, unless answered again meanwhile).

Every error is a ``detail`` of one line: a query or path parameter that does not parse or is out of
range (``offset=-1``, ``wait=soon``) a 422 naming it (:func:`invalid_request`).

``/media/<path>`` serves files under ``<warehouse>/media`` (frames, CAD meshes and renders,
overlays); ``/vendor/three/`` the three.js package that ``make web-vendor`` unpacked (no CDN).
The pages send their tab's client id as the ``X-Cadestate-Client`` header (claims; a request
without one counts every claim as another client's).
"""

from __future__ import annotations

import getpass
import os
import sys
import threading
from collections.abc import Mapping, Sequence
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

from fastapi import Body, FastAPI, Header, HTTPException, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse
from fastapi.staticfiles import StaticFiles

from cadestate.config import Config
from cadestate.webapp import queue
from cadestate.webapp.answers import Conflict, IngestFailed, answers_as_of, ingest_pending, shown, submit
from cadestate.webapp.claims import Claims, Item
from cadestate.webapp.resume import Resumer
from schemas.labels import KINDS
from tasks.human.label_format import MAX_LABEL_BYTES, SAME_POINT_M, LabelError, one_line
from tasks.human.labels import latest_tasks, withdrawn_why
from tasks.status import answered_since_run, clips_left_unrun
from warehouse import Warehouse
from warehouse.read_cache import ReadCache

STATIC = Path(__file__).parent / "static"
MAX_WAIT_S = 30.0
"""The longest ``GET /api/clips/<clip>?wait=`` holds a request."""
MAX_CLIENT_ID = 64
"""The longest client id a page may send (``X-Cadestate-Client``)."""
THREE_VERSION = "0.187.0"
"""The three.js release the viewer uses (``make web-vendor`` fetches it from npm, sha256-checked)."""


def vendor_dir() -> Path:
    """Where ``make web-vendor`` unpacks three.js: ``$CADESTATE_WEB_VENDOR`` or ``~/.cache/cadestate/web``."""
    return Path(os.environ.get("CADESTATE_WEB_VENDOR", Path.home() / ".cache" / "cadestate" / "web")).expanduser()


def three_dir() -> Path:
    return vendor_dir() / f"three-{THREE_VERSION}" / "package"


CLIENT_HEADER = "X-Cadestate-Client"


def checked_client(client: str | None) -> str | None:
    """The client id a request sent (:data:`CLIENT_HEADER`), checked: a 422 naming the header when
    it is empty or longer than :data:`MAX_CLIENT_ID`."""
    if client is not None and not 0 < len(client) <= MAX_CLIENT_ID:
        raise HTTPException(422, f"header {CLIENT_HEADER}: a client id of 1 to {MAX_CLIENT_ID} characters, not {len(client)}")
    return client


def required_client(client: str | None) -> str:
    """:func:`checked_client`, which a claim cannot do without (422 when missing)."""
    if client is None:
        raise HTTPException(422, f"header {CLIENT_HEADER}: missing (the page's client id, which holds the item)")
    return checked_client(client)


def item_ref(payload: object) -> Item:
    """The item a page names to claim it, ``{clip, kind, track_id}`` (-1: a manual-track task); a
    422 naming the field when it is not one."""
    if not isinstance(payload, dict) or set(payload) != {"clip", "kind", "track_id"}:
        raise HTTPException(422, "claim: $: an object with clip, kind and track_id, nothing else")
    clip, kind, track = payload["clip"], payload["kind"], payload["track_id"]
    if not isinstance(clip, str):
        raise HTTPException(422, "claim: $.clip: a clip name")
    if kind not in KINDS:
        raise HTTPException(422, f"claim: $.kind: one of {', '.join(KINDS)}")
    if isinstance(track, bool) or not isinstance(track, int):
        raise HTTPException(422, "claim: $.track_id: an integer (-1: a manual-track task)")
    return clip, kind, track


PLACES = {"query": "query parameter", "path": "path parameter", "header": "header", "cookie": "cookie"}
"""How :func:`invalid_request` names where a request's value came from (FastAPI's ``loc[0]``)."""


def invalid_request(errors: Sequence[Mapping[str, Any]]) -> str:
    """FastAPI's validation errors of a request (a query or path parameter that is not a number or
    is out of range, a body that is not JSON) as one line naming each parameter, as the app's other
    errors are: "query parameter offset: input should be greater than or equal to 0 (got '-1')"
    (FastAPI's default was a JSON list of objects, which a page showed as it is)."""
    said = []
    for error in errors:
        source, *names = [str(part) for part in error["loc"]]
        message = error["msg"][:1].lower() + error["msg"][1:]
        if error["type"] == "json_invalid":
            message = f"not JSON: {error.get('ctx', {}).get('error', message)}"
        elif isinstance(error.get("input"), str):
            message += f" (got {error['input']!r})"
        where = "body" if source == "body" else f"{PLACES.get(source, source)} {'.'.join(names)}"
        said.append(f"{where}: {message}")
    return one_line("; ".join(said))


def create_app(config: Config, annotator: str | None = None, resumer: Resumer | None = None) -> FastAPI:
    """The app over ``config``'s warehouse; answers are signed ``annotator`` (default: the user).
    ``resumer``: the background resume (default: a :class:`Resumer` running the clip's flow)."""
    cache = ReadCache()  # each page view reads the clip's task tables again; the resumes write and read them too
    wh = Warehouse(config.warehouse.root, compact_after=config.warehouse.compact_after_files).cache_reads(cache=cache)
    lock = threading.Lock()
    clips_queue = queue.Queue(wh)
    claims = Claims(wh.root)  # in the warehouse (its root as resolved: ~ too): every app over it sees them
    worker = resumer or Resumer(config, read_cache=cache)
    who = annotator if annotator is not None else getpass.getuser()
    tol = config.pose.coplanar_tol

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        worker.start()
        report = ingest_pending(wh, lock, coplanar_tol=tol)  # answers a crash left un-ingested
        left = clips_left_unrun(wh, config, answered_since_run(wh))  # answered while no app ran, not yet taken in
        for clip in sorted({*(report.clips if report else []), *left}):
            worker.request(clip)
        app.state.pending_errors = list(report.errors) if report else []  # shown on the start page too
        for line in app.state.pending_errors:
            print(f"error: {line}", file=sys.stderr, flush=True)
        for line in report.warnings if report else []:
            print(f"warning: {line}", file=sys.stderr, flush=True)
        yield
        worker.stop()

    app = FastAPI(title="cadestate annotate", lifespan=lifespan)

    @app.middleware("http")
    async def bounded(request: Request, call_next):
        """A body larger than a label file may be is refused before it is read (FastAPI read and
        parsed any size, then the answer's check refused it: 7 s and 250 MB of memory for 24 MB),
        and so is one of no stated length (chunked: read whole before its size was known)."""
        size = request.headers.get("content-length", "")
        if request.method == "POST" and not size.isdigit():
            return JSONResponse({"detail": "a request's body needs a Content-Length (as the app's pages send): one sent "
                                           "in chunks is refused"}, status_code=411)
        if size.isdigit() and int(size) > MAX_LABEL_BYTES:
            return JSONResponse({"detail": f"the request's body is {int(size) / 1e6:.1f} MB, more than an answer may be "
                                           f"({MAX_LABEL_BYTES / 1e6:.0f} MB)"}, status_code=413)
        return await call_next(request)

    @app.exception_handler(RequestValidationError)
    async def refused(request: Request, e: RequestValidationError) -> JSONResponse:
        return JSONResponse({"detail": invalid_request(e.errors())}, status_code=422)

    app.state.warehouse, app.state.resumer, app.state.lock = wh, worker, lock
    app.state.queue, app.state.claims = clips_queue, claims
    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    if three_dir().is_dir():
        app.mount("/vendor/three", StaticFiles(directory=three_dir()), name="three")

    @app.get("/")
    def index() -> FileResponse:
        return FileResponse(STATIC / "index.html")

    @app.get("/annotate/{kind}")
    def page(kind: str) -> FileResponse:
        if kind not in KINDS:
            raise HTTPException(404, f"no page for {kind!r} (kinds: {', '.join(KINDS)})")
        return FileResponse(STATIC / f"{kind}.html")

    @app.get("/media/{path:path}")
    def media(path: str) -> FileResponse:
        media_root = (wh.root / "media").resolve()
        try:
            target = (media_root / path).resolve()
            found = target.is_relative_to(media_root) and target.is_file()
        except (OSError, ValueError):  # a name too long, a NUL byte
            found = False
        if not found:
            raise HTTPException(404, f"media/{path}: no such file")
        return FileResponse(target, headers={"Cache-Control": "max-age=3600"})

    def known_clip(clip: str) -> str:
        """``clip``, or a 404 when the warehouse does not hold it."""
        if not wh.has_partition("clips", clip):
            raise HTTPException(404, f"unknown clip {clip!r}")
        return clip

    def clip_view(clip: str, held: set[Item]) -> dict:
        resume = worker.status(clip)  # first: when it says ready, the tasks read next are what the resume left
        state = clips_queue.state(clip)
        tasks = [t.as_dict(held) for t in state.tasks]
        return {"clip": clip, "tasks": tasks, "waiting": sum(t["waiting"] for t in tasks), "runs": state.runs,
                "resume": resume, "next": queue.first_waiting(state.tasks, held)}

    @app.get("/api/clips")
    def clips(offset: int = Query(0, ge=0), limit: int | None = Query(None, ge=1),
              client: str | None = Header(None, alias=CLIENT_HEADER)) -> dict:
        held = claims.held_by_others(checked_client(client))
        names = clips_queue.clips()
        views = [clip_view(c, held) for c in names[offset:None if limit is None else offset + limit]]
        return {"annotator": who, "clips": views, "total": len(names), "offset": offset,
                "next": clips_queue.next_item(held=held, names=names), "held": clips_queue.waiting_among(held, names),
                "label_errors": getattr(app.state, "pending_errors", [])}

    @app.get("/api/clips/{clip}")
    def one_clip(clip: str, wait: float = Query(0.0, ge=0.0), client: str | None = Header(None, alias=CLIENT_HEADER)) -> dict:
        client, clip = checked_client(client), known_clip(clip)
        if wait > 0:  # a worker thread of the server's pool blocks, not the event loop
            worker.wait_idle(clip, min(wait, MAX_WAIT_S))
        return clip_view(clip, claims.held_by_others(client))

    @app.get("/api/next")
    def next_item(clip: str | None = None, client: str | None = Header(None, alias=CLIENT_HEADER)) -> JSONResponse:
        held = claims.held_by_others(checked_client(client))
        return JSONResponse(clips_queue.next_item(None if clip is None else known_clip(clip), held))

    @app.post("/api/claims")
    def claim(payload: object = Body(...), client: str | None = Header(None, alias=CLIENT_HEADER)) -> dict:
        client, item = required_client(client), item_ref(payload)
        known_clip(item[0])  # a claim of no clip was kept until it lapsed, for nothing
        other = claims.claim(client, item)
        return {"held_by_other": other is not None, "age_s": None if other is None else round(claims.age_s(other), 1),
                "hold_s": claims.hold_s}

    @app.post("/api/claims/release")
    def release(payload: object = Body(...), client: str | None = Header(None, alias=CLIENT_HEADER)) -> dict:
        claims.release(required_client(client), item_ref(payload))
        return {}

    @app.get("/api/tasks/{clip}/{task_id}")
    def task(clip: str, task_id: str, client: str | None = Header(None, alias=CLIENT_HEADER)) -> dict:
        held = claims.held_by_others(checked_client(client))
        as_of = answers_as_of(wh, clip)  # first: an answer landing meanwhile then counts as unseen
        doc = queue.task_document(wh, clip, task_id)
        if doc is None:
            raise HTTPException(404, f"no task {task_id!r} for clip {clip!r}")
        kind = doc["task"]["kind"]
        newest = latest_tasks(wh, clip).get(kind)
        return {**doc, "annotator": who, "resume": worker.status(clip), "as_of": as_of,
                "held": sorted(t for c, k, t in held if c == clip and k == kind),
                "current": newest is None or newest["task_id"] == task_id,
                "withdrawn": withdrawn_why(newest),
                "pose": {"coplanar_tol": tol, "min_axis_span": config.pose.min_axis_span, "same_point_m": SAME_POINT_M}}

    @app.get("/api/verification_layers/{clip}/{task_id}/{track_id}")
    def layers(clip: str, task_id: str, track_id: int) -> list[dict]:
        from cadestate.webapp.overlays import verification_layers

        doc = queue.task_document(wh, clip, task_id)
        if doc is None or doc["task"]["kind"] != "verification":
            raise HTTPException(404, f"no verification task {task_id!r} for clip {clip!r}")
        item = next((it for it in doc["task"]["items"] if it["track_id"] == track_id), None)
        if item is None:
            raise HTTPException(404, f"track {track_id} is not an item of task {task_id}")
        try:
            return verification_layers(wh, clip, task_id, item)
        except Exception as e:  # noqa: BLE001  (a missing mesh or frame, a renderer failing: the page says so)
            raise HTTPException(503, one_line(shown(wh, f"cannot render track {track_id}'s posed model: {type(e).__name__}: {e}")))

    @app.post("/api/answers")
    def answer(payload: object = Body(...), as_of: str | None = None) -> dict:
        try:
            done = submit(wh, payload, annotator=who, lock=lock, as_of=as_of, coplanar_tol=tol)
        except LabelError as e:
            raise HTTPException(422, str(e)) from None
        except Conflict as e:
            raise HTTPException(409, str(e)) from None
        except IngestFailed as e:
            raise HTTPException(500, str(e)) from None
        if done.rows:  # an answer sent again (saved already) changes nothing: no resume
            worker.request(done.clip)
        return {"path": done.path, "clip": done.clip, "kind": done.kind, "task_id": done.task_id, "warnings": done.warnings,
                "rows": done.rows, "resume": worker.status(done.clip)}

    return app
