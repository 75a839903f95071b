"""``cadestate``: the one command line of the pipeline.

Heavy modules (Prefect, PyAV, DuckDB) are imported inside the commands so that ``--help`` is instant
and Prefect's environment is set (per warehouse) before Prefect is first imported.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import sys
from enum import Enum
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from cadestate.config import Config, ConfigError, WarehouseConfig, describe_defaults, load_config, to_toml

app = typer.Typer(
    help="CAD-Estate annotation pipeline: RGB walkthrough videos -> CAD models with 9-DoF poses.\n\n"
    "Typical session:  cadestate ingest VIDEO CAMERAS.txt  ->  cadestate status  ->  "
    "cadestate sql \"SELECT * FROM frames LIMIT 5\".  Every table is also a view in "
    "<warehouse>/catalog.duckdb for any DuckDB client.",
    no_args_is_help=True,
    rich_markup_mode=None,
    pretty_exceptions_enable=False,
)
config_app = typer.Typer(help="Show or check the configuration (one TOML file, a section per stage).", no_args_is_help=True)
demo_app = typer.Typer(help="Synthetic demo clips (video + RealEstate10K camera file).", no_args_is_help=True)
cad_app = typer.Typer(help="The CAD library: ingest CAD collections, render them, export them in the official layout.", no_args_is_help=True)
app.add_typer(config_app, name="config")
app.add_typer(demo_app, name="demo")
bench_app = typer.Typer(help="The synthetic benchmark: rendered walkthroughs with exact ground truth, evaluators.", no_args_is_help=True)
app.add_typer(cad_app, name="cad")
app.add_typer(bench_app, name="bench")
out = Console()
err = Console(stderr=True, soft_wrap=True)  # error lines stay whole (greppable)


@dataclasses.dataclass
class State:
    config_path: Optional[Path] = None
    warehouse: Optional[Path] = None
    verbose: bool = False

    def config(self) -> Config:
        cfg = load_config(self.config_path)
        if self.warehouse:
            cfg = dataclasses.replace(cfg, warehouse=WarehouseConfig(root=str(self.warehouse)))
        return cfg

    def open_warehouse(self):
        from warehouse import Warehouse

        return Warehouse(self.config().warehouse.root)


@app.callback()
def main_options(
    ctx: typer.Context,
    config: Annotated[Optional[Path], typer.Option("--config", "-c", help="Config TOML (default: $CADESTATE_CONFIG, else ./cadestate.toml, else built-in defaults).")] = None,
    warehouse: Annotated[Optional[Path], typer.Option("--warehouse", "-w", help="Warehouse root (overrides [warehouse] root and $CADESTATE_WAREHOUSE).")] = None,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Show Prefect's flow and task logs.")] = False,
) -> None:
    ctx.obj = State(config, warehouse, verbose)


def _print_reports(reports) -> int:
    table = Table("clip", "stage", "state", "rows", "seconds", "message", title="stage runs")
    colours = {"completed": "green", "cached": "cyan", "failed": "red", "skipped": "yellow"}
    for r in reports:
        table.add_row(escape(r.clip), r.stage, f"[{colours[r.state]}]{r.state}[/]", str(r.rows_written),
                      f"{r.duration_s:.2f}", escape(r.message))
    out.print(table)
    failed = [r for r in reports if r.state == "failed"]
    for r in failed:
        err.print(f"[red]error:[/] clip {escape(r.clip)}, stage {r.stage}: {escape(r.message)}", highlight=False)
    return 1 if failed else 0


@app.command()
def ingest(
    ctx: typer.Context,
    sources: Annotated[list[Path], typer.Argument(help="VIDEO CAMERAS.txt for one clip, or one or more folders of <name>.mp4 + <name>.txt pairs.")],
    clip: Annotated[Optional[str], typer.Option(help="Clip name (one clip only; default: the video's file name without suffix).")] = None,
    progress: Annotated[bool, typer.Option(help="Show progress bars.")] = True,
) -> None:
    """Ingest clips and run the pipeline on them (the annotate_clip flow; build_dataset for several).

    Camera files are RealEstate10K text files: line 1 the video URL, then one line per frame with
    timestamp (µs), fx fy cx cy (normalised), 0 0, and a 3x4 world->camera [R|t], row-major.

    \b
    Examples:
      cadestate ingest room.mp4 room.txt --clip room_01
      cadestate ingest clips/            (every <name>.mp4 with its <name>.txt)
    """
    from tasks.ingest import ClipSource, discover_clips

    if len(sources) == 2 and sources[0].is_file() and sources[1].is_file():
        items = [ClipSource(clip or sources[0].stem, sources[0], sources[1])]
    else:
        if clip:
            raise typer.BadParameter("--clip names one clip: give VIDEO CAMERAS.txt, not folders")
        items = [s for folder in sources for s in discover_clips(folder)]
    _run(ctx.obj, items, progress)


@app.command()
def run(
    ctx: typer.Context,
    clips: Annotated[Optional[list[str]], typer.Argument(help="Clips to rerun (default: every ingested clip).")] = None,
    progress: Annotated[bool, typer.Option(help="Show progress bars.")] = True,
) -> None:
    """Rerun the pipeline on ingested clips: stages whose config, code and inputs are unchanged are cached (no work)."""
    from tasks.ingest import ClipSource, clip_inputs

    wh = ctx.obj.open_warehouse()
    names = clips or wh.partitions("clips")
    if not names:
        err.print("no clip is ingested yet: see `cadestate ingest --help`")
        raise typer.Exit(1)
    items = []
    for name in names:
        video, cameras, _ = clip_inputs(wh, name)
        items.append(ClipSource(name, video, cameras))
    _run(ctx.obj, items, progress)


def _run(state: State, items, progress: bool) -> None:
    from flows.runtime import prepare_prefect_environment

    cfg = state.config()
    root = Path(cfg.warehouse.root).resolve()
    prepare_prefect_environment(root, state.verbose)  # before Prefect is first imported
    from flows.annotate_clip import run_clips

    err.print(f"running {len(items)} clip(s) into {root}; Prefect's local API starts first (~20 s)")
    raise typer.Exit(_print_reports(run_clips(items, cfg, show_progress=progress)))


@app.command()
def status(
    ctx: typer.Context,
    clips: Annotated[Optional[list[str]], typer.Argument(help="Clips to show (default: all).")] = None,
) -> None:
    """Each clip's (and CAD library's) stages: last run, and whether it is stale (config, code or inputs changed since)."""
    from tasks.status import pipeline_status

    wh, cfg = ctx.obj.open_warehouse(), ctx.obj.config()
    for scope, title in (("clip", "clips"), ("library", "CAD libraries")):
        rows = pipeline_status(wh, cfg, clips, scope)
        table = Table(scope, "stage", "last run", "status", "rows", "up to date", title=title)
        for r in rows:
            fresh = "[green]yes[/]" if not r.stale_reasons else "[yellow]no: " + "; ".join(r.stale_reasons) + "[/]"
            table.add_row(escape(r.clip), r.stage, r.last_run_at, r.status, str(r.rows_written), fresh)
        out.print(table if rows else f"no {title} yet")


class Format(str, Enum):
    table = "table"
    csv = "csv"
    json = "json"


@app.command()
def sql(
    ctx: typer.Context,
    query: Annotated[str, typer.Argument(help="SQL over the warehouse views (see `cadestate tables`).")],
    format: Annotated[Format, typer.Option("--format", "-f", help="Output format.")] = Format.table,
) -> None:
    """Run a SQL query on the catalog (read-only) and print the result.

    Example:  cadestate sql "SELECT clip, count(*) FROM frames GROUP BY clip" --format csv
    """
    import duckdb

    from warehouse import connect

    con = connect(ctx.obj.open_warehouse(), read_only=True)
    try:
        cur = con.execute(query)
        names = [d[0] for d in cur.description] if cur.description else []
        rows = cur.fetchall() if names else []
    except duckdb.Error as e:
        raise CliError(f"SQL error: {e}") from None
    finally:
        con.close()
    if format is Format.json:
        print(json.dumps([dict(zip(names, r)) for r in rows], default=str, indent=1))
    elif format is Format.csv:
        writer = csv.writer(sys.stdout)
        writer.writerow(names)
        writer.writerows(rows)
    else:
        table = Table(*names)
        for r in rows:
            table.add_row(*("NULL" if v is None else escape(str(v)) for v in r))
        out.print(table)


@app.command()
def tables(
    ctx: typer.Context,
    name: Annotated[Optional[str], typer.Argument(help="A table: show its columns with units and frames.")] = None,
) -> None:
    """List the warehouse tables (row counts), or one table's columns."""
    import pyarrow.parquet as pq

    wh = ctx.obj.open_warehouse()
    if name:
        spec = wh.spec(name)
        table = Table("column", "type", "unit", "frame", "description", title=f"{name}: {spec.description}")
        for row in spec.describe():
            table.add_row(*map(escape, row))
        out.print(table)
        out.print(f"key: {', '.join(spec.key)}   mode: {spec.mode}   partitioned by clip")
        return
    table = Table("table", "rows", "clips", "description")
    for tname, spec in wh.tables.items():
        files = wh.files(tname)
        rows = sum(pq.ParquetFile(f).metadata.num_rows for f in files)
        table.add_row(tname, str(rows), str(len(wh.partitions(tname))), escape(spec.description))
    out.print(table)


@app.command()
def catalog(ctx: typer.Context) -> None:
    """Rebuild <warehouse>/catalog.duckdb (after moving a warehouse, say)."""
    from warehouse import refresh_catalog

    out.print(f"catalog: {refresh_catalog(ctx.obj.open_warehouse())}")


@config_app.command("show")
def config_show(
    ctx: typer.Context,
    defaults: Annotated[bool, typer.Option("--defaults", help="Print every key with its documentation and default.")] = False,
) -> None:
    """Print the effective configuration as TOML (or the documented defaults)."""
    print(describe_defaults() if defaults else to_toml(ctx.obj.config()))


@config_app.command("check")
def config_check(path: Annotated[Path, typer.Argument(help="Config TOML to validate.")]) -> None:
    """Validate a config file: unknown sections or keys and bad values are errors naming the key."""
    load_config(path)
    out.print(f"{path}: ok")


@demo_app.command("make")
def demo_make(
    out_dir: Annotated[Path, typer.Argument(help="Folder for <name>.mp4 and <name>.txt.")],
    name: Annotated[str, typer.Option(help="Clip name.")] = "demo_0000",
    seed: Annotated[int, typer.Option(help="Random seed (same seed, same clip).")] = 0,
    frames: Annotated[int, typer.Option(help="Video frames at 30 fps; every 2nd is a camera line.")] = 276,
) -> None:
    """Generate a synthetic walkthrough clip with exact cameras (138 camera lines by default)."""
    from bench.demo_clip import DemoClipSpec, make_demo_clip

    clip = make_demo_clip(out_dir, DemoClipSpec(name=name, seed=seed, num_video_frames=frames))
    out.print(f"wrote {clip.video_path} and {clip.cameras_path} ({len(clip.frame_indices)} cameras)")


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
    library: Annotated[Optional[str], typer.Option(help="Library name for shapenet/folder sources (default: from the folder).")] = None,
    progress: Annotated[bool, typer.Option(help="Show progress bars.")] = True,
) -> None:
    """Canonicalise a CAD collection (metres, +Y up, front +Z, centred), detect symmetries, render views.

    \b
    Sources:
      sweethome3d  a folder of *.sh3f catalogues (default: Debian's sweethome3d-furniture, `make cad-library`)
      shapenet     ShapeNetCore v2: <synset>/<model_id>/models/model_normalized.obj
      folder       meshes (OBJ/GLB/PLY/OFF/STL) + models.csv with columns id,class[,file,licence,creator,unit_m]
    Unreadable, empty or degenerate models are skipped and listed in the cad_issues table.
    """
    from flows.runtime import prepare_prefect_environment
    from tasks.cad_sources import default_source, guess_kind, source_items

    cfg = ctx.obj.config()
    path = source or (Path(cfg.cad_ingest.source) if cfg.cad_ingest.source else default_source())
    if not path.is_dir():
        raise CliError(f"{path}: CAD source folder not found" + ("" if source else " (run `make cad-library`)"))
    items = source_items(guess_kind(path) if kind is SourceKind.auto else kind.value, path, library)
    root = Path(cfg.warehouse.root).resolve()
    prepare_prefect_environment(root, ctx.obj.verbose)
    from flows.cad_library import run_cad_library

    err.print(f"{len(items)} models from {path} into {root}; Prefect's local API starts first (~20 s)")
    raise typer.Exit(_print_reports(run_cad_library(items, cfg, show_progress=progress)))


@cad_app.command("export-official")
def cad_export_official(
    ctx: typer.Context,
    out_dir: Annotated[Path, typer.Argument(help="New (or empty) folder to write.")],
    library: Annotated[Optional[list[str]], typer.Option(help="Only these libraries (repeatable; default: all).")] = None,
) -> None:
    """Write the library in the official CAD-Estate layout (shapenet_classes.json, symmetry_dict.json,
    <class>/<cad_id>.npz with float32[T,3,3] vertices), loadable by the official cad_estate code."""
    from tasks.cad_export import export_official

    count = export_official(ctx.obj.open_warehouse(), out_dir, library)
    out.print(f"wrote {count} models to {out_dir}")


@cad_app.command("sheet")
def cad_sheet(
    ctx: typer.Context,
    out_file: Annotated[Path, typer.Argument(help="PNG to write.")],
    where: Annotated[str, typer.Option(help="SQL condition on cad_models, e.g. \"class = 'chair'\".")] = "true",
    limit: Annotated[int, typer.Option(help="At most this many models.")] = 48,
) -> None:
    """A contact sheet of CAD models (first rendered view, name, class and symmetry) to look at."""
    from tasks.cad_sheet import contact_sheet

    count = contact_sheet(ctx.obj.open_warehouse(), out_file, where, limit)
    out.print(f"wrote {out_file} ({count} models)")


@bench_app.command("generate")
def bench_generate(
    ctx: typer.Context,
    bench_dir: Annotated[Path, typer.Option("--out", help="Benchmark folder (clips already there are kept).")],
    seed: Annotated[int, typer.Option(help="Benchmark seed (clip i uses seed*1000+i).")] = 20261123,
    clips: Annotated[int, typer.Option(help="Number of clips.")] = 12,
    frames: Annotated[int, typer.Option(help="Video frames per clip at 30 fps; every 2nd is a camera line.")] = 276,
    progress: Annotated[bool, typer.Option(help="Show progress bars.")] = True,
) -> None:
    """Generate walkthrough clips of furnished rooms from the CAD library, with exact ground truth
    (official frames.json/objects.json, RealEstate10K cameras, visibility). Needs `cadestate cad ingest`."""
    from bench.benchmark import generate
    from bench.walkthrough import WalkthroughSpec

    manifest, seconds = generate(bench_dir, seed, clips, ctx.obj.open_warehouse(), WalkthroughSpec(num_video_frames=frames), progress)
    timing = f", {sum(seconds) / len(seconds):.1f} s per clip" if seconds else ""
    out.print(f"{bench_dir}: {len(manifest.clips)} clips ({len(seconds)} generated now{timing}, "
              f"{len(manifest.clips) - len(seconds)} already there)")


@bench_app.command("run")
def bench_run(
    ctx: typer.Context,
    bench_dir: Annotated[Path, typer.Argument(help="Benchmark folder.")],
    progress: Annotated[bool, typer.Option(help="Show progress bars.")] = True,
) -> None:
    """Write the simulated annotators' label files (<bench>/labels/, once), then run the pipeline
    stages that exist on every benchmark clip (cached stages do no work)."""
    from bench.benchmark import clip_sources, read_manifest
    from bench.labels import simulate_labels

    made = simulate_labels(bench_dir, list(read_manifest(bench_dir).clips), ctx.obj.open_warehouse(), progress)
    err.print(f"simulated labels: {made} clip(s) labelled now")
    _run(ctx.obj, clip_sources(bench_dir), progress)


@bench_app.command("report")
def bench_report(
    bench_dir: Annotated[Path, typer.Argument(help="Benchmark folder.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print the metrics as JSON instead of markdown.")] = False,
) -> None:
    """Report the benchmark: metrics of the stages that exist, dataset statistics, example frames with
    ground-truth boxes (written to <bench>/report/ and <bench>/report.md)."""
    from bench.benchmark import report, report_markdown

    result = report(bench_dir)
    markdown = report_markdown(result)
    (bench_dir / "report.md").write_text(markdown)
    print(json.dumps(result, indent=1) if as_json else markdown)


class CliError(Exception):
    """An error to print as one line, without a traceback."""


def main() -> None:
    """Entry point: known input errors become one clear line on stderr and exit status 2."""
    from bench.benchmark import BenchmarkError
    from tasks.cad_export import ExportError
    from tasks.cad_sources import CadSourceError
    from tasks.cameras import CameraFileError
    from tasks.video import VideoError
    from warehouse import WarehouseError

    try:
        app()
    except (CliError, ConfigError, CameraFileError, VideoError, WarehouseError, CadSourceError, ExportError,
            BenchmarkError, FileNotFoundError) as e:
        err.print(f"[red]error:[/] {escape(str(e))}", highlight=False)
        sys.exit(2)
