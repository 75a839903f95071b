"""Annotation app: from the last answer of a task to the clip's NEXT TASK being ready (issue 15).

A real pipeline clip: the tests' small CAD library (``tests/conftest.py``: SMALL_LIBRARY, every
library stage run by its flow) and one rendered walkthrough (the browser tests' size), run until it
pauses at its manual-track task. ``cadestate annotate``'s app (its real :class:`Resumer`: the
worker thread resuming the clip) then gets the simulated annotators' answers
(:func:`bench.simulated_labels.answer_tasks`) over HTTP, task after task. Timed per task: from
posting its last answer (validation, label file, ingest included) until ``/api/next?clip=``
serves the next task's first item, i.e. until the background resume paused the clip at its
next human task; the last task's resume (to the end of the flow) is reported apart. Each round is
also split into its stage work (the stage runs it started) and the rest (issue 16's share outside
stage work), and so are all rounds together; a round starts once the last one's record in Prefect
is over (:mod:`cadestate.webapp.resume`), as it would at an annotator's pace, and the first once
the app has warmed up (``app_start_and_warm_up_s``), as while an annotator reads the first task.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import statistics
import time
from pathlib import Path

from bench.walkthrough import WalkthroughSpec

SEED = 3
DEMO_SEED = 7
"""``make run``'s demo clip (the Makefile's DEMO_SEED)."""
RESUME_TIMEOUT_S = 900.0


def _library_config(root: Path):
    """A Config over ``root`` holding the small CAD library, every library stage run."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from conftest import small_library_items

    from cadestate.config import CadIngestConfig, CadViewsConfig, Config, WarehouseConfig
    from flows.cad_library import run_cad_library

    config = Config(warehouse=WarehouseConfig(root=str(root)), cad_ingest=CadIngestConfig(samples=512, workers=1),
                    cad_views=CadViewsConfig(views=4, size=96))
    reports = run_cad_library(small_library_items(), config, show_progress=False)
    failed = [r.message for r in reports if r.state != "completed"]
    if failed:
        raise RuntimeError(f"the small CAD library did not build: {failed[0]}")
    return config


def _paused_clip(config, bench_dir: Path, seed: int, spec: WalkthroughSpec, split: str, first: set[str]) -> str:
    """Generate one walkthrough clip of ``seed`` and run it (as a ``split`` clip) until it pauses at
    the human tasks ``first``; returns its name."""
    from bench.benchmark import clip_sources, generate
    from flows.annotate_clip import run_clips
    from warehouse import Warehouse

    manifest, _ = generate(bench_dir, seed, 1, Warehouse(config.warehouse.root), spec, show_progress=False)
    source = dataclasses.replace(clip_sources(bench_dir)[0], split=split)
    paused = {r.stage for r in run_clips([source], config, show_progress=False) if r.state == "paused"}
    if paused != first:
        raise RuntimeError(f"the clip did not pause at {sorted(first)} (paused: {sorted(paused)})")
    return manifest.clips[0]


def _answers(bench_dir: Path, wh, clip: str) -> list[dict]:
    """The simulated annotators' answers to the clip's open tasks, as a page posts them."""
    from bench.simulated_labels import answer_tasks

    docs = []
    for path in answer_tasks(bench_dir, wh, clip):
        doc = json.loads(path.read_text())
        path.unlink()
        docs.append({k: v for k, v in doc.items() if k not in ("format", "created_at", "annotator")})
    return docs


def _wait_next(client, clip: str, task_id: str, timeout_s: float) -> dict | None:
    """Poll until the clip's resume is idle and its next item is not of ``task_id``; returns it (None: nothing waits)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        view = client.get(f"/api/clips/{clip}?wait=30").json()  # answered when the resume ends, as the page waits
        if view["resume"]["state"] == "failed":
            raise RuntimeError(f"the resume of {clip} failed: {view['resume']['message']}")
        if view["resume"]["state"] not in ("queued", "running") and (view["next"] or {}).get("task_id") != task_id:
            return view["next"]
        time.sleep(0.1)
    raise TimeoutError(f"{clip}: no next task {timeout_s:.0f} s after answering {task_id}")


def run(tmp: Path) -> dict:
    """The timings (module docstring), built under the folder ``tmp``."""
    from flows.runtime import prepare_prefect_environment
    from tasks.cad.sources import default_source

    if not default_source().is_dir():
        return {"skipped": f"Sweet Home 3D furniture not found at {default_source()} (make cad-library)"}
    tmp.mkdir(parents=True, exist_ok=True)
    prepare_prefect_environment(tmp / "wh")
    config = _library_config(tmp / "wh")
    spec = WalkthroughSpec(width=480, height=270, num_video_frames=60, sample_every=2, alone_scale=0.5)
    clip = _paused_clip(config, tmp / "bench", SEED, spec, "val", {"manual_tracks"})
    return rounds(config, clip, tmp / "bench")


def library_copy(source: Path, dest: Path) -> None:
    """Copy the warehouse ``source`` to ``dest`` without its clips (every table partition, media,
    task and input folder named after one), its catalog or its Prefect home: its CAD libraries."""
    import shutil

    from warehouse import Warehouse

    clips = set(Warehouse(source).partitions("clips"))
    skip = {"_prefect", "_running", "_locks", "_staging", "_cache", "catalog.duckdb"}

    def ignored(_folder: str, names: list[str]) -> list[str]:
        return [n for n in names if n in skip or n in clips or n.removeprefix("clip=") in clips]

    shutil.copytree(source, dest, ignore=ignored)


def run_demo(tmp: Path, library: Path) -> dict:
    """The same rounds on ``make run``'s demo clip (seed :data:`DEMO_SEED`, the paper's frame size, a
    train clip: its tasks are CAD selection, correspondences and verification) over the whole CAD
    library, taken from the warehouse ``library`` (copied: it is not changed). Its clips are left
    out of the copy: ``make run`` leaves the demo clip there answered, and a copy of it would never
    pause."""
    from cadestate.config import Config, WarehouseConfig
    from flows.runtime import prepare_prefect_environment

    if not (library / "tables" / "cad_models").is_dir():
        return {"skipped": f"no CAD library in {library} (make run, or cadestate cad ingest)"}
    tmp.mkdir(parents=True, exist_ok=True)
    library_copy(library, tmp / "wh")
    prepare_prefect_environment(tmp / "wh")
    config = Config(warehouse=WarehouseConfig(root=str(tmp / "wh")))
    clip = _paused_clip(config, tmp / "bench", DEMO_SEED, WalkthroughSpec(), "train", {"cad_selection"})
    return rounds(config, clip, tmp / "bench")


def rounds(config, clip: str, bench_dir: Path) -> dict:
    """Answer the paused ``clip``'s tasks through the app (``bench_dir``: its benchmark folder, whose
    ground truth the simulated annotators use), task after task; the module docstring's timings."""
    import httpx

    from bench.annotate_bench import serve_app
    from bench.cli_bench import split_round
    from warehouse import Warehouse

    wh = Warehouse(config.warehouse.root)
    t0 = time.perf_counter()
    server, _, base = serve_app(config)
    per_task: dict[str, dict] = {}
    try:
        server.config.app.state.resumer.warmed.wait(RESUME_TIMEOUT_S)  # as while an annotator reads the first task
        warm_s = time.perf_counter() - t0
        with httpx.Client(base_url=base, timeout=600) as client:
            nxt = client.get(f"/api/next?clip={clip}").json()
            while nxt:
                docs = _answers(bench_dir, wh, clip)
                if not docs:
                    raise RuntimeError(f"the simulated annotators did not answer {nxt['task_id']}")
                _settled(client, clip)
                for doc in docs:
                    start, t0 = dt.datetime.now(dt.timezone.utc), time.perf_counter()  # the last post starts the clock
                    r = client.post("/api/answers", json=doc)
                    r.raise_for_status()
                after = _wait_next(client, clip, nxt["task_id"], RESUME_TIMEOUT_S)
                wall = time.perf_counter() - t0
                per_task[f"{nxt['kind']} -> {after['kind'] if after else 'done'}"] = split_round(wh, start, wall)
                nxt = after
            _settled(client, clip)  # the last record, before the server goes
    finally:
        server.should_exit = True
    to_next = [r["wall_s"] for k, r in per_task.items() if not k.endswith("done")]
    wall, stage = sum(r["wall_s"] for r in per_task.values()), sum(r["stage_s"] for r in per_task.values())
    return {"app_start_and_warm_up_s": round(warm_s, 2), "answer_to_next_task_median_s": round(statistics.median(to_next), 2) if to_next else None,
            "answer_to_next_task_s": {k: r["wall_s"] for k, r in per_task.items()}, "rounds": per_task,
            "all_rounds": {"wall_s": round(wall, 2), "stage_s": round(stage, 2),
                           "outside_share": round(1 - stage / wall, 3) if wall else None}}


def _settled(client, clip: str, timeout_s: float = RESUME_TIMEOUT_S) -> None:
    """Wait until the clip's last resume has also been recorded in Prefect (not a round's time:
    an annotator's next answer comes seconds later; here it would come at once)."""
    end = time.monotonic() + timeout_s
    while client.get(f"/api/clips/{clip}").json()["resume"]["state"] in ("queued", "running", "recording"):
        if time.monotonic() > end:
            raise TimeoutError(f"{clip}: its resume was not recorded in Prefect within {timeout_s:.0f} s")
        time.sleep(0.05)
