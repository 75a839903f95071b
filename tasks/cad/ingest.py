"""Stage ``cad_ingest``: canonicalise one CAD library, detect symmetries, sample surfaces.

Reads: the items of one library (:mod:`tasks.cad.sources`). Writes: ``cad_models``,
``cad_samples`` and ``cad_issues`` for that library, and one canonical GLB per model under
``media/cad/<library>/<digest of the meshes>/`` (a rerun that writes the same meshes keeps
their paths; the output digest covers their bytes).

Canonical CAD frame: metres, +Y up, front +Z, origin at the centre of the axis-aligned bounding
box. A source's mesh gets, in order: its pre-rotation (Sweet Home 3D ``modelRotation``), then a
per-axis scale to the catalogue size (Sweet Home 3D) or a uniform unit scale, then the
translation that centres its bounding box. An item that cannot be read, is empty, or is
degenerate is skipped and listed in ``cad_issues``, as is a warning (a file it refers to missing,
a class outside the vocabulary, a folder model over :data:`MAX_EXTENT_M` or under
:data:`SMALL_EXTENT_M`); the stage's message counts both; the stage never stops halfway. A
library none of whose items could be ingested fails the stage (naming the first item's problem)
and keeps what it held.
"""

from __future__ import annotations

import multiprocessing
import signal
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import trimesh

from cadestate.config import CadIngestConfig
from cadestate.lineage import digest, folder_digest, table_digest
from cadestate.progress import progress
from tasks.cad.classes import BY_NAME
from tasks.cad.sources import CadItem, items_digest, load_item, rotation_matrix
from tasks.cad.symmetry import detect_symmetry, sample_surface
from tasks.stage import StageContext, StageDef, StageOutput
from warehouse import Warehouse

MEDIA_KIND = "cad"
MIN_EXTENT_M = 1e-3
"""A model whose largest extent is below this is degenerate."""
MAX_EXTENT_M = 25.0
"""A folder model whose largest extent is above this gets a warning: its mesh is likely in other units
(millimetres, centimetres) than its ``unit_m`` says; a room's objects are smaller."""
SMALL_EXTENT_M = 0.05
"""A folder model whose largest extent is below this gets a warning: a ``unit_m`` of 0.001 on a mesh in
metres (a 1.2 mm desk); a room's objects are larger."""


MAX_DEATHS_IN_A_ROW = 5
"""Worker processes that may die in a row, each ingesting one model alone, before the library fails
(:func:`_map_items`): more are workers that cannot run at all, not models that kill them."""


class CadItemError(ValueError):
    """An item that cannot be ingested (recorded in ``cad_issues``, then skipped)."""


@dataclass(frozen=True)
class CanonicalModel:
    """A model in the canonical CAD frame.

    Attributes:
        scene: trimesh.Scene of the model's parts, transforms baked in (canonical frame).
        mesh: trimesh.Trimesh, all parts concatenated (geometry only).
        extent: float64[3] bounding-box size in metres (x, y, z).
    """

    scene: trimesh.Scene
    mesh: trimesh.Trimesh
    extent: np.ndarray


def canonical_transform(bounds: np.ndarray, item: CadItem) -> np.ndarray:
    """float64[4,4] from the source frame (after pre-rotation) to the canonical frame.

    Args:
        bounds: float64[2,3] bounding box of the pre-rotated mesh, in source units.
        item: gives the catalogue size (per-axis scale) or the unit (uniform scale).
    """
    extent = bounds[1] - bounds[0]
    scale = np.full(3, item.unit_m)
    if item.size_m is not None:
        size = np.asarray(item.size_m)
        usable = (extent > 1e-9) & (size > 0)  # flat axes (a rug's height) keep the unit scale
        scale[usable] = size[usable] / extent[usable]
    centre = (bounds[0] + bounds[1]) / 2 * scale
    T = np.diag([*scale, 1.0])
    T[:3, 3] = -centre
    return T


def canonicalise(scene: trimesh.Scene, item: CadItem) -> CanonicalModel:
    """The item's scene in the canonical frame (see module docstring)."""
    parts = [g for g in scene.dump(concatenate=False) if isinstance(g, trimesh.Trimesh) and len(g.faces)]
    if not parts:
        raise CadItemError("no triangles in the mesh")
    if not all(np.isfinite(p.vertices).all() for p in parts):
        raise CadItemError("non-finite vertex coordinates")
    R = np.eye(4)
    R[:3, :3] = rotation_matrix(item)
    for p in parts:
        p.apply_transform(R)
    bounds = np.array([np.min([p.bounds[0] for p in parts], 0), np.max([p.bounds[1] for p in parts], 0)])
    T = canonical_transform(bounds, item)
    for p in parts:
        p.apply_transform(T)
    mesh = trimesh.util.concatenate([trimesh.Trimesh(p.vertices, p.faces, process=False) for p in parts])
    extent = mesh.bounds[1] - mesh.bounds[0]
    if extent.max() < MIN_EXTENT_M:
        units = f" (unit_m {item.unit_m:g}: is the mesh in other units?)" if item.source == "folder" and item.unit_m != 1 else ""
        raise CadItemError(f"degenerate: largest extent {extent.max():.2g} m{units}")
    if mesh.area <= 0:
        raise CadItemError("degenerate: zero surface area")
    return CanonicalModel(trimesh.Scene(parts), mesh, extent)


def _is_textured(scene: trimesh.Scene) -> bool:
    """Whether a part carries a texture image of more than 2 x 2 pixels (trimesh gives an OBJ whose
    material file is missing a 2 x 2 placeholder)."""
    for g in scene.geometry.values():
        material = getattr(g.visual, "material", None)
        for image in (getattr(material, "image", None), getattr(material, "baseColorTexture", None)):
            if image is not None and max(image.size) > 2:
                return True
    return False


MAX_FILE_NAME = 255
"""Longest file name (bytes) of the file systems the warehouse lives on."""
LONGEST_SUFFIX = "_00.png"
"""The longest suffix a model's files add to its cad_id (its views: ``<cad_id>_NN.png``)."""


@dataclass(frozen=True)
class ItemResult:
    """What ingesting one item produced: its ``cad_models`` row (None when skipped), its surface
    samples float32[N, 3] (canonical frame), and its ``cad_issues`` rows."""

    model: dict | None
    points: np.ndarray | None
    issues: list[dict]


def ingest_item(item: CadItem, cfg: CadIngestConfig, out_dir: Path) -> ItemResult:
    """Canonicalise one item, write ``out_dir/<cad_id>.glb``; never raises for a bad item."""
    issue = {"library": item.library, "item": item.item, "source_path": item.path}
    if len(f"{item.cad_id}{LONGEST_SUFFIX}".encode()) > MAX_FILE_NAME:  # its files' names: it failed the whole library
        return ItemResult(None, None, [{**issue, "severity": "skipped", "problem": (
            f"its id makes file names longer than {MAX_FILE_NAME} bytes ({item.cad_id[:40]}...): give it a shorter one")}])
    try:  # through its GLB: a texture the exporter cannot write (a float TIFF) failed the whole library
        scene, missing = load_item(item)
        model = canonicalise(scene, item)
        if not np.isfinite(np.asarray(model.mesh.vertices, np.float32)).all():  # stored as float32: inf, symmetric
            raise ValueError("coordinates beyond float32's range (about 3e38)")
        points = sample_surface(model.mesh, cfg.samples, seed=0)
        symmetry = detect_symmetry(points, cfg.symmetry_tolerance)
        glb = model.scene.export(file_type="glb")
        (out_dir / f"{item.cad_id}.glb").write_bytes(glb)
    except Exception as e:  # any unreadable item is reported and skipped
        return ItemResult(None, None, [{**issue, "severity": "skipped", "problem": f"{type(e).__name__}: {e}"}])
    problems = [f"missing or unreadable files (rendered without them): {', '.join(missing)}"] if missing else []
    if item.source == "folder" and item.cls == "other" and item.category.lower() != "other":
        problems.append(f"class {item.category!r} is none of the vocabulary's (tasks/cad/classes.py) nor a synonym of "
                        "one: ingested as 'other'")
    if item.source == "folder" and model.extent.max() > MAX_EXTENT_M:  # a desk in millimetres was a 1.2 km desk
        problems.append(f"largest extent {model.extent.max():.2g} m, more than {MAX_EXTENT_M:g} m: is the mesh in other "
                        "units? models.csv's unit_m gives metres per mesh unit (0.001 for millimetres)")
    if item.source == "folder" and model.extent.max() < SMALL_EXTENT_M:
        problems.append(f"largest extent {model.extent.max():.2g} m, less than {SMALL_EXTENT_M:g} m: is the mesh in other "
                        "units? models.csv's unit_m gives metres per mesh unit (1 for metres)")
    issues = [{**issue, "severity": "warning", "problem": "; ".join(problems)}] if problems else []  # one row an item
    row = {
        "cad_id": item.cad_id, "class": item.cls, "class_id": BY_NAME[item.cls].id, "name": item.name,
        "source_category": item.category, "source": item.source, "source_path": item.path, "licence": item.licence,
        "creator": item.creator, "extent": model.extent.tolist(), "symmetry": symmetry.order,
        "symmetry_errors": [symmetry.errors[k] for k in (2, 4, 36)], "num_vertices": len(model.mesh.vertices),
        "num_faces": len(model.mesh.faces), "textured": _is_textured(model.scene),
    }
    return ItemResult(row, points.astype(np.float32), issues)


def _map_items(items: list[CadItem], cfg: CadIngestConfig, out_dir: Path) -> Iterator[ItemResult]:
    """ingest_item over ``items`` in order, on ``cfg.workers`` processes (spawned: safe beside threads).

    The workers start with Ctrl-C's SIGINT blocked (a signal mask is inherited across fork and
    exec, and they are spawned as items are submitted, in this thread): a Ctrl-C reaches the
    terminal's whole process group, and a worker still importing printed its KeyboardInterrupt
    traceback under the command's one line; the command's end takes its workers down
    (:func:`flows.runtime.exit_now`). A worker that dies (the kernel's out-of-memory killer on a huge
    mesh, a crash in native code) broke the pool and failed the whole library: the items that may
    have been in its workers then (the next ``workers + 1`` unfinished) run one at a time in a pool
    of one, so the one that kills its worker alone is known and skipped (:func:`_died`), and the
    rest go on in a new pool; :data:`MAX_DEATHS_IN_A_ROW` deaths in a row (workers that cannot
    start at all) end the library."""
    if cfg.workers == 1 or len(items) < 2:
        yield from (ingest_item(item, cfg, out_dir) for item in items)
        return
    todo, suspects, deaths = list(items), 0, 0
    while todo:
        with ProcessPoolExecutor(1 if suspects else cfg.workers, mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = []
            try:
                blocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
                try:  # a worker may die while the items are still being submitted: submit raises then
                    futures += (pool.submit(ingest_item, item, cfg, out_dir) for item in (todo[:suspects] or todo))
                finally:
                    signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
                for future in futures:
                    result = future.result()
                    todo.pop(0)
                    suspects, deaths = max(0, suspects - 1), 0
                    yield result
            except BrokenProcessPool:  # its futures are failed by the pool's own thread: cancelling them raced it
                if not suspects:
                    suspects = min(len(todo), cfg.workers + 1)
                    continue
                deaths += 1  # alone, the first unfinished is the one its worker was ingesting
                if deaths >= MAX_DEATHS_IN_A_ROW:
                    raise CadItemError(f"{deaths} worker processes died in a row, each ingesting one model alone (the "
                                       f"last: {todo[0].path}): they cannot run here (out of memory?)") from None
                suspects -= 1
                yield _died(todo.pop(0), out_dir)
            except BaseException:  # the caller stopped early (GeneratorExit), or Ctrl-C: what is not started, never is
                for future in futures:
                    future.cancel()
                raise


def _died(item: CadItem, out_dir: Path) -> ItemResult:
    """The skipped result of an item whose worker process died ingesting it (its mesh, perhaps
    half-written, removed)."""
    (out_dir / f"{item.cad_id}.glb").unlink(missing_ok=True)
    return ItemResult(None, None, [{"library": item.library, "item": item.item, "source_path": item.path, "severity": "skipped",
                                    "problem": "its worker process died ingesting it (out of memory? see the kernel log)"}])


def _points_column(points: list[np.ndarray], list_type: pa.ListType) -> pa.ListArray:
    """``cad_samples.points`` of ``points`` (float32[N_i, 3] each), built from one flat array: as
    Python lists a model's 4,096 points took 0.73 MB, ShapeNetCore's 52,472 models ~38 GB."""
    flat = np.concatenate([p.reshape(-1) for p in points]) if points else np.zeros(0, np.float32)
    xyz = pa.FixedSizeListArray.from_arrays(pa.array(flat, pa.float32()), type=list_type.value_type)
    offsets = np.concatenate([[0], np.cumsum([len(p) for p in points])]).astype(np.int32)
    return pa.ListArray.from_arrays(pa.array(offsets), xyz, type=list_type)


def ingest_library(wh: Warehouse, cfg: CadIngestConfig, library: str, items: list[CadItem], run_id: str,
                   show_progress: bool = True) -> StageOutput:
    """Ingest every item of ``library`` (see module docstring); returns rows written to ``cad_models``."""
    models, points, issues = [], [], []
    with wh.staging() as staged:
        results = _map_items(items, cfg, staged)
        for result in progress(results, total=len(items), description=f"cad {library}", enabled=show_progress):
            issues += [{**i, "library": library} for i in result.issues]
            if result.model is None:
                continue
            models.append({**result.model, "library": library})
            points.append(result.points)
        if items and not models:  # retrieval would rank every clip against an empty library
            first = issues[0]
            raise CadItemError(f"no model of CAD library {library!r} could be ingested ({len(items)} skipped; the "
                               f"first, {first['source_path']}: {first['problem']})")
        meshes = folder_digest(staged)
        version = meshes[:16]  # by content: a rerun that writes the same meshes keeps their paths (task files name them)
        models = [{**m, "mesh_path": f"media/{MEDIA_KIND}/{library}/{version}/{m['cad_id']}.glb"} for m in models]
        wh.publish_media(MEDIA_KIND, library, staged, version, content=True)
    table = pa.Table.from_pylist(models, schema=wh.spec("cad_models").schema)
    rows = wh.write("cad_models", library, table)  # first: the one whose key check may refuse
    schema = wh.spec("cad_samples").schema
    wh.write("cad_samples", library, pa.table([pa.array([library] * len(models), pa.string()), table.column("cad_id"),
                                               _points_column(points, schema.field("points").type)], schema=schema))
    wh.write("cad_issues", library, pa.Table.from_pylist(issues, schema=wh.spec("cad_issues").schema))
    wh.prune_media(MEDIA_KIND, library, keep=version)
    skipped, warned = (sum(i["severity"] == severity for i in issues) for severity in ("skipped", "warning"))
    counts = [f"{skipped} item(s) skipped"] * bool(skipped) + [f"{warned} item(s) with warnings"] * bool(warned)
    said = [f"{', '.join(counts)}, see cad_issues"] if counts else []  # warnings went unsaid: never seen
    outside = [m["source_category"] for m in models if m["source"] == "shapenet" and m["class"] == "other"]
    if outside:  # one line, not a row per model (ShapeNetCore's airplanes alone are 4,045)
        said.append(f"{len(outside)} model(s) of ShapeNet synsets outside the vocabulary (tasks/cad/classes.py) "
                    f"ingested as 'other': {', '.join(sorted(set(outside)))}")
    return StageOutput(rows, digest(table_digest(table.drop_columns(["mesh_path"])), meshes), message="; ".join(said))


def _run(ctx: StageContext) -> StageOutput:
    return ingest_library(ctx.wh, ctx.cfg, ctx.unit, ctx.source, ctx.run_id, ctx.show_progress)


def _source_inputs(items: list[CadItem]) -> list[str]:
    return [items_digest(items)]


STAGE = StageDef(
    name="cad_ingest", section="cad_ingest", scope="library", upstream=(), tables=("cad_models", "cad_samples", "cad_issues"),
    description="canonicalise a CAD library, detect symmetries, sample surfaces",
    run=_run, source_inputs=_source_inputs,
)
