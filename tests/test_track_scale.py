"""Tracking at clip scale (issue 21): bench/track_scale.py's synthetic clips and measurement, the bound's bench rows."""

from __future__ import annotations

import numpy as np
import pytest

from bench.track_scale import measure_in_subprocess, synthetic_clip


def test_synthetic_clip_has_exactly_n_detections_in_frame_order():
    c = synthetic_clip(3001, seed=2)
    assert len(c.det_id) == len(c.frame_index) == len(c.boxes) == len(c.vectors) == 3001
    assert np.all(np.diff(c.frame_index) >= 0) and c.vectors.shape[1] == 768
    assert c.frame_index.max() < len(c.cameras.K)
    per_object = np.bincount(c.truth[c.truth >= 0])
    assert np.median(per_object[per_object > 0]) > 20  # objects are seen over many frames, as in a walkthrough
    assert np.mean(c.truth < 0) < 0.2  # and some boxes are clutter


def test_measurement_reports_time_and_peak_memory_of_its_own_process():
    row = measure_in_subprocess(1000)
    assert row["detections"] == 1000 and row["pairs"] > 10_000 and row["tracks"] > 0
    assert 0 < row["rss_before_mb"] <= row["peak_rss_mb"] < 2000
    assert row["seconds"] > 0 and row["cpu_seconds"] > 0


@pytest.mark.slow
def test_35k_detections_track_in_bounded_memory():
    # issue 21: materialising both descriptors of every pair took ~6 KB a pair (13 GB for this clip's
    # 2.4M pairs); the chunked cues keep the whole process under 4 GB (measured ~0.9 GB)
    row = measure_in_subprocess(35_000)
    assert row["peak_rss_mb"] < 4096
    assert row["seconds"] < 120  # the target is 60 s on 2 idle cores; loose for shared CI machines


def test_bound_bench_rows_compare_the_heuristic_with_the_bound():
    from bench import track_bound_bench
    from bench.track_bench import random_instance

    rng = np.random.default_rng(1)
    out = track_bound_bench.run([(f"random n={n}", random_instance(n, rng, per_frame=6, window=6, noise=0.6))
                                 for n in (30, 80)])
    assert out["summary"]["graphs"] == 2
    for r in out["rows"]:
        assert r["heuristic"] <= r["bound"] + 1e-6 and r["bound"] <= r["positive_weights"] + 1e-6
        assert 0.9 < r["ratio"] <= 1.0 + 1e-9 and r["bound_converged"]
    assert out["summary"]["min_ratio"] == min(r["ratio"] for r in out["rows"])
