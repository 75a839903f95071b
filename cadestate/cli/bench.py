"""``cadestate bench``: the synthetic benchmark (generate, run, report) and single demo clips (demo)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from cadestate.cli.common import bench_app, err, out


@bench_app.command("generate")
def bench_generate(
    ctx: typer.Context,
    bench_dir: Annotated[Path, typer.Option("--out", help="Benchmark folder (clips already there, made with the same --seed and --frames, are kept).")],
    seed: Annotated[int, typer.Option(min=0, help="Benchmark seed (clip i uses seed*1000+i); the default is the default benchmark's. make "
                                         "bench's fresh seed and the seeds already used while tuning: bench/seeds.py.")] = 20261123,
    clips: Annotated[int, typer.Option(min=1, help="Number of clips.")] = 12,
    frames: Annotated[int, typer.Option(min=1, help="Video frames per clip at 30 fps; every 2nd is a camera line.")] = 276,
    progress: Annotated[bool, typer.Option(help="Show progress bars.")] = True,
) -> None:
    """Generate walkthrough clips of furnished rooms from the CAD library, with exact ground truth
    (official frames.json/objects.json, RealEstate10K cameras, visibility). Needs `cadestate cad ingest`.

    \b
    Examples:
      # the default benchmark (12 clips), then run and report it
      cadestate bench generate --out data/bench/default
      cadestate bench run data/bench/default
      cadestate bench report data/bench/default
      # a seed never used while tuning, in a folder of its own
      cadestate bench generate --out data/bench/fresh --seed 3000017 --clips 8
    """
    from bench.benchmark import generate
    from bench.walkthrough import WalkthroughSpec

    manifest, seconds = generate(bench_dir, seed, clips, ctx.obj.open_warehouse(), WalkthroughSpec(num_video_frames=frames), progress)
    timing = f", {sum(seconds) / len(seconds):.1f} s per clip" if seconds else ""
    out.print(f"{escape(str(bench_dir))}: {len(manifest.clips)} clips ({len(seconds)} generated now{timing}, "
              f"{len(manifest.clips) - len(seconds)} already there)")


@bench_app.command("run")
def bench_run(
    ctx: typer.Context,
    bench_dir: Annotated[Path, typer.Argument(help="Benchmark folder.")],
    progress: Annotated[bool, typer.Option(help="Show progress bars.")] = True,
    max_rounds: Annotated[int, typer.Option(min=1, help="At most this many runs of the clips.")] = 6,
    annotator_seed: Annotated[int, typer.Option(
        min=0, help="The simulated annotators' seed (their noise: clicks, picks, boxes). One "
             "run's yield moves by a few objects with it; run other seeds in other warehouses (-w) to see how "
             "much.")] = 0,
    sfm_cameras: Annotated[bool, typer.Option(
        "--sfm-cameras",
        help="Withhold the camera files: each clip's video alone is ingested under its benchmark name and gets "
             "its cameras by SfM (the `cameras` stage), as `cadestate ingest VIDEO` does. Use another warehouse "
             "(-w) than the run with camera files, to compare the two reports.")] = False,
) -> None:
    """Run the pipeline on every benchmark clip, the simulated annotators answering its human tasks
    through label files (<bench>/labels/<clip>/), which are ingested, and the clips rerun until none
    waits: video to verified poses (cached stages do no work). Also writes the simulated annotators'
    clicks on the ground-truth tracks (<bench>/simulated_clicks/<clip>.json, once), the input of
    `python -m bench.pose_bench` (the solver alone).

    \b
    Examples:
      cadestate bench run data/bench/default
      # cameras by SfM instead of the camera files, in a warehouse of its own
      cadestate -w data/wh_sfm bench run data/bench/default --sfm-cameras
    """
    import dataclasses

    from bench.benchmark import clip_sources, read_manifest, require_library
    from bench.labels import simulate_labels

    from tasks.status import stale_libraries

    stale = stale_libraries(ctx.obj.open_warehouse(), ctx.obj.config())
    if stale:  # the report would measure retrieval against descriptors the configuration no longer makes
        lib, reasons = next(iter(sorted(stale.items())))
        more = f" (and {len(stale) - 1} more librar{'y' if len(stale) == 2 else 'ies'})" if len(stale) > 1 else ""
        err.print(f"CAD library {escape(lib)} is stale ({'; '.join(reasons)}){more}: run `cadestate cad ingest` first")
        raise typer.Exit(1)
    clips = list(read_manifest(bench_dir).clips)
    require_library(bench_dir, clips, ctx.obj.open_warehouse())
    sources = {s.clip: dataclasses.replace(s, cameras=None) if sfm_cameras else s for s in clip_sources(bench_dir)}
    made = simulate_labels(bench_dir, clips, ctx.obj.open_warehouse(), progress)
    err.print(f"simulated clicks on every ground-truth object: {made} clip(s) made now")
    from bench.noise import DEFAULT_NOISE
    from bench.simulated_labels import annotate_until_done, merge_rounds
    from cadestate.cli.common import print_reports
    from flows.runtime import prepare_prefect_environment

    cfg = ctx.obj.config()
    prepare_prefect_environment(ctx.obj.root(cfg), ctx.obj.verbose, cfg.prefect.startup_timeout_s)
    from flows.annotate_clip import run_clips

    reports, waiting = annotate_until_done(
        bench_dir, ctx.obj.open_warehouse(), clips, lambda todo: run_clips([sources[c] for c in todo], cfg, progress),
        max_rounds, dataclasses.replace(DEFAULT_NOISE, seed=annotator_seed), log=err.print,
        coplanar_tol=cfg.pose.coplanar_tol)
    code = print_reports(merge_rounds(reports))
    if waiting:
        err.print(f"still waiting after {max_rounds} run(s): {escape(', '.join(waiting))}")
    raise typer.Exit(code or (1 if waiting else 0))


@bench_app.command("report")
def bench_report(
    ctx: typer.Context,
    bench_dir: Annotated[Path, typer.Argument(help="Benchmark folder.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print the metrics as JSON instead of markdown (report.md and "
                                                          "report/ are written either way).")] = False,
) -> None:
    """Report the benchmark (first naming the clips the warehouse has not run to the end), leading with
    the dataset's yield (objects in view with exactly one accepted,
    correct pose; duplicates; false annotations; tracks per object; human items per posed object; per
    split), then metrics of the stages that exist, dataset statistics, example frames with ground-truth
    boxes (written to <bench>/report/ and <bench>/report.md).

    \b
    Examples:
      cadestate bench report data/bench/default
      cadestate bench report data/bench/default --json > metrics.json
    """
    from bench.benchmark import report, report_markdown
    from cadestate.atomic import atomic_write_bytes

    result = report(bench_dir, wh=ctx.obj.open_warehouse(must_exist=True))
    markdown = report_markdown(result)
    atomic_write_bytes(bench_dir / "report.md", markdown.encode())
    print(json.dumps(result, indent=1) if as_json else markdown)


@bench_app.command("demo")
def bench_demo(
    out_dir: Annotated[Path, typer.Argument(help="Folder for <name>.mp4 and <name>.txt.")],
    name: Annotated[str, typer.Option(help="File stem and video id (an ingest of the files makes clip <name>_0).")] = "demo_0000",
    seed: Annotated[int, typer.Option(min=0, help="Random seed (same seed, same clip).")] = 0,
    frames: Annotated[int, typer.Option(min=1, help="Video frames at 30 fps; every 2nd is a camera line.")] = 276,
) -> None:
    """Generate one synthetic walkthrough clip with exact cameras (138 camera lines by default): a quick
    input for `cadestate ingest` (its retrieval needs a CAD library: `cadestate cad ingest`); making it needs none.

    \b
    Examples:
      cadestate bench demo demo/
      cadestate ingest demo/demo_0000.mp4 demo/demo_0000.txt
    """
    from bench.demo_clip import DemoClipSpec, make_demo_clip
    from cadestate.cli.common import cannot_write
    from warehouse.store import check_name

    check_name(name)  # it names the clip's files (and the clip an ingest of them makes)
    with cannot_write(out_dir, "the demo clip"):
        clip = make_demo_clip(out_dir, DemoClipSpec(name=name, seed=seed, num_video_frames=frames))
    out.print(f"wrote {escape(str(clip.video_path))} and {escape(str(clip.cameras_path))} ({len(clip.frame_indices)} cameras)")

