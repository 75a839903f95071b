"""``make bench``'s command budgets: ratios to the bare baseline, wall and CPU, and a failing verdict."""

from __future__ import annotations

import sys

import pytest

from bench.cli_bench import BASELINE, measure, ratio_lines, ratios


def test_a_command_over_its_budget_in_wall_or_cpu_time_fails_the_verdict():
    times = {BASELINE: {"wall_s": 0.1, "cpu_s": 0.1}, "fast": {"wall_s": 0.12, "cpu_s": 0.11},
             "slow wall": {"wall_s": 0.4, "cpu_s": 0.12}, "slow cpu": {"wall_s": 0.12, "cpu_s": 0.4}}
    within = ratios(times, {"fast": 1.5}, repeats=5)
    assert within["budgets_ok"] and within["commands"]["fast"] == {
        "s": 0.12, "ratio": 1.2, "cpu_ratio": 1.1, "budget": 1.5, "ok": True}
    over = ratios(times, {"fast": 1.5, "slow wall": 3.0, "slow cpu": 3.0}, repeats=5)
    assert not over["budgets_ok"]
    assert [c for c, row in over["commands"].items() if not row["ok"]] == ["slow wall", "slow cpu"]
    lines = ratio_lines(over)
    assert "fast" in lines[1] and lines[1].endswith("ok") and "budget 1.5x" in lines[1]
    assert lines[2].endswith("OVER BUDGET") and "wall  4.00x" in lines[2]


def test_measure_takes_wall_and_cpu_time_of_each_command():
    spin = "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.2: pass"
    times = measure({"idle": [sys.executable, "-c", "pass"], "spin": [sys.executable, "-c", spin]}, repeats=3)
    assert times["spin"]["cpu_s"] >= 0.2 > times["idle"]["cpu_s"]
    assert times["spin"]["wall_s"] >= times["spin"]["cpu_s"] * 0.9


def test_label_round_lines_give_each_round_its_share_and_the_target_verdict():
    from bench.cli_bench import demo_round_line, round_lines

    lines = round_lines({"ephemeral": {"wall_s": 6.0, "outside_share": 0.98}, "server": {"error": ["boom"]},
                         "app_server": {"wall_s": 0.2, "outside_share": 0.27, "rounds": 5}})
    assert lines[0] == "label round, labels ingest, ephemeral Prefect: 6.00 s, 98 % outside stage work"  # no target
    assert lines[1] == "label round, labels ingest, server up: boom"
    assert "(median of 5): 0.20 s, 27 % outside" in lines[2] and lines[2].endswith("OVER TARGET")
    demo = {"rounds": {"a": {}, "b": {}, "c": {}}, "all_rounds": {"wall_s": 1.31, "stage_s": 1.08, "outside_share": 0.176}}
    assert demo_round_line(demo).endswith("(3 rounds): 1.31 s, 18 % outside stage work  target < 20 %  ok")
    assert demo_round_line({"skipped": "no CAD library in w"}).endswith(": no CAD library in w")


def test_the_demo_warehouse_holds_the_cad_libraries_and_one_clip(wh, tmp_path):
    """bench.cli_bench.demo_warehouse: the budgets' warehouse, cut from one that also holds a benchmark's clips."""
    from bench.cli_bench import demo_warehouse
    from tests.test_warehouse import clip_rows, run_rows
    from warehouse import Warehouse

    for clip in ("a", "b"):
        wh.write("clips", clip, clip_rows(clip))
        wh.write("runs", clip, run_rows(clip, 2))
    root, clip = demo_warehouse(wh.root, tmp_path / "demo", "b")
    demo = Warehouse(root)
    assert clip == "b" and demo.partitions("clips") == demo.partitions("runs") == ["b"]
    assert demo.read("runs").equals(wh.read("runs", ["b"]))
    assert demo_warehouse(wh.root, tmp_path / "first")[1] == "a"  # no demo clip: the first


def test_the_demo_rounds_copy_the_cad_libraries_and_no_clip(wh, tmp_path):
    """bench.annotate_resume.library_copy: make run leaves its demo clip answered in the default
    warehouse; a copy that kept it would never pause, and make bench's demo rounds failed so."""
    from bench.annotate_resume import library_copy
    from tests.test_warehouse import clip_rows, run_rows
    from warehouse import Warehouse

    for clip in ("demo", "lib"):
        wh.write("runs", clip, run_rows(clip, 2))
    wh.write("clips", "demo", clip_rows("demo"))
    for folder in ("media/frames/demo", "media/cad/lib", "label_tasks/demo", "_prefect/home"):
        (wh.root / folder).mkdir(parents=True)
        (wh.root / folder / "f.txt").write_text("x")
    library_copy(wh.root, tmp_path / "copy")
    copy = Warehouse(tmp_path / "copy")
    assert copy.partitions("clips") == [] and copy.partitions("runs") == ["lib"]
    assert copy.read("runs").equals(wh.read("runs", ["lib"]))
    assert (tmp_path / "copy/media/cad/lib/f.txt").is_file()
    assert not any((tmp_path / "copy" / f).exists() for f in ("media/frames/demo", "label_tasks/demo", "_prefect"))


@pytest.mark.parametrize("module", ["bench", "bench.pose_bench", "bench.retrieval_bench", "bench.detect_throughput",
                                    "bench.cli_bench", "bench.annotate_bench"])
def test_bench_scripts_answer_help_instead_of_running(module):
    """They took no arguments and ran (minutes) on --help; now --help prints what they measure."""
    import importlib
    import subprocess

    done = subprocess.run([sys.executable, "-m", module, "--help"], capture_output=True, text=True, timeout=60)
    doc = importlib.import_module(module if module != "bench" else "bench.__main__").__doc__
    assert done.returncode == 0 and done.stdout.split("\n")[0] == doc.strip().split("\n")[0], done.stdout + done.stderr
    other = subprocess.run([sys.executable, "-m", module, "--clips", "3"], capture_output=True, text=True, timeout=60)
    assert other.returncode == 2 and "takes no arguments (got --clips 3)" in other.stderr
