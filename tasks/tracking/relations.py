"""What people said about a clip's tracks, in force: "track N is not an object" and "track A is
the same object as track B" (``track_relations``, ingested from the labels' ``not_objects`` and
``same_as_track``).

The table is history; only the statements of each task's answer in force count:

- ``manual_track``: those of the label in force of the clip's current manual-track task (its
  newest ``label_tasks`` row of the kind; the newest file answering it replaces the whole answer):
  ``not_objects``, and each drawn object said to be existing track N, whose manual track
  (:func:`manual_track_ids`) is then a fragment of N;
- ``cad_selection``: per track of the current CAD-selection task, the statement of its answer in
  force (``same_as_track``: the track is a fragment of track N);
- ``verification``: per track of the verification task whose verdicts ``verified_poses`` holds, the
  statement of its answer in force (``same_as_track``: its pose shows the object of track N, a
  duplicate: the track joins N's object and only N's pose is kept).

:func:`relations_in_force` resolves chains (A -> B -> C: A and B belong to C); statements that
form a cycle are ignored with a warning (the tracks on it stay objects of their own). A fragment
of a track that is not an object is no object either; when statements of several kinds say
different things about the same track, a drawn object's wins over a CAD-selection answer's, which
wins over a verification answer's (the task asked first).

Who acts on them: the dataset export (:mod:`tasks.dataset.objects`: no object for a not-object
track, fragments join their root's object) and the later human tasks (:func:`left_out_tracks`:
CAD selection, correspondences and verification do not ask about the tracks the manual-track
answer says are no object or are another track).
"""

from __future__ import annotations

import logging
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field

from cadestate.lineage import digest, once_per_reading
from schemas.tracking import MANUAL_TRACK_BASE
from warehouse import Warehouse

log = logging.getLogger(__name__)


def manual_track_ids(rows: list[dict]) -> dict[int, int]:
    """object_index -> track id of the drawn objects (``manual_track_labels`` rows of one label):
    ``MANUAL_TRACK_BASE`` + a digest of the object's ``source_id`` (its id in the annotation tool),
    else of its class and boxes, so a revised answer that drops or reorders objects keeps every
    other object's id (and the clicks given on it). Clashes take the next free id, in object order."""
    objects: dict[int, list[dict]] = {}
    for r in sorted(rows, key=lambda r: (r["object_index"], r["timestamp_us"])):
        objects.setdefault(r["object_index"], []).append(r)
    span = 2**31 - 1 - MANUAL_TRACK_BASE
    ids: dict[int, int] = {}
    for index, boxes in objects.items():
        key = boxes[0]["source_id"] or "\n".join([boxes[0]["label"]] + [f"{b['timestamp_us']} {[round(v, 6) for v in b['box']]}"
                                                                         for b in boxes])
        offset = zlib.crc32(key.encode()) % span
        while MANUAL_TRACK_BASE + offset in ids.values():
            offset = (offset + 1) % span
        ids[index] = MANUAL_TRACK_BASE + offset
    return ids


@dataclass(frozen=True)
class TrackRelations:
    """A clip's relations in force. ``not_objects``: tracks said to show no object;
    ``fragments``: fragment -> the root track it belongs to (chains resolved); ``drawn``: the
    manual tracks whose drawn object was said to be an existing track; ``warnings``: statements
    ignored (cycles), one line each."""

    not_objects: frozenset[int] = frozenset()
    fragments: Mapping[int, int] = field(default_factory=dict)
    drawn: frozenset[int] = frozenset()
    warnings: tuple[str, ...] = ()

    def root(self, track_id: int) -> int:
        """The track that speaks for ``track_id``'s object (itself unless it is a fragment)."""
        return self.fragments.get(track_id, track_id)

    def is_object(self, track_id: int) -> bool:
        """False when the track, or the track it is a fragment of, is said to be no object."""
        return track_id not in self.not_objects and self.root(track_id) not in self.not_objects

    def pose_speakers(self, posed: Mapping[int, int]) -> set[int]:
        """Of the tracks with an accepted pose, ``posed`` (track -> key-frames of its pose), those
        whose pose the export keeps: one per object, its root's when the root's pose was accepted,
        else its fragment's of most key-frames, then lowest id (a pose accepted as "the same object
        as track N" speaks for N's object when N's was rejected); none for tracks of no object."""
        by_root: dict[int, list[tuple[bool, int, int]]] = {}
        for t, keyframes in posed.items():
            if self.is_object(t):
                by_root.setdefault(self.root(t), []).append((self.root(t) != t, -keyframes, t))
        return {min(candidates)[2] for candidates in by_root.values()}


def resolve_fragments(edges: Mapping[int, int]) -> tuple[dict[int, int], list[str]]:
    """fragment -> root from the statements ``edges`` (track -> the track it is a fragment of):
    each chain followed to a track that is no fragment. The statements of tracks on a cycle are
    dropped (one warning per cycle), so those tracks are roots."""
    edges = dict(edges)
    warnings: list[str] = []
    for start in sorted(edges):
        path, t = [], start
        while t in edges and t not in path:
            path.append(t)
            t = edges[t]
        if t in path:
            cycle = path[path.index(t):]
            warnings.append(f"tracks {' -> '.join(map(str, cycle + [t]))} are each said to be a fragment of the next, a "
                            "cycle: these statements are ignored")
            for c in cycle:
                del edges[c]
    roots: dict[int, int] = {}
    for start in edges:
        t = start
        while t in edges:
            t = edges[t]
        roots[start] = t
    return roots, warnings


def _statements(wh: Warehouse, clip: str, kind: str, files: set[tuple]) -> list[dict]:
    """``track_relations`` rows of ``kind`` from the label files ``files`` ((label_sha256, ingested_at))."""
    if not files or not wh.has_partition("track_relations", clip):
        return []
    rows = wh.read("track_relations", [clip]).to_pylist()
    return [r for r in rows if r["kind"] == kind and (r["label_sha256"], r["ingested_at"]) in files]


def manual_answer_statements(wh: Warehouse, clip: str, task_id: str) -> tuple[set[int], dict[int, int]]:
    """(tracks that are no object, {drawn object's index in the answer: the existing track it is})
    of the answer in force of the manual-track task ``task_id`` (none: empty)."""
    files = [f for f in wh.read("label_files", [clip], columns=["label_sha256", "ingested_at", "task_id", "kind"]).to_pylist()
             if f["kind"] == "manual_track" and f["task_id"] == task_id] if wh.has_partition("label_files", clip) else []
    if not files:
        return set(), {}
    newest = max(files, key=lambda f: f["ingested_at"])
    said = _statements(wh, clip, "manual_track", {(newest["label_sha256"], newest["ingested_at"])})
    return ({int(r["track_id"]) for r in said if r["relation"] == "not_object"},
            {int(r["object_index"]): int(r["track_id"]) for r in said if r["relation"] == "same_object"})


def manual_statements(wh: Warehouse, clip: str) -> tuple[set[int], dict[int, int]]:
    """(tracks that are no object, {manual track id: the existing track its drawn object is}) of
    the answer in force of the clip's current manual-track task (none: empty)."""
    from tasks.human.labels import latest_task_of_kind

    task = latest_task_of_kind(wh, clip, "manual_track")
    if task is None:
        return set(), {}
    not_objects, same = manual_answer_statements(wh, clip, task["task_id"])
    if not same:
        return not_objects, {}
    from tasks.human.answers_in_force import current_answers

    ids = manual_track_ids(current_answers(wh, "manual_track", [clip], task["task_id"]).to_pylist())
    return not_objects, {ids[i]: track for i, track in same.items() if i in ids}


def same_as_statements(wh: Warehouse, clip: str, kind: str, task_id: str | None) -> dict[int, int]:
    """{track: the track it is the same object as} from the answers in force of the clip's task
    ``task_id`` of ``kind`` (cad_selection or verification; None: no such task)."""
    from tasks.human.answers_in_force import current_answers

    if task_id is None:
        return {}
    answers = current_answers(wh, kind, [clip], task_id).to_pylist()
    in_force = {(int(r["track_id"]), r["label_sha256"], r["ingested_at"]) for r in answers}
    said = _statements(wh, clip, kind, {(sha, at) for _, sha, at in in_force})
    return {int(r["track_id"]): int(r["other_track_id"]) for r in said
            if r["relation"] == "same_object" and (int(r["track_id"]), r["label_sha256"], r["ingested_at"]) in in_force}


def cad_selection_statements(wh: Warehouse, clip: str) -> dict[int, int]:
    """{track: the track it is a fragment of} from the answers in force of the clip's current
    CAD-selection task."""
    from tasks.human.cad_selection import cad_selection_task_id

    return same_as_statements(wh, clip, "cad_selection", cad_selection_task_id(wh, clip))


def verification_statements(wh: Warehouse, clip: str) -> dict[int, int]:
    """{track: the track whose object its pose shows} (the duplicates people named) from the answers
    in force of the verification task whose verdicts ``verified_poses`` holds: the poses the export
    reads and the statements about them come from one task."""
    if clip not in wh.partitions("verified_poses"):
        return {}
    tasks = sorted(set(wh.read("verified_poses", [clip], columns=["task_id"]).column("task_id").to_pylist()))
    return {t: other for task_id in tasks for t, other in same_as_statements(wh, clip, "verification", task_id).items()}


def relations_in_force(wh: Warehouse, clip: str) -> TrackRelations:
    """The clip's relations in force (module docstring); cycles are logged as warnings."""
    not_objects, drawn = manual_statements(wh, clip)
    edges = {**verification_statements(wh, clip), **cad_selection_statements(wh, clip), **drawn}
    fragments, warnings = resolve_fragments(edges)
    for w in warnings:
        log.warning("clip %s: %s", clip, w)
    return TrackRelations(frozenset(no_object_chains(not_objects, edges, fragments)), fragments, frozenset(drawn),
                          tuple(warnings))


def no_object_chains(not_objects: set[int], edges: Mapping[int, int], fragments: Mapping[int, int]) -> set[int]:
    """``not_objects`` and every fragment whose chain to its root (``edges``: track -> the track it
    is a fragment of; ``fragments``: fragment -> root) passes a track said to be no object: a
    fragment of a track that is no object is no object either, however many links away."""
    out = set(not_objects)
    for start, root in fragments.items():
        t = start
        while t != root and t not in not_objects:
            t = edges[t]
        if t in not_objects:
            out.add(start)
    return out


@once_per_reading
def left_out_tracks(wh: Warehouse, clip: str) -> frozenset[int]:
    """Tracks the manual-track answer in force says are no object or are an existing track: the
    CAD-selection, correspondence and verification tasks do not list them."""
    not_objects, drawn = manual_statements(wh, clip)
    return frozenset(not_objects) | frozenset(drawn)


def left_out_digest(wh: Warehouse, clip: str) -> str:
    """Digest of :func:`left_out_tracks`: part of the inputs of the stages that leave them out."""
    return digest("left out", *map(str, sorted(left_out_tracks(wh, clip))))
