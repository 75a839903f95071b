"""``cadestate cad export-official``: the CAD library in the official CAD-Estate layout.

Layout (what ``cad_estate.objects.load_shapenet_metadata`` / ``load_objects`` read)::

    shapenet_classes.json      [{"id": <class id>, "human_readable": <class name>}, ...] (every class
                               of the vocabulary, in vocabulary order, so label indices are stable)
    symmetry_dict.json         {"<class id>_<cad_id>": K, ...}
    <class id>/<cad_id>.npz    vertices: float32[T, 3, 3] triangle soup in the canonical CAD frame;
                               label: the class id; mesh_id: the cad_id
    ATTRIBUTION.csv            cad_id, library, name, licence, creator, source: every model's terms
                               (most of Sweet Home 3D's are CC-BY: whoever shares the meshes credits them)

Class ids are ShapeNet synsets where ShapeNet has the class (``cadestate-<name>`` otherwise), so
objects annotated on our library load with the official code. Written into a temporary folder
beside ``out`` and renamed into place at the end: an interrupted export leaves nothing behind (a
killed one's folder is removed by the next export into ``out``).
"""

from __future__ import annotations

import contextlib
import csv
import fcntl
import json
import os
import re
import shutil
import uuid
import zipfile
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from cadestate.progress import progress
from tasks.cad.classes import CLASSES
from tasks.cad.sources import archive_of, read_java_properties
from tasks.stage import waits_for_people
from warehouse import Warehouse
from warehouse.store import warn


class ExportError(ValueError):
    """The export cannot be written (the destination holds files, or the library is empty)."""


def check_new_folder(out: Path) -> None:
    """Refuse (:class:`ExportError`) an export destination ``out`` that is a file or a folder holding
    files (a killed export's temporary folder in it removed first: :func:`remove_leftovers`)."""
    if out.exists() and not out.is_dir():
        raise ExportError(f"{out}: exists and is not a folder; choose a new folder")
    remove_leftovers(out)
    if out.exists() and any(out.iterdir()):
        raise ExportError(f"{out}: exists and is not empty; choose a new folder")


def make_folder(folder: Path, named: Path | None = None, exist_ok: bool = False) -> Path:
    """Make ``folder`` and its parents; :class:`ExportError` naming ``named`` (default: ``folder``)
    when it cannot be made there (no permission, a file in the path)."""
    try:
        folder.mkdir(parents=True, exist_ok=exist_ok)
    except OSError as e:
        raise ExportError(f"{named or folder}: cannot write there: {e.strerror or e}") from None
    return folder


def temp_home(out: Path) -> Path:
    """The folder that holds the temporary folders of exports into ``out``: its parent, or ``out``
    itself where ``out`` is a folder on a file system of its own (a mounted drive, a container's
    volume), from which nothing can be renamed into it."""
    try:
        if out.is_dir() and os.stat(out).st_dev != os.stat(out.parent).st_dev:
            return out
    except OSError:
        pass
    return out.parent


@contextlib.contextmanager
def temp_folder_beside(out: Path) -> Iterator[Path]:
    """A new hidden folder ``.<name>.<uuid>.tmp`` beside ``out`` (an absolute path: ``.`` has no
    name to put beside; inside ``out`` where it is a mount point: :func:`temp_home`) to write an
    export into before moving it to ``out`` (:class:`ExportError`
    when none can be made there); removed on leaving, whatever ends the export. It is made inside
    the ``try``: a signal between making it and a caller's ``try`` (SIGTERM's exit) had left it
    behind. It is locked (``flock``) while in use, and the earlier ones that no process holds, left
    by an export that could not clean up (SIGKILL, power loss), are removed first (:func:`remove_leftovers`).
    An existing ``out`` that cannot be written is refused first: the export was written in full
    beside it, then a traceback when moved in."""
    if out.is_dir() and not os.access(out, os.W_OK | os.X_OK):
        raise ExportError(f"{out}: cannot write there: permission denied")
    remove_leftovers(out)
    made: list[Path] = []
    held: list[int] = []
    try:
        for _ in range(3):
            made.append(temp_home(out) / f".{out.name}.{uuid.uuid4().hex}.tmp")
            make_folder(made[-1], named=out)
            held.append(os.open(made[-1], os.O_RDONLY | os.O_DIRECTORY))
            fcntl.flock(held[-1], fcntl.LOCK_EX)
            if made[-1].exists() and os.path.samestat(os.fstat(held[-1]), os.stat(made[-1])):
                break  # else another export's remove_leftovers took it between making and locking: a new one
        else:
            raise ExportError(f"{out}: cannot keep a temporary folder beside it (removed as soon as made)")
        yield made[-1]
    finally:
        for folder in made:
            shutil.rmtree(folder, ignore_errors=True)
        for fd in held:
            os.close(fd)


def remove_leftovers(out: Path) -> None:
    """Remove the temporary folders of earlier exports into ``out`` (:func:`temp_folder_beside`)
    that no process holds (``flock``), each named on stderr, and what an export killed while it
    moved its entries into ``out`` left there (:func:`remove_unfinished_move`)."""
    remove_unfinished_move(out)
    prefix = f".{out.name}."
    try:
        found = [e for e in temp_home(out).iterdir() if e.name.startswith(prefix) and e.name.endswith(".tmp")
                 and re.fullmatch(r"[0-9a-f]{32}", e.name[len(prefix):-len(".tmp")])]
    except OSError:  # no parent folder yet: nothing left there
        return
    for folder in sorted(found):
        _remove_unheld(folder)


def _remove_unheld(folder: Path) -> None:
    """Remove ``folder`` (a real folder, not a link) if no process holds its lock, saying so on stderr."""
    try:
        if folder.is_symlink():
            return
        fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    except OSError:
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:  # an export running now holds it
        os.close(fd)
        return
    try:
        shutil.rmtree(folder, ignore_errors=True)
    finally:
        os.close(fd)
    warn(f"removed {folder}: the temporary folder of an earlier export that did not finish")


MOVING = ".cadestate-moving"
"""The file in an export's destination that names the entries being moved into it (:func:`publish`)."""


def publish(tmp: Path, out: Path, remove: Sequence[str] = ()) -> None:
    """Move the finished export ``tmp`` to ``out``: renamed whole when ``out`` is not there, else
    (a folder, the current one say, which a rename cannot replace) entry by entry into it, in name
    order, each replacing an entry of its name there (a folder is renamed aside, then removed),
    then the files of ``out`` named in ``remove`` (an earlier export's that this one does not
    write) removed. Meanwhile ``out/``:data:`MOVING` names those entries (JSON) and is locked
    (``flock``): an export killed then (SIGKILL, power loss) left some of them moved and the others
    not, which the next export into ``out`` removes (:func:`remove_unfinished_move`); it had
    refused that folder (not empty, or holding a report's pages and no report) until the user
    removed them."""
    if not out.exists():
        tmp.rename(out)
        return
    entries = sorted(tmp.iterdir())
    journal = out / MOVING
    fd = _locked_journal(journal)
    try:
        os.write(fd, json.dumps([e.name for e in entries] + list(remove)).encode())
        for entry in entries:
            there = out / entry.name
            if there.is_dir() and not there.is_symlink():
                aside = there.with_name(f".{there.name}.{uuid.uuid4().hex}.old")
                there.rename(aside)
                entry.rename(there)
                shutil.rmtree(aside, ignore_errors=True)
            else:
                os.replace(entry, there)
        for name in remove:
            (out / name).unlink(missing_ok=True)
        journal.unlink()
    finally:
        os.close(fd)


def _locked_journal(journal: Path) -> int:
    """The :data:`MOVING` file ``journal``, open, locked and emptied for this export: emptied only
    once locked (another export's list while it moves is what a kill of it would be cleaned up by),
    and opened again when the one locked was removed meanwhile (by the export that held it, or the
    check of a killed one): a list written there would be in no file."""
    while True:
        fd = os.open(journal, os.O_WRONLY | os.O_CREAT | os.O_NOFOLLOW, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            with contextlib.suppress(FileNotFoundError):
                if os.path.samestat(os.fstat(fd), os.stat(journal)):
                    os.ftruncate(fd, 0)
                    return fd
        except BaseException:
            os.close(fd)
            raise
        os.close(fd)


def remove_unfinished_move(out: Path) -> None:
    """Remove the entries that an export killed while moving them into ``out`` (:func:`publish`)
    had moved there or set aside, those it had yet to move replacing them (its :data:`MOVING` file
    names them), and that file, unless a process holds it (an export moving in now); named on
    stderr. ``out`` then holds no entry of those names, as though that export had not started
    moving: the next export's checks pass as for a folder without them."""
    journal = out / MOVING
    try:
        fd = os.open(journal, os.O_RDONLY | os.O_NOFOLLOW)
    except OSError:  # none (or not a file of ours)
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:  # an export moving its entries in now
            return
        try:
            if not os.path.samestat(os.fstat(fd), os.stat(journal)):  # finished and removed; the file there now is
                return                                                  # another export's, which holds it
            with open(fd, encoding="utf-8", closefd=False) as f:
                names = json.loads(f.read())
        except FileNotFoundError:  # finished and removed by its export
            return
        except (OSError, ValueError):  # killed while writing it: nothing moved yet
            names = []
        names = {n for n in names if isinstance(n, str) and n not in ("", ".", "..", MOVING) and "/" not in n} \
            if isinstance(names, list) else set()
        aside = re.compile(r"\.(.+)\.[0-9a-f]{32}\.old")
        found = sorted(e for e in out.iterdir() if e.name in names or ((m := aside.fullmatch(e.name)) and m.group(1) in names))
        for entry in found:
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)
        journal.unlink(missing_ok=True)
    finally:
        os.close(fd)
    if found:
        warn(f"removed {', '.join(e.name for e in found)} from {out}: an earlier export into it was stopped while "
             "moving them in")


@dataclass(frozen=True)
class ExportClips:
    """The clips a dataset export writes (``chosen``, in order, each once) and its clips whose
    verification has not completed as they stand (``unfinished``: it never ran, waits for verdicts,
    or a task waits for people since, e.g. clicks on models chosen anew; :func:`verification_completed`):
    left out by default, written as they are when ``named`` (``--clips``)."""

    chosen: list[str]
    unfinished: list[str]
    named: bool = False

    def note(self, hint: str = " (name them with --clips to export them as they are)") -> str:
        """The warning line about ``unfinished`` ('' when none); ``hint`` ends the line of clips left out."""
        if not self.unfinished:
            return ""
        shown = some_named(self.unfinished)
        if self.named:
            return (f"{len(self.unfinished)} clip(s) written as they are, not verified as they stand (the poses accepted "
                    f"so far; the others read as not posed): {shown}")
        return (f"left out {len(self.unfinished)} clip(s) not verified as they stand (verification not completed, or a "
                f"task waits for people since): {shown}{hint}")


def some_named(names: Sequence[str], limit: int = 10) -> str:
    """The first ``limit`` of ``names``, comma-separated, and how many more."""
    return ", ".join(names[:limit]) + (f" and {len(names) - limit} more" if len(names) > limit else "")


def verification_completed(wh: Warehouse, clips: Sequence[str]) -> set[str]:
    """The ``clips`` whose newest verification run completed (every solved pose has its verdict)
    and no stage of which has run since with a run that waits for people with nothing answered
    (:func:`tasks.stage.waits_for_people`): the stages after such a run wait and are not run, so
    the verdicts on record judge the poses of answers no longer in force (every track's model
    chosen anew leaves pose and verification waiting for clicks on the new models)."""
    runs = wh.read("runs", list(clips), columns=["clip", "stage", "run_id", "status", "rows_written"])
    newest: dict[tuple[str, str], tuple[str, str, int]] = {}
    for clip, stage, run_id, status, rows in zip(*(runs.column(c).to_pylist()
                                                   for c in ("clip", "stage", "run_id", "status", "rows_written"))):
        if (clip, stage) not in newest or run_id > newest[clip, stage][0]:
            newest[clip, stage] = (run_id, status, rows or 0)
    verified = {clip: run_id for (clip, stage), (run_id, status, _) in newest.items()
                if stage == "verification" and status == "completed"}
    waiting = {clip for (clip, _), (run_id, status, rows) in newest.items()
               if clip in verified and run_id > verified[clip] and waits_for_people(status, rows)}
    return set(verified) - waiting


def export_clips(wh: Warehouse, clips: Sequence[str] | None) -> ExportClips:
    """The clips a dataset export writes: ``clips`` (repeats dropped), default every clip with
    frames whose verification completed (:class:`ExportError` when one has no frames, or there is none)."""
    known = wh.partitions("frames")
    chosen = list(dict.fromkeys(clips)) if clips else known
    done = verification_completed(wh, [c for c in chosen if c in known])
    unfinished = [c for c in chosen if c in known and c not in done]
    if not clips:
        chosen = [c for c in known if c in done]
    missing = [c for c in chosen if c not in known]
    if missing:
        raise ExportError(f"clip {missing[0]!r} has no frames in {wh.root} (known: {', '.join(known) or 'none'})")
    if not chosen and unfinished:
        raise ExportError(f"no clip of {wh.root} is verified as it stands yet ({len(unfinished)} with frames: "
                          f"{', '.join(unfinished[:5])}{', ...' if len(unfinished) > 5 else ''}); run them on "
                          "(`cadestate run`), or name them with --clips to export them as they are")
    if not chosen:
        raise ExportError(f"no clip with frames in {wh.root}; run `cadestate ingest` and `cadestate run` first")
    return ExportClips(chosen, unfinished, bool(clips))


def load_mesh(mesh_file: Path) -> trimesh.Scene:
    """A canonical mesh of the warehouse; :class:`ExportError` naming the file when it cannot be
    read (the warehouse's copy removed or damaged), not one of trimesh's many errors naming none."""
    try:
        return trimesh.load(mesh_file, force="scene")
    except Exception as e:  # trimesh raises many kinds for a damaged file (ValueError, KeyError, struct.error, ...)
        raise ExportError(f"{mesh_file}: cannot read this CAD model's mesh (missing or damaged: "
                          f"{' '.join(str(e).split())[:200]})") from None


def triangle_soup(mesh_file: Path) -> np.ndarray:
    """float32[T, 3, 3] triangles of a canonical mesh (all parts, transforms applied;
    :func:`load_mesh`)."""
    parts = [g for g in load_mesh(mesh_file).dump(concatenate=False) if isinstance(g, trimesh.Trimesh)]
    if not parts:
        raise ExportError(f"{mesh_file}: cannot read this CAD model's mesh (missing or damaged: no triangles)")
    return np.concatenate([p.vertices[p.faces] for p in parts]).astype(np.float32)


def catalogue_notices(models: list[dict]) -> dict[str, str]:
    """{Sweet Home 3D catalogue: its licence line as written} of the catalogues ``models`` (rows of
    ``cad_models``) come from: the line holds the copyright notice that CC BY asks to keep
    ("Copyright © 2003-2008 Andrew Kator & Jennifer Legaz"), which the licence's SPDX id drops. A
    catalogue that cannot be read any more (moved) gives none, said once."""
    notices = {}
    for archive in sorted({archive_of(m["source_path"]) for m in models if m["source"] == "sweethome3d"}):
        try:
            with zipfile.ZipFile(archive) as z:
                notices[archive] = read_java_properties(z.read("PluginFurnitureCatalog.properties")).get("license", "").strip()
        except (OSError, KeyError, zipfile.BadZipFile) as e:
            warn(f"{archive}: cannot read its licence line for ATTRIBUTION.csv's notice column ({e}): its models' "
                 "notices are empty")
    return notices


def export_official(wh: Warehouse, out: Path, libraries: Sequence[str] | None = None, show_progress: bool = True) -> int:
    """Write the official layout of ``libraries`` (default: all) to ``out``; returns the model count."""
    out = Path(os.path.abspath(out))
    check_new_folder(out)
    held = wh.partitions("cad_models")
    unknown = [lib for lib in libraries or () if lib not in held]
    if unknown:
        raise ExportError(f"no CAD library {unknown[0]!r} in {wh.root} (libraries: {', '.join(held) or 'none'})")
    models = wh.read("cad_models", partitions=libraries, columns=["cad_id", "class_id", "symmetry", "mesh_path", "library",
                                                                  "name", "licence", "creator", "source", "source_path"]).to_pylist()
    if not models:
        raise ExportError("no CAD model in the warehouse (run `cadestate cad ingest` first)")
    with temp_folder_beside(out) as tmp:
        classes = [{"id": c.id, "human_readable": c.name} for c in CLASSES]
        (tmp / "shapenet_classes.json").write_text(json.dumps(classes, indent=1))
        symmetry = {f"{m['class_id']}_{m['cad_id']}": m["symmetry"] for m in models}
        (tmp / "symmetry_dict.json").write_text(json.dumps(symmetry, indent=1, sort_keys=True))
        notices = catalogue_notices(models)
        with open(tmp / "ATTRIBUTION.csv", "w", newline="", encoding="utf-8") as f:
            columns = ["cad_id", "library", "name", "licence", "creator", "source", "notice"]
            writer = csv.DictWriter(f, columns, extrasaction="ignore")
            writer.writeheader()
            writer.writerows({**m, "notice": notices.get(archive_of(m["source_path"]), "")}
                             for m in sorted(models, key=lambda m: m["cad_id"]))
        for m in progress(models, total=len(models), description="export", enabled=show_progress):
            folder = tmp / m["class_id"]
            folder.mkdir(exist_ok=True)
            np.savez_compressed(folder / f"{m['cad_id']}.npz", vertices=triangle_soup(wh.root / m["mesh_path"]),
                                label=m["class_id"], mesh_id=m["cad_id"])
        publish(tmp, out)
    return len(models)
