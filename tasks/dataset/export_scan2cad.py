"""``cadestate export scan2cad``: the dataset's accepted poses as Scan2CAD files (skanti/Scan2CAD).

Each clip is a "scan" named as ``export official`` names the clip (``id_scan`` and ``<name>.csv``:
``<video_id>_<start_us>``, the CAD-Estate scene name, :func:`tasks.dataset.export_official.export_names`;
a warehouse clip named otherwise is written under that name, so both exports join on it); the
world is the clip's aligned world (metres, +Y up: the camera file's world turned by
``clips.up_rotation``, :mod:`tasks.video.world_up`), so every scan's own transform is the identity. Written into a temporary folder beside ``out`` and moved into
place at the end (:func:`tasks.cad.export.publish`); ``out`` is new, empty, or the folder of an
earlier Scan2CAD export, which then holds this export alone (its CSV files of scans not written
this time are removed as the new files move in: :func:`earlier_csvs`):

- ``<name>.csv``: one row per posed physical object, ``catid,id_cad,tx,ty,tz,qw,qx,qy,qz,sx,sy,sz``,
  no header (``EvaluateBenchmark.py`` reads every row as an alignment): the class id, the CAD id,
  translation (m, world), rotation (w, x, y, z) CAD -> world, scale along the CAD axes;
- ``full_annotations.json``: the same objects as Scan2CAD annotations, a list of
  ``{id_scan, trs, n_aligned_models, aligned_models: [{id_cad, catid_cad, sym, trs: {translation,
  rotation, scale}, center, bbox}]}``; ``sym`` is the model's tag (``__SYM_NONE``,
  ``__SYM_ROTATE_UP_2``, ``_4``, ``_INF``); ``center`` = (0, 0, 0) (our CAD frame is centred on
  the model's bounding box) and ``bbox`` its half size (m, CAD frame);
- ``cad_appearances.json``: ``{id_scan: {"<catid>_<id_cad>": count}}``, how often each model
  appears in each scan (the evaluation script caps predictions per model with it).

Scan2CAD has no mirror flag: a mirrored model is a CAD model of its own, ``<cad_id>`` +
:data:`MIRRORED_SUFFIX` (its geometry is the model with x -> -x).
"""

from __future__ import annotations

import csv
import io
import json
import os
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from tasks.cad.export import ExportError, export_clips, publish, remove_leftovers, some_named, temp_folder_beside
from tasks.dataset.export_official import export_names
from tasks.dataset.objects import ClipDataset, clip_dataset
from warehouse import Warehouse

MIRRORED_SUFFIX = "_mirrored"
SYMMETRY_TAGS = {1: "__SYM_NONE", 2: "__SYM_ROTATE_UP_2", 4: "__SYM_ROTATE_UP_4", 36: "__SYM_ROTATE_UP_INF"}
CSV_COLUMNS = ("catid", "id_cad", "tx", "ty", "tz", "qw", "qx", "qy", "qz", "sx", "sy", "sz")
JSON_FILES = ("full_annotations.json", "cad_appearances.json")
IDENTITY = {"translation": [0.0, 0.0, 0.0], "rotation": [1.0, 0.0, 0.0, 0.0], "scale": [1.0, 1.0, 1.0]}
"""The transform of every scan this export writes (a clip's world is its scan's)."""


def scan2cad_cad_id(cad_id: str, mirrored: bool) -> str:
    """The Scan2CAD CAD id of a (possibly mirrored) model: the mirrored model is its own id."""
    return cad_id + MIRRORED_SUFFIX if mirrored else cad_id


def split_cad_id(id_cad: str) -> tuple[str, bool]:
    """Inverse of :func:`scan2cad_cad_id`: (cad_id, mirrored)."""
    return (id_cad[: -len(MIRRORED_SUFFIX)], True) if id_cad.endswith(MIRRORED_SUFFIX) else (id_cad, False)


@dataclass(frozen=True)
class Alignment:
    """One CSV row: ``catid`` class id, ``id_cad``, ``translation`` (m, world), ``rotation``
    (w, x, y, z) CAD -> world, ``scale`` along the CAD axes."""

    catid: str
    id_cad: str
    translation: tuple[float, float, float]
    rotation: tuple[float, float, float, float]
    scale: tuple[float, float, float]

    def row(self) -> list[str]:
        return [self.catid, self.id_cad, *(repr(float(v)) for v in (*self.translation, *self.rotation, *self.scale))]


def alignments(ds: ClipDataset) -> list[Alignment]:
    """The clip's posed objects as Scan2CAD alignments (track id order)."""
    return [Alignment(o.class_id, scan2cad_cad_id(o.cad_id, o.pose.is_mirrored), o.pose.translation, o.pose.rotation,
                      o.pose.scale) for o in ds.objects if o.pose is not None and o.cad_id is not None]


def csv_text(rows: Sequence[Alignment]) -> str:
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerows(a.row() for a in rows)
    return buf.getvalue()


def write_csv(path: Path, rows: Sequence[Alignment]) -> None:
    """``rows`` as a Scan2CAD per-scan CSV, UTF-8 whatever the locale (a model id of any script)."""
    path.write_text(csv_text(rows), encoding="utf-8")


def read_csv(path: Path) -> list[Alignment]:
    """A Scan2CAD per-scan CSV (UTF-8) back into alignments; a bad row names the file and line."""
    out = []
    with open(path, newline="", encoding="utf-8") as f:
        for i, row in enumerate(csv.reader(f), 1):
            if len(row) != len(CSV_COLUMNS):
                raise ExportError(f"{path}:{i}: expected {len(CSV_COLUMNS)} columns ({','.join(CSV_COLUMNS)}), got {len(row)}")
            try:
                v = [float(x) for x in row[2:]]
            except ValueError:
                raise ExportError(f"{path}:{i}: columns tx..sz must be numbers") from None
            out.append(Alignment(row[0], row[1], tuple(v[0:3]), tuple(v[3:7]), tuple(v[7:10])))
    return out


def annotation(ds: ClipDataset, name: str) -> dict:
    """The clip's Scan2CAD annotation entry, scan ``name`` (identity scan transform)."""
    models = []
    for o in ds.objects:
        if o.pose is None or o.cad_id is None:
            continue
        models.append({"id_cad": scan2cad_cad_id(o.cad_id, o.pose.is_mirrored), "catid_cad": o.class_id,
                       "sym": SYMMETRY_TAGS.get(o.symmetry, "__SYM_NONE"),
                       "trs": {"translation": list(o.pose.translation), "rotation": list(o.pose.rotation),
                               "scale": list(o.pose.scale)},
                       "center": [0.0, 0.0, 0.0], "bbox": [e / 2 for e in (o.extent or (0.0, 0.0, 0.0))]})
    return {"id_scan": name, "trs": dict(IDENTITY),
            "n_aligned_models": len(models), "aligned_models": models}


def earlier_csvs(out: Path) -> list[Path]:
    """The CSV files of the earlier Scan2CAD export in ``out`` (none when ``out`` is missing or
    empty). :class:`ExportError` when ``out`` is a file, or a folder that is not an export's: one
    without ``full_annotations.json``, or holding anything but :data:`JSON_FILES` and ``*.csv`` files."""
    if out.exists() and not out.is_dir():
        raise ExportError(f"{out}: exists and is not a folder; choose a new folder")
    remove_leftovers(out)  # a killed export's temporary folder, inside ``out`` where it is a mount point
    entries = sorted(out.iterdir()) if out.exists() else []
    if not entries:
        return []
    other = [e.name for e in entries if not e.is_file() or (e.name not in JSON_FILES and e.suffix != ".csv")]
    if other:
        raise ExportError(f"{out}: holds {other[0]!r}, which no Scan2CAD export writes; choose a new folder "
                          "(or that of an earlier export, which it replaces)")
    if not (out / JSON_FILES[0]).is_file():
        raise ExportError(f"{out}: holds files but no {JSON_FILES[0]}: not the folder of a Scan2CAD export; "
                          "choose a new folder")
    csvs = [e for e in entries if e.suffix == ".csv"]
    if not _ours(out / JSON_FILES[0], {e.stem for e in csvs}):
        raise ExportError(f"{out}: its {JSON_FILES[0]} is not one `cadestate export scan2cad` wrote (a scan with a "
                          "transform of its own, or a CSV file of no scan: Scan2CAD's own files?); choose a new folder")
    return csvs


def _ours(path: Path, stems: set[str]) -> bool:
    """Whether ``path`` is the ``full_annotations.json`` of an export of ours: every scan's transform
    :data:`IDENTITY`, and a scan for each of the folder's CSV files (``stems``). Scan2CAD's own
    release (scans in ScanNet's frames, beside ``unique_cads.csv``) is not: an export replaced it."""
    try:
        scans = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    if not isinstance(scans, list) or not all(isinstance(a, dict) and a.get("trs") == IDENTITY for a in scans):
        return False
    return stems <= {a.get("id_scan") for a in scans}


def export_scan2cad(wh: Warehouse, out: Path, clips: Sequence[str] | None = None) -> dict[str, int]:
    """Write the Scan2CAD files of ``clips`` (default: every clip whose verification completed,
    :func:`export_clips`) to ``out`` (see the module: new, empty or an earlier export's folder,
    which then holds this export alone); returns counts (scans, alignments, and ``note``: the
    warning lines, '' when none). A clip with no accepted pose is no scan (Scan2CAD's evaluation
    divides by a scan's models): left out, its file of an earlier export removed, and named. Two
    exported clips of one scan name (one video, one first timestamp) are refused, naming them (a
    clip left out has no scan to clash)."""
    out = Path(os.path.abspath(out))
    earlier = earlier_csvs(out)
    selection = export_clips(wh, clips)
    names = export_names(wh, selection.chosen)[0]
    annotations, appearances, total, empty = [], {}, 0, []
    written: dict[str, str] = {}  # scan name -> its clip
    with temp_folder_beside(out) as tmp:
        for clip, name in zip(selection.chosen, names):
            ds = clip_dataset(wh, clip)
            ds.require_models()  # a model gone from cad_models has no box to write
            rows = alignments(ds)
            if not rows:
                empty.append(clip)
                continue
            if name in written:
                raise ExportError(f"clips {written[name]}, {clip} would both be exported as {name!r} (one video, one "
                                  "first timestamp); export one of them")
            written[name] = clip
            write_csv(tmp / f"{name}.csv", rows)
            annotations.append(annotation(ds, name))
            appearances[name] = dict(sorted(Counter(f"{a.catid}_{a.id_cad}" for a in rows).items()))
            total += len(rows)
        (tmp / JSON_FILES[0]).write_text(json.dumps(annotations, indent=1))
        (tmp / JSON_FILES[1]).write_text(json.dumps(appearances, indent=1))
        # the earlier export's scans not written this time go as the new files come (a kill meanwhile:
        # the next export removes both, not the old full_annotations.json naming CSVs already gone)
        publish(tmp, out, remove=[e.name for e in earlier if not (tmp / e.name).exists()])
    notes = [selection.note()] if selection.note() else []
    if empty:
        notes.append(f"left out {len(empty)} clip(s) with no accepted pose (no Scan2CAD scan): {some_named(empty)}")
    return {"scans": len(annotations), "alignments": total, "note": "\n".join(notes)}
