"""``cadestate cad``: ingest CAD collections, look at them, export them in the official layout."""

from __future__ import annotations

import os
from enum import Enum
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.markup import escape

from cadestate.cli.common import CliError, cad_app, cannot_write, check_writable, err, out, print_reports


class SourceKind(str, Enum):
    auto = "auto"
    sweethome3d = "sweethome3d"
    shapenet = "shapenet"
    folder = "folder"


@cad_app.command("ingest")
def cad_ingest(
    ctx: typer.Context,
    source: Annotated[Optional[Path], typer.Argument(help="CAD source folder (default: [cad_ingest] source, else the embedded Sweet Home 3D library).")] = None,
    kind: Annotated[SourceKind, typer.Option(help="Source layout (auto: guess from the folder).")] = SourceKind.auto,
    library: Annotated[Optional[str], typer.Option(help="Library name for shapenet/folder sources (default: the folder's name; ShapeNet: shapenet).")] = None,
    progress: Annotated[bool, typer.Option(help="Show progress bars.")] = True,
) -> None:
    """Canonicalise a CAD collection (metres, +Y up, front +Z, centred), detect symmetries, render views.

    \b
    Sources:
      sweethome3d  a folder of *.sh3f catalogues (default: Debian's
                   sweethome3d-furniture, `make cad-library`)
      shapenet     ShapeNetCore v2: <synset>/<model_id>/models/
                   model_normalized.obj (a category folder may be named
                   instead, chairs/: its name gives the class)
      folder       meshes (OBJ/GLB/PLY/OFF/STL, +Y up) + models.csv with
                   columns id,class[,file,licence,creator,unit_m] (file:
                   default <id>.*; unit_m: metres per mesh unit, 0.001 for
                   millimetres)

    Unreadable, empty or degenerate models are skipped and listed in the cad_issues table, as are
    warnings (missing textures, unknown classes, a folder model over 25 m): `cadestate sql "SELECT * FROM
    cad_issues"`. Run again after the folder changed: the library is ingested again, models gone
    from it are dropped, the others keep their ids; an unchanged folder is cached.

    \b
    Examples:
      # the embedded Sweet Home 3D library (make cad-library)
      cadestate cad ingest
      cadestate cad ingest /data/ShapeNetCore.v2
      cadestate cad ingest my_meshes/ --library mine
    """
    from flows.runtime import prepare_prefect_environment
    from tasks.cad.sources import default_source, guess_kind, source_items

    cfg = ctx.obj.config()
    path = source or (Path(cfg.cad_ingest.source) if cfg.cad_ingest.source else default_source())
    if path.is_file():  # a library's models.csv, or one catalogue: "not found" sent the user looking for it
        raise CliError(f"{path}: a file, not a CAD source folder: give its folder ({path.parent})")
    if not path.is_dir():
        raise CliError(f"{path}: CAD source folder not found" + ("" if source else " (run `make cad-library`)"))
    path = path.resolve()  # one folder, one library and one lineage, from whatever working directory
    chosen = guess_kind(path) if kind is SourceKind.auto else kind.value
    if library is not None:
        if chosen == "sweethome3d":
            raise CliError("--library: a Sweet Home 3D source names one library per catalogue (sh3d-<catalogue>)")
        from warehouse import WarehouseError, check_name

        try:
            check_name(library, "library")
        except WarehouseError as e:
            raise CliError(f"--library: {e}") from None
    root = ctx.obj.root(cfg)
    items = source_items(chosen, path, library, held_ids(root))
    check_writable(root)
    held_elsewhere(root, items)
    api = prepare_prefect_environment(root, ctx.obj.verbose, cfg.prefect.startup_timeout_s, start_api=True)
    from flows.cad_library import run_cad_library

    models = f"{len(items)} model{'' if len(items) == 1 else 's'}"
    err.print(f"{models} from {escape(str(path))} into {escape(str(root))} " + (f"on the Prefect server at {api}" if api else
              "(Prefect's local API starts alongside, ~3 s; `cadestate server start` saves it)"))
    raise typer.Exit(print_reports(run_cad_library(items, cfg, show_progress=progress), unit="library"))


def _root_of(paths: list[str]) -> str:
    """The folder holding every file of ``paths`` (an archive member counts as its archive)."""
    from tasks.cad.sources import archive_of

    return os.path.commonpath([os.path.dirname(archive_of(p)) for p in paths])


def held_ids(root: Path) -> list[tuple[str, str, str]]:
    """(cad_id, name, source category) of every model the warehouse holds (none in a new one): what
    :func:`tasks.cad.sources.unique_keys` needs to keep their ids."""
    from warehouse import Warehouse

    if not (root / "tables" / "cad_models").is_dir():
        return []
    held = Warehouse(root).read("cad_models", columns=["cad_id", "name", "source_category"])
    return list(zip(*(held.column(c).to_pylist() for c in held.column_names)))


def held_elsewhere(root: Path, items: list) -> None:
    """Refuse items of a library the warehouse holds from another source folder (two folders of
    one name would replace each other's models)."""
    from warehouse import Warehouse

    if not (root / "tables" / "cad_models").is_dir():
        return
    wh = Warehouse(root)
    for library in sorted({i.library for i in items} & set(wh.partitions("cad_models"))):
        if all(i.source == "sweethome3d" for i in items if i.library == library):
            continue  # named after its catalogue (sh3d-<catalogue>): the same catalogue moved (another $CADESTATE_SH3D_DIR)
        held = [p for p in wh.read("cad_models", partitions=[library], columns=["source_path"]).column(0).to_pylist()
                if os.path.isabs(p)]  # stored relative by older versions: not comparable
        theirs, ours = Path(_root_of(held)) if held else None, Path(_root_of([i.path for i in items if i.library == library]))
        # one source: one folder holds the other's files (models added or skipped move the common folder)
        if theirs is not None and not (ours.is_relative_to(theirs) or theirs.is_relative_to(ours)):
            raise CliError(f"library {library!r} already holds models from {theirs}, not {ours}: "
                           f"give this source another name with --library NAME")


@cad_app.command("export-official")
def cad_export_official(
    ctx: typer.Context,
    out_dir: Annotated[Path, typer.Argument(help="New (or empty) folder to write.")],
    library: Annotated[Optional[list[str]], typer.Option(metavar="<library>", help="Only these libraries (repeatable; default: all).")] = None,
) -> None:
    """Write the library in the official CAD-Estate layout (shapenet_classes.json, symmetry_dict.json,
    <class id>/<cad_id>.npz with float32[T,3,3] vertices: a ShapeNet synset id, or cadestate-<class> for a
    class ShapeNet lacks; ATTRIBUTION.csv with every model's licence), loadable by the official
    cad_estate code.

    \b
    Examples:
      cadestate cad export-official release/cad/
      cadestate cad export-official mine_only/ --library mine
    """
    from tasks.cad.export import export_official

    count = export_official(ctx.obj.open_warehouse(must_exist=True), out_dir, library)
    out.print(f"wrote {count} models to {escape(str(out_dir))}")


@cad_app.command("sheet")
def cad_sheet(
    ctx: typer.Context,
    out_file: Annotated[Path, typer.Argument(help="PNG to write.")],
    where: Annotated[str, typer.Option(help="SQL condition on cad_models, e.g. \"class = 'chair'\".")] = "true",
    limit: Annotated[int, typer.Option(min=1, help="At most this many models.")] = 48,
) -> None:
    """A contact sheet of CAD models (first rendered view, name, class and symmetry) to look at.

    \b
    Examples:
      cadestate cad sheet models.png
      cadestate cad sheet chairs.png --where "class = 'chair'" --limit 100
    """
    from tasks.cad.sheet import contact_sheet
    from warehouse.query import QueryError

    if out_file.suffix.lower() not in (".png", ".jpg", ".jpeg", ".webp"):
        raise CliError(f"{out_file}: a picture's name: .png, .jpg or .webp")
    wh = ctx.obj.open_warehouse(must_exist=True)
    try:
        with cannot_write(out_file, "the sheet"):
            count = contact_sheet(wh, out_file, where, limit)
    except QueryError as e:
        raise CliError(f"--where {where!r}: {e}") from None
    if not count:
        raise CliError(f"no CAD model with rendered views matches --where {where!r}: nothing written "
                       "(`cadestate sql \"SELECT class, count(*) FROM cad_models GROUP BY class\"` lists the classes)")
    out.print(f"wrote {escape(str(out_file))} ({count} models)")
