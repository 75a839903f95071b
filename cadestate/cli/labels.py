"""``cadestate labels``: the human tasks' label files: ingest, validate, schemas, tool imports."""

from __future__ import annotations

import json
from enum import Enum
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.markup import escape

from cadestate.cli.common import CliError, app, cannot_write, err, out

labels_app = typer.Typer(help="Label files of the human tasks: ingest them, validate them, print their JSON Schemas, "
                              "import manual tracks from CVAT or Label Studio.", no_args_is_help=True)
app.add_typer(labels_app, name="labels")


class Which(str, Enum):
    label = "label"
    task = "task"


class FrameMap(str, Enum):
    frames = "frames"
    video = "video"


MaxMbOpt = Annotated[float, typer.Option("--max-mb", min=1e-6, help="Refuse label files larger than this (MB).")]
DEFAULT_MAX_MB = 20.0
"""``--max-mb``: tasks.human.label_format.MAX_LABEL_BYTES in MB (a test keeps the two equal)."""


def _problems(errors: list[str], warnings: list[str]) -> None:
    """Print each warning and error on one stderr line of its own (``warning:`` / ``error:``)."""
    from tasks.human.label_format import one_line

    for w in warnings:
        err.print(f"[yellow]warning:[/] {escape(one_line(w))}", highlight=False, emoji=False)
    for e in errors:
        err.print(f"[red]error:[/] {escape(one_line(e))}", highlight=False, emoji=False)


def _say(text: str) -> None:
    """One stdout line (``text``: rich markup), never wrapped: paths are long, lines stay greppable."""
    from tasks.human.label_format import one_line

    out.print(one_line(text), soft_wrap=True, highlight=False, emoji=False)


@labels_app.command("ingest")
def labels_ingest(
    ctx: typer.Context,
    sources: Annotated[list[Path], typer.Argument(help="Folders of label files (every *.json below them), or files.")],
    resume: Annotated[bool, typer.Option(help="Rerun the flow of every clip with new labels (cached stages do no work).")] = True,
    progress: Annotated[bool, typer.Option(help="Show progress bars.")] = True,
    max_mb: MaxMbOpt = DEFAULT_MAX_MB,
) -> None:
    """Validate label files, append the valid ones to the label tables (idempotent) and resume the
    clips they answer.

    Each file is ingested on its own, all or nothing, and its outcome printed: ingested, already
    ingested, or an `error:` line (file and field); a bad file stops no other. The clips with new
    labels are rerun (the stages their labels made stale, e.g. cad_selection, and what follows;
    everything upstream is cached), and so are the clips of files ingested before whose stages have
    not taken them in (the command was stopped before its rerun ended: run it again). Exit status 1 when any file was not ingested or a resumed
    stage failed, 2 when a path given does not exist (then nothing is ingested).

    \b
    Examples:
      cadestate labels ingest labels/
      cadestate labels ingest labels/room_0/selection.json labels/room_0/verdicts.json
      # keep the answers now, rerun the clips later (`cadestate run`)
      cadestate labels ingest labels/room_0/ --no-resume
    """
    from tasks.human.label_ingest import ingest_labels
    from tasks.status import clips_left_unrun

    cfg = ctx.obj.config()
    report = ingest_labels(ctx.obj.open_warehouse(must_exist=True), sources, coplanar_tol=cfg.pose.coplanar_tol, max_bytes=round(max_mb * 1e6))
    for path in report.ingested:
        _say(f"{escape(path)}: ingested")
    for path in report.duplicates:
        _say(f"{escape(path)}: already ingested")
    _say(f"{len(report.ingested)} label file(s) ingested, {len(report.duplicates)} already ingested, "
         f"{len(report.errors)} not ingested; {report.coplanar_keyframes} co-planar key-frame(s)")
    if not (report.ingested or report.duplicates or report.errors):
        err.print(f"[yellow]warning:[/] no label file (*.json) in {escape(', '.join(map(str, sources)))}: is it the "
                  "folder the annotators' files went to?", highlight=False)
    for table, rows in sorted(report.rows.items()):
        _say(f"  {table}: {rows} row(s)")
    if report.clips:
        _say(f"clips with new labels: {escape(', '.join(report.clips))}")
    wh = ctx.obj.open_warehouse(must_exist=True)
    unrun = clips_left_unrun(wh, cfg, report.earlier_clips) if resume else []
    if unrun:
        _say(f"clips whose labels were ingested but not yet run (a resume was stopped): {escape(', '.join(unrun))}")
    _problems(report.errors, report.warnings)
    code = 0 if report.ok else 1
    if resume and (report.clips or unrun):
        from cadestate.cli.common import run_sources
        from tasks.video.ingest import registered_source

        todo = report.clips + unrun
        clips = [c for c in todo if c not in resume_served(ctx, wh.root, todo)]
        if clips:
            code = max(code, run_sources(ctx.obj, [registered_source(wh, c) for c in clips], progress, exit=False))
    raise typer.Exit(code)


def resume_served(ctx: typer.Context, root: Path, clips: list[str]) -> list[str]:
    """Resume, through the Prefect server's API, the suspended runs of ``clips`` (clips run by
    `cadestate serve`); returns the clips resumed. Without a server up, none is."""
    from flows.runtime import prepare_prefect_environment
    from flows.server import running_server

    if running_server(root) is None:
        return []
    prepare_prefect_environment(root, ctx.obj.verbose)
    from flows.deployments import resume_clips

    resumed = resume_clips(clips)
    for clip in resumed:
        out.print(f"resumed the suspended run of {escape(clip)} on the Prefect server")
    return resumed


@labels_app.command("validate")
def labels_validate(
    ctx: typer.Context,
    files: Annotated[list[Path], typer.Argument(help="Label files to check, or folders of them (every *.json below).")],
    offline: Annotated[bool, typer.Option(help="Check the format only, not against the warehouse.")] = False,
    max_mb: MaxMbOpt = DEFAULT_MAX_MB,
) -> None:
    """Check label files without ingesting them (format, then the warehouse: clip, task, tracks,
    frames). Prints `ok`, `warning:` lines (legal but suspicious values) or an `error:` line per file;
    the files are checked together as `labels ingest` checks them (each against the ones before it,
    with its warnings; a file ingested before is said so and skipped, as ingest skips it). Exit status 1 when any file is bad, 2 when a path given does not exist (as
    `labels ingest`); the other paths are still checked.

    \b
    Examples:
      cadestate labels validate labels/
      # the format alone, where the warehouse is not
      cadestate labels validate answer.json --offline
    """
    from tasks.human.label_ingest import check_files, ingested_sha256, label_paths, order_warnings
    from tasks.human.labels import ClipFacts

    facts = None if offline else ClipFacts(ctx.obj.open_warehouse(must_exist=True))
    bad = missing = 0
    paths: list[Path] = []
    for source in files:
        try:
            found = label_paths(source)
        except FileNotFoundError as e:
            missing += 1
            _problems([str(e)], [])
            continue
        if not found:
            bad += 1
            _problems([f"{source}: no label file (*.json) in this folder"], [])
        paths += found
    valid = []
    known = {} if facts is None else ingested_sha256(facts.wh)
    for checked in check_files(paths, facts, known, round(max_mb * 1e6)):
        name = escape(str(checked.path))
        if checked.error is not None:
            bad += 1
            _problems([checked.error], [])
        elif checked.ingested_for is not None:  # as ingest: skipped, neither its links nor its warnings count again
            before = "are an earlier file's of these" if checked.in_batch else f"were ingested before (clip {escape(checked.ingested_for)})"
            _say(f"{name}: ok, its bytes {before}: `labels ingest` skips it")
        else:
            lf = checked.lf
            valid.append(lf)
            _say(f"{name}: ok ({lf.kind}, task {escape(lf.task_id)}, {len(lf.label.answers)} answer(s))")
            _problems([], list(lf.warnings))
    if facts is not None:
        _problems([], order_warnings(facts.wh, valid))
    raise typer.Exit(2 if missing else 1 if bad else 0)


def _schema(kind: str, which: str) -> dict:
    """The JSON Schema of the ``which`` file of ``kind``: the published one (``schemas/json/``, equal
    to the generated one), else generated from the dataclasses."""
    from schemas.label_kinds import published_schema

    doc = published_schema(kind, which)
    if doc is None:
        from schemas.labels import json_schema

        doc = json_schema(kind, which)
    return doc


@labels_app.command("schema")
def labels_schema(
    kind: Annotated[Optional[str], typer.Argument(help="manual_track | cad_selection | correspondences | verification (default: all).")] = None,
    which: Annotated[Which, typer.Option("--file", help="The label file's schema or the task file's.")] = Which.label,
    write: Annotated[Optional[Path], typer.Option(help="Write every schema (each kind's task and label file) into this folder instead of printing.")] = None,
) -> None:
    """Print the JSON Schema (draft 2020-12) of a label or task file.

    \b
    Examples:
      cadestate labels schema correspondences
      cadestate labels schema verification --file task
      cadestate labels schema --write label_schemas/
    """
    from schemas.label_kinds import KINDS

    if write is not None:
        from schemas.labels import publish_schemas

        if kind is not None or which is not Which.label:
            raise CliError("--write writes every kind's task and label schemas: give it without KIND and --file")

        with cannot_write(write, "the schemas", "; give a folder"):
            written = publish_schemas(str(write))
        for p in written:
            out.print(p)
        return
    if kind is not None and kind not in KINDS:
        raise CliError(f"unknown kind {kind!r} (kinds: {', '.join(KINDS)})")
    doc = _schema(kind, which.value) if kind else {f"{k}.{which.value}": _schema(k, which.value) for k in KINDS}
    print(json.dumps(doc, indent=2, ensure_ascii=False))


def _label_map(pairs: list[str] | None) -> dict[str, str]:
    out_map = {}
    for p in pairs or []:
        if "=" not in p:
            raise CliError(f"--map {p!r}: expected TOOL_LABEL=CLASS")
        k, v = p.split("=", 1)
        out_map[k] = v
    return out_map


def _write_import(result, out_dir: Path, source: Path, clip: str, tool: str) -> None:
    """Write the label file ``<clip>.<export name>.<first 8 hex of the export's SHA-256>.<tool>.json``:
    two exports of one name (CVAT names every export annotations.xml) never overwrite each other."""
    from cadestate.lineage import file_sha256
    from tasks.human.label_format import one_line
    from tasks.human.label_import import write_label

    for d in result.dropped:  # the export's ids and names may hold line breaks: each line stays one
        err.print(f"[yellow]left out:[/] {escape(one_line(d))}", highlight=False, emoji=False)
    _problems([], result.warnings)
    with cannot_write(out_dir, "the label file"):
        path = write_label(result.document, out_dir, f"{clip}.{source.stem}.{file_sha256(source)[:8]}.{tool}")
    n = len(result.document["answers"])
    _say(f"{escape(str(path))}: {n} manual track(s) for task {escape(result.document['task_id'])}; "
         f"ingest with `cadestate labels ingest {escape(str(out_dir))}`")


ClipOpt = Annotated[str, typer.Option("--clip", help="The clip the annotations are for.")]
TaskOpt = Annotated[Optional[str], typer.Option("--task", help="The manual_track task answered (default: the clip's newest).")]
OutOpt = Annotated[Path, typer.Option("--out", help="Folder to write the label file to.")]
FrameOpt = Annotated[FrameMap, typer.Option("--frame-map", help="frames: tool frame n = the clip's n-th extracted frame; "
                                                                  "video: tool frame n = video frame n.")]
MapOpt = Annotated[Optional[list[str]], typer.Option("--map", metavar="<label=class>", help="Rename a tool label: TOOL_LABEL=CLASS (repeatable).")]


@labels_app.command("import-cvat")
def labels_import_cvat(
    ctx: typer.Context,
    file: Annotated[Path, typer.Argument(help="CVAT for video 1.1 annotations.xml.")],
    clip: ClipOpt,
    task: TaskOpt = None,
    out_dir: OutOpt = Path("labels"),
    frame_map: FrameOpt = FrameMap.frames,
    all_frames: Annotated[bool, typer.Option(help="Keep interpolated boxes too (default: keyframe=1 boxes only).")] = False,
    skip_source: Annotated[Optional[list[str]], typer.Option(metavar="<source>", help="Leave out tracks with this source (repeatable; e.g. file: pre-loaded tracks).")] = None,
    label_map: MapOpt = None,
) -> None:
    """Make a manual_track label file from a CVAT for video 1.1 export of a task, a job or a
    project (boxes in pixels; frames as CVAT numbers them, a project's from the clip's task).

    \b
    Examples:
      cadestate labels import-cvat annotations.xml --clip room_0
      cadestate labels ingest labels/
    """
    from tasks.human.label_import_cvat import import_cvat

    result = import_cvat(ctx.obj.open_warehouse(must_exist=True), file, clip, task, frame_map=frame_map.value, keyframes_only=not all_frames,
                         skip_sources=tuple(skip_source or ()), label_map=_label_map(label_map))
    _write_import(result, out_dir, file, clip, "cvat")


@labels_app.command("import-labelstudio")
def labels_import_labelstudio(
    ctx: typer.Context,
    file: Annotated[Path, typer.Argument(help="Label Studio JSON export with videorectangle results.")],
    clip: ClipOpt,
    task: TaskOpt = None,
    out_dir: OutOpt = Path("labels"),
    frame_map: FrameOpt = FrameMap.frames,
    label_map: MapOpt = None,
) -> None:
    """Make a manual_track label file from a Label Studio video export (percent boxes, 1-based frames).

    \b
    Examples:
      cadestate labels import-labelstudio export.json --clip room_0 --map Couch=sofa
      cadestate labels ingest labels/
    """
    from tasks.human.label_import_labelstudio import import_labelstudio

    result = import_labelstudio(ctx.obj.open_warehouse(must_exist=True), file, clip, task, frame_map=frame_map.value,
                                label_map=_label_map(label_map))
    _write_import(result, out_dir, file, clip, "labelstudio")
