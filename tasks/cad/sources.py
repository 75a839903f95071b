"""CAD sources: the Sweet Home 3D furniture library (our default), ShapeNetCore v2, any folder of meshes.

Each source lists :class:`CadItem` records (metadata only) and loads an item's mesh on demand with
:func:`load_item`, as the source stores it (its own units and orientation; the ingest stage
canonicalises). Sources:

- Sweet Home 3D: a folder of ``*.sh3f`` catalogues (zip files: ``PluginFurnitureCatalog.properties``
  plus OBJ/MTL/texture files), as Debian's ``sweethome3d-furniture`` installs them under
  ``usr/share/sweethome3d/furniture``. One library per catalogue; people (the Reallusion set and
  the "Characters" category) are left out. Meshes are in centimetres, +Y up, front +Z;
  ``modelRotation`` (a 3x3 matrix) applies first; the catalogue's width/height/depth is the size.
- ShapeNetCore v2: ``<root>/<synset>/<model_id>/models/model_normalized.obj`` (+Y up; ShapeNet's
  normalised units are kept, as CAD-Estate's own ShapeNet poses assume); the library is
  ``shapenet`` unless named. A category folder may be named instead of a synset id (``chairs/``):
  its name gives the class (:func:`class_of_category`).
- A folder: meshes (OBJ/GLB/GLTF/PLY/OFF/STL) with ``models.csv``: columns ``id,class`` and
  optionally ``file`` (default: the one ``<id>.*`` mesh), ``licence``, ``creator``, ``unit_m``
  (metres per mesh unit, default 1).
"""

from __future__ import annotations

import csv
import glob
import io
import os
import posixpath
import re
import zipfile
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import trimesh

from cadestate.lineage import digest
from tasks.cad.classes import BY_NAME, CLASSES, class_of_label, classify

MESH_SUFFIXES = (".obj", ".glb", ".gltf", ".ply", ".off", ".stl")
SH3D_EXCLUDED_SETS = ("reallusion",)
SH3D_EXCLUDED_CATEGORIES = ("characters",)
SH3D_LICENCES = {  # catalogue header licence -> SPDX identifier
    "public domain": "CC0-1.0",
    "creative commons attribution 3.0 united states": "CC-BY-3.0-US",
    "creative commons attribution 3.0": "CC-BY-3.0",
}
SHAPENET_MESH = Path("models") / "model_normalized.obj"
SH3D_SUBDIR = "sweethome3d-furniture_1.8-1/usr/share/sweethome3d/furniture"
"""Where ``make cad-library`` unpacks Debian's sweethome3d-furniture 1.8-1, under the cache folder."""


class CadSourceError(ValueError):
    """A CAD source that cannot be read at all (a single bad item is an issue, not an error)."""


@dataclass(frozen=True)
class CadItem:
    """One model of a source, before canonicalisation.

    ``size_m`` is the catalogue size (x, y, z) in metres when the source states one (Sweet Home 3D),
    ``unit_m`` the metres per mesh unit otherwise; ``rotation`` a 3x3 row-major matrix applied
    to the mesh first (Sweet Home 3D ``modelRotation``), or None.
    """

    library: str
    item: str
    name: str
    category: str
    cls: str
    source: str
    path: str  # file, or "archive.sh3f!member"
    licence: str
    creator: str
    size_m: tuple[float, float, float] | None = None
    unit_m: float = 1.0
    rotation: tuple[float, ...] | None = None
    key: str = ""
    """The id within the library when ``slug(item)`` is not unique there (:func:`unique_keys`)."""

    @property
    def cad_id(self) -> str:
        return f"{self.library}.{self.key or slug(self.item)}"


def slug(text: str) -> str:
    """A file-name-safe id: lower case letters, digits, '-'."""
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-") or "item"


def read_java_properties(data: bytes) -> dict[str, str]:
    """Parse a Java .properties file (ISO-8859-1, ``\\uXXXX`` escapes, continuation lines)."""
    text = data.decode("latin-1")
    props: dict[str, str] = {}
    logical = ""
    for raw in text.splitlines():
        line = raw.lstrip() if not logical else raw.lstrip()
        if not logical and (not line or line[0] in "#!"):
            continue
        if re.search(r"(?<!\\)(\\\\)*\\$", line):  # odd number of trailing backslashes: continues
            logical += line[:-1]
            continue
        logical += line
        match = re.match(r"((?:\\.|[^=:\s\\])+)\s*[=:\s]\s*(.*)", logical)
        if match:
            key, value = (re.sub(r"\\u([0-9a-fA-F]{4})", lambda m: chr(int(m.group(1), 16)), part) for part in match.groups())
            props[key.replace("\\", "")] = re.sub(r"\\(.)", r"\1", value)
        logical = ""
    return props


def _sh3d_licence(header: str) -> str:
    lowered = header.lower()
    return next((spdx for text, spdx in SH3D_LICENCES.items() if lowered.startswith(text)), header.strip() or "unknown")


def _numbers(archive: Path, key: str, text: str, counts: tuple[int, ...]) -> tuple[float, ...]:
    """The finite numbers of catalogue entry ``key``'s value ``text``, as many as one of ``counts``;
    else :class:`CadSourceError` naming the catalogue and the key (a comma decimal: a traceback was all)."""
    try:
        values = tuple(float(v) for v in text.split())
    except ValueError:
        values = (float("nan"),)
    if len(values) not in counts or not np.isfinite(values).all():
        many = " or ".join(str(c) for c in counts if c)
        raise CadSourceError(f"{archive}: PluginFurnitureCatalog.properties: {key} = {text!r} is not {many} number(s)")
    return values


def sweethome3d_items(folder: Path) -> Iterator[CadItem]:
    """Items of every ``*.sh3f`` catalogue in ``folder`` (people excluded)."""
    catalogues = sorted(Path(folder).glob("*.sh3f"))
    if not catalogues:
        raise CadSourceError(f"{folder}: no Sweet Home 3D catalogues (*.sh3f); run `make cad-library`")
    seen: set[tuple[str, str, str]] = set()  # (library, item, category): what unique_keys tells apart
    for archive in catalogues:
        if archive.stem.lower() in SH3D_EXCLUDED_SETS:
            continue
        library = "sh3d-" + slug(archive.stem)
        try:
            with zipfile.ZipFile(archive) as z:
                props = read_java_properties(z.read("PluginFurnitureCatalog.properties"))
        except (zipfile.BadZipFile, KeyError, OSError) as e:
            why = "no PluginFurnitureCatalog.properties in it" if isinstance(e, KeyError) else f"not a readable zip ({e})"
            raise CadSourceError(f"{archive}: {why}") from None
        licence = _sh3d_licence(props.get("license", ""))
        indices = sorted(int(k.split("#")[1]) for k in props if k.startswith("name#") and k.split("#")[1].isdigit())
        for i in indices:
            get = lambda key, default="": props.get(f"{key}#{i}", default)  # noqa: E731
            if get("category").lower() in SH3D_EXCLUDED_CATEGORIES:
                continue
            rotation = _numbers(archive, f"modelRotation#{i}", get("modelRotation"), (0, 9)) or None
            name = get("name")
            item = get("id").split("#", 1)[-1] or f"{name}-{i}"  # the id is optional in a catalogue
            # a second entry of that id (two creators' "#chair", a copied entry) in that category: its own
            # id, else its index, so the two are two models (they were given one cad_id, and failed on it)
            item = next(k for k in (item, get("id"), f"{get('id') or name}-{i}") if (library, k, get("category")) not in seen)
            seen.add((library, item, get("category")))
            yield CadItem(
                library=library, item=item, name=name, category=get("category"),
                cls=classify(name, get("category"), f"{library}.{slug(item)}"), source="sweethome3d",
                path=f"{archive}!{get('model').lstrip('/')}", licence=licence, creator=get("creator") or props.get("provider", ""),
                size_m=tuple(_numbers(archive, f"{k}#{i}", get(k, "0"), (1,))[0] / 100.0
                             for k in ("width", "height", "depth")),
                unit_m=0.01, rotation=rotation,
            )


def shapenet_items(root: Path, library: str = "shapenet") -> Iterator[CadItem]:
    """Items of a ShapeNetCore v2 folder (``<synset>/<model_id>/models/model_normalized.obj``; a
    category folder named otherwise, holding a model, is one too: its name gives the class)."""
    if not any(Path(root).glob(f"*/*/{SHAPENET_MESH.as_posix()}")):
        raise CadSourceError(f"{root}: no <synset>/<model_id>/{SHAPENET_MESH} files")
    categories = [d for d in Path(root).iterdir() if d.is_dir() and (
        re.fullmatch(r"\d{8}", d.name) or any(d.glob(f"*/{SHAPENET_MESH.as_posix()}")))]  # named ones: 0 models, exit 0
    # every model folder of a category folder, its mesh there or not (one without is a cad_issues row, not nothing)
    folders = sorted(d for category in categories for d in category.iterdir() if d.is_dir())
    for mesh in (d / SHAPENET_MESH for d in folders):
        synset, model_id = mesh.parts[-4], mesh.parts[-3]
        yield CadItem(library=library, item=model_id, name=model_id, category=synset, cls=class_of_category(synset),
                      source="shapenet", path=str(mesh), licence="ShapeNet terms of use", creator="ShapeNet")


def class_of_category(category: str) -> str:
    """The class a collection's own category names (a models.csv class, a ShapeNet-layout folder):
    the class of that name or ShapeNet synset id, else the class whose COCO labels hold it ("car"),
    else :func:`classify` of it; each tried as written, then with its words singular ("washers",
    "Dining Tables": the names and the rules' whole words missed a plural); else 'other'.
    Here, not in :mod:`tasks.cad.classes`: most stages import that, and its code digest with it."""
    text = category.strip().lower()
    named = {c.id: c.name for c in CLASSES}.get(text, text)
    singular = re.sub(r"(?<=[a-z])(?:(?<=ch|sh|ss)es|(?<![su])s)\b", "", text)
    for find in (lambda t: t if t in BY_NAME else None, class_of_label, classify):
        for t in (named, singular):
            if (c := find(t)) not in (None, "other"):
                return c
    return "other"


def folder_items(folder: Path, library: str | None = None) -> Iterator[CadItem]:
    """Items of a folder of meshes described by ``models.csv`` (see module docstring)."""
    folder = Path(folder)
    table = folder / "models.csv"
    if not table.is_file():
        raise CadSourceError(f"{folder}: no models.csv (columns: id,class[,file,licence,creator,unit_m])")
    try:
        with open(table, newline="", encoding="utf-8-sig") as f:  # -sig: a spreadsheet's byte-order mark
            reader = csv.DictReader(f, skipinitialspace=True)  # "id, class": a hand-written table's spaces
            reader.fieldnames = [name.strip() for name in reader.fieldnames or ()]  # "id ,class" too
            rows = [(reader.line_num, row) for row in reader]  # the line a row ends on (quoted line breaks)
    except UnicodeDecodeError as e:
        raise CadSourceError(f"{table}: not UTF-8 text (byte {e.start}); save it as UTF-8") from None
    except csv.Error as e:  # a quote left open swallows the rest of the table into one field
        raise CadSourceError(f"{table}:{reader.line_num}: {e} (a quote opened and not closed?)") from None
    if not {"id", "class"} <= set(reader.fieldnames or ()):
        raise CadSourceError(f"{table}: needs a header with columns id and class")
    library = library or slug(folder.name)
    lines: dict[str, int] = {}  # id -> its line
    for line, row in rows:
        if not any((v or "").strip() for k, v in row.items() if k is not None) and None not in row:
            continue  # an empty row (a spreadsheet's trailing ",,,")
        if None in row or any(row.get(k) is None for k in ("id", "class")):
            fields = sum(len(v) if k is None else 1 for k, v in row.items() if v is not None)  # extras: a list under None
            raise CadSourceError(f"{table}:{line}: {fields} field(s), the header has {len(reader.fieldnames)}")
        name = row["id"].strip()
        if not name:
            raise CadSourceError(f"{table}:{line}: empty id")
        if name in lines:  # two models of one id: it failed after every model was ingested, on a duplicate key
            raise CadSourceError(f"{table}:{line}: id {name!r} is on line {lines[name]} too; an id names one model")
        lines[name] = line
        if file := (row.get("file") or "").strip():
            path = folder / file
        else:
            candidates = sorted(p for p in folder.glob(f"{glob.escape(name)}.*") if p.suffix.lower() in MESH_SUFFIXES)
            if len(candidates) > 1:
                raise CadSourceError(f"{table}:{line}: id {name!r} has {len(candidates)} meshes "
                                     f"({', '.join(p.name for p in candidates)}); name one in a file column")
            path = candidates[0] if candidates else folder / f"{name}.<mesh>"
        try:
            unit = float(row.get("unit_m") or 1.0)
        except ValueError:
            raise CadSourceError(f"{table}:{line}: unit_m is not a number: {row['unit_m']!r}") from None
        if not (np.isfinite(unit) and unit > 0):
            raise CadSourceError(f"{table}:{line}: unit_m must be a positive number of metres per mesh unit, "
                                 f"not {row['unit_m']!r}")
        yield CadItem(library=library, item=name, name=name, category=row["class"].strip(),
                      cls=class_of_category(row["class"]), source="folder", path=str(path),
                      licence=row.get("licence") or "unknown", creator=row.get("creator") or "unknown", unit_m=unit)
    if not lines:  # it ingested nothing, and said so with an empty table and exit 0
        raise CadSourceError(f"{table}: lists no model (a row per model under the header)")


class _FolderResolver(trimesh.resolvers.ZipResolver):
    """Resolves an OBJ's MTL and textures among the files of its folder in the catalogue zip,
    remembering the names it could not find (missing textures are reported, not fatal)."""

    def __init__(self, archive: zipfile.ZipFile, folder: str):
        prefix = folder.rstrip("/") + "/" if folder else ""
        super().__init__({n[len(prefix):]: archive.read(n) for n in archive.namelist()
                          if n.startswith(prefix) and not n.endswith("/")})
        self.missing: list[str] = []

    def get(self, name: str) -> bytes:
        try:
            return _readable(name, super().get(name))
        except KeyError:
            self.missing.append(name)
            raise
        except OSError:
            self.missing.append(f"{name} (unreadable)")
            raise


def archive_of(path: str) -> str:
    """The file holding the model at ``path`` (an item's or a ``cad_models.source_path``): its
    catalogue for a member of a Sweet Home 3D catalogue (``<catalogue>.sh3f!<member>``), else the
    path itself (a loose file's path, or a folder above a catalogue, may hold a '!')."""
    archive, sep, _ = path.rpartition(".sh3f!")  # the last
    return f"{archive}.sh3f" if sep else path


def archive_member(item: CadItem) -> tuple[str, str] | None:
    """(archive, member) of an item inside a catalogue zip (Sweet Home 3D), None for a loose file."""
    if item.source != "sweethome3d":
        return None
    archive = archive_of(item.path)
    return archive, item.path[len(archive) + 1:]


def load_item(item: CadItem) -> tuple[trimesh.Scene, list[str]]:
    """The item's mesh as its source stores it, and the names of files it refers to that are missing
    (or, marked so, unreadable)."""
    if (inside := archive_member(item)) is not None:
        archive_path, member = inside
        with zipfile.ZipFile(archive_path) as archive:
            resolver = _FolderResolver(archive, posixpath.dirname(member))
            loaded = trimesh.load(io.BytesIO(archive.read(member)), file_type=Path(member).suffix[1:].lower(),
                                  resolver=resolver, force="scene")
        return loaded, sorted(set(resolver.missing))
    path = Path(item.path)
    if not path.is_file():
        raise FileNotFoundError(f"{item.path}: mesh file not found")
    resolver = _LocalResolver(path.parent)
    loaded = trimesh.load(str(path), resolver=resolver, force="scene")
    return loaded, sorted(set(resolver.missing))


class _LocalResolver(trimesh.resolvers.FilePathResolver):
    """A file-system resolver that remembers the names it could not find."""

    def __init__(self, folder: Path):
        super().__init__(str(folder))
        self.missing: list[str] = []

    def get(self, name: str) -> bytes:
        try:
            data = super().get(name)
        except (OSError, KeyError):
            self.missing.append(name)
            raise
        try:
            return _readable(name, data)
        except OSError:
            self.missing.append(f"{name} (unreadable)")
            raise


IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".gif", ".tga", ".tif", ".tiff", ".webp"})


def _readable(name: str, data: bytes) -> bytes:
    """``data``, or OSError for an image file PIL cannot identify: trimesh drops such a texture
    without a word (it opens images as this does, reading the header only)."""
    if Path(name).suffix.lower() in IMAGE_SUFFIXES:
        from PIL import Image

        try:
            Image.open(io.BytesIO(data))
        except Exception as e:  # PIL raises UnidentifiedImageError, SyntaxError, ValueError...
            raise OSError(f"{name}: {e}") from None
    return data


def source_items(kind: str, path: Path, library: str | None = None,
                 held: Iterable[tuple[str, str, str]] = ()) -> list[CadItem]:
    """Items of a source of kind ``sweethome3d``, ``shapenet`` or ``folder``, each of a unique cad_id;
    ``held`` as :func:`unique_keys` takes it."""
    if kind == "sweethome3d":
        items = list(sweethome3d_items(path))
    elif kind == "shapenet":
        items = list(shapenet_items(path, library or "shapenet"))
    elif kind == "folder":
        items = list(folder_items(path, library))
    else:
        raise CadSourceError(f"unknown CAD source kind {kind!r} (sweethome3d, shapenet, folder)")
    for item in items:  # its name goes into tables, which hold UTF-8 text only
        if _shown(item.path) != item.path or _shown(item.item) != item.item:
            raise CadSourceError(f"{_shown(item.path)}: a model's file or folder name that is not UTF-8: rename it")
    return unique_keys(items, held)


def unique_keys(items: list[CadItem], held: Iterable[tuple[str, str, str]] = ()) -> list[CadItem]:
    """``items`` with a unique cad_id each: ids that ``slug`` makes alike ("Chair A" and "chair-a",
    two names of other scripts, one ShapeNet model id under two synsets) get the slug and a digest
    of their name and source category (wherever the source is mounted) as ``key``; the others keep
    their slug. ``held`` is (cad_id, name, source category) of each model the warehouse holds
    already: a model keeps the id it was given (labels name it), so when a new item comes to slug
    like one held, the held one keeps its plain slug if it alone of the alike matches its row's name
    and category, and the newcomer takes the digest; a model held under its digest keeps it."""
    held_as = {cad_id: (name, category) for cad_id, name, category in held}
    alike = Counter(item.cad_id for item in items)
    holders = Counter(item.cad_id for item in items if alike[item.cad_id] > 1 and
                      held_as.get(item.cad_id) == (item.name, item.category))
    keyed = [replace(item, key=f"{slug(item.item)}-{digest(item.item, item.category)[:8]}") for item in items]
    return [with_digest if with_digest.cad_id in held_as or (alike[item.cad_id] > 1 and not (
            holders[item.cad_id] == 1 and held_as.get(item.cad_id) == (item.name, item.category))) else item
            for item, with_digest in zip(items, keyed)]


def guess_kind(path: Path) -> str:
    """The kind of source at ``path``: .sh3f catalogues, a models.csv folder, or ShapeNet's layout."""
    path = Path(path)
    if any(path.glob("*.sh3f")):
        return "sweethome3d"
    if (path / "models.csv").is_file():
        return "folder"
    if any(path.glob(f"*/*/{SHAPENET_MESH.as_posix()}")):
        return "shapenet"
    # what would make it one (the error named none)
    if any(path.glob(f"*/{SHAPENET_MESH.as_posix()}")):
        raise CadSourceError(f"{path}: a category folder of the ShapeNet layout: give the folder above it ({path.parent})")
    if meshes := [p for p in path.iterdir() if p.suffix.lower() in MESH_SUFFIXES]:
        raise CadSourceError(f"{path}: {len(meshes)} mesh file(s) but no models.csv: write one, a row per model "
                             "(columns id,class[,file,licence,creator,unit_m])")
    raise CadSourceError(f"{path}: not a CAD source (no *.sh3f catalogues, no models.csv, no ShapeNet layout)")


def rotation_matrix(item: CadItem) -> np.ndarray:
    """The item's 3x3 pre-rotation (identity when none)."""
    return np.eye(3) if item.rotation is None else np.asarray(item.rotation, dtype=np.float64).reshape(3, 3)


def item_folder(item: CadItem) -> Path | None:
    """The folder of the files a loose mesh may refer to (materials, textures): for a models.csv
    source the folder of the models.csv above it (``meshes/chair.obj`` and ``textures/wood.png``
    beside each other: its own folder missed a repainted texture), else its own folder, or for
    ShapeNet's ``<model>/models/model_normalized.obj`` the model's folder (its ``images/``); None
    for a mesh inside an archive (the archive is one file)."""
    if archive_member(item) is not None:
        return None
    folder = Path(item.path).parent
    if item.source == "folder":
        return next((p for p in Path(item.path).parents if (p / "models.csv").is_file()), folder)
    return folder.parent if folder.name == SHAPENET_MESH.parent.name and item.source == "shapenet" else folder


def items_digest(items: list[CadItem]) -> str:
    """Lineage digest of a library's items: their metadata, and the size and mtime of their source
    files and of every file under their folders (:func:`item_folder`: a repainted material or a new
    texture is a change); content hashes of whole CAD collections would cost more than ingesting them.
    A warehouse inside a folder (``cadestate cad ingest .`` beside the default ``data/warehouse``) is
    left out: its own writes changed the digest, and the library was ingested anew every time."""
    files = {inside[0] if (inside := archive_member(item)) else item.path for item in items}
    folders = sorted({f for f in map(item_folder, items) if f is not None})
    walked: set[Path] = set()
    for folder in folders:  # sorted: a folder comes after every folder above it
        if walked.intersection(folder.parents):
            continue
        walked.add(folder)
        for top, dirs, names in os.walk(folder):
            dirs[:] = sorted(d for d in dirs if not _is_warehouse(Path(top) / d))
            files.update(os.path.join(top, n) for n in names if os.path.isfile(os.path.join(top, n)))
    parts = []
    for f in sorted(files):
        stat = Path(f).stat() if Path(f).exists() else None
        name = _shown(f)  # a stray texture named in Latin-1 failed the whole library, naming no file
        parts.append(f"{name}:{stat.st_size}:{stat.st_mtime_ns}" if stat else f"{name}:missing")
    return digest(*(repr(item) for item in items), *parts)


def _is_warehouse(folder: Path) -> bool:
    """Whether ``folder`` is a warehouse's root (its tables and catalog; warehouse.store.TABLES_DIR,
    warehouse.catalog.CATALOG_FILE)."""
    return (folder / "tables").is_dir() and (folder / "catalog.duckdb").exists()


def _shown(path: str) -> str:
    """``path`` as text that can be written: itself when it is UTF-8, else its bytes with the ones
    that are not UTF-8 as escapes (``textur\\xe9.png``)."""
    return path.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


def default_source() -> Path:
    """The embedded default: Sweet Home 3D's furniture as ``make cad-library`` unpacks it
    (``$CADESTATE_SH3D_DIR``, else under ``~/.cache/cadestate``)."""
    return Path(os.environ.get("CADESTATE_SH3D_DIR", Path.home() / ".cache" / "cadestate" / SH3D_SUBDIR)).expanduser()
