"""End-to-end wall time of the benchmark's clips, broken down by stage (``make bench``).

Read from the ``runs`` table that ``cadestate bench run`` filled: per clip and stage, the seconds
of the runs that made its current output (:func:`stage_seconds`: its last completed run and the
paused runs it resumed; cached runs are not recorded). Reported per stage as the median over clips, with the
median of each clip's total. What the table cannot see is left out: Prefect's scheduling, and
the simulated annotators' own time (``bench run`` logs it per round).
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from statistics import median

from bench.benchmark import read_manifest
from tasks.registry import stages_of
from warehouse import Warehouse


def stage_seconds(wh: Warehouse, clips: list[str]) -> dict[str, dict[str, float]]:
    """clip -> stage -> seconds of the runs that made its current output, summed: its last
    ``completed`` run and the runs since the ``completed`` one before it (the pauses that run
    resumed; earlier history, e.g. reruns after a code change, is left out). Clips without runs are
    left out."""
    runs: dict[tuple[str, str], list[dict]] = defaultdict(list)
    for r in wh.read("runs", [c for c in clips if c in wh.partitions("runs")],
                     columns=["clip", "stage", "status", "started_at", "duration_s"]).to_pylist():
        runs[(r["clip"], r["stage"])].append(r)
    out: dict[str, dict[str, float]] = defaultdict(dict)
    for (clip, stage), rs in runs.items():
        rs.sort(key=lambda r: r["started_at"])
        done = [i for i, r in enumerate(rs) if r["status"] == "completed"]
        chain = rs[done[-2] + 1 if len(done) > 1 else 0: done[-1] + 1] if done else rs
        out[clip][stage] = sum(float(r["duration_s"] or 0.0) for r in chain)
    return dict(out)


def run(bench_dir: Path = Path("data/bench/default"), wh: Warehouse | None = None) -> dict:
    """Median seconds per stage and per clip over the benchmark's clips that ran."""
    if not (Path(bench_dir) / "manifest.json").is_file():
        return {"skipped": f"{bench_dir}: no benchmark (`cadestate bench generate`)"}
    wh = wh or Warehouse("data/warehouse")
    per_clip = stage_seconds(wh, list(read_manifest(bench_dir).clips))
    if not per_clip:
        return {"skipped": f"{bench_dir}: no clip has run (`cadestate bench run {bench_dir}`)"}
    seen = {s for c in per_clip.values() for s in c}
    stages = [s.name for s in stages_of("clip") if s.name in seen]
    return {"clips": len(per_clip),
            "median_s_per_stage": {s: round(median(c.get(s, 0.0) for c in per_clip.values()), 2) for s in stages},
            "median_s_per_clip": round(median(sum(c.values()) for c in per_clip.values()), 1)}
