"""``cadestate export`` (the dataset in the official CAD-Estate layout, or as Scan2CAD files) and
``cadestate stats`` (the dataset's figures and cost, for any warehouse)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.markup import escape

from cadestate.cli.common import CliError, app, cannot_write, err, out

export_app = typer.Typer(help="Write the dataset out: the official CAD-Estate layout, or Scan2CAD files.", no_args_is_help=True)
app.add_typer(export_app, name="export")


@export_app.command("official")
def export_official(
    ctx: typer.Context,
    out_dir: Annotated[Path, typer.Argument(help="New (or empty) folder to write.")],
    clips: Annotated[Optional[list[str]], typer.Option("--clips", metavar="<clip>", help="Only these clips (repeatable; default: all whose verification completed).")] = None,
    cad: Annotated[bool, typer.Option(help="Also write the CAD root (cad/, as `cadestate cad export-official`).")] = True,
    progress: Annotated[bool, typer.Option(help="Show progress bars.")] = True,
) -> None:
    """Write annotations/<clip>/{frames,objects}.json (pixel intrinsics; one object per physical object,
    poses only where accepted in verification), frames/<video_id>/<video_id>_<timestamp>.jpg, the CAD
    root cad/ and scene_list.txt: what the official cad_estate dataset classes read.

    \b
    Examples:
      cadestate export official release/
      # two clips, without the CAD root
      cadestate export official val_only/ --clips room_0 --clips hall_0 --no-cad
    """
    from tasks.dataset.export_official import export_dataset

    counts = export_dataset(ctx.obj.open_warehouse(must_exist=True), out_dir, clips, cad, progress)
    if note := counts["note"]:
        err.print(f"warning: {note}", highlight=False, markup=False)
    out.print(f"wrote {escape(str(out_dir))}: {counts['clips']} clips, {counts['frames']} frames, {counts['objects']} objects "
              f"({counts['posed_objects']} posed), {counts['cad_models']} CAD models")


@export_app.command("scan2cad")
def export_scan2cad(
    ctx: typer.Context,
    out_dir: Annotated[Path, typer.Argument(help="New or empty folder, or that of an earlier `export scan2cad` (replaced: it then holds this export alone).")],
    clips: Annotated[Optional[list[str]], typer.Option("--clips", metavar="<clip>", help="Only these clips (repeatable; default: all whose verification completed).")] = None,
) -> None:
    """Write the accepted poses as Scan2CAD files: <name>.csv rows catid,id_cad,tx,ty,tz,qw,qx,qy,qz,sx,sy,sz
    (no header), full_annotations.json and cad_appearances.json, a scan per clip under the name `export
    official` gives it; a mirrored model is the CAD id <cad_id>_mirrored.

    \b
    Examples:
      cadestate export scan2cad scan2cad/
      cadestate export scan2cad val_scan2cad/ --clips room_0 --clips hall_0
    """
    from tasks.dataset.export_scan2cad import export_scan2cad as write

    counts = write(ctx.obj.open_warehouse(must_exist=True), out_dir, clips)
    if note := counts["note"]:
        err.print(f"warning: {note}", highlight=False, markup=False)
    out.print(f"wrote {escape(str(out_dir))}: {counts['scans']} scans, {counts['alignments']} alignments")


@app.command("stats")
def stats(
    ctx: typer.Context,
    where: Annotated[str, typer.Option(help="SQL condition on the clips table, e.g. \"split = 'val'\".")] = "true",
    html: Annotated[Optional[Path], typer.Option("--html", help="Also write an HTML report into this folder.")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of a table.")] = False,
) -> None:
    """The dataset's yield (posed objects of all its objects), its figures (the paper's Table 2 and
    section 4: scenes, posed objects, classes, posed objects per scene and per frame, CAD models, frames per scene, nearest/farthest distance ratio, truncation)
    and its cost (compute seconds per stage, human items answered, annotation seconds the label files
    record per kind and per posed object, and how many answered items recorded none). The dataset is
    what `export official` writes: the clips of --where whose verification completed (the others are
    named on stderr: their poses still unjudged would read as not posed).

    \b
    Examples:
      cadestate stats
      cadestate stats --where "split = 'val'" --html val_stats/
    """
    from tasks.dataset.stats import cost_lines, dataset_tables, select_clips, statistics, statistics_lines
    from warehouse.query import QueryError

    wh = ctx.obj.open_warehouse(must_exist=True)
    if html is not None:  # refused before any figure is printed
        from tasks.dataset.stats_report import check_report_folder

        check_report_folder(html.absolute())
    try:
        clips = select_clips(wh, where)
    except QueryError as e:
        raise CliError(f"--where {where!r}: {e}") from None
    if clips.unfinished:
        err.print(f"[yellow]warning:[/] {escape(clips.note(hint=''))}", highlight=False)
    elif not clips.chosen and where != "true":  # all zeros, said as if a dataset of nothing had been asked for
        err.print(f"[yellow]warning:[/] --where {escape(repr(where))}: no clip matches it", highlight=False)
    if html is None:
        figures = statistics(dataset_tables(wh, clips.chosen))
    else:  # each clip's dataset read once, for its figures and its page
        from tasks.dataset.stats_report import write_report

        with cannot_write(html, "the HTML report", "; give a folder"):
            figures, index = write_report(wh, clips.chosen, html)
    if as_json:
        out.print_json(json.dumps(figures))
    else:
        for label, value in statistics_lines(figures):
            out.print(f"{escape(label)}: {escape(value)}", highlight=False)
        for label, value in cost_lines(figures):
            out.print(f"{escape(label)}: {escape(value)}", highlight=False)
    if html is not None:
        (err if as_json else out).print(f"wrote {escape(str(index))}", highlight=False)  # stdout stays one JSON document
