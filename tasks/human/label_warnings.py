"""Warnings on valid label files that may not do what their annotator meant (``labels ingest``
prints them; the files are ingested):

- an answer to a task that a rerun has withdrawn (:func:`tasks.human.shared.withdraw_task`), or
  replaced (its answers count only where they still hold on the newest task:
  :mod:`tasks.human.choices_in_force`, :mod:`tasks.human.clicks_in_force`; a manual-track answer
  not at all: the newest task waits for its own);
- a manual-track answer that leaves out objects of the one it replaces (the newest manual-track
  answer of a task is the whole answer: two tools' exports are not added up);
- correspondences for a track that leave out key-frames clicked by the answer they replace (the
  newest answer of a track is its whole answer: two sessions' clicks are not added up);
- an answer given before the one it replaces (the answer ingested last is in force, whenever it
  was given: a folder synced late put a 09:00 "accept" over an 11:00 "reject" without a word).
"""

from __future__ import annotations

import datetime as dt
import json

from tasks.human.labels import LabelFile, latest_tasks
from warehouse import Warehouse

Work = dict[tuple[str, int | None], tuple[str, list, dt.datetime | None]]
"""(task id, track id; None for a manual-track answer) -> (the file's path, what it did: the
objects' tool ids (None each when it gives none), or the track's clicked key-frames (empty for
other kinds), and when its answers were given: None when it does not say)."""


def _work(kind: str, answers: list) -> dict[int | None, list]:
    """What each answer of a label document did (see :data:`Work`), by track."""
    if kind == "manual_track":
        return {None: [a.get("source_id") if isinstance(a, dict) else None for a in answers]}
    if kind == "correspondences":
        return {a["track_id"]: [k.get("timestamp_us") for k in a.get("keyframes", [])]
                for a in answers if isinstance(a, dict) and "track_id" in a}
    return {a["track_id"]: [] for a in answers if isinstance(a, dict) and "track_id" in a}


def _dropped(earlier: list, now: list) -> int:
    """Objects (or key-frames) of an earlier answer that a newer one leaves out: by id where both
    have ids, else by count."""
    if earlier and all(x is not None for x in earlier) and all(x is not None for x in now):
        return len(set(earlier) - set(now))
    return max(0, len(earlier) - len(now))


class LabelWarnings:
    """Warnings for the files of one ingest, in order: each file is compared with the answers
    ingested before it (the warehouse's, then the earlier files of the same ingest)."""

    def __init__(self, wh: Warehouse):
        self.wh = wh
        self._work: dict[str, Work] = {}  # clip -> its answers' work, read once per clip
        self._tasks: dict[str, dict[str, dict]] = {}  # clip -> kind -> newest label_tasks row

    def _clip_work(self, clip: str) -> Work:
        if clip not in self._work:
            rows = self.wh.read("label_files", [clip], columns=["kind", "task_id", "source_path", "ingested_at", "created_at",
                                                                "document"]).to_pylist() if self.wh.has_partition("label_files", clip) else []
            work: Work = {}
            for r in sorted(rows, key=lambda r: r["ingested_at"]):
                try:
                    answers = json.loads(r["document"]).get("answers", [])
                except (ValueError, AttributeError):
                    answers = []
                for track, did in _work(r["kind"], answers if isinstance(answers, list) else []).items():
                    work[(r["task_id"], track)] = (r["source_path"], did, r["created_at"])
            self._work[clip] = work
        return self._work[clip]

    def check(self, lf: LabelFile) -> list[str]:
        """The warnings of ``lf``; it is then counted as ingested for the files after it."""
        out = []
        if lf.clip not in self._tasks:
            self._tasks[lf.clip] = latest_tasks(self.wh, lf.clip, columns=["task_id", "kind", "created_at", "num_items"])
        newest = self._tasks[lf.clip].get(lf.kind)
        if newest is not None and newest["task_id"] != lf.task_id and not newest["num_items"]:  # it asks nothing
            out.append(f"{lf.path}: answers task {lf.task_id}, which a rerun withdrew (nothing of its kind is asked now): "
                       "its answers count only if a later run asks about its tracks again")
        elif newest is not None and newest["task_id"] != lf.task_id:
            replaced = f"{lf.path}: answers task {lf.task_id}, which a rerun replaced with {newest['task_id']}: "
            out.append(replaced + (f"a manual-track answer answers its own task only, so {newest['task_id']} still waits for "
                                   "one (an import made again answers the newest task)" if lf.kind == "manual_track" else
                                   "its answers count only where they still hold on the newest task (`cadestate status` "
                                   "says what waits)"))
        work = self._clip_work(lf.clip)
        document = json.loads(lf.document)
        older = []
        for track, did in _work(lf.kind, document["answers"]).items():
            before, earlier, given = work.get((lf.task_id, track), ("", [], None))
            if given is not None and lf.created_at is not None and lf.created_at < given:
                older.append((track, before, given))
            if (lost := _dropped(earlier, did)):
                if track is None:
                    out.append(f"{lf.path}: its answer replaces that of {before} for task {lf.task_id} and leaves out "
                               f"{lost} of its object(s): the newest manual-track answer is the whole answer, so put "
                               "every object drawn in one file")
                else:
                    out.append(f"{lf.path}: its clicks for track {track} replace those of {before} and leave out {lost} "
                               f"of its key-frame(s): the newest answer of a track is its whole answer, so give every "
                               "key-frame's clicks in one file")
            work[(lf.task_id, track)] = (str(lf.path), did, lf.created_at)
        if older:
            track, before, given = older[0]
            which = "its answer" if track is None else f"its answer for track {track}" + (
                f" (and {len(older) - 1} more)" if len(older) > 1 else "")
            out.append(f"{lf.path}: {which} was given at {lf.created_at:%Y-%m-%d %H:%M:%S} UTC, before the one it replaces "
                       f"({before}, given at {given:%Y-%m-%d %H:%M:%S} UTC): the answer ingested last is in force, whenever "
                       "it was given")
        return out
