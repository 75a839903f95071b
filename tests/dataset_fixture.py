"""Hand-built warehouses for the dataset tests: a generated clip's frames, tracks from its
ground-truth boxes and accepted poses equal to its ground truth (no pipeline run)."""

from __future__ import annotations

from pathlib import Path

from PIL import Image

from conftest import table_rows
from tasks.cad.classes import CLASSES
from tasks.video.camera_file import CameraTrack, parse_camera_file
from tasks.video.decode import decode_at
from tasks.video.frames import frames_table
from warehouse import Warehouse

CLASS_NAME = {c.id: c.name for c in CLASSES}
"""Class id (what objects.json holds) -> class name (what the warehouse's tables hold)."""


def write_frames(wh: Warehouse, clip: str, video: Path, cameras: Path, width: int, height: int) -> CameraTrack:
    """The ``clips`` and ``frames`` rows of a clip, its images decoded from ``video`` (JPEG)."""
    cams = parse_camera_file(cameras)
    media = wh.root / "media" / "frames" / clip / "test"
    media.mkdir(parents=True)
    paths = []
    for ts, f in zip(cams.timestamps_us.tolist(), decode_at(video, cams.timestamps_us)):
        Image.fromarray(f.rgb).save(media / f"{ts:013d}.jpg")
        paths.append(wh.relative(media / f"{ts:013d}.jpg"))
    wh.write("frames", clip, frames_table(clip, cams, paths, width, height, cams.timestamps_us))
    wh.write("clips", clip, table_rows("clips", [{"clip": clip, "url": cams.url, "width": width, "height": height,
                                                 "up_rotation": [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0]}]))  # a +Y-up world
    return cams


def write_tracks(wh: Warehouse, clip: str, cams: CameraTrack, tracks: dict) -> None:
    """Automatic tracks ``{track id: (ground-truth object, its track entries)}`` as detections."""
    index = {ts: i for i, ts in enumerate(cams.timestamps_us.tolist())}
    dets, members, rows = [], [], []
    for tid, (_, entries) in tracks.items():
        rows.append({"clip": clip, "track_id": tid, "label": "chair"})
        for e in entries:
            det = index[e.timestamp] * 10000 + tid
            dets.append({"clip": clip, "det_id": det, "timestamp_us": e.timestamp, "frame_index": index[e.timestamp],
                         "box": list(e.box), "label": "chair"})
            members.append({"clip": clip, "track_id": tid, "det_id": det, "frame_index": index[e.timestamp],
                            "timestamp_us": e.timestamp})
    wh.write("detections", clip, table_rows("detections", dets))
    wh.write("track_detections", clip, table_rows("track_detections", members))
    wh.write("tracks", clip, table_rows("tracks", rows))


def write_accepted(wh: Warehouse, clip: str, posed: dict, keyframes: dict | None = None,
                   rejected: dict | None = None) -> None:
    """``verified_poses`` (accepted, the ground-truth pose) and ``poses`` rows of ``{track id: object}``,
    and the completed verification run; ``rejected`` {track id: object}: poses refused in verification
    (``verified_poses`` only)."""
    verdicts = [(t, o, True) for t, o in posed.items()] + [(t, o, False) for t, o in (rejected or {}).items()]
    wh.write("verified_poses", clip, table_rows("verified_poses", [
        {"clip": clip, "track_id": str(t), "cad_id": o.cad_id, "class": CLASS_NAME[o.cls], "accepted": ok,
         "translation": list(o.translation), "rotation": list(o.rotation), "scale": list(o.scale),
         "is_mirrored": o.is_mirrored, "comment": None} for t, o, ok in verdicts]))
    wh.write("poses", clip, table_rows("poses", [{"clip": clip, "track_id": str(t),
                                                  "num_keyframes": (keyframes or {}).get(t, 2)} for t in posed]))
    wh.write("runs", clip, table_rows("runs", [{"clip": clip, "run_id": "20260101T000000Z-verified", "stage": "verification",
                                                "status": "completed", "duration_s": 0.0}]))  # every pose judged: the clip is exported


def write_selection(wh: Warehouse, clip: str, chosen: dict[int, str | None]) -> None:
    """A cad_selection task answered: ``cad_candidates`` (the chosen model, rank 1, per track) and
    the label file choosing ``{track id: cad_id or None}`` (what :func:`tasks.human.cad_selection.selected_models` reads)."""
    from tasks.human.cad_selection import cad_selection_task_id

    wh.write("cad_candidates", clip, table_rows("cad_candidates", [
        {"clip": clip, "track_id": t, "rank": 1, "cad_id": c or "none"} for t, c in chosen.items()]))
    task = cad_selection_task_id(wh, clip)
    head = {"clip": clip, "label_sha256": "sel", "task_id": task}
    wh.write("label_files", clip, table_rows("label_files", [{**head, "kind": "cad_selection", "num_answers": len(chosen)}]))
    wh.write("cad_selection_labels", clip, table_rows("cad_selection_labels", [
        {**head, "track_id": t, "cad_id": c, "rank": 1 if c else None} for t, c in chosen.items()]))


def write_manual_track_task(wh: Warehouse, clip: str, keyframes: list[int]) -> None:
    """A manual_track task on the key-frames ``keyframes`` (µs) and a label file answering it."""
    import json

    head = {"clip": clip, "task_id": f"{clip}.manual_track.t"}
    wh.write("label_tasks", clip, table_rows("label_tasks", [
        {**head, "kind": "manual_track", "num_items": len(keyframes),
         "document": json.dumps({"keyframes": [{"timestamp_us": ts} for ts in keyframes]})}]))
    wh.write("label_files", clip, table_rows("label_files", [
        {**head, "label_sha256": "mt", "kind": "manual_track", "num_answers": 1}]))
