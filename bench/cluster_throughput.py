"""Clips per hour of a batch, with the thread runner and with a local Dask cluster (issue 21, ``make bench``).

A batch of ``--clips`` generated clips (no CAD library: every stage runs, retrieval and what
follows on nothing) is ingested by one real ``cadestate ingest FOLDER`` process into a fresh
warehouse, once per runner: ``[prefect] task_runner = "threads"`` and ``"dask"`` (no address: a
local cluster), both with ``max_workers = WORKERS``. Two clip sizes (``SIZES``): ``paper``, the
paper's average clip (640x360, 138 camera lines, as :mod:`bench.frames_throughput`), what a dataset
of RealEstate10K clips holds; ``small`` (320x192, 30 camera lines), where the command's fixed costs
(Python, Prefect and its API, a Dask cluster) weigh most. Per size and runner:

- ``wall_s``: the command's wall time (Prefect's start, the cluster's, every clip), and ``clips_per_hour``;
- ``cpu_s``: CPU seconds of the command and every process it started (user + system);
- ``stage_s``: the seconds of its stage runs, summed from ``runs.duration_s``;
- ``orchestration_share``: what the batch took beyond its stage work spread over the workers,
  ``(wall_s - stage_s / WORKERS) / (stage_s / WORKERS)`` (0: no time outside stages). Stage
  seconds are wall time with two clips sharing the cores, so contention counts as stage work;
- ``over_bare``: the batch's wall time against the bare baseline's, minus 1: what orchestration
  costs, measured rather than derived from stage seconds.

``bare`` is the baseline on the same batch: one Python process without Prefect (never imported)
that checks the clips as ``cadestate ingest FOLDER`` does and runs each clip's stages
(:func:`tasks.stage_chain.run_unit`, the chain a flow's task runs) on ``WORKERS`` threads, into a
fresh warehouse. It runs before the runners and after them; the faster of the two is the baseline
(runs of one batch varied by about 10 % on this machine).

``threads_server_up`` is the thread runner again with a Prefect server up for the warehouse
(started before, as ``cadestate server start`` leaves one): no ephemeral API to start, its CPU
during the batch counted in ``cpu_s``.

    python -m bench.cluster_throughput --clips 20 [--size paper] [--runner threads]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.cli_bench import children_cpu_s, command_env

WORKERS = 2
RUNNERS = ("threads", "dask")


SIZES = {"paper": dict(width=640, height=360, num_video_frames=276, sample_every=2),
         "small": dict(width=320, height=192, num_video_frames=90, sample_every=3)}
"""The clips of a batch, by size (:class:`bench.demo_clip.DemoClipSpec` fields)."""


def make_batch(folder: Path, clips: int, size: str) -> Path:
    """``clips`` clips of ``size`` (``<name>.mp4`` + ``<name>.txt``) in ``folder``."""
    from bench.demo_clip import DemoClipSpec, make_demo_clip

    spec = DemoClipSpec(**SIZES[size])
    for i in range(clips):
        make_demo_clip(folder, dataclasses.replace(spec, name=f"batch{i:03d}", seed=100 + i))
    return folder


def _server_cpu_s(root: Path) -> float:
    """CPU seconds (user + system) of the warehouse's Prefect server and its children so far; 0 without one."""
    import psutil

    from flows.server import running_server

    server = running_server(root)
    if server is None:
        return 0.0
    processes = [psutil.Process(server.pid)] + psutil.Process(server.pid).children(recursive=True)
    return sum(sum(p.cpu_times()[:2]) for p in processes)


def bare_batch(batch: Path, root: Path) -> int:
    """The bare baseline (module docstring): every clip of ``batch`` into the warehouse ``root``
    with the default config, each clip's stages on one of ``WORKERS`` threads. Returns the number
    of failed stage runs (each is printed)."""
    from concurrent.futures import ThreadPoolExecutor

    from cadestate.config import Config, WarehouseConfig
    from tasks.stage_chain import run_unit
    from tasks.video.ingest import ClipSource, check_clip_inputs, discover_clips, official_clip_name

    config = Config(warehouse=WarehouseConfig(root=str(root)))
    sources = []
    for video, cameras in discover_clips(batch):
        checked = check_clip_inputs(video, cameras, 0, False)
        sources.append(ClipSource(official_clip_name(checked.cameras, cameras, None), video, cameras))
    with ThreadPoolExecutor(WORKERS) as pool:
        reports = [r for unit in pool.map(lambda s: run_unit(str(root), "clip", s.clip, config, s, False), sources)
                   for r in unit]
    failed = [r for r in reports if r.state == "failed"]
    for r in failed:
        print(f"{r.clip} {r.stage}: {r.message}", file=sys.stderr)
    return len(failed)


def _bare(batch: Path, workdir: Path) -> dict:
    """The bare baseline in its own process (Python's start and imports counted, as the command's
    are), into a warehouse under the new folder ``workdir``."""
    workdir.mkdir()
    root = workdir / "w-bare"
    env = command_env()
    cpu0, t0 = children_cpu_s(), time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "bench.cluster_throughput", "--bare-into", str(root), str(batch)],
                          capture_output=True, text=True, env=env, cwd=workdir)
    wall, cpu = time.perf_counter() - t0, children_cpu_s() - cpu0
    if done.returncode != 0:
        return {"error": (done.stderr.strip().splitlines() or ["failed"])[-1]}
    clips = len(list(batch.glob("*.mp4")))
    return {"clips": clips, "wall_s": round(wall, 1), "cpu_s": round(cpu, 1), "clips_per_hour": round(3600 * clips / wall)}


def run_batch(runner: str, batch: Path, workdir: Path, server: bool = False) -> dict:
    """Ingest every clip of ``batch`` into a fresh warehouse with ``runner``; its numbers. With
    ``server``, a Prefect server is started for the warehouse first (``cadestate server start``; its
    start is ``server_start_s``, not counted in ``wall_s``; its CPU during the batch is in ``cpu_s``)."""
    from warehouse import Warehouse

    config = workdir / f"{runner}.toml"
    config.write_text(f'[prefect]\ntask_runner = "{runner}"\nmax_workers = {WORKERS}\n')
    root = workdir / f"w-{runner}{'-server' if server else ''}"
    env = command_env()
    cli = [sys.executable, "-m", "cadestate", "-c", str(config), "-w", str(root)]
    extra: dict = {}
    if server:
        t0 = time.perf_counter()
        subprocess.run([*cli, "server", "start", "--port", "0"], capture_output=True, env=env, cwd=workdir, check=True)
        extra["server_start_s"] = round(time.perf_counter() - t0, 1)
    try:
        server0, cpu0, t0 = _server_cpu_s(root), children_cpu_s(), time.perf_counter()
        done = subprocess.run([*cli, "ingest", str(batch), "--no-progress"], capture_output=True, text=True, env=env, cwd=workdir)
        wall, cpu = time.perf_counter() - t0, children_cpu_s() - cpu0 + _server_cpu_s(root) - server0
    finally:
        if server:
            subprocess.run([*cli, "server", "stop"], capture_output=True, env=env, cwd=workdir)
    if done.returncode != 0:
        return {"error": (done.stderr.strip().splitlines() or ["failed"])[-1]}
    runs = Warehouse(root).read("runs", columns=["clip", "stage", "status", "duration_s"]).to_pylist()
    stage = sum(float(r["duration_s"] or 0.0) for r in runs)
    clips = len({r["clip"] for r in runs})
    return {"clips": clips, "wall_s": round(wall, 1), "cpu_s": round(cpu, 1), "stage_s": round(stage, 1), **extra,
            "clips_per_hour": round(3600 * clips / wall), "orchestration_share": round((wall - stage / WORKERS) / (stage / WORKERS), 3)}


def run(clips: int = 20, runners: tuple[str, ...] = RUNNERS, sizes: tuple[str, ...] = tuple(SIZES)) -> dict:
    """The numbers of each runner on one batch of ``clips`` clips of each size."""
    result: dict = {"workers": WORKERS, "batch_clips": clips}
    for size in sizes:
        with tempfile.TemporaryDirectory(prefix="cadestate-throughput-") as tmp:
            batch = make_batch(Path(tmp) / "batch", clips, size)
            first = _bare(batch, Path(tmp) / "first")
            rows = {runner: run_batch(runner, batch, Path(tmp)) for runner in runners}
            if "threads" in runners:  # what a long-lived server (`cadestate server start`) saves each command
                rows["threads_server_up"] = run_batch("threads", batch, Path(tmp), server=True)
            last = _bare(batch, Path(tmp) / "last")
            bare = min((first, last), key=lambda r: r.get("wall_s", float("inf"))) | {
                "wall_s_first_last": [first.get("wall_s"), last.get("wall_s")]}
            for row in rows.values():
                if "wall_s" in row and "wall_s" in bare:
                    row["over_bare"] = round(row["wall_s"] / bare["wall_s"] - 1, 3)
            result[size] = {"bare": bare} | rows
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--clips", type=int, default=20, help="clips in the batch (default 20, as make bench)")
    parser.add_argument("--runner", choices=RUNNERS, action="append", help="only this runner (repeatable; default both)")
    parser.add_argument("--size", choices=tuple(SIZES), action="append", help="only clips of this size (repeatable; default both)")
    parser.add_argument("--bare-into", nargs=2, metavar=("WAREHOUSE", "BATCH"), type=Path,
                        help="run only the bare baseline of the folder BATCH into WAREHOUSE (what the bench runs in its own process)")
    args = parser.parse_args(argv)
    if args.bare_into:
        return 1 if bare_batch(args.bare_into[1], args.bare_into[0]) else 0
    if args.clips < 1:
        parser.error("--clips must be at least 1")
    print(json.dumps(run(args.clips, tuple(args.runner or RUNNERS), tuple(args.size or SIZES)), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
