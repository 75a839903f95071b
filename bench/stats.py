"""Dataset statistics as in the paper's Table 2 (``tbl:general_statistics``).

From (frames.json, objects.json) pairs, one per clip ("scene" in the paper):

- ``clips``, ``frames`` (frames.json entries), ``objects`` (all tracks in objects.json);
- ``posed_objects``: objects with a pose (the paper's "#Posed objects");
- ``cad_models``: distinct cad_id among posed objects; ``classes``: distinct classes among them;
  ``classes_over_1000`` / ``classes_over_100``: classes with more than 1000 / 100 posed objects;
- ``objects_per_clip``: posed objects / clips; ``frames_per_clip``: frames / clips;
- ``objects_per_frame``: posed objects visible per frame (having a track box on that frame's
  timestamp), averaged over all frames of frames.json (paper: 7.9 for CAD-Estate).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping, Sequence

from schemas.official import FramesFile, ObjectsFile

_ROWS = (("clips", "#Scenes (clips)"), ("posed_objects", "#Posed objects"), ("objects", "#Objects (tracks)"),
         ("classes", "#Classes"), ("classes_over_1000", "#Classes >1000"), ("classes_over_100", "#Classes >100"),
         ("objects_per_clip", "#Objects per scene"), ("objects_per_frame", "#Objects per frame (visible)"),
         ("cad_models", "#CAD models"), ("frames", "#Frames"), ("frames_per_clip", "#Frames per scene"))


def dataset_statistics(clips: Sequence[tuple[FramesFile, ObjectsFile]]) -> dict[str, float | int]:
    """Table 2 statistics of the given clips (see the module docstring); averages are 0 for no clips."""
    n_frames = n_objects = visible = 0
    per_class: Counter[str] = Counter()
    cads: set[str] = set()
    for frames, objects in clips:
        if frames.clip_name != objects.clip_name:
            raise ValueError(f"frames.json of {frames.clip_name!r} paired with objects.json of {objects.clip_name!r}")
        n_frames += len(frames.frames)
        n_objects += len(objects.objects)
        stamps = {f.timestamp for f in frames.frames}
        for o in objects.objects:
            if o.translation is None:
                continue
            per_class[o.cls] += 1
            if o.cad_id is not None:
                cads.add(o.cad_id)
            visible += len({t.timestamp for t in o.track} & stamps)
    n_clips = len(clips)
    posed = sum(per_class.values())
    return {
        "clips": n_clips, "frames": n_frames, "objects": n_objects, "posed_objects": posed,
        "cad_models": len(cads), "classes": len(per_class),
        "classes_over_1000": sum(v > 1000 for v in per_class.values()),
        "classes_over_100": sum(v > 100 for v in per_class.values()),
        "objects_per_clip": posed / n_clips if n_clips else 0.0,
        "objects_per_frame": visible / n_frames if n_frames else 0.0,
        "frames_per_clip": n_frames / n_clips if n_clips else 0.0,
    }


def statistics_markdown(stats: Mapping[str, float | int] | Mapping[str, Mapping[str, float | int]]) -> str:
    """A markdown table like Table 2: one statistics dict, or {column name: dict} (e.g. Train/Val/Total)."""
    columns = {"Total": stats} if "clips" in stats else dict(stats)
    lines = ["| Dataset | " + " | ".join(columns) + " |", "|---|" + "---:|" * len(columns)]
    for key, label in _ROWS:
        cells = []
        for s in columns.values():
            v = s[key]
            cells.append(f"{v:.1f}" if isinstance(v, float) else str(v))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
