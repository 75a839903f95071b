"""Commands over clips, the warehouse and the configuration: ingest, run, status, sql, tables, catalog, compact, config, demo."""

from __future__ import annotations

import math
import sys
from enum import Enum
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.markup import escape
from rich.table import Column, Table

from cadestate.cli.common import CliError, State, check_writable, run_sources, app, config_app, err, out
from cadestate.config import dataset_splits, describe_defaults, load_config, to_toml


def _version(asked: bool) -> None:
    """``--version``: the installed package's version, then exit."""
    if asked:
        from importlib.metadata import version

        out.print(f"cadestate {version('cadestate')}", highlight=False)
        raise typer.Exit()


@app.callback()
def main_options(
    ctx: typer.Context,
    config: Annotated[Optional[Path], typer.Option("--config", "-c", help="Config TOML (default: $CADESTATE_CONFIG, else ./cadestate.toml, else built-in defaults); its relative paths are taken from the current folder.")] = None,
    warehouse: Annotated[Optional[Path], typer.Option("--warehouse", "-w", help="Warehouse root (overrides [warehouse] root and $CADESTATE_WAREHOUSE).")] = None,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Show Prefect's flow and task logs.")] = False,
    version: Annotated[bool, typer.Option("--version", is_eager=True, callback=_version,
                                          help="Print cadestate's version and exit.")] = False,
) -> None:
    ctx.obj = State(config, warehouse, verbose)


@app.command()
def ingest(
    ctx: typer.Context,
    sources: Annotated[list[Path], typer.Argument(help="VIDEO [CAMERAS.txt] for one clip (no camera file: SfM), or folders of <name>.<mp4|mkv|webm|mov|avi> + "
                                                         "<name>.txt pairs (every video needs its .txt).")],
    clip: Annotated[Optional[str], typer.Option(help="Clip name, <video_id>_<start_us> as in CAD-Estate (one clip only; default: "
                                                     "derived from the camera file: the video id of its URL line, its first "
                                                     "timestamp).")] = None,
    split: Annotated[Optional[str], typer.Option(
        help="Dataset split of these clips: train, val, test ([manual_tracks] splits, val and test by default, get "
             "the manual-track task). Default: a clip ingested before keeps its split, a new one is train. "
             "Changing it reruns what depends on it.")] = None,
    time_offset_us: Annotated[int, typer.Option("--time-offset-us", min=0, max=2**63 - 1, help=(
        "Subtract N µs from every camera timestamp to find its frame in the video (RealEstate10K counts from the "
        "start of the full YouTube video; a clip cut from it starts at 0). Kept in `clips`; timestamps stay as written."))] = 0,
    align_start: Annotated[bool, typer.Option("--align-start", help=(
        "Map the first camera timestamp to the video's first frame; allowed only when every timestamp lies past the "
        "video's end. The offset chosen is printed."))] = False,
    intrinsics: Annotated[Optional[str], typer.Option(help=(
        "Without a camera file: the camera's fx,fy,cx,cy for SfM, in pixels of the picture upright as a player "
        "shows it (a phone video held in portrait: its portrait width and height), before any non-square pixel "
        "stretch (default: the focal length is estimated, the principal point at the image centre)."))] = None,
    progress: Annotated[bool, typer.Option(help="Show progress bars.")] = True,
) -> None:
    """Ingest clips and run the pipeline on them (the annotate_clip flow; build_dataset for several).

    Camera files are RealEstate10K text files: line 1 the video URL, then one line per frame with
    timestamp (µs), fx fy cx cy (normalised), 0 0, and a 3x4 world->camera [R|t], row-major.
    Every camera file, video and the [detect] model are checked before anything starts: a bad one
    is refused (naming the file and line, or the config key) and nothing is written.

    Clips are named as in CAD-Estate, <video_id>_<start_us>: the video id of the camera file's URL
    line (a YouTube id, else the URL's last path segment) and its first timestamp.

    A video alone (no camera file) gets its cameras by structure from motion (the `cameras` stage,
    pycolmap; [cameras] in the config) and is named <video file stem>_0. Every clip's world is
    turned to +Y up at ingest ([ingest] up).

    \b
    Examples:
      # clip room_0 (room.txt: URL file:///videos/room.mp4, first timestamp 0)
      cadestate ingest room.mp4 room.txt
      # no camera file: cameras by SfM, clip room_0
      cadestate ingest room.mp4
      # a RealEstate10K camera file of a clip cut from its video
      cadestate ingest clip.mp4 clip.txt --align-start
      # any id for a non-YouTube video; the start is its first timestamp (µs)
      cadestate ingest room.mp4 room.txt --clip kitchen_1200000
      # every <name>.mp4 with its <name>.txt; then clips of the val split
      cadestate ingest clips/
      cadestate ingest val_clips/ --split val
    """
    import dataclasses
    from collections import Counter

    from tasks.config_checks import check_config
    from tasks.video.ingest import (ClipSource, check_clip_inputs, check_video_ids, discover_clips, official_clip_name,
                              registered_splits, sfm_source, VIDEO_SUFFIXES)

    sfm_intrinsics = _parse_intrinsics(intrinsics)
    missing = [s for s in sources if not s.exists()]
    if missing:
        raise CliError(f"{missing[0]}: no such file or folder")
    if align_start and time_offset_us:
        raise typer.BadParameter("--align-start and --time-offset-us exclude each other")
    if len(sources) == 1 and sources[0].is_file():
        if time_offset_us or align_start:
            raise typer.BadParameter("--time-offset-us and --align-start need a camera file (SfM cameras are in video time)")
        cfg = ctx.obj.config()
        item = sfm_source(sources[0], clip, sfm_intrinsics)
        items, urls = [item], [(item.clip, item.video.resolve().as_uri())]
    else:
        if sfm_intrinsics:
            raise typer.BadParameter("--intrinsics is for a video without a camera file")
        if len(sources) == 2 and sources[0].is_file() and sources[1].is_file():
            if sources[1].suffix.lower() in VIDEO_SUFFIXES or sources[0].suffix.lower() == ".txt":
                raise typer.BadParameter(f"{sources[0]} {sources[1]}: two files are VIDEO CAMERAS.txt, in that order; "
                                         "videos without a camera file are ingested one at a time")
            pairs = [(sources[0], sources[1])]
        else:
            if clip:
                raise typer.BadParameter("--clip names one clip: give VIDEO CAMERAS.txt (or VIDEO alone), not folders")
            if files := [s for s in sources if s.is_file()]:  # discover_clips said "not a folder" of a video
                raise typer.BadParameter(f"{files[0]}: a file among {len(sources)} paths: give one clip (VIDEO "
                                         "[CAMERAS.txt]) or folders of clips (each <name>.mp4 with its <name>.txt)")
            pairs = [pair for folder in sources for pair in discover_clips(folder)]
        cfg = ctx.obj.config()
        items, urls = [], []
        for video, cameras in pairs:  # the ingest stage checks again; here a bad input stops everything before it starts
            checked = check_clip_inputs(video, cameras, time_offset_us, align_start, cfg.frames.max_timestamp_error_us)
            for warning in checked.warnings:
                err.print(f"[yellow]warning:[/] {escape(warning)}", highlight=False)
            if align_start:
                err.print(f"{escape(str(cameras))}: --align-start: time offset {checked.time_offset_us} µs (the first "
                          "timestamp is the video's first frame)", highlight=False)
            items.append(ClipSource(official_clip_name(checked.cameras, cameras, clip), video, cameras,
                                    time_offset_us=checked.time_offset_us))
            urls.append((items[-1].clip, checked.cameras.url))
    known_splits = dataset_splits(cfg)
    if split is not None and split not in known_splits:
        raise typer.BadParameter(f"{split!r} is none of {', '.join(known_splits)} (the splits of the dataset and "
                                 "[manual_tracks] splits)", param_hint="--split")
    check_config(cfg)
    wh = ctx.obj.open_warehouse()
    check_video_ids(wh, urls)
    twice = [c for c, n in Counter(s.clip for s in items).items() if n > 1]
    if twice:
        named = [f"{s.video}" for s in items if s.clip == twice[0]]
        raise CliError(f"clip {twice[0]!r} is named by {len(named)} inputs ({', '.join(named)}): one would replace "
                       "the other; ingest them apart with --clip NAME")
    known = registered_splits(wh)
    items = [dataclasses.replace(s, split=split or known.get(s.clip, "train")) for s in items]
    run_sources(ctx.obj, items, progress)


def _parse_intrinsics(text: str | None) -> tuple[float, float, float, float] | None:
    """``--intrinsics fx,fy,cx,cy`` (pixels, positive focal lengths) as floats."""
    if text is None:
        return None
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 4 or not all(map(math.isfinite, values)) or values[0] <= 0 or values[1] <= 0:
        raise typer.BadParameter(f"--intrinsics must be fx,fy,cx,cy in pixels (four finite numbers, fx and fy > 0), "
                                 f"got {text!r}")
    return values  # type: ignore[return-value]


@app.command()
def run(
    ctx: typer.Context,
    clips: Annotated[Optional[list[str]], typer.Argument(help="Clips to rerun (default: every ingested clip; a name "
                                                              "that starts with '-' after --: run -- -0AK9iy8y0c_0).")] = None,
    progress: Annotated[bool, typer.Option(help="Show progress bars.")] = True,
) -> None:
    """Rerun the pipeline on ingested clips (each keeps its split): stages whose config, code and inputs are
    unchanged are cached (no work).

    \b
    Examples:
      # after editing cadestate.toml: only the stale stages work
      cadestate run
      cadestate -c other.toml run room_0 hall_0
    """
    from tasks.config_checks import check_config
    from tasks.video.ingest import registered_source

    cfg = ctx.obj.config()
    check_config(cfg)  # a bad [detect] or [pose] stops the run before it starts
    wh = ctx.obj.open_warehouse(must_exist=True)
    names = list(dict.fromkeys(clips)) if clips else wh.partitions("clips")  # a clip named twice runs once
    if not names:
        err.print("no clip is ingested yet: see `cadestate ingest --help`")
        raise typer.Exit(1)
    items = [registered_source(wh, name) for name in names]
    run_sources(ctx.obj, items, progress)


SUMMARY_AFTER = 8
"""`cadestate status` without clips named shows one line per clip beyond this many clips (unless --stages)."""


@app.command()
def status(
    ctx: typer.Context,
    clips: Annotated[Optional[list[str]], typer.Argument(help="Clips to show (default: all).")] = None,
    stages: Annotated[bool, typer.Option("--stages", help=f"Every stage of every clip, also beyond {SUMMARY_AFTER} clips.")] = False,
) -> None:
    """Each clip's (and CAD library's) stages: last run, and whether it is stale (config, code or inputs changed
    since); then, per clip, the human tasks it waits for (the task file and how many items are unanswered).
    Beyond 8 clips, and none named, one line per clip (where it stands, its stale stages): name clips
    or give --stages for every stage.

    \b
    Examples:
      cadestate status
      cadestate status room_0
      # what a config would make stale, before running it
      cadestate -c other.toml status
    """
    from tasks.status import clip_notes, clip_summaries, pipeline_status, read_runs

    wh, cfg = ctx.obj.open_warehouse(must_exist=True), ctx.obj.config()
    runs = read_runs(wh, clips, keep=True)  # clips' and libraries' alike; read again only when runs came or went
    shown: set[str] = set()
    for scope, title in (("clip", "clips"), ("library", "CAD libraries")):
        rows = pipeline_status(wh, cfg, clips, scope, runs)
        names = sorted({r.clip for r in rows})
        shown.update(names)
        if scope == "clip" and not clips and not stages and len(names) > SUMMARY_AFTER:
            table = Table(*(Column(name, no_wrap=True) for name in ("clip", "stands", "last run", "done")),
                          Column("fresh", min_width=5), title=f"{title} (times UTC), one line each")
            for c in clip_summaries(rows):
                fresh = "[green]yes[/]" if not c.stale else f"[yellow]no: {len(c.stale)} from {c.stale[0]}[/]"
                table.add_row(escape(c.clip), c.stands, c.last_run_at, f"{c.done}/{c.stages}", fresh)
            out.print(table)
            out.print(f"{len(names)} clips: `cadestate status CLIP...` or `--stages` shows every stage")
        else:
            table, why = _stage_table(rows, scope, title, inline=True)
            if _wider_than_terminal(table):  # the reasons would be folded to a word a line: under the table instead
                table, why = _stage_table(rows, scope, title, inline=False)
            if _wider_than_terminal(table):  # 80 columns: times without the year, long names folded, no cell cut short
                table, why = _stage_table(rows, scope, title, inline=False, narrow=True)
            if rows or not clips:  # names found in neither scope are one error below, not a line per scope
                out.print(table if rows else f"no {title} yet")
            for line in why:
                out.print(line, highlight=False)
        for r in rows:
            if r.status == "paused":
                out.print(f"[magenta]{escape(r.clip)} waits[/] at {r.stage}: {escape(r.message)}")
            elif r.status == "interrupted":
                dashes = "-- " if r.clip.startswith("-") else ""  # a clip named by a YouTube id that starts with '-'
                again = f"`cadestate run {dashes}{escape(r.clip)}`" if scope == "clip" else "`cadestate cad ingest` of its source"
                out.print(f"[red]{escape(r.clip)} was interrupted[/] at {r.stage} ({r.last_run_at}): {escape(r.message)}; "
                          f"{again} reruns it")
        for note in clip_notes(rows):
            out.print(f"[yellow]note:[/] {escape(note)}")
    unknown = [c for c in dict.fromkeys(clips or ()) if c not in shown]
    if unknown:
        raise CliError(f"no clip or CAD library named {', '.join(unknown)} in {wh.root}")


def _stage_table(rows, scope: str, title: str, inline: bool, narrow: bool = False) -> tuple[Table, list[str]]:
    """The status table of one scope, and the lines that go under it: each stale stage's reasons
    in its 'fresh' cell (``inline``), or numbered there and written out under the table.
    ``narrow``: times without the year, and clip and stage names folded over lines where the
    terminal is too narrow (they were cut to "bench-5-…", as the rows and the notes' numbers)."""
    names = (Column(scope, overflow="fold"), Column("stage", overflow="fold")) if narrow else \
        (Column(scope, no_wrap=True), Column("stage", no_wrap=True))
    rows_width = max([len("rows"), *(len(str(r.rows_written)) for r in rows)])
    table = Table(*names, *(Column(name, no_wrap=True) for name in ("last run", "status")),
                  Column("rows", no_wrap=True, min_width=rows_width),
                  Column("fresh", min_width=5 if inline else len(f"no ({len(rows)})")),
                  title=f"{title} (times UTC{', month-day' if narrow else ''})")
    notes: list[str] = []
    for r in rows:
        reasons = "; ".join(r.stale_reasons)
        if not r.stale_reasons:
            fresh = "[green]yes[/]"
        elif inline:
            fresh = f"[yellow]no: {escape(reasons)}[/]"
        else:
            notes.append(f"[yellow]({len(notes) + 1})[/] {escape(r.clip)} {r.stage}: {escape(reasons)}")
            fresh = f"[yellow]no ({len(notes)})[/]"
        when = r.last_run_at[5:] if narrow and r.last_run_at[:4].isdigit() else r.last_run_at
        table.add_row(escape(r.clip), r.stage, when, r.status, str(r.rows_written), fresh)
    return table, notes


def _wider_than_terminal(table: Table) -> bool:
    """Whether ``table`` at its natural width overflows the terminal (never without one: lines stay whole)."""
    from rich.measure import Measurement

    return out.is_terminal and Measurement.get(out, out.options.update_width(10**6), table).maximum > out.width


@app.command()
def stages(
    markdown: Annotated[bool, typer.Option("--markdown", help="Print Markdown tables (as in the README).")] = False,
) -> None:
    """The pipeline's stages, in order: what each runs after, the tables it writes, its config
    section, its module and what it does. A stage is declared in its module (``STAGE = StageDef(...)``);
    adding one is writing such a module.

    \b
    Examples:
      cadestate stages
      # the README's stage tables (a test compares them)
      cadestate stages --markdown
    """
    from tasks.registry import extra_shown, stages_markdown, stages_of

    for scope, title in (("clip", "per clip"), ("library", "per CAD library")):
        if markdown:
            out.print(f"{title}:\n\n{stages_markdown(scope)}\n", markup=False, highlight=False)
            continue
        table = Table("stage", "after", "writes", "config", "module", "what it does", title=f"stages {title}")
        for st in stages_of(scope):
            table.add_row(st.name, ", ".join(st.upstream + st.after), ", ".join(st.tables),
                          escape(", ".join(filter(None, (st.section and f"[{st.section}]", *map(extra_shown, st.extra_sections))))), st.module, escape(st.description))
        out.print(table)


TABLE_ROWS = 1000
"""Rows that `cadestate sql` shows in the table format unless --limit says otherwise."""


class Format(str, Enum):
    table = "table"
    csv = "csv"
    json = "json"


@app.command()
def sql(
    ctx: typer.Context,
    query: Annotated[str, typer.Argument(help="One read-only SQL statement over the warehouse views (see `cadestate tables`).")],
    format: Annotated[Format, typer.Option("--format", "-f", help="Output format: table, or csv / json (streamed).")] = Format.table,
    limit: Annotated[Optional[int], typer.Option(min=0, help=f"Print at most this many rows (default: {TABLE_ROWS} for table, all for csv and json).")] = None,
) -> None:
    """Run one read-only SQL statement over the warehouse's tables and print the result.

    Read-only: one SELECT (or WITH, FROM, VALUES, TABLE, DESCRIBE, SHOW, SUMMARIZE), or EXPLAIN of
    one. Any other statement (COPY, EXPORT, ATTACH, INSTALL, LOAD, SET, PRAGMA, CREATE, INSERT, ...)
    is refused (a change inside a SELECT fails: nothing can change the views), and only the
    warehouse's table files can be read: no other file, no network, no extension. The table format shows the first rows (--limit) and counts the others, and a list of
    more than 8 items (an embedding) as its first 6 and its length; csv and json stream every row
    whole as it comes (json: an array, one row a line).

    \b
    Example:
      cadestate sql "SELECT clip, count(*) FROM frames GROUP BY clip" --format csv
    """
    from warehouse.query import run_query, split, write_csv, write_json

    with run_query(ctx.obj.open_warehouse(must_exist=True), query, limit=None if format is Format.table else limit) as result:
        if format is Format.json:
            write_json(result, sys.stdout)
        elif format is Format.csv:
            write_csv(result, sys.stdout)
        else:
            rows, rest = split(result.batches, TABLE_ROWS if limit is None else limit)
            cells = [[cell_text(v) for v in r] for r in rows]
            natural = sum(max([len(n), *(len(r[i]) for r in cells)]) + 3 for i, n in enumerate(result.names)) + 1
            if out.is_terminal and natural > out.width and out.width < MIN_CELL * len(result.names):
                print_records(result.names, cells)  # too many columns to share the width: one per line
            else:
                table = Table(*map(escape, result.names))
                for r in cells:
                    table.add_row(*map(escape, r))
                out.print(table)
            if rest:
                out.print(f"{rest:,} more rows not shown (--limit N, or --format csv or json for every row)")


LIST_SHOWN = 8
"""A list value (an embedding's 768 floats) of more items than this shows its first ones and its
length in the table format; csv and json hold it whole."""


def cell_text(value: object) -> str:
    """A value as the table format shows it: NULL for None, a long list shortened."""
    if value is None:
        return "NULL"
    if isinstance(value, list) and len(value) > LIST_SHOWN:
        return f"[{', '.join(map(str, value[:LIST_SHOWN - 2]))}, ... ({len(value):,} items)]"
    return str(value)


MIN_CELL = 10
"""A terminal narrower than this many columns per result column shows the rows as records."""


def print_records(names: list[str], rows: list[list[str]]) -> None:
    """Each row as a record: a rule naming it, then one ``name  value`` line per column."""
    pad = max(map(len, names), default=0)
    for i, row in enumerate(rows, 1):
        out.rule(f"row {i}", align="left", style="dim")
        for name, value in zip(names, row):
            out.print(f"[bold]{escape(name.ljust(pad))}[/]  {escape(value)}", highlight=False)


@app.command()
def tables(
    ctx: typer.Context,
    name: Annotated[Optional[str], typer.Argument(help="A table: show its columns with units and frames.")] = None,
) -> None:
    """List the warehouse tables (row counts), or one table's columns (no warehouse needed: the data
    model is the code's).

    \b
    Examples:
      cadestate tables
      # columns with units and coordinate frames
      cadestate tables poses
    """
    wh = ctx.obj.open_warehouse(must_exist=not name)
    if name:
        spec = wh.spec(name)
        table = Table("column", "type", "unit", "frame", "description", title=f"{name}: {spec.description}")
        for row in spec.describe():
            table.add_row(*map(escape, row))
        out.print(table)
        out.print(f"key: {', '.join(spec.key)}   mode: {spec.mode}   partitioned by {spec.schema[0].name}")
        return
    from warehouse.kept import row_counts  # kept while no table file came or went: no DuckDB then

    table = Table("table", "rows", "partitions", "description")  # clips, or CAD libraries (`tables NAME` says which)
    counts = row_counts(wh)
    for tname, info in wh.info.items():
        table.add_row(tname, str(counts[tname]), str(len(wh.partitions(tname))), escape(info.description))
    out.print(table)


@app.command()
def catalog(ctx: typer.Context) -> None:
    """Rebuild <warehouse>/catalog.duckdb, the views for DuckDB clients (derived data: nothing is lost),
    checking every table's files anew.

    Views are made once and read the table files at query time, so writes need no rebuild. Opening
    the catalog through cadestate rebuilds it anyway when it is broken, was built for another folder
    (a moved or copied warehouse) or a table's schema changed. A table with files of an older schema
    is read by name (slower); once its files are rewritten (`cadestate compact`), this command makes
    its view fast again.

    \b
    Examples:
      cadestate catalog
      duckdb -readonly data/warehouse/catalog.duckdb "SELECT count(*) FROM poses"
    """
    from warehouse.catalog import rebuild_catalog

    out.print(f"catalog: {escape(str(rebuild_catalog(ctx.obj.open_warehouse(must_exist=True), recheck=True)))}")


@app.command()
def compact(
    ctx: typer.Context,
    tables: Annotated[Optional[list[str]], typer.Argument(help="Append-mode tables to compact (default: every one; `cadestate tables NAME` gives a table's mode).")] = None,
    min_files: Annotated[int, typer.Option("--min-files", min=2, help="Compact a partition only if it has at least this many files.")] = 2,
    whole: Annotated[bool, typer.Option("--whole", help="Take the snapshot from every file, not from the last snapshot and the files it lacks (after a file was changed in place, under its old name).")] = False,
) -> None:
    """Merge each partition of the append-mode tables (one file per write) into one file, then take
    a snapshot of the tables in the catalog so that SQL opens only the files written since.

    SQL over a table opens every file of it, one or more per clip: at thousands of clips that is
    seconds per query. The snapshot keeps the rows of every file written until a minute ago in
    catalog.duckdb (tables with descriptors or point sets excepted); queries read it and the newer
    files. Run it after a batch of clips, or on a schedule; nothing goes stale meanwhile, queries
    only get slower as files pile up.

    Safe while the pipeline runs and while others read: a partition's old files and its merged
    file are swapped in one step, so a reader sees either, never both; a query that had listed the
    old files fails (`cadestate sql`: rerun it) rather than answer wrong. Writes compact a partition
    by themselves past [warehouse] compact_after_files files. Prints one line per partition compacted.

    \b
    Example:
      cadestate compact runs --min-files 10
    """
    from warehouse.catalog import CATALOG_FILE, compact_warehouse

    wh = ctx.obj.open_warehouse(must_exist=True)
    check_writable(wh.root)
    done = compact_warehouse(wh, tables, min_files, whole)
    for table, n in sorted(done.renamed.items()):
        out.print(f"{table}: {n} file(s) renamed to this version's layout", markup=False, highlight=False)
    for c in done.compacted:
        out.print(f"{c.table} {c.partition}: {c.files} files -> 1 ({c.rows} rows)", markup=False, highlight=False)
    out.print(f"compacted {len(done.compacted)} partition(s)")
    out.print(f"snapshot of {len(done.snapshotted)} table(s) in {wh.root / CATALOG_FILE}", markup=False, highlight=False)


@config_app.command("show")
def config_show(
    ctx: typer.Context,
    defaults: Annotated[bool, typer.Option("--defaults", help="Print every key with its documentation and default.")] = False,
) -> None:
    """Print the effective configuration as TOML (or the documented defaults).

    \b
    Examples:
      # a starting point to edit
      cadestate config show > my.toml
      cadestate config show --defaults
    """
    print(describe_defaults() if defaults else to_toml(ctx.obj.config()))


@config_app.command("check")
def config_check(
    ctx: typer.Context,
    path: Annotated[Optional[Path], typer.Argument(help="Config TOML to validate (default: the one commands read: -c, "
                                                        "$CADESTATE_CONFIG, ./cadestate.toml).")] = None,
) -> None:
    """Validate a config file: unknown sections or keys, bad values (nan and inf included), keys that
    contradict each other and a [detect] model that does not fit its adapter and labels are errors
    naming the key.

    \b
    Examples:
      cadestate config check my.toml && cadestate -c my.toml run
      # the config the other commands read (here none: the built-in defaults)
      cadestate config check
    """
    from tasks.config_checks import check_config

    config = load_config(path or ctx.obj.config_path)
    check_config(config)
    out.print(f"{escape(config.source or 'the built-in defaults')}: ok", highlight=False)
