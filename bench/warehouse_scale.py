"""The warehouse at 1,000 and 10,000 clips (issue 21, ``make bench``): per-write cost, ``cadestate
status`` of one clip, and typical SQL through the catalog.

A synthetic warehouse of N clips is written in the project's layout (:mod:`warehouse.store`:
``tables/<table>/clip=<clip>/<time>-<id>.parquet``, ``runs`` as one history file per clip, the CAD
library under ``library=<name>``) straight with pyarrow, not through the pipeline: a few hundred thousand
Parquet files in minutes. Rows are plausible and typed by the real schemas (:data:`schemas.TABLES`):
per clip its ``clips`` row, ``FRAMES`` frames, three detections a frame, six tracks, five poses of
library models, and the twelve stage runs of ``runs``; one library of ``MODELS`` CAD models.
Clips take their rows from one of a few generated templates (only names and times differ), which is
what keeps writing 10,000 clips fast.

Measured on it (medians of ``REPEATS``): the three queries below over the files alone
(``files_only``), then the snapshot ``cadestate compact`` takes (:mod:`warehouse.snapshot`; once,
reading every file: ``snapshot_build_s``), then ``Warehouse.write`` of one ``runs`` row (append)
and of a clip's ``tracks`` (replace), which leave files newer than the snapshot, ``cadestate status
<clip>`` as a fresh process (wall; beside it ``python -c "import duckdb"``, what every command
pays before it starts), and the three queries through :func:`warehouse.catalog.connect` (a fresh
connection each):

- objects per class: ``poses`` grouped by class;
- poses joined with ``cad_models``: accepted models per licence and class;
- runs of one clip: its stage runs in time order.

    python -m bench.warehouse_scale --clips 1000 10000

Prints one JSON object; ``ok`` when every row at the largest size is under 1 s and grows
sub-linearly (under 10x from 1k to 10k clips).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from statistics import median

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from schemas import TABLES

FRAMES = 30
"""Frames per synthetic clip (a 3 s clip; the paper's average is 138: rows per file, not files, change)."""
MODELS = 800
TEMPLATES = 8
REPEATS = 5
CLASSES = ("chair", "table", "sofa", "bed", "cabinet", "display", "plant", "bookshelf")
STAGES = ("cameras", "ingest", "frames", "detect", "embed", "tracking", "manual_tracks", "retrieval", "cad_selection",
          "correspondence_task", "pose", "verification")
LIBRARY = "synthetic"
QUERIES = {
    "objects_per_class": "SELECT class, count(*) AS objects FROM poses WHERE status = 'ok' GROUP BY class ORDER BY objects DESC",
    "poses_join_cad_models": "SELECT m.licence, m.class, count(*) AS poses, avg(p.loss_reprojection) AS px FROM poses p "
                             "JOIN cad_models m ON m.cad_id = p.cad_id GROUP BY ALL ORDER BY poses DESC",
    "runs_of_one_clip": "SELECT stage, status, started_at, duration_s FROM runs WHERE clip = ? ORDER BY started_at",
}


def clip_name(i: int) -> str:
    return f"synth{i:06d}_0"


def _table(name: str, columns: dict[str, object]) -> pa.Table:
    """A table of ``name``'s schema from ``columns`` (name -> values)."""
    schema = TABLES[name].schema
    return pa.Table.from_pydict({f.name: pa.array(columns[f.name], type=f.type) for f in schema}, schema=schema)


def _rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(n, 3, 3)))
    return q * np.sign(np.linalg.det(q))[:, None, None]


def template(rng: np.random.Generator, clip: str, models: list[str], classes: list[str]) -> dict[str, pa.Table]:
    """One clip's rows of every table it has (clip stages' tables and its runs)."""
    ts = (np.arange(FRAMES) * 100_000).astype(np.int64)
    R = _rotations(rng, FRAMES)
    centres = np.cumsum(rng.normal(0, 0.05, (FRAMES, 3)), axis=0) + [0, 1.5, 0]
    t = -np.einsum("nij,nj->ni", R, centres)
    n_det = 3 * FRAMES
    det_frame = np.repeat(np.arange(FRAMES), 3)
    lo = rng.uniform(0, 0.6, (n_det, 2))
    labels = rng.choice(CLASSES, n_det)
    pick = rng.choice(len(models), 5, replace=False)
    utc = dt.timezone.utc
    starts = [dt.datetime(2026, 1, 1, tzinfo=utc) + dt.timedelta(seconds=2 * k) for k in range(len(STAGES))]
    rows = lambda n, v: [v] * n  # noqa: E731
    return {
        "clips": _table("clips", {
            "clip": [clip], "url": [f"https://www.youtube.com/watch?v={clip}"], "source_video": ["v.mp4"],
            "source_cameras": ["c.txt"], "video_path": [f"inputs/{clip}/video.mp4"], "cameras_path": [f"inputs/{clip}/cameras.txt"],
            "video_sha256": ["0" * 64], "cameras_sha256": ["1" * 64], "num_cameras": [FRAMES], "first_timestamp_us": [0],
            "last_timestamp_us": [int(ts[-1])], "width": [640], "height": [360], "fps": [30.0], "duration_us": [int(ts[-1])],
            "codec": ["h264"], "ingested_at": [starts[0]], "split": ["train"], "time_offset_us": [0], "cameras_source": ["given"],
            "up_rotation": [np.eye(3).ravel().tolist()], "up_source": ["auto"], "up_note": [""], "up_line_segments": [0]}),
        "frames": _table("frames", {
            "clip": rows(FRAMES, clip), "timestamp_us": ts, "frame_index": np.arange(FRAMES, dtype=np.int32) * 3,
            "image_path": [f"media/frames/{clip}/r/{k:06d}.jpg" for k in range(FRAMES)], "width": rows(FRAMES, 640),
            "height": rows(FRAMES, 360), "video_time_us": ts, "timestamp_error_us": np.zeros(FRAMES, np.int64),
            "intrinsics": rows(FRAMES, [0.8, 1.4, 0.5, 0.5]), "K": rows(FRAMES, [512.0, 0, 320, 0, 504, 180, 0, 0, 1]),
            "world_to_camera_R": list(R.reshape(FRAMES, 9)), "world_to_camera_t": list(t),
            "camera_to_world_R": list(R.transpose(0, 2, 1).reshape(FRAMES, 9)), "camera_center": list(centres),
            "camera_interpolated": rows(FRAMES, False)}),
        "detections": _table("detections", {
            "clip": rows(n_det, clip), "det_id": np.arange(n_det), "timestamp_us": ts[det_frame],
            "frame_index": det_frame.astype(np.int32) * 3, "box": list(np.hstack([lo, lo + rng.uniform(0.1, 0.4, (n_det, 2))])),
            "label": labels, "label_id": rng.integers(0, 80, n_det).astype(np.int32),
            "score": rng.uniform(0.3, 0.95, n_det).astype(np.float32), "model_sha256": rows(n_det, "2" * 64)}),
        "tracks": _table("tracks", {
            "clip": rows(6, clip), "track_id": np.arange(6, dtype=np.int32), "label": labels[:6], "label_votes": rng.uniform(3, 30, 6),
            "first_timestamp_us": rows(6, 0), "last_timestamp_us": rows(6, int(ts[-1])), "first_frame_index": rows(6, 0),
            "last_frame_index": rows(6, 3 * (FRAMES - 1)), "num_detections": rows(6, FRAMES // 2),
            "mean_score": rng.uniform(0.4, 0.9, 6).astype(np.float32), "cohesion": rng.uniform(0, 5, 6)}),
        "poses": _table("poses", {
            "clip": rows(5, clip), "track_id": [str(k) for k in range(5)], "cad_id": [models[k] for k in pick],
            "class": [classes[k] for k in pick], "status": ["ok", "ok", "ok", "ok", "high_residual"], "message": rows(5, ""),
            "translation": list(rng.normal(0, 2, (5, 3))), "rotation": rows(5, [1.0, 0, 0, 0]),
            "scale": list(rng.uniform(0.8, 1.2, (5, 3))), "is_mirrored": rows(5, False), "symmetry": rows(5, 1),
            "upright": rows(5, True), "coplanar_axis": rows(5, -1), "num_keyframes": rows(5, 4), "num_points": rows(5, 20),
            "loss_total": rng.uniform(1, 9, 5), "loss_reprojection": rng.uniform(1, 8, 5), "loss_up": rows(5, 0.0),
            "loss_front": rows(5, 0.0), "keyframe_timestamps_us": rows(5, [0, 1_000_000]),
            "keyframe_error_px": rows(5, [2.0, 3.0]), "parallax_deg": rng.uniform(2, 20, 5), "iterations": rows(5, 30),
            "start": rows(5, 0), "loss_floor": rows(5, 0.0), "floor_prior": rows(5, "kept"), "floor_height": rows(5, 0.0),
            "support_track": rows(5, None), "support_height": rows(5, None), "config_hash": rows(5, "3" * 16)}),
        "runs": _table("runs", {
            "clip": rows(len(STAGES), clip), "run_id": [f"r{k:02d}" for k in range(len(STAGES))], "stage": STAGES,
            "status": rows(len(STAGES), "completed"), "config_hash": rows(len(STAGES), "c"), "inputs_hash": rows(len(STAGES), "i"),
            "output_hash": rows(len(STAGES), "o"), "code_hash": rows(len(STAGES), "k"), "started_at": starts,
            "duration_s": rng.uniform(0.1, 5, len(STAGES)), "rows_written": rows(len(STAGES), 10),
            "message": rows(len(STAGES), "")}),
    }


def cad_models(rng: np.random.Generator) -> pa.Table:
    """The synthetic library: ``MODELS`` models over :data:`CLASSES`."""
    n = MODELS
    classes = [CLASSES[k % len(CLASSES)] for k in range(n)]
    return _table("cad_models", {
        "library": [LIBRARY] * n, "cad_id": [f"{LIBRARY}.m{k:04d}" for k in range(n)], "class": classes,
        "class_id": ["0"] * n, "name": [f"m{k}" for k in range(n)], "source_category": classes, "source": ["synthetic"] * n,
        "source_path": [f"m{k}.obj" for k in range(n)], "licence": [("CC0", "CC-BY 3.0")[k % 2] for k in range(n)],
        "creator": ["bench"] * n, "extent": list(rng.uniform(0.3, 2, (n, 3))), "symmetry": [1] * n,
        "symmetry_errors": [[0.0, 0.0, 0.0]] * n, "num_vertices": [1000] * n, "num_faces": [2000] * n, "textured": [False] * n,
        "mesh_path": [f"cad/{LIBRARY}/m{k}.glb" for k in range(n)]})


def _with_clip(table: pa.Table, clip: str, shift_s: float) -> pa.Table:
    """``table`` as clip ``clip``'s (its ``clip`` column replaced; ``started_at`` shifted by ``shift_s``)."""
    table = table.set_column(table.schema.get_field_index("clip"), table.schema.field("clip"), pa.array([clip] * table.num_rows))
    if "started_at" in table.schema.names:
        i = table.schema.get_field_index("started_at")
        shifted = [v + dt.timedelta(seconds=shift_s) for v in table.column(i).to_pylist()]
        table = table.set_column(i, table.schema.field(i), pa.array(shifted, type=table.schema.field(i).type))
    return table


def build(root: Path, clips: int, seed: int = 0) -> float:
    """Write a synthetic warehouse of ``clips`` clips under ``root``; returns the seconds it took."""
    from warehouse import Warehouse

    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    wh = Warehouse(root)
    library = cad_models(rng)
    folder = wh.partition_dir("cad_models", LIBRARY)
    folder.mkdir(parents=True)
    pq.write_table(library, folder / f"{0:020d}-00000000.parquet")
    models, classes = library.column("cad_id").to_pylist(), library.column("class").to_pylist()
    templates = [template(rng, "t", models, classes) for _ in range(TEMPLATES)]
    for i in range(clips):
        clip = clip_name(i)
        for table, rows in templates[i % TEMPLATES].items():
            folder = wh.partition_dir(table, clip)
            folder.mkdir(parents=True)
            pq.write_table(_with_clip(rows, clip, 60.0 * i), folder / f"{i + 1:020d}-00000000.parquet")
    return time.perf_counter() - t0


def _median_s(fn: Callable[[], object], repeats: int = REPEATS) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return round(median(times), 4)


def measure(root: Path, clips: int) -> dict:
    """The rows of one size: the queries over the files alone, the snapshot's build, per-write
    cost, ``status`` of one clip, the three queries (seconds)."""
    from warehouse import Warehouse, connect
    from warehouse.catalog import snapshot_lock, take_snapshots

    wh = Warehouse(root)
    one = clip_name(clips // 2)
    connect(wh).close()  # the catalog is made once (its first build reads every schema file): not timed

    def query(sql: str) -> None:
        con = connect(wh)
        try:
            con.execute(sql, [one] if "?" in sql else []).fetchall()
        finally:
            con.close()

    files_only = {name: _median_s(lambda: query(sql), 3) for name, sql in QUERIES.items()}
    t0 = time.perf_counter()
    with snapshot_lock(wh):
        take_snapshots(wh)
    snapshot_build_s = round(time.perf_counter() - t0, 2)
    run = _with_clip(template(np.random.default_rng(1), one, ["m"] * 5, ["chair"] * 5)["runs"].slice(0, 1), one, 0)
    tracks = wh.read("tracks", [one])
    wh.write("runs", one, run)  # imports and the after-write check, once per process: not timed
    out: dict[str, object] = {"clips": clips, "files_only": files_only, "snapshot_build_s": snapshot_build_s}
    out["write_runs_append_s"] = _median_s(lambda: wh.write("runs", one, run))
    out["write_tracks_replace_s"] = _median_s(lambda: wh.write("tracks", one, tracks))
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    status = [sys.executable, "-m", "cadestate", "-w", str(root), "status", one]
    out["status_one_clip_s"] = _median_s(lambda: subprocess.run(status, env=env, capture_output=True, check=True), 3)
    bare = [sys.executable, "-c", "import duckdb"]  # what any command pays first: not a row of its own
    out["baseline_import_duckdb"] = _median_s(lambda: subprocess.run(bare, env=env, check=True), 3)
    for name, sql in QUERIES.items():
        out[f"sql_{name}_s"] = _median_s(lambda: query(sql), 3)
    return out


def run(sizes: tuple[int, ...] = (1000, 10_000), workdir: Path | None = None) -> dict:
    """Build and measure a warehouse of each size (in ``workdir``, made if missing; default a temporary folder)."""
    if workdir is not None:
        workdir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="cadestate-scale-", dir=workdir) as tmp:
        rows = []
        for n in sizes:
            root = Path(tmp) / f"w{n}"
            built = build(root, n)
            rows.append({**measure(root, n), "build_s": round(built, 1)})
    timed = [k for k in rows[-1] if k.endswith("_s") and k not in ("build_s", "snapshot_build_s")]  # not the baseline
    growth = {k: round(rows[-1][k] / rows[0][k], 2) for k in timed} if len(rows) > 1 else {}
    ok = all(rows[-1][k] < 1.0 for k in timed) and all(g < rows[-1]["clips"] / rows[0]["clips"] for g in growth.values())
    return {"sizes": rows, "growth": growth, "ok": ok}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--clips", type=int, nargs="+", default=[1000, 10_000], help="sizes (default 1000 10000)")
    parser.add_argument("--workdir", type=Path, default=None, help="where to write the warehouses (default: a temporary folder)")
    args = parser.parse_args(argv)
    if any(n < 1 for n in args.clips):
        parser.error("--clips: sizes must be at least 1")
    print(json.dumps(run(tuple(args.clips), args.workdir), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
