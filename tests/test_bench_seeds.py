"""The benchmark seeds' record (bench/seeds.py): make bench's fresh seed was never used while tuning."""

from __future__ import annotations

import re
from pathlib import Path

from bench.seeds import DEFAULT_SEED, FRESH_SEED, USED_SEEDS, seed_note

ROOT = Path(__file__).resolve().parents[1]


def test_make_bench_reports_the_recorded_fresh_seed():
    makefile = (ROOT / "Makefile").read_text()
    (seed,) = re.findall(r"^FRESH_SEED \?= (\d+)$", makefile, flags=re.M)
    assert int(seed) == FRESH_SEED


def test_fresh_seed_was_never_used_and_the_fitted_models_seeds_are_recorded():
    from tasks.tracking.calibration import CALIBRATION
    from tasks.tracking.merge_calibration import MERGE_CALIBRATION

    assert FRESH_SEED not in USED_SEEDS and FRESH_SEED != DEFAULT_SEED
    fitted = set(CALIBRATION["training_seeds"]) | set(MERGE_CALIBRATION["training_seeds"])
    assert fitted and fitted <= set(USED_SEEDS) and DEFAULT_SEED in USED_SEEDS


def test_seed_note_says_whether_numbers_may_flatter():
    assert seed_note(60606).startswith("Seed 60606 was used while tuning (world-up tolerance")
    assert f"seed {FRESH_SEED} is the fresh one" in seed_note(60606)
    assert seed_note(FRESH_SEED) == f"Seed {FRESH_SEED} is the fresh seed: nothing was chosen on it (bench/seeds.py)."
    unknown = next(s for s in range(1, 100) if s not in USED_SEEDS and s != FRESH_SEED)
    assert "not in bench/seeds.py's record" in seed_note(unknown)
