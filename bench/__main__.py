"""``python -m bench`` (``make bench``): run the benchmarks, print and save their numbers."""

from __future__ import annotations

import json
import os
import platform
import sys
from pathlib import Path

from bench import (annotate_bench, cad_throughput, cli_bench, cluster_throughput, descriptor_eval, detect_throughput,
                   detector_eval, frames_throughput, pose_bench, retrieval_bench, sfm_bench, stage_times, track_bench, warehouse_scale)
from bench.seeds import FRESH_SEED

RESULTS = Path("bench/results")
BENCHMARKS = [Path(os.environ.get("BENCH_DIR", "data/bench/default")),
              Path(os.environ.get("FRESH_DIR", f"data/bench/fresh-{FRESH_SEED}"))]
"""The default benchmark and one of a seed never used while training or tuning (``make bench`` runs both)."""


def main() -> int:
    RESULTS.mkdir(parents=True, exist_ok=True)
    results = {
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}",
        "frames": frames_throughput.run(Path("data/bench/perf")),
        "cad": cad_throughput.run(),
        "detection": detect_throughput.run(Path("data/bench/perf")),
        "pose": pose_bench.run(),
        "sfm": {str(b): sfm_bench.run(b) for b in BENCHMARKS if b.is_dir()},
        "retrieval": retrieval_bench.sizes(),
        "detectors": detector_eval.run([b for b in BENCHMARKS if b.is_dir()]),
        "retrieval_descriptor": descriptor_eval.run([b for b in BENCHMARKS if b.is_dir()], track_bench.open_warehouse(), tracks=True),
        "tracking": track_bench.run(track_bench.BENCH_DIR, quick=True),  # without a benchmark: its synthetic parts
        "end_to_end": stage_times.run(),
        "commands": cli_bench.run(),
        "annotation_app": annotate_bench.run(),
        "warehouse_scale": warehouse_scale.run((1000, 10_000)),
        "clips_per_hour": cluster_throughput.run(clips=20),
    }
    results["budgets_ok"] = results["commands"]["commands"]["budgets_ok"]
    (RESULTS / "latest.json").write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(results, indent=2))
    print(f"saved {RESULTS / 'latest.json'}")
    print("\n".join(cli_bench.ratio_lines(results["commands"]["commands"]) + cli_bench.round_lines(results["commands"]["label_round"])
                    + [cli_bench.demo_round_line(results["annotation_app"].get("demo_clip", {}))]))
    if not results["budgets_ok"]:
        print("budgets_ok: false (a command is over its budget, above)")
        return 1
    return 0


if __name__ == "__main__":
    from bench.script_args import no_arguments

    no_arguments(__doc__)
    sys.exit(main())
