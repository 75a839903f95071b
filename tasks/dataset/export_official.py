"""``cadestate export official``: the dataset in the layout of the official CAD-Estate release.

Layout (what the official ``cad_estate`` dataset classes read)::

    annotations/<clip>/frames.json    image_size (H, W); per frame timestamp (µs), key_frame (a
                                      key-frame of the manual-track task), intrinsics (fx, fy, cx, cy)
                                      in pixels, extrinsics world->camera {translation, rotation (w,x,y,z)}
    annotations/<clip>/objects.json   one object per physical object (tasks.dataset.objects)
    frames/<video_id>/<video_id>_<timestamp>.jpg   the frame images (the official code's own path:
                                      ``frames.load_images`` joins the video id and
                                      ``f"{video_id}_{timestamp}.jpg"``)
    cad/                              the CAD root of ``cadestate cad export-official``
    scene_list.txt                    the exported clip names, one a line (a split file)

World: frames and poses are written in the world of the clip's camera file (the rotation to +Y up
that ingest applied, ``clips.up_rotation``, is undone: :meth:`ClipDataset.in_input_world`), so the
exported extrinsics are the camera file's own.
A symmetric model's pose is the turn about its +Y through which its clicks reproject
(:mod:`tasks.dataset.symmetry_turn`): the same shape in the same place as the accepted pose.

Clip names are ``<video_id>_<start_us>`` (:mod:`tasks.video.clip_names`): a warehouse clip whose name
is not that of its camera file is exported under the derived name. Refused, naming the warehouse
clips: two clips under one name, two clips of different source videos that share a video id (their
frames would overwrite each other), two clips of one video whose images of one frame differ, and an
object whose chosen model is no longer in ``cad_models``. By default only clips whose
verification completed are exported (:func:`tasks.cad.export.export_clips`). Written into a temporary folder
beside ``out`` and moved into place at the end.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Sequence
from pathlib import Path

from cadestate.geometry import matrix_to_quaternion, pixel_intrinsics
from cadestate.progress import progress
from schemas.official import (Correspondence, Frame, FramesFile, ObjectAnnotation, ObjectsFile, TrackEntry, frames_to_json,
                              objects_to_json, write_json)
from tasks.cad.export import (ExportError, check_new_folder, export_clips, export_official as export_cad_root, publish,
                              temp_folder_beside)
from tasks.dataset.objects import ClipDataset, DatasetFrame, DatasetObject, clip_dataset
from tasks.dataset.symmetry_turn import turn_poses_to_clicks
from tasks.video.clip_names import ClipNameError, check_clip_name, derive_clip_name, shared_video_ids, video_id_of
from warehouse import Warehouse


def official_clip_name(clip: str, url: str, first_us: int) -> str:
    """The clip's name in the export: its own when it is ``<video_id>_<start_us>`` of its camera
    file (``url`` its line 1, ``first_us`` its first timestamp), else the name derived from them."""
    try:
        check_clip_name(clip, url, first_us, f"clip {clip}'s camera file")
        return clip
    except ClipNameError:
        pass
    try:
        return derive_clip_name(url, first_us, f"clip {clip}'s camera file")
    except ClipNameError as e:
        raise ExportError(str(e)) from None


def export_names(wh: Warehouse, clips: Sequence[str]) -> tuple[list[str], list[str]]:
    """The export names (:func:`official_clip_name`) and URL lines of ``clips``, from the ``clips``
    table and each clip's first frame, without reading their datasets."""
    urls = {r["clip"]: r["url"] for r in wh.read("clips", list(clips), columns=["clip", "url"]).to_pylist()}
    missing = [c for c in clips if c not in urls]
    if missing:
        raise ExportError(f"clip {missing[0]!r} is not in the clips table of {wh.root} (cadestate ingest)")
    names = []
    for clip in clips:
        stamps = wh.read("frames", [clip], columns=["timestamp_us"]).column("timestamp_us").to_pylist()
        names.append(official_clip_name(clip, urls[clip], min(stamps, default=0)))
    return names, [urls[c] for c in clips]


def official_frames(frames: Sequence[DatasetFrame]) -> tuple[Frame, ...]:
    """``frames.json`` entries of ``frames`` (pixel intrinsics, world->camera translation and quaternion)."""
    return tuple(Frame(f.timestamp_us, f.key_frame, tuple(float(v) for v in pixel_intrinsics(f.K)),
                       tuple(float(v) for v in f.t), tuple(float(v) for v in matrix_to_quaternion(f.R)))
                 for f in frames)


def frames_file(ds: ClipDataset, name: str) -> FramesFile:
    """The clip's ``frames.json`` content (pixel intrinsics, world->camera extrinsics)."""
    return FramesFile(name, ds.image_size, official_frames(ds.frames))


def object_annotation(o: DatasetObject) -> ObjectAnnotation:
    """One ``objects.json`` entry: the pose only when accepted, correspondences on annotated key-frames."""
    track = tuple(TrackEntry(ts, box, tuple(Correspondence(tuple(xy), tuple(xyz)) for xy, xyz in o.correspondences[ts])
                             if ts in o.correspondences else None)
                  for ts, box in sorted(o.boxes.items()))
    p = o.pose
    return ObjectAnnotation(track_id=str(o.track_id), cls=o.class_id, is_track_automatic=o.automatic,
                            is_mirrored=o.is_mirrored, track=track, cad_id=o.cad_id,
                            translation=p and tuple(float(v) for v in p.translation),
                            rotation=p and tuple(float(v) for v in p.rotation),
                            scale=p and tuple(float(v) for v in p.scale))


def _put_jpeg(src: Path, dst: Path) -> None:
    """``dst`` (a new file) as a JPEG of the frame image ``src``: hard-linked (or copied) when it is
    one, else converted. The warehouse's image and the export's are then one file: edit an exported
    image by replacing it, not in place."""
    if src.suffix.lower() not in (".jpg", ".jpeg"):
        from PIL import Image

        try:
            with Image.open(src) as image:
                rgb = image.convert("RGB")
        except (OSError, ValueError) as e:  # truncated, not an image
            raise ExportError(f"{src}: cannot read this frame's image ({e}); --clips exports the other clips") from None
        rgb.save(dst, quality=95)
        return
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def check_exportable(clips: Sequence[str], urls: Sequence[str], names: Sequence[str]) -> None:
    """Refuse (:class:`ExportError`, naming the warehouse clips) two clips under one export name and
    clips of different videos (``urls``, their camera files' line 1) under one video id."""
    by_name: dict[str, list[str]] = {}
    for clip, name in zip(clips, names):
        by_name.setdefault(name, []).append(clip)
    twice = {n: c for n, c in by_name.items() if len(c) > 1}
    if twice:
        name, which = next(iter(twice.items()))
        raise ExportError(f"clips {', '.join(which)} would both be exported as {name!r} (one video, one first "
                          "timestamp); export one of them")
    clip_of = dict(zip(names, clips))
    shared = shared_video_ids(zip(names, urls))
    if shared:
        vid, which = next(iter(shared.items()))
        raise ExportError(f"clips {', '.join(clip_of[n] for n in which)} come from different videos but share the "
                          f"video id {vid!r}; their frames would overwrite each other in frames/<video_id>/")


def write_clip(wh: Warehouse, tmp: Path, clip: str, name: str,
               frame_of: dict[Path, tuple[str, Path]]) -> list[ObjectAnnotation]:
    """Write the clip's ``annotations/<name>/`` and its frames into the export folder ``tmp``
    (``frame_of``: the frames of its video written so far, -> (clip, warehouse image); a frame an
    earlier clip wrote is checked to be the same image); returns its objects."""
    ds = turn_poses_to_clicks(clip_dataset(wh, clip).in_input_world())
    ds.require_models()  # a model gone from cad_models: the official loader would fail on its mesh
    folder = tmp / "annotations" / name
    folder.mkdir(parents=True)
    write_json(folder / "frames.json", frames_to_json(frames_file(ds, name)))
    objects = [object_annotation(o) for o in ds.objects]
    write_json(folder / "objects.json", objects_to_json(ObjectsFile(name, tuple(objects))))
    vid = video_id_of(name)
    (tmp / "frames" / vid).mkdir(parents=True, exist_ok=True)
    for f in ds.frames:
        dst = tmp / "frames" / vid / f"{vid}_{f.timestamp_us}.jpg"
        src = wh.root / f.image_path
        if dst in frame_of:  # two clips of one video, overlapping: one frame, or a refusal
            first, image = frame_of[dst]
            if image.read_bytes() != src.read_bytes():
                raise ExportError(f"clips {first} and {ds.clip} both hold frame {dst.name} of video {vid!r} "
                                  "with different images; export one of them")
            continue
        _put_jpeg(src, dst)
        frame_of[dst] = (ds.clip, src)
    return objects


def export_dataset(wh: Warehouse, out: Path, clips: Sequence[str] | None = None, cad: bool = True,
                   show_progress: bool = True) -> dict[str, int]:
    """Write the official layout of ``clips`` (default: every clip whose verification completed,
    :func:`export_clips`) to ``out`` (new or empty); returns counts (clips, frames, objects, posed
    objects, CAD models, and ``note``: :meth:`ExportClips.note`). One clip's dataset is in memory at
    a time (:func:`write_clip`), the clips of one video one after the other (only they can share a
    frame): all of them at once took ~0.4 MB a clip, gigabytes at the published 19,512 clips."""
    out = Path(os.path.abspath(out))
    check_new_folder(out)
    selection = export_clips(wh, clips)
    names, urls = export_names(wh, selection.chosen)
    check_exportable(selection.chosen, urls, names)
    counts = {"clips": len(names), "frames": 0, "objects": 0, "posed_objects": 0, "cad_models": 0,
              "note": selection.note()}
    frame_of: dict[Path, tuple[str, Path]] = {}  # the current video's exported frames -> (clip, warehouse image)
    video = None
    with temp_folder_beside(out) as tmp:
        if cad:  # first: a model that cannot be written ends the export before hours of clips
            try:
                counts["cad_models"] = export_cad_root(wh, tmp / "cad", show_progress=show_progress)
            except ExportError as e:
                raise ExportError(f"{e} (the CAD root; --no-cad exports the clips without it)") from None
        order = sorted(zip(names, selection.chosen), key=lambda nc: (video_id_of(nc[0]), nc[0]))
        for name, clip in progress(order, total=len(order), description="clips", enabled=show_progress):
            if video_id_of(name) != video:
                counts["frames"] += len(frame_of)  # images written: a frame two clips share counts once
                frame_of.clear()
                video = video_id_of(name)
            objects = write_clip(wh, tmp, clip, name, frame_of)
            counts["objects"] += len(objects)
            counts["posed_objects"] += sum(o.translation is not None for o in objects)
        counts["frames"] += len(frame_of)
        (tmp / "scene_list.txt").write_text("".join(f"{n}\n" for n in sorted(names)))
        publish(tmp, out)
    return counts
