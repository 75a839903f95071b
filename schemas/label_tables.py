"""The warehouse tables of the human tasks: the tasks written, the label files ingested and their
answers (one table per kind), the effort and the statements about tracks (see :mod:`schemas.labels`
for the files themselves)."""

from __future__ import annotations

import pyarrow as pa

from schemas.base import CLIP, TableSpec, column, vector
from schemas.core import UTC_TS
from schemas.labels import CAD, IMAGE

def _answer_table(name: str, description: str, key: tuple[str, ...], columns: list[pa.Field]) -> TableSpec:
    """An append-mode answer table: (clip, label_sha256, ingested_at, task_id) then ``columns``."""
    head = [CLIP, column("label_sha256", pa.string(), "SHA-256 of the label file (label_files.label_sha256)."),
            column("ingested_at", UTC_TS, "When the label file was ingested (label_files.ingested_at)."),
            column("task_id", pa.string(), "The task answered (label_tasks.task_id).")]
    return TableSpec(name=name, mode="append", key=("clip", "ingested_at", "label_sha256", *key),
                     description=description, schema=pa.schema(head + columns))


LABEL_TASKS = TableSpec(
    name="label_tasks",
    mode="append",
    key=("clip", "created_at", "task_id"),
    description="Every task file written for people (history): its kind, path, and the document itself.",
    schema=pa.schema([
        CLIP,
        column("task_id", pa.string(), "Unique id of the task."),
        column("kind", pa.string(), "manual_track | cad_selection | correspondences | verification."),
        column("path", pa.string(), "The task file, relative to the warehouse root."),
        column("task_sha256", pa.string(), "SHA-256 of the task file."),
        column("num_items", pa.int32(), "Tracks to answer (manual_track: key-frames)."),
        column("created_at", UTC_TS, "When the task was written."),
        column("document", pa.string(), "The task file's JSON (what labels are validated against)."),
    ]),
)

LABEL_FILES = TableSpec(
    name="label_files",
    mode="append",
    key=("clip", "ingested_at", "label_sha256"),
    description="Every ingested label file (history; a newer label for the same task and track supersedes an older one).",
    schema=pa.schema([
        CLIP,
        column("label_sha256", pa.string(), "SHA-256 of the file's bytes (a file is ingested once)."),
        column("ingested_at", UTC_TS, "When it was ingested (strictly increasing: 'newer' means ingested later)."),
        column("task_id", pa.string(), "The task answered."),
        column("kind", pa.string(), "manual_track | cad_selection | correspondences | verification."),
        column("source_path", pa.string(), "The file's path when it was ingested."),
        column("annotator", pa.string(), "Who answered (from the file).", nullable=True),
        column("created_at", UTC_TS, "When the answers were given (from the file).", nullable=True),
        column("num_answers", pa.int32(), "Answers in the file (tracks; manual_track: objects drawn)."),
        column("document", pa.string(), "The label file's JSON, as ingested."),
    ]),
)

MANUAL_TRACK_LABELS = _answer_table(
    "manual_track_labels", "Boxes of the objects people drew for manual-track tasks (one row per box; history).",
    ("object_index", "timestamp_us"), [
        column("object_index", pa.int32(), "0-based index of the object within its label file."),
        column("label", pa.string(), "Class of the object."),
        column("source_id", pa.string(), "The object's id in the annotation tool.", nullable=True),
        column("timestamp_us", pa.int64(), "Frame of the box.", unit="µs"),
        column("box", vector(4), "(ymin, xmin, ymax, xmax), normalised.", frame=IMAGE),
    ])

CAD_SELECTION_LABELS = _answer_table(
    "cad_selection_labels", "The CAD model people chose per track, or none (history).", ("track_id",), [
        column("track_id", pa.int32(), "tracks.track_id."),
        column("cad_id", pa.string(), "The chosen cad_id; null: none of the candidates.", nullable=True),
        column("rank", pa.int32(), "The chosen candidate's rank in the task (null: none).", nullable=True),
    ])

CORRESPONDENCE_LABELS = _answer_table(
    "correspondence_labels", "3D<->2D clicks per track and key-frame, with the co-planarity found at ingest (history; "
    "the clicks in force for the newest correspondences task go to `correspondences`).", ("track_id", "timestamp_us", "point_index"), [
        column("track_id", pa.int32(), "tracks.track_id."),
        column("timestamp_us", pa.int64(), "Key-frame.", unit="µs"),
        column("point_index", pa.int32(), "0-based index of the click within its key-frame."),
        column("cad_id", pa.string(), "CAD model clicked on."),
        column("point_2d", vector(2), "Image point (x, y), normalised.", frame=IMAGE),
        column("point_3d", vector(3), "Point on the CAD model.", unit="m", frame=CAD),
        column("is_mirrored", pa.bool_(), "The annotator mirrored the model for this track."),
        column("keyframe_coplanar", pa.bool_(), "The key-frame's 3D points lie on one plane (tasks.pose.checks, "
                                                "[pose] coplanar_tol)."),
        column("keyframe_coplanar_axis", pa.int32(), "CAD axis (0 x, 1 y, 2 z) nearest the normal of that plane; -1 none."),
        column("track_coplanar_axis", pa.int32(), "The same for all of the answer's points (symmetry-aware, as the "
                                                  "solver ties the scale along it); -1 none."),
    ])

VERIFICATION_LABELS = _answer_table(
    "verification_labels", "Verdicts of people on solved poses (history).", ("track_id",), [
        column("track_id", pa.int32(), "tracks.track_id."),
        column("cad_id", pa.string(), "The posed CAD model (from the task)."),
        column("accepted", pa.bool_(), "True: the rendered CAD aligns on every key-frame."),
        column("comment", pa.string(), "Free text.", nullable=True),
        column("same_as_track", pa.int32(), "'Same object as track N' (the answer's same_as_track, also kept in "
                                            "track_relations); null: its own object, or a label ingested before the column.",
               nullable=True),
    ])

LABEL_EFFORT = _answer_table(
    "label_effort", "Seconds annotators spent per answered item, from the label files' `seconds` (what annotation costs "
    "per object, as the paper reports; answers without `seconds` have no row; history).", ("kind", "track_id"), [
        column("kind", pa.string(), "manual_track | cad_selection | correspondences | verification."),
        column("track_id", pa.int32(), "The track answered; -1: a manual_track task (answered whole, one item)."),
        column("annotator", pa.string(), "Who answered (label_files.annotator).", nullable=True),
        column("seconds", pa.float64(), "Time spent on the item.", unit="s"),
    ])

TRACK_RELATIONS = _answer_table(
    "track_relations", "What annotators said about tracks besides answering them (history): a track is no object, or the "
    "same object as another; only the statements of the answers in force count (tasks.tracking.relations).", ("statement_index",), [
        column("statement_index", pa.int32(), "0-based index of the statement within its label file."),
        column("kind", pa.string(), "The label's kind (manual_track | cad_selection | verification)."),
        column("relation", pa.string(), "not_object (manual_track `not_objects`: track_id shows no object; the export drops it "
                                        "and the later human tasks leave it out) | same_object (cad_selection `same_as_track`: "
                                        "track_id is a fragment of other_track_id, merged into its root's object by the export; "
                                        "verification `same_as_track`: track_id's pose shows the object of other_track_id, a "
                                        "duplicate; manual_track `same_as_track`: the drawn object object_index of the label is "
                                        "existing track track_id: its manual track is a fragment of track_id, and the later "
                                        "human tasks leave that manual track out)."),
        column("track_id", pa.int32(), "The track the statement is about."),
        column("other_track_id", pa.int32(), "same_object from cad_selection or verification: the track it is a fragment "
                                             "(or a duplicate) of.", nullable=True),
        column("object_index", pa.int32(), "same_object from manual_track: the drawn object (manual_track_labels.object_index).",
               nullable=True),
    ])

ANSWER_TABLES = {"manual_track": MANUAL_TRACK_LABELS, "cad_selection": CAD_SELECTION_LABELS,
                 "correspondences": CORRESPONDENCE_LABELS, "verification": VERIFICATION_LABELS}
LABEL_TABLES = (LABEL_TASKS, LABEL_FILES, *ANSWER_TABLES.values(), LABEL_EFFORT, TRACK_RELATIONS)
SIDE_TABLES = (LABEL_EFFORT, TRACK_RELATIONS)
"""Tables filled at ingest beside a file's answer table (written before its commit record)."""
