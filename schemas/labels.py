"""The four human tasks of the paper (Sec. 3.1-3.5): task files, label files and label tables.

A stage that needs people writes a **task file** (everything an annotation UI needs) and pauses;
people answer with a **label file**; ``cadestate labels ingest DIR`` validates label files, keeps
them in the warehouse and resumes the clips. Both are JSON; their JSON Schemas (draft 2020-12) are
generated from the dataclasses below (:func:`json_schema`, ``cadestate labels schema KIND``) and
published in ``schemas/json/``.

Kinds (``kind``):

- ``manual_track`` (3.1, val/test): draw the objects the automatic tracks missed, as boxes on a
  few regularly spaced key-frames; the automatic tracks are shown.
- ``cad_selection`` (3.2): per track, pick the best of (up to) 10 CAD candidates, or none.
- ``correspondences`` (3.3): per track, 4-6 clicks per key-frame pairing a point on the CAD model
  with an image point; the annotator may mirror the model.
- ``verification`` (3.5): per track, the posed CAD rendered over its key-frames: accept or reject;
  poses whose boxes overlap are flagged ("may be the same object as track N") and the annotator
  may say so (``same_as_track``: the export keeps track N's pose only).

Conventions (as in the official CAD-Estate files, :mod:`schemas.official`): timestamps are camera
timestamps in µs (rows of ``frames``); boxes are (ymin, xmin, ymax, xmax) normalised to [0, 1];
image points are (x, y) normalised by width and height, origin top-left, x right, y down; 3D
points are in the canonical, unmirrored CAD frame (metres, +Y up, front +Z, bbox-centred; see
:mod:`schemas.pose`); paths are relative to the warehouse root; ``track_id`` is ``tracks.track_id``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from cadestate.names import NAME  # a task id is a file name, as a clip's
from schemas.dataclass_json import fixed, json_schema_of, spec
from schemas.label_kinds import KINDS, LABEL_FORMAT, TASK_FORMAT, schema_file_name

Kind = Literal["manual_track", "cad_selection", "correspondences", "verification"]

UNIT = {"minimum": 0.0, "maximum": 1.0}
Box = tuple[float, float, float, float]
BOX = "Box (ymin, xmin, ymax, xmax), normalised by image height (y) and width (x)."
IMAGE = "image, normalised [0,1], origin top-left, x right, y down"
CAD = "canonical CAD (+Y up, front +Z, unmirrored)"
TRACK_ID = {"minimum": 0, "maximum": 2**31 - 1}  # tracks.track_id is an int32
CAD_EXTENT_M = 100.0
"""Bound on |coordinate| of a point on a canonical (bbox-centred, metres) CAD model: no object of a
room walkthrough reaches 100 m from its centre, so a bigger value is a unit or typing error."""
SECONDS = {"minimum": 0.0, "maximum": 86400.0}
"""Bound on the seconds an annotator spends on one item (a day: more is a clock error)."""
FORMAT = "Format and version of the file."
WITHDRAWN = ("None: the stage withdrew its earlier task of this kind (a rerun asks nothing of it; the instructions "
             "say why).")
KIND = "The task kind."


# ------------------------------------------------------------------------------ shared records

@dataclass(frozen=True, kw_only=True)
class TimedBox:
    """A box on one frame."""

    timestamp_us: int = spec("Camera timestamp of the frame (a `frames` row).", unit="µs")
    box: Box = spec(BOX, frame=IMAGE, items=UNIT)


@dataclass(frozen=True, kw_only=True)
class KeyframeView:
    """A key-frame shown to the annotator, with the object's box when it has one there."""

    timestamp_us: int = spec("Camera timestamp (a `frames` row).", unit="µs")
    frame_index: int = spec("frames.frame_index.", minimum=0)
    image_path: str = spec("The frame's image, relative to the warehouse root.")
    box: Box | None = spec(BOX + " Null: no box on this frame.", frame=IMAGE, items=UNIT, default=None)
    overlay_path: str | None = spec("Verification only: the posed CAD rendered over the frame, relative to the "
                                    "warehouse root.", default=None)


@dataclass(frozen=True, kw_only=True)
class ExistingTrack:
    """A track found already (shown so that only missing objects are drawn)."""

    track_id: int = spec("tracks.track_id.", **TRACK_ID)
    label: str = spec("Class (tracks.label).")
    boxes: tuple[TimedBox, ...] = spec("Its boxes on the task's key-frames.")


@dataclass(frozen=True, kw_only=True)
class CadCandidate:
    """One retrieved CAD model (a `cad_candidates` row)."""

    rank: int = spec("1 = shown first: by score, with at most [retrieval] max_per_class of one class while other classes have models.",
                     minimum=1, maximum=2**31 - 1)
    cad_id: str = spec("cad_models.cad_id.", minLength=1)
    library: str = spec("CAD library of the model.")
    cad_class: str = spec("cad_models.class.")
    score: float = spec("Retrieval score in [0, 1].")
    mesh_path: str = spec("The canonical mesh, relative to the warehouse root.")
    render_paths: tuple[str, ...] = spec("Renders of the model (cad_views), relative to the warehouse root.")


@dataclass(frozen=True, kw_only=True)
class Pose:
    """A 9-DoF pose, official order: X_world = T + R · diag(S) · diag(-1, 1, 1)[mirrored] · X_cad."""

    translation: tuple[float, float, float] = spec("T.", unit="m", frame="world (+Y up)")
    rotation: tuple[float, float, float, float] = spec("R as a unit quaternion (w, x, y, z).", frame="CAD -> world")
    scale: tuple[float, float, float] = spec("S along the CAD axes.", frame=CAD)
    is_mirrored: bool = spec("Mirror x -> -x before scaling.")


# ------------------------------------------------------------------------------ answers

@dataclass(frozen=True, kw_only=True)
class ManualTrackAnswer:
    """One object the automatic tracks missed: its class and its boxes."""

    label: str = spec("Class of the object.", minLength=1)
    boxes: tuple[TimedBox, ...] = spec("Boxes on the frames where the object is visible (one per frame).", minItems=1)
    source_id: str | None = spec("The object's id in the annotation tool (e.g. 'cvat:3'), for tracing.", default=None)
    same_as_track: int | None = spec("'This is track N': the drawn boxes show existing track N of the task (filling its "
                                     "gaps), not a new object (kept in track_relations: the boxes make a manual track that "
                                     "the later tasks skip and the export merges into track N). Null: a new object.",
                                     default=None, **TRACK_ID)


@dataclass(frozen=True, kw_only=True)
class CadSelectionAnswer:
    """The CAD model chosen for one track."""

    track_id: int = spec("tracks.track_id.", **TRACK_ID)
    cad_id: str | None = spec("The chosen candidate's cad_id; null: none of the candidates is similar enough "
                              "(the track leaves the pipeline).", minLength=1)
    same_as_track: int | None = spec("'Same object as track N': this track is a fragment of track N of the task; "
                                     "cad_id must then be null (the object is posed through track N).",
                                     default=None, **TRACK_ID)
    seconds: float | None = spec("Time the annotator spent on this item.", unit="s", default=None, **SECONDS)


@dataclass(frozen=True, kw_only=True)
class CorrespondencePoint:
    """One click: an image point and the matching point on the CAD model."""

    x: float = spec("Image x, normalised by the width.", frame=IMAGE, **UNIT)
    y: float = spec("Image y, normalised by the height.", frame=IMAGE, **UNIT)
    xyz: tuple[float, float, float] = spec("The point on the CAD model.", unit="m", frame=CAD,
                                           items={"minimum": -CAD_EXTENT_M, "maximum": CAD_EXTENT_M})


@dataclass(frozen=True, kw_only=True)
class CorrespondenceKeyframe:
    """The clicks of one key-frame (different points on every key-frame are fine)."""

    timestamp_us: int = spec("Camera timestamp of the key-frame (a `frames` row).", unit="µs")
    points: tuple[CorrespondencePoint, ...] = spec("4-6 correspondences.", minItems=4, maxItems=6)


@dataclass(frozen=True, kw_only=True)
class CorrespondenceAnswer:
    """The correspondences of one track."""

    track_id: int = spec("tracks.track_id.", **TRACK_ID)
    cad_id: str = spec("The CAD model clicked on (the task's cad_id for the track).", minLength=1)
    is_mirrored: bool = spec("The annotator mirrored the model (x -> -x); 3D points stay unmirrored.")
    keyframes: tuple[CorrespondenceKeyframe, ...] = spec("Key-frames annotated (one entry per timestamp), at least two: "
                                                         "one view gives no depth.", minItems=2)
    seconds: float | None = spec("Time the annotator spent on this item.", unit="s", default=None, **SECONDS)


@dataclass(frozen=True, kw_only=True)
class VerificationAnswer:
    """The verdict on one track's pose: accept only if the CAD aligns on every key-frame."""

    track_id: int = spec("tracks.track_id.", **TRACK_ID)
    verdict: Literal["accept", "reject"] = spec("accept: aligned on all key-frames; reject: otherwise.")
    same_as_track: int | None = spec("'Same object as track N': this pose shows the object of track N of the task (a "
                                     "duplicate, e.g. one the item's maybe_same_as flags); the export keeps N's pose only and "
                                     "lists this track in N's object's merged tracks. Allowed with either verdict. Null (or "
                                     "absent): an object of its own.", default=None, omit_default=True, **TRACK_ID)
    comment: str | None = spec("Free text.", default=None)
    seconds: float | None = spec("Time the annotator spent on this item.", unit="s", default=None, **SECONDS)


# ------------------------------------------------------------------------------ task items

@dataclass(frozen=True, kw_only=True)
class CadSelectionItem:
    """One track to choose a CAD model for."""

    track_id: int = spec("tracks.track_id.", **TRACK_ID)
    label: str = spec("Class of the track.")
    keyframes: tuple[KeyframeView, ...] = spec("Evenly spaced frames of the track, with its box.", minItems=1)
    candidates: tuple[CadCandidate, ...] = spec("The retrieved candidates, best first.", minItems=1, maxItems=10)
    previous: CadSelectionAnswer | None = spec("The answer given before: on this task, or a model chosen on an earlier one "
                                               "for the same object and still among the candidates "
                                               "(tasks.human.choices_in_force); the item counts as answered. Null: none.",
                                               default=None)


@dataclass(frozen=True, kw_only=True)
class CorrespondenceItem:
    """One track to click correspondences for, with the chosen CAD model."""

    track_id: int = spec("tracks.track_id.", **TRACK_ID)
    label: str = spec("Class of the track.")
    cad_id: str = spec("The chosen CAD model.", minLength=1)
    library: str = spec("Its CAD library.")
    mesh_path: str = spec("Its canonical mesh (metres, +Y up, front +Z), relative to the warehouse root.")
    render_paths: tuple[str, ...] = spec("Renders of the model, relative to the warehouse root.")
    symmetry: int = spec("Symmetry order about +Y (1, 2, 4, 36).", minimum=1)
    keyframes: tuple[KeyframeView, ...] = spec("Key-frames to annotate, with the track's box.", minItems=1)
    previous: CorrespondenceAnswer | None = spec("Clicks given before that answer this item: on this task, or on an earlier "
                                                 "one for the same model and object (tasks.human.clicks_in_force); the item "
                                                 "counts as answered. Null: none.", default=None)


@dataclass(frozen=True, kw_only=True)
class VerificationItem:
    """One posed track to verify; ``keyframes[*].overlay_path`` are the renders to judge."""

    track_id: int = spec("tracks.track_id.", **TRACK_ID)
    label: str = spec("Class of the track.")
    cad_id: str = spec("The posed CAD model.", minLength=1)
    mesh_path: str = spec("Its canonical mesh, relative to the warehouse root.")
    pose: Pose = spec("The solved pose that was rendered.")
    keyframes: tuple[KeyframeView, ...] = spec("Key-frames with overlays.", minItems=1)
    maybe_same_as: tuple[int, ...] = spec("'May be the same object as track N': the other tracks of the task whose posed "
                                          "CAD box overlaps this one's by at least [verification] duplicate_overlap of the "
                                          "smaller box's volume (tasks.pose.duplicates), ascending; absent when none. The "
                                          "annotator says so with the answer's same_as_track.",
                                          default=(), omit_default=True, items=TRACK_ID)
    previous: VerificationAnswer | None = spec("The verdict given before: on this task, or on an earlier one on the same "
                                               "model whose overlay has since moved by at most [verification] carry_max_px "
                                               "(tasks.human.verdicts_in_force); the item counts as answered. Null: none.",
                                               default=None)


# ------------------------------------------------------------------------------ files

@dataclass(frozen=True, kw_only=True)
class TaskHeader:
    """Fields every task file has."""

    format: str = spec("Format and version.", default="")
    kind: str = spec("The task kind.", default="")
    task_id: str = spec("Unique id of the task (letters, digits, '_', '.', '-').", pattern=NAME.pattern)
    clip: str = spec("Clip name.", minLength=1)
    created_at: str = spec("When the task was written, ISO 8601 UTC.")
    image_size: tuple[int, int] = spec("(height, width) of the clip's frames.", unit="px", items={"minimum": 1})
    instructions: str = spec("What to do, for the annotator.", default="")


@dataclass(frozen=True, kw_only=True)
class LabelHeader:
    """Fields every label file has."""

    format: str = spec("Format and version.", default="")
    kind: str = spec("The task kind.", default="")
    task_id: str = spec("The task answered (its task file's task_id).", minLength=1)
    clip: str = spec("Clip name (the task's).", minLength=1)
    annotator: str | None = spec("Who answered (free text).", default=None)
    created_at: str | None = spec("When the answers were given, ISO 8601 (orders labels ingested together).", default=None)


@dataclass(frozen=True, kw_only=True)
class ManualTrackTask(TaskHeader):
    """Draw the objects that no existing track covers, as boxes on the key-frames (Sec. 3.1)."""

    format: str = fixed(FORMAT, TASK_FORMAT)
    kind: str = fixed(KIND, "manual_track")
    keyframes: tuple[KeyframeView, ...] = spec("Regularly spaced key-frames to draw on. " + WITHDRAWN)
    existing_tracks: tuple[ExistingTrack, ...] = spec("Tracks found already, with their boxes on the key-frames.")
    classes: tuple[str, ...] = spec("Allowed classes; empty: any.")
    previous: tuple[ManualTrackAnswer, ...] = spec("Objects drawn before, if any: this task's answer in force (with what "
                                                   "each was said to be), else the boxes of the clip's newest earlier answer.",
                                                   default=())
    previous_not_objects: tuple[int, ...] = spec("Tracks said to show no object in this task's answer in force (a new "
                                                 "answer replaces it, so a page shows them ticked).", default=(), items=TRACK_ID)


@dataclass(frozen=True, kw_only=True)
class CadSelectionTask(TaskHeader):
    """Per track, choose the CAD candidate that looks closest to the object, or none (Sec. 3.2)."""

    format: str = fixed(FORMAT, TASK_FORMAT)
    kind: str = fixed(KIND, "cad_selection")
    items: tuple[CadSelectionItem, ...] = spec("Tracks to answer. " + WITHDRAWN)


@dataclass(frozen=True, kw_only=True)
class CorrespondenceTask(TaskHeader):
    """Per track and key-frame, click 4-6 3D<->2D point correspondences (Sec. 3.3)."""

    format: str = fixed(FORMAT, TASK_FORMAT)
    kind: str = fixed(KIND, "correspondences")
    items: tuple[CorrespondenceItem, ...] = spec("Tracks to answer. " + WITHDRAWN)


@dataclass(frozen=True, kw_only=True)
class VerificationTask(TaskHeader):
    """Per track, accept the pose only if the rendered CAD aligns on every key-frame (Sec. 3.5)."""

    format: str = fixed(FORMAT, TASK_FORMAT)
    kind: str = fixed(KIND, "verification")
    items: tuple[VerificationItem, ...] = spec("Tracks to answer. " + WITHDRAWN)


@dataclass(frozen=True, kw_only=True)
class ManualTrackLabel(LabelHeader):
    """The objects drawn for a manual-track task; an empty list: nothing is missing. A newer label
    for the same task replaces the whole answer."""

    format: str = fixed(FORMAT, LABEL_FORMAT)
    kind: str = fixed(KIND, "manual_track")
    answers: tuple[ManualTrackAnswer, ...] = spec("The missing objects.")
    not_objects: tuple[int, ...] = spec("'Track N is not an object': existing tracks of the task that show no object "
                                        "(false detections); kept in track_relations: the later tasks skip them, the export "
                                        "drops them.",
                                        default=(), items=TRACK_ID)
    seconds: float | None = spec("Time the annotator spent on the task (its one item).", unit="s", default=None, **SECONDS)


@dataclass(frozen=True, kw_only=True)
class CadSelectionLabel(LabelHeader):
    """CAD choices for some or all tracks of a cad_selection task."""

    format: str = fixed(FORMAT, LABEL_FORMAT)
    kind: str = fixed(KIND, "cad_selection")
    answers: tuple[CadSelectionAnswer, ...] = spec("One per answered track.", minItems=1)


@dataclass(frozen=True, kw_only=True)
class CorrespondenceLabel(LabelHeader):
    """Correspondences for some or all tracks of a correspondences task."""

    format: str = fixed(FORMAT, LABEL_FORMAT)
    kind: str = fixed(KIND, "correspondences")
    answers: tuple[CorrespondenceAnswer, ...] = spec("One per answered track.", minItems=1)


@dataclass(frozen=True, kw_only=True)
class VerificationLabel(LabelHeader):
    """Verdicts for some or all tracks of a verification task."""

    format: str = fixed(FORMAT, LABEL_FORMAT)
    kind: str = fixed(KIND, "verification")
    answers: tuple[VerificationAnswer, ...] = spec("One per answered track.", minItems=1)


TASK_CLASSES: dict[str, type] = {"manual_track": ManualTrackTask, "cad_selection": CadSelectionTask,
                                 "correspondences": CorrespondenceTask, "verification": VerificationTask}
LABEL_CLASSES: dict[str, type] = {"manual_track": ManualTrackLabel, "cad_selection": CadSelectionLabel,
                                  "correspondences": CorrespondenceLabel, "verification": VerificationLabel}
Task = ManualTrackTask | CadSelectionTask | CorrespondenceTask | VerificationTask
Label = ManualTrackLabel | CadSelectionLabel | CorrespondenceLabel | VerificationLabel


def json_schema(kind: str, which: Literal["task", "label"] = "label") -> dict:
    """The JSON Schema (draft 2020-12) of the ``which`` file of ``kind``."""
    classes = TASK_CLASSES if which == "task" else LABEL_CLASSES if which == "label" else None
    if classes is None or kind not in classes:
        raise KeyError(f"unknown schema {kind!r}/{which!r} (kinds: {', '.join(KINDS)}; which: task, label)")
    return json_schema_of(classes[kind], schema_id=f"https://cadestate.invalid/schemas/{kind}.{which}.schema.json",
                          title=f"cadestate {kind} {which} file")



def publish_schemas(folder: str | None = None) -> list[str]:
    """Write every task and label JSON Schema to ``folder`` (default ``schemas/json/``); returns the paths."""
    import json
    from pathlib import Path

    from cadestate.atomic import atomic_write_bytes

    out = Path(folder) if folder else Path(__file__).parent / "json"
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for kind in KINDS:
        for which in ("task", "label"):
            path = out / schema_file_name(kind, which)
            atomic_write_bytes(path, (json.dumps(json_schema(kind, which), indent=2, ensure_ascii=False) + "\n").encode())
            paths.append(str(path))
    return paths
