"""Annotation app timings (``python -m bench``, ``make bench``): in Debian's Chromium, headless.

On a synthetic warehouse (one clip, 640x360 frames, no pipeline run):
- ``manual_track_page_ms``: open the manual-track page of a clip with 30 tracks (6 key-frames,
  every track boxed on each) until the key-frame and its boxes are drawn (median of 5 loads);
- ``model_30k_triangles_ms``: open the correspondences page until a 30k-triangle model is shown
  in the WebGL viewer (software rendering: SwiftShader), and the viewer's own load time;
- ``next_item_ms``: submit a CAD selection answer in the page until the next item of that clip is
  shown (validation, label file, ingest, next page; median of 5);
- ``answer_to_next_task_median_s``: on a real pipeline clip, from posting the last answer of a
  task until the clip's next task is ready (the app's background resume of the clip's flow;
  :mod:`bench.annotate_resume`), median over its tasks, with each task's time; and the same on
  ``make run``'s demo clip over the whole CAD library (``demo_clip``: a train clip, so CAD
  selection, correspondences and verification), each round's share outside stage work.
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

CLIP = "bench-annotate_0"
STAMPS = [i * 500_000 for i in range(6)]
H, W = 360, 640


def _warehouse(root: Path):
    import trimesh
    from PIL import Image

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from conftest import table_rows
    from schemas.labels import (CadCandidate, CadSelectionItem, CadSelectionTask, CorrespondenceItem, CorrespondenceTask,
                                ExistingTrack, KeyframeView, ManualTrackTask, TimedBox)
    from tasks.human.labels import write_task
    from warehouse import Warehouse

    wh = Warehouse(root)
    wh.write("clips", CLIP, table_rows("clips", [{"clip": CLIP, "fps": 10.0, "width": W, "height": H}]))
    wh.write("frames", CLIP, table_rows("frames", [{"clip": CLIP, "timestamp_us": t, "frame_index": i, "width": W, "height": H}
                                                   for i, t in enumerate(STAMPS)]))
    rng = np.random.default_rng(0)
    kfs = []
    for i, t in enumerate(STAMPS):
        path = root / "media" / "frames" / CLIP / f"{t}.jpg"
        path.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(rng.integers(0, 255, (H, W, 3), dtype=np.uint8)).save(path, quality=85)
        kfs.append(KeyframeView(timestamp_us=t, frame_index=i, image_path=f"media/frames/{CLIP}/{t}.jpg", box=(0.2, 0.2, 0.6, 0.5)))
    mesh = trimesh.creation.icosphere(subdivisions=5)  # 20,480 faces
    mesh = trimesh.util.concatenate([mesh, trimesh.creation.icosphere(subdivisions=4).apply_translation([0, 1.2, 0])])  # + 5,120
    mesh = trimesh.util.concatenate([mesh, trimesh.creation.icosphere(subdivisions=4).apply_translation([1.2, 0, 0])])  # ~30k
    (root / "media" / "cad").mkdir(parents=True, exist_ok=True)
    mesh.export(root / "media" / "cad" / "m30k.glb")
    head = dict(clip=CLIP, created_at="2026-01-01T00:00:00+00:00", image_size=(H, W))
    tracks = tuple(ExistingTrack(track_id=k, label="chair", boxes=tuple(
        TimedBox(timestamp_us=t, box=(0.02 * (k % 10), 0.03 * k, 0.02 * (k % 10) + 0.3, 0.03 * k + 0.1)) for t in STAMPS))
        for k in range(30))
    write_task(wh, ManualTrackTask(task_id=f"{CLIP}.mt", **head, keyframes=tuple(kfs), classes=("chair", "table"),
                                   existing_tracks=tracks))
    cands = tuple(CadCandidate(rank=i + 1, cad_id=f"m{i}", library="lib", cad_class="chair", score=0.5, mesh_path="media/cad/m30k.glb",
                               render_paths=()) for i in range(10))
    write_task(wh, CadSelectionTask(task_id=f"{CLIP}.cs", **head, items=tuple(
        CadSelectionItem(track_id=k, label="chair", keyframes=tuple(kfs), candidates=cands) for k in range(30))))
    write_task(wh, CorrespondenceTask(task_id=f"{CLIP}.co", **head, items=(CorrespondenceItem(
        track_id=0, label="chair", cad_id="m30k", library="lib", mesh_path="media/cad/m30k.glb", render_paths=(), symmetry=1,
        keyframes=tuple(kfs)),)))
    return wh, len(mesh.faces)


def serve_app(config, resumer=None) -> tuple:
    """``cadestate annotate``'s app over ``config`` (``resumer``: its default, the real one, when
    None) on a free local port, in a thread; returns (server, thread, base URL) once it serves."""
    import uvicorn

    from cadestate.webapp.app import create_app
    from flows.server import free_port

    port = free_port("127.0.0.1")
    server = uvicorn.Server(uvicorn.Config(create_app(config, "bench", resumer), host="127.0.0.1", port=port,
                                           log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    while not server.started:
        time.sleep(0.05)
    return server, thread, f"http://127.0.0.1:{port}"


def run() -> dict:
    """The timings (module docstring); a reason string when Chromium or Playwright is missing."""
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        return {"skipped": "playwright not installed"}
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from browser import chromium_path, launch

    if chromium_path() is None:
        return {"skipped": "chromium not installed (make browser)"}
    from cadestate.config import Config, WarehouseConfig
    from cadestate.webapp.resume import Resumer

    with tempfile.TemporaryDirectory() as tmp:
        wh, triangles = _warehouse(Path(tmp) / "wh")
        config = Config(warehouse=WarehouseConfig(root=str(wh.root)))
        server, thread, base = serve_app(config, Resumer(config, run=lambda clip: "not run"))
        out: dict = {"model_triangles": triangles}
        with sync_playwright() as p:
            browser = launch(p)
            page = browser.new_page(viewport={"width": 1400, "height": 860})
            loads = []
            for _ in range(5):
                t0 = time.perf_counter()
                page.goto(f"{base}/annotate/manual_track?clip={CLIP}&task={CLIP}.mt")
                page.wait_for_function("() => document.querySelector('#draw') && document.querySelector('#draw').width > 0")
                loads.append((time.perf_counter() - t0) * 1000)
            out["manual_track_page_30_tracks_ms"] = round(statistics.median(loads), 1)
            t0 = time.perf_counter()
            page.goto(f"{base}/annotate/correspondences?clip={CLIP}&task={CLIP}.co")
            page.wait_for_selector("#viewer[data-ready='1']", timeout=120_000)
            out["model_30k_triangles_ms"] = round((time.perf_counter() - t0) * 1000, 1)
            out["model_30k_viewer_load_ms"] = round(page.evaluate("viewer.loadMs"), 1)
            nexts = []
            page.goto(f"{base}/annotate/cad_selection?clip={CLIP}&task={CLIP}.cs&track=0")
            for k in range(5):
                page.wait_for_selector(".cand")
                page.click(".cand >> nth=0")
                t0 = time.perf_counter()
                page.click("#submit")
                page.wait_for_url(f"**track={k + 1}")
                page.wait_for_selector(".cand")
                nexts.append((time.perf_counter() - t0) * 1000)
            out["next_item_same_task_ms"] = round(statistics.median(nexts), 1)
            browser.close()
        server.should_exit = True
        thread.join(10)
        out.update(_next_task(Path(tmp) / "resume"))
    return out


def _next_task(tmp: Path, library: Path = Path("data/warehouse")) -> dict:
    """:func:`bench.annotate_resume.run` and :func:`bench.annotate_resume.run_demo` (over the CAD
    library of the default warehouse, which ``make bench`` ingests with ``cadestate cad ingest``,
    copied with its clips), each failure as one line (the other timings stand)."""
    from bench import annotate_resume

    def guarded(run) -> dict:
        try:
            return run()
        except Exception as e:  # noqa: BLE001
            return {"answer_to_next_task": f"failed: {type(e).__name__}: {e}".splitlines()[0]}

    out = guarded(lambda: annotate_resume.run(tmp / "walkthrough"))
    out["demo_clip"] = guarded(lambda: annotate_resume.run_demo(tmp / "demo", library))
    return out


if __name__ == "__main__":
    from bench.script_args import no_arguments

    no_arguments(__doc__)
    print(run())
