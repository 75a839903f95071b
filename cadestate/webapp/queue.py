"""What waits for people: the open tasks of every clip, their items, and the next item to do.

A clip's open task of a kind is its newest task file of that kind (``label_tasks``), unless it
asks nothing (withdrawn: :func:`tasks.human.labels.asks_nothing`), with items that are not
answered as the stages count them (:func:`tasks.human.answers_in_force.answered_items`); a
manual-track task is one item, answered whole. Kinds come in pipeline order (manual_track, cad_selection,
correspondences, verification).

The start page asks for its clips' tasks every 5 s, and the next item scans the clips from the
first: a :class:`Queue` keeps each clip's tasks and stage runs with what they were read from
(:class:`warehouse.kept.KeptInMemory`) and reads a clip again only when one of its files came or
went (an answer ingested, a resume's new task or run): an unchanged clip costs a listing of each
of its partitions (well under 1 ms, where reading its tasks took 3-25 ms). A copy of each state is
kept in ``_cache/reads/queue/<clip>.json``, so that an app started again does not read every clip
again (1,000 finished clips: 43 s).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Collection
from dataclasses import dataclass, field
from functools import cache

from schemas.labels import KINDS
from cadestate.webapp.claims import Item
from cadestate.webapp.served_task import served, with_pose_outcomes
from tasks.human.answers_in_force import answered_items
from tasks.human.labels import asks_nothing, latest_tasks
from warehouse import Warehouse
from warehouse.kept import KeptInMemory, OnDisk


@dataclass
class OpenTask:
    """One task of a clip: its id, kind, item track ids (manual_track: ``[-1]``, the whole task),
    those still unanswered, and (correspondences) those answered whose clicks gave no pose
    (:func:`cadestate.webapp.served_task.with_pose_outcomes`: to be clicked again)."""

    clip: str
    kind: str
    task_id: str
    items: list[int]
    waiting: list[int] = field(default_factory=list)
    pose_failed: list[int] = field(default_factory=list)

    def as_dict(self, held: Collection[Item] = ()) -> dict:
        """As the API gives it; ``held_tracks``: the waiting items another client holds
        (``held``: :meth:`cadestate.webapp.claims.Claims.held_by_others`)."""
        return {"clip": self.clip, "kind": self.kind, "task_id": self.task_id, "items": len(self.items),
                "waiting": len(self.waiting), "waiting_tracks": self.waiting, "pose_failed": self.pose_failed,
                "held_tracks": [t for t in self.waiting if (self.clip, self.kind, t) in held], "url": self.url}

    @property
    def url(self) -> str:
        """The task's page."""
        return f"/annotate/{self.kind}?clip={self.clip}&task={self.task_id}"


def clip_tasks(wh: Warehouse, clip: str) -> list[OpenTask]:
    """The newest task of each kind of ``clip`` (answered or not), in pipeline order."""
    out = []
    newest = latest_tasks(wh, clip)
    for kind in KINDS:
        row = newest.get(kind)
        if row is None:
            continue
        doc = json.loads(row["document"])
        if asks_nothing(doc):  # withdrawn: a rerun asks nothing of this kind
            continue
        items = [-1] if kind == "manual_track" else [int(it["track_id"]) for it in doc["items"]]
        done = answered_items(wh, clip, doc)
        waiting = [t for t in items if t not in done]
        failed = [int(it["track_id"]) for it in with_pose_outcomes(wh, clip, doc)["items"] if "pose_failed" in it] \
            if kind == "correspondences" else []
        out.append(OpenTask(clip, kind, doc["task_id"], items, waiting, failed))
    return out


def clips(wh: Warehouse) -> list[str]:
    """Every registered clip, sorted."""
    return sorted(wh.partitions("clips"))


def stage_runs(wh: Warehouse, clip: str) -> list[dict]:
    """The last run of each stage of ``clip`` (stage, status, message), in the order they started."""
    if not wh.has_partition("runs", clip):
        return []
    last: dict[str, dict] = {}
    for r in wh.read("runs", [clip], columns=["stage", "status", "started_at", "message"]).sort_by("started_at").to_pylist():
        last[r["stage"]] = {"stage": r["stage"], "status": r["status"], "message": r["message"] or ""}
    return list(last.values())


@dataclass(frozen=True)
class ClipState:
    """What the warehouse says of one clip: its tasks (:func:`clip_tasks`) and its last stage runs
    (:func:`stage_runs`). Kept and shared (:class:`Queue`): not to be changed."""

    tasks: list[OpenTask]
    runs: list[dict]

    def as_json(self) -> dict:
        return {"tasks": [dataclasses.asdict(t) for t in self.tasks], "runs": self.runs}

    @classmethod
    def from_json(cls, d: dict) -> ClipState:
        return cls([OpenTask(**t) for t in d["tasks"]], d["runs"])


@cache
def code_version() -> str:
    """Digest of the code that works out a :class:`ClipState` (this module and the logic it
    imports, as a stage's code digest: :mod:`tasks.registry`): kept states of other code are not used."""
    from tasks.registry import code_digest

    return code_digest(__name__)


class Queue:
    """The clips of ``wh`` as a long-lived app reads them again and again (module docstring)."""

    def __init__(self, wh: Warehouse):
        self.wh = wh
        self._kept = KeptInMemory(OnDisk(wh.root / "_cache" / "reads" / "queue", code_version(), ClipState.as_json,
                                         ClipState.from_json))

    def clips(self) -> list[str]:
        """:func:`clips` (the kept states of clips gone are dropped)."""
        names = clips(self.wh)
        self._kept.keep_only(names)
        return names

    def state(self, clip: str) -> ClipState:
        return self._kept.get(self.wh, clip, lambda: ClipState(clip_tasks(self.wh, clip), stage_runs(self.wh, clip)))

    def next_item(self, clip: str | None = None, held: Collection[Item] = (), names: list[str] | None = None) -> dict | None:
        """The first waiting item (of ``clip``, else of any clip: of ``names``, :meth:`clips` when
        None) not in ``held``: clip, kind, task id, track id (-1: a manual-track task) and the
        page's URL; None when nothing waits."""
        for c in [clip] if clip else names if names is not None else self.clips():
            if (item := first_waiting(self.state(c).tasks, held)) is not None:
                return item
        return None

    def waiting_among(self, items: Collection[Item], names: Collection[str]) -> int:
        """How many of ``items`` (claims: :meth:`cadestate.webapp.claims.Claims.held_by_others`)
        still wait, in the clips ``names``: a claim on an item answered since (its page left open
        after the answer, renewing it) or on no item holds back nothing."""
        clips_held = set(names) & {c for c, _, _ in items}
        return sum((c, t.kind, track) in items for c in sorted(clips_held) for t in self.state(c).tasks for track in t.waiting)


def first_waiting(tasks: list[OpenTask], held: Collection[Item] = ()) -> dict | None:
    """The first waiting item of ``tasks`` (one clip's, :func:`clip_tasks`) not in ``held`` (another
    client's: :mod:`cadestate.webapp.claims`), as :meth:`Queue.next_item` gives it."""
    for t in tasks:
        for track in t.waiting:
            if (t.clip, t.kind, track) in held:
                continue
            url = t.url + ("" if track < 0 else f"&track={track}")
            return {"clip": t.clip, "kind": t.kind, "task_id": t.task_id, "track_id": track, "url": url}
    return None


def task_document(wh: Warehouse, clip: str, task_id: str) -> dict | None:
    """The newest document of a task (as stored in ``label_tasks``, as the app serves it:
    :mod:`cadestate.webapp.served_task`), with ``answered``: the track ids answered
    (:func:`tasks.human.answers_in_force.answered_items`; manual_track: ``[-1]`` once answered)."""
    from tasks.human.labels import latest_task

    if not wh.has_partition("clips", clip):
        return None
    row = latest_task(wh, clip, task_id)
    if row is None:
        return None
    doc = json.loads(row["document"])
    return {"task": served(wh, clip, doc), "answered": sorted(answered_items(wh, clip, doc))}
