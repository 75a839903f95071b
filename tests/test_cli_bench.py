"""``make bench``'s command budgets: ratios to the bare baseline, wall and CPU, and a failing verdict."""

from __future__ import annotations

import sys

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
