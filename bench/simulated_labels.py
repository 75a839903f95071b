"""The benchmark's simulated annotators answer the pipeline's human tasks through real label files.

:func:`answer_tasks` reads a clip's open task files (the newest ``label_tasks`` row of each kind,
items without an answer in force), answers them as the simulated annotators of
:mod:`bench.annotators` would, with the noise model :class:`bench.noise.AnnotatorNoise`, and writes
label files (validated by :func:`tasks.human.labels.validate_label`) to ``<bench>/labels/<clip>/``:

- ``manual_track`` (val/test clips): the ground-truth objects that no automatic track of the task
  matches (:func:`bench.retrieval_bench.track_truth`), drawn with
  :func:`bench.annotators.draw_manual_track` on the task's key-frames where they are not an
  ignore region (mostly hidden or cut off), as the task's class that corresponds to the object's
  (:func:`tasks.cad.classes.class_of_label`); objects of no such class are left out.
  ``source_id``: ``gt:<ground-truth track id>``. Nothing missing: an empty answer.
- ``cad_selection``: a track matched to a ground-truth object (:func:`bench.retrieval_bench.track_truth`; a manual
  track too, by its boxes) gets :func:`bench.annotators.select_cad` of the object's true model among the track's candidates
  (shape distances of the meshes); an unmatched track (a false positive, or a track mixing
  objects) gets null ("none fits"), so the loop ends.
- ``correspondences``: :func:`bench.annotators.annotate_correspondences` on the task's key-frames,
  clicking on the **selected** model (the mesh the task shows) placed at the ground-truth object's
  pose, with the other objects of the scene occluding. When the selected model is not the true one
  the clicks are where that model would be if it stood in the object's place (what a person
  clicking on the shown model would do). A track with fewer than two clickable key-frames (an
  answer needs two: one view gives no depth) gets a new cad_selection answer null (the annotator
  gives up on the model), so nothing waits forever.
- ``verification``: :func:`bench.annotators.verify_pose` of the solved pose with the posed model,
  seen through the clip's own cameras (the warehouse's ``frames``: the camera file's or SfM's, as
  the verification page shows it), against the true model at the true pose through the true
  cameras, on the task's key-frames; unmatched tracks: reject.
  Duplicates flagged by the task (``maybe_same_as``) are resolved from the ground truth
  (:func:`same_as_answers`): of the tracks on one ground-truth object linked by flags, one keeps its
  pose (an accepted one first, then the lowest track id) and the others answer ``same_as_track`` it.

The noise of a pick or a click on a track is drawn from the object the track follows, not from its
track id (:meth:`_Clip.dice`): two pipelines compared on one benchmark (another detector, another
tracking) see the same person where they hand over the same object.

:func:`annotate_until_done` is the ``cadestate bench run`` loop: run the clips,
answer their open tasks, ingest the labels (:func:`tasks.human.label_ingest.ingest_labels`), rerun the
clips that got labels, until no clip waits or ``max_rounds``.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from pathlib import Path

import trimesh

from bench.annotators import Pose, annotate_correspondences, draw_manual_track, mesh_shape_distance, select_cad, verify_pose
from bench.benchmark import CLASS_NAMES, ignore_rule
from bench.noise import DEFAULT_NOISE, AnnotatorNoise
from bench.retrieval_bench import track_truth
from cadestate.render import Instance, Renderer, RenderMesh, object_to_world
from schemas.official import FramesFile, read_frames, read_objects
from tasks.cad.classes import class_of_label
from tasks.dataset.export_official import official_frames
from tasks.dataset.objects import DatasetFrame, clip_frames
from tasks.human.answers_in_force import answered_items
from tasks.human.label_ingest import DEFAULT_COPLANAR_TOL, ingest_labels
from tasks.human.labels import LabelError, label_document, latest_task_of_kind, parse_task, utc_now, validate_label
from tasks.tracking.clip_tracks import clip_tracks
from warehouse import Warehouse, atomic_write_bytes

LABELS = "labels"
ANNOTATOR = "simulated (bench.annotators)"
KINDS = ("manual_track", "cad_selection", "correspondences", "verification")


def label_dir(bench_dir: Path, clip: str) -> Path:
    """Where the simulated annotators write the clip's label files."""
    return Path(bench_dir) / LABELS / clip


class _Clip:
    """What the simulated annotators know of one clip: ground truth, meshes, track -> object."""

    def __init__(self, bench_dir: Path, wh: Warehouse, clip: str):
        self.wh, self.clip = wh, clip
        self.frames = read_frames(Path(bench_dir) / clip / "frames.json")
        self.objects = {o.track_id: o for o in read_objects(Path(bench_dir) / clip / "objects.json").objects}
        tracks = clip_tracks(wh, clip)
        self.truth = track_truth(bench_dir, wh, clip, tracks)
        self.sizes = {t: len(track.boxes) for t, track in tracks.items()}
        self.shown = shown_frames(wh, clip, self.frames)
        self.index = {f.timestamp: i for i, f in enumerate(self.frames.frames)}
        self.models = {r["cad_id"]: r for r in wh.read("cad_models", columns=["cad_id", "mesh_path", "symmetry"]).to_pylist()}
        self._meshes: dict[str, trimesh.Scene] = {}
        self._distances: dict[tuple[str, str], float] = {}

    def gt_id(self, track_id: int) -> str | None:
        """The ground-truth object the track follows (:func:`bench.retrieval_bench.track_truth`), or None."""
        return self.truth.get(track_id) or self.truth.get(str(track_id))

    def dice(self, track_id: int) -> tuple[str, ...]:
        """The salt of the simulated person's noise on one track: the object it follows and the
        track's rank among that object's tracks (most boxes first, then track id), or the track id
        when it follows none. Track ids are arbitrary (another detector or tracking renumbers them),
        so a person's clicks and picks on an object's main track stay the same draw when only the
        numbering or a stray fragment changes: two pipelines compared on one benchmark differ by
        what they do, not by re-rolled dice."""
        gt_id = self.gt_id(track_id)
        if gt_id is None:
            return ("track", str(track_id))
        order = sorted((-self.sizes.get(int(t), 0), int(t)) for t, g in self.truth.items() if g == gt_id)
        return ("object", gt_id, str([t for _, t in order].index(int(track_id))))

    def gt(self, track_id: int):
        o = self.objects.get(self.gt_id(track_id) or "")
        return o if o is not None and o.translation is not None and o.cad_id in self.models else None

    def mesh(self, cad_id: str):
        if cad_id not in self._meshes:
            self._meshes[cad_id] = trimesh.load(self.wh.root / self.models[cad_id]["mesh_path"], force="scene")
        return self._meshes[cad_id]

    def distance(self, a: str, b: str) -> float:
        key = tuple(sorted((a, b)))
        if key not in self._distances:
            self._distances[key] = (mesh_shape_distance(self.mesh(a), self.mesh(b))
                                    if a in self.models and b in self.models else float("inf"))
        return self._distances[key]

    def occluders(self, except_id: str) -> list[Instance]:
        return [Instance(RenderMesh.from_trimesh(self.mesh(o.cad_id)),
                         object_to_world(o.translation, o.rotation, o.scale, o.is_mirrored), k + 1)
                for k, o in enumerate(self.objects.values())
                if o.track_id != except_id and o.translation is not None and o.cad_id in self.models]

    def keyframes(self, views) -> list[int]:
        return [self.index[v.timestamp_us] for v in views if v.timestamp_us in self.index]


def frames_like_truth(wh: Warehouse, clip: str, truth: FramesFile) -> tuple[DatasetFrame, ...]:
    """The clip's cameras as the pipeline has them (the warehouse's ``frames``, in its +Y-up world:
    the camera file's turned, or SfM's), frame for frame with the ground truth ``truth`` (the
    same timestamps)."""
    by_time = {f.timestamp_us: f for f in clip_frames(wh, clip)}
    missing = [f.timestamp for f in truth.frames if f.timestamp not in by_time]
    if missing:
        raise LabelError(f"clip {clip}: no frame at {missing[0]} µs of its ground truth in the warehouse "
                         f"({len(missing)} of {len(truth.frames)} missing)")
    return tuple(by_time[f.timestamp] for f in truth.frames)


def shown_frames(wh: Warehouse, clip: str, truth: FramesFile) -> FramesFile:
    """:func:`frames_like_truth` as a frames file (what the verification page shows the clip through)."""
    return FramesFile(truth.clip_name, truth.image_size, official_frames(frames_like_truth(wh, clip, truth)))


def open_tasks(wh: Warehouse, clip: str) -> list[tuple[object, list]]:
    """(task, its items not answered: :func:`tasks.human.answers_in_force.answered_items`) of the newest
    task of each kind, if any waits (a manual-track task is answered whole: its items are its
    key-frames until it is)."""
    out = []
    for kind in KINDS:
        row = latest_task_of_kind(wh, clip, kind)
        if row is None:
            continue
        task = parse_task(row["document"], row["path"])
        done = answered_items(wh, clip, json.loads(row["document"]))
        if kind == "manual_track":
            todo = [] if done else list(task.keyframes)
        else:
            todo = [it for it in task.items if it.track_id not in done]
        if todo:
            out.append((task, todo))
    return out


def task_label(cls: str, classes: tuple[str, ...]) -> str | None:
    """The first of the task's ``classes`` that stands for ground-truth class ``cls`` (a class id;
    :func:`tasks.cad.classes.class_of_label`), or None."""
    name = CLASS_NAMES.get(cls)
    return next((label for label in classes if name and class_of_label(label) == name), None)


def _draw_missing(c: _Clip, bench_dir: Path, task, noise: AnnotatorNoise) -> list[dict]:
    """The manual-track answer: the objects no automatic track of the task matches (module docstring)."""
    found = {c.truth.get(t.track_id) for t in task.existing_tracks}
    stamps = {kf.timestamp_us for kf in task.keyframes}
    keyframes = FramesFile(c.frames.clip_name, c.frames.image_size, tuple(f for f in c.frames.frames if f.timestamp in stamps))
    gt_ignore = ignore_rule(bench_dir, c.clip)
    answers = []
    for o in sorted(c.objects.values(), key=lambda o: o.track_id):
        label = task_label(o.cls, task.classes)
        if o.track_id in found or label is None:
            continue
        shown = dataclasses.replace(o, track=tuple(e for e in o.track if e.timestamp in stamps and not gt_ignore(o, e)))
        boxes = [e for e in draw_manual_track(keyframes, shown, noise, noise.rng(c.clip, "manual_track", o.track_id))
                 if e.box[0] < e.box[2] and e.box[1] < e.box[3]]
        if boxes:
            answers.append({"label": label, "source_id": f"gt:{o.track_id}",
                            "boxes": [{"timestamp_us": int(e.timestamp), "box": [float(v) for v in e.box]} for e in boxes]})
    return answers


def _select(c: _Clip, item, noise: AnnotatorNoise) -> dict:
    o = c.gt(item.track_id)
    cad_id = None
    if o is not None:
        cad_id = select_cad(o.cad_id, [k.cad_id for k in item.candidates], c.distance, noise,
                            noise.rng(c.clip, "select_cad", *c.dice(item.track_id)))
    return {"track_id": item.track_id, "cad_id": cad_id}


def _correspond(c: _Clip, item, noise: AnnotatorNoise, renderer: Renderer) -> dict | None:
    o = c.gt(item.track_id)
    if o is None or item.cad_id not in c.models:
        return None
    keyframes = c.keyframes(item.keyframes)
    if not keyframes:
        return None
    clicks = annotate_correspondences(c.frames, o, c.mesh(item.cad_id), noise=noise,
                                      rng=noise.rng(c.clip, "correspondences", *c.dice(item.track_id), item.cad_id),
                                      renderer=renderer, symmetry_order=int(item.symmetry), keyframes=keyframes,
                                      occluders=c.occluders(o.track_id))
    if len(clicks) < 2:  # one view gives no depth: the label format refuses an answer on one key-frame
        return None
    return {"track_id": item.track_id, "cad_id": item.cad_id, "is_mirrored": bool(o.is_mirrored),
            "keyframes": [{"timestamp_us": int(kf.timestamp),
                           "points": [{"x": float(x), "y": float(y), "xyz": [float(v) for v in xyz]}
                                      for (x, y), xyz in zip(kf.xy, kf.xyz)]} for kf in clicks]}


def _verify(c: _Clip, item, noise: AnnotatorNoise, renderer: Renderer) -> dict:
    """The verdict on one posed track: its model, posed, against the same model where the object
    is (the ground truth's pose, where :func:`_correspond` clicked it). A look-alike chosen in CAD
    selection is judged on its alignment, as people judge an overlay of a model that is not the
    object's own; against the true model's silhouette it failed for its shape alone (issue 18)."""
    o = c.gt(item.track_id)
    ok = False
    if o is not None and item.cad_id in c.models:
        p = item.pose  # in the world of the warehouse's frames, seen through them; the ground truth through its own
        ok = verify_pose(c.frames, o, Pose(tuple(p.translation), tuple(p.rotation), tuple(p.scale), bool(p.is_mirrored)),
                         c.mesh(item.cad_id), c.keyframes(item.keyframes), noise=noise,
                         renderer=renderer, pose_frames=c.shown)
    return {"track_id": item.track_id, "verdict": "accept" if ok else "reject",
            "comment": None if o is not None else "no ground-truth object"}


def same_as_answers(task, truth: Callable[[int], object], verdicts: dict[int, str]) -> dict[int, int]:
    """track -> the track it is the same object as, for the items of verification ``task``:
    the tracks linked by the task's flags (``maybe_same_as``) that ``truth`` (track id -> its
    ground-truth object id, None: none) puts on one object form a group; each group's keeper is
    the track accepted (``verdicts``: track -> verdict, absent: not answered) with the lowest id,
    else its lowest id, and the others are the same as it."""
    group = {it.track_id: {it.track_id} for it in task.items}
    for it in task.items:
        for other in it.maybe_same_as:
            if other in group and truth(it.track_id) is not None and truth(it.track_id) == truth(other):
                merged = group[it.track_id] | group[other]
                for t in merged:
                    group[t] = merged
    out = {}
    for members in {frozenset(g) for g in group.values() if len(g) > 1}:
        keeper = min(members, key=lambda t: (verdicts.get(t) != "accept", t))
        out |= {t: keeper for t in sorted(members) if t != keeper}
    return out


def _write(wh: Warehouse, folder: Path, kind: str, clip: str, task_id: str, answers: list[dict]) -> Path:
    """Validate the label document, then write it as ``<task_id>.<n>.json`` (n: next free)."""
    doc = label_document(kind, clip, task_id, answers, annotator=ANNOTATOR, created_at=utc_now().isoformat())
    data = (json.dumps(doc, indent=1, allow_nan=False) + "\n").encode()
    n = 0
    while (folder / f"{task_id}.{n}.json").exists():
        n += 1
    path = folder / f"{task_id}.{n}.json"
    validate_label(path, wh, data=data)  # a simulator bug must not reach the warehouse
    atomic_write_bytes(path, data)
    return path


def answer_tasks(bench_dir: Path, wh: Warehouse, clip: str, noise: AnnotatorNoise = DEFAULT_NOISE) -> list[Path]:
    """Answer the clip's open tasks as the simulated annotators (module docstring); returns the
    label files written under ``<bench>/labels/<clip>/`` (not ingested)."""
    tasks = open_tasks(wh, clip)
    if not tasks:
        return []
    c = _Clip(bench_dir, wh, clip)
    folder = label_dir(bench_dir, clip)
    folder.mkdir(parents=True, exist_ok=True)
    H, W = c.frames.image_size
    written = []
    with Renderer(W, H) as renderer:
        for task, items in tasks:
            if task.kind == "manual_track":  # an empty answer too: "nothing is missing" completes the task
                written.append(_write(wh, folder, task.kind, clip, task.task_id, _draw_missing(c, bench_dir, task, noise)))
                continue
            if task.kind == "cad_selection":
                answers = [_select(c, it, noise) for it in items]
            elif task.kind == "correspondences":
                answers, give_up = [], []
                for it in items:
                    a = _correspond(c, it, noise, renderer)
                    (answers.append(a) if a is not None else give_up.append(it.track_id))
                if give_up:  # under two key-frames to click on: the annotator rejects the model instead
                    sel = latest_task_of_kind(wh, clip, "cad_selection")
                    if sel is not None:
                        sel_task = parse_task(sel["document"], sel["path"])
                        ids = {it.track_id for it in sel_task.items}
                        none = [{"track_id": t, "cad_id": None} for t in give_up if t in ids]
                        if none:
                            written.append(_write(wh, folder, "cad_selection", clip, sel_task.task_id, none))
            else:
                answers = [_verify(c, it, noise, renderer) for it in items]
                verdicts = {it.track_id: it.previous.verdict for it in task.items if it.previous is not None}
                verdicts |= {a["track_id"]: a["verdict"] for a in answers}
                same = same_as_answers(task, c.gt_id, verdicts)
                answers = [{**a, "same_as_track": same[a["track_id"]]} if a["track_id"] in same else a for a in answers]
            if answers:
                written.append(_write(wh, folder, task.kind, clip, task.task_id, answers))
    return written


def annotate_until_done(bench_dir: Path, wh: Warehouse, clips: list[str], run: Callable[[list[str]], list],
                        max_rounds: int = 6, noise: AnnotatorNoise = DEFAULT_NOISE,
                        log: Callable[[str], None] = lambda s: None,
                        coplanar_tol: float = DEFAULT_COPLANAR_TOL) -> tuple[list, list[str]]:
    """Run ``clips`` (``run(clips)`` -> stage reports), answer the open tasks of the clips that
    wait, ingest the label files (``coplanar_tol``: the config's ``[pose] coplanar_tol``, as
    ``labels ingest`` takes it), rerun those clips; until none waits or ``max_rounds`` runs.
    Returns (the reports of every run, the clips still waiting)."""
    reports: list = []
    todo = list(clips)
    for round_ in range(max_rounds):
        new = run(todo)
        reports += new
        waiting = sorted({r.clip for r in new if r.state == "paused"})
        if not waiting or round_ == max_rounds - 1:
            return reports, waiting
        started = time.perf_counter()
        written = {clip: answer_tasks(bench_dir, wh, clip, noise) for clip in waiting}
        resumed = []
        for clip, paths in written.items():
            if not paths:
                continue
            report = ingest_labels(wh, paths, coplanar_tol=coplanar_tol)  # only this round's: the folder may hold another warehouse's
            if report.errors:
                raise LabelError("; ".join(report.errors))
            resumed += report.clips
        log(f"round {round_ + 1}: {len(waiting)} clip(s) waited; {sum(map(len, written.values()))} label file(s) "
            f"written and ingested in {time.perf_counter() - started:.1f} s; resuming {len(resumed)}")
        if not resumed:
            return reports, waiting
        todo = sorted(set(resumed))
    return reports, []


def merge_rounds(reports: list) -> list:
    """One report per (clip, stage) over the runs of :func:`annotate_until_done`, in first-run
    order: the state, rows and message of its last run that did work (a later ``cached`` run
    changed nothing), and the seconds of all its runs summed."""
    merged: dict[tuple[str, str], object] = {}
    total: dict[tuple[str, str], float] = {}
    for r in reports:
        key = (r.clip, r.stage)
        total[key] = total.get(key, 0.0) + r.duration_s
        if key not in merged or r.state != "cached":
            merged[key] = r
    return [dataclasses.replace(r, duration_s=total[k]) for k, r in merged.items()]
