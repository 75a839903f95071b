"""A task document as the app serves it (:func:`served`): each item's ``previous`` is the answer in
force now, and a correspondences item whose clicks gave no pose says why (``pose_failed``).

The stages write an item's earlier answer into the task file (``previous``; a manual-track task's
``previous`` and ``previous_not_objects``) when they run, so a task file shows an answer given to
it only after the clip's resume has run. A page reopened before that (the browser's Back, a 409's
"reload"), or after a resume that failed, showed the answer as it was when the task was written:
an empty manual-track answer that Enter then saved over the objects drawn, a choice another
person made that the page did not show. Here the answers in force to the task itself
(:func:`tasks.human.answers_in_force.current_answers`) replace the items' ``previous``; answers
carried from an older task (written by the stage) stay where the task has no answer of its own.

The pose stage runs after the correspondences task, so a pose the solver could not make from a
person's clicks (``high_residual``: a click far from its model point, ``low_parallax``, ...) was
lost without a word to them: the item's page now shows the status, the solver's message and the
error of each key-frame, while the answer that gave it is still the one in force (a newer answer
not yet solved shows nothing).
"""

from __future__ import annotations

from schemas.dataclass_json import to_json
from schemas.labels import CadSelectionAnswer, VerificationAnswer
from tasks.human.answers_in_force import current_answers
from tasks.human.clicks_in_force import to_answer
from tasks.tracking.relations import same_as_statements
from warehouse import Warehouse


def _by_track(rows: list[dict]) -> dict[int, list[dict]]:
    out: dict[int, list[dict]] = {}
    for r in rows:
        out.setdefault(int(r["track_id"]), []).append(r)
    return out


def _previous(wh: Warehouse, clip: str, kind: str, task_id: str, rows: list[dict]) -> dict[int, dict]:
    """{track: its answer in force (label JSON)} from the rows of task ``task_id``'s answers of ``kind``."""
    by_track = _by_track(rows)
    if kind == "correspondences":
        return {t: to_json(to_answer(t, rs)) for t, rs in by_track.items()}
    same = same_as_statements(wh, clip, kind, task_id)
    if kind == "cad_selection":
        return {t: to_json(CadSelectionAnswer(track_id=t, cad_id=rs[0]["cad_id"], same_as_track=same.get(t)))
                for t, rs in by_track.items()}
    return {t: to_json(VerificationAnswer(track_id=t, verdict="accept" if rs[0]["accepted"] else "reject",
                                          comment=rs[0]["comment"], same_as_track=same.get(t)))
            for t, rs in by_track.items()}


def with_answers_in_force(wh: Warehouse, clip: str, doc: dict) -> dict:
    """The task document ``doc`` with the answers in force to it as its items' ``previous`` (module
    docstring); ``doc`` itself is not changed."""
    kind, task_id = doc["kind"], doc["task_id"]
    rows = current_answers(wh, kind, [clip], task_id).to_pylist()
    if not rows:
        return doc
    if kind == "manual_track":
        from tasks.human.manual_tracks import previous_answer

        objects, not_objects = previous_answer(wh, clip, task_id, answered=True)
        return {**doc, "previous": [to_json(o) for o in objects], "previous_not_objects": list(not_objects)}
    now = _previous(wh, clip, kind, task_id, rows)
    return {**doc, "items": [{**it, "previous": now[int(it["track_id"])]} if int(it["track_id"]) in now else it
                             for it in doc["items"]]}


def _latest_pose_run(wh: Warehouse, clip: str):
    """When the clip's newest completed pose run started (None: never)."""
    if not wh.has_partition("runs", clip):
        return None
    runs = wh.read("runs", [clip], filters=[("stage", "==", "pose"), ("status", "==", "completed")], columns=["started_at"])
    return max(runs.column("started_at").to_pylist(), default=None)


def with_pose_outcomes(wh: Warehouse, clip: str, doc: dict) -> dict:
    """A correspondences task ``doc`` whose items answered here, and solved since, without an ``ok``
    pose carry ``pose_failed``: {status, message, keyframe_error_px: {timestamp_us: px}}."""
    if doc["kind"] != "correspondences" or not wh.has_partition("poses", clip):
        return doc
    solved_at = _latest_pose_run(wh, clip)
    answered: dict[int, object] = {}  # track -> when its newest answer in force (of any of the clip's tasks) came
    for r in current_answers(wh, "correspondences", [clip]).to_pylist():
        answered[int(r["track_id"])] = max(answered.get(int(r["track_id"]), r["ingested_at"]), r["ingested_at"])
    failed = {}
    for p in wh.read("poses", [clip], columns=["track_id", "status", "message", "keyframe_timestamps_us",
                                               "keyframe_error_px"]).to_pylist():
        t = int(p["track_id"])
        if p["status"] != "ok" and t in answered and solved_at is not None and answered[t] <= solved_at:
            errors = dict(zip(map(str, p["keyframe_timestamps_us"] or []), p["keyframe_error_px"] or []))
            failed[t] = {"status": p["status"], "message": p["message"], "keyframe_error_px": errors}
    return {**doc, "items": [{**it, "pose_failed": failed[int(it["track_id"])]} if int(it["track_id"]) in failed else it
                             for it in doc["items"]]}


def served(wh: Warehouse, clip: str, doc: dict) -> dict:
    """The task document ``doc`` as the app serves it (module docstring)."""
    return with_pose_outcomes(wh, clip, with_answers_in_force(wh, clip, doc))
