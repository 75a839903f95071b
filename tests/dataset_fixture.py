"""Hand-built warehouses for the dataset tests: a generated clip's frames, tracks from its
ground-truth boxes and accepted poses equal to its ground truth (no pipeline run)."""

from __future__ import annotations

from pathlib import Path

from PIL import Image

from conftest import table_rows
from tasks.cameras import CameraTrack, parse_camera_file
from tasks.frames import frames_table
from tasks.video import decode_at
from warehouse import Warehouse


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


def write_accepted(wh: Warehouse, clip: str, posed: dict, keyframes: dict | None = None) -> None:
    """``verified_poses`` (accepted, the ground-truth pose) and ``poses`` rows of ``{track id: object}``."""
    wh.write("verified_poses", clip, table_rows("verified_poses", [
        {"clip": clip, "track_id": str(t), "cad_id": o.cad_id, "class": "x", "accepted": True,
         "translation": list(o.translation), "rotation": list(o.rotation), "scale": list(o.scale),
         "is_mirrored": o.is_mirrored, "comment": None} for t, o in posed.items()]))
    wh.write("poses", clip, table_rows("poses", [{"clip": clip, "track_id": str(t),
                                                  "num_keyframes": (keyframes or {}).get(t, 2)} for t in posed]))
