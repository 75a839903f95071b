"""The cache of a unit's stage chain (:mod:`flows.stage_chain`): which recorded run makes a stage's
run needless. The flows' behaviour on real clips is in ``test_flows.py``."""

from __future__ import annotations

import datetime as dt

from flows.stage_chain import Signature, cached_run, report_of
from tasks.stage import StageRun

A, B = Signature("cfgA", "code", "in"), Signature("cfgB", "code", "in")


def row(signature: Signature, output: str, status: str = "completed", stage: str = "tracking", minute: int = 0) -> dict:
    return {"run_id": f"r{minute}", "stage": stage, "status": status, "config_hash": signature.config_hash,
            "code_hash": signature.code_hash, "inputs_hash": signature.inputs_hash, "output_hash": output,
            "started_at": dt.datetime(2026, 1, 1, 0, minute, tzinfo=dt.timezone.utc), "rows_written": 3,
            "duration_s": 1.5, "message": f"run {minute}"}


def test_a_run_with_the_same_signature_is_reused():
    hit = cached_run([row(A, "out1")], "c", "tracking", A)
    assert hit == StageRun("c", "tracking", "r0", "completed", "cfgA", "in", "out1", "code", 3, 1.5, "run 0")
    assert report_of(hit, cached=True).state == "cached"


def test_any_other_digest_or_stage_is_a_miss():
    runs = [row(A, "out1")]
    assert cached_run(runs, "c", "tracking", B) is None
    assert cached_run(runs, "c", "tracking", Signature("cfgA", "other code", "in")) is None
    assert cached_run(runs, "c", "tracking", Signature("cfgA", "code", "other inputs")) is None
    assert cached_run(runs, "c", "detect", A) is None
    assert cached_run([], "c", "tracking", A) is None


def test_a_run_whose_output_a_later_run_replaced_is_not_reused():
    """Config A, then B writes another output: back to A, the tables hold B's output, so A runs again."""
    assert cached_run([row(A, "out1", minute=0), row(B, "out2", minute=1)], "c", "tracking", A) is None
    # B wrote what A had written: the tables hold A's output, A is reused
    assert cached_run([row(A, "out1", minute=0), row(B, "out1", minute=1)], "c", "tracking", A).run_id == "r0"
    # A ran again after B: its latest run counts
    again = [row(A, "out1", minute=0), row(B, "out2", minute=1), row(A, "out1", minute=2)]
    assert cached_run(again, "c", "tracking", A).run_id == "r2"


def test_failed_and_interrupted_runs_are_never_reused_nor_hide_the_output():
    runs = [row(A, "out1", minute=0), row(A, "", "failed", minute=1), row(B, "", "interrupted", minute=2)]
    assert cached_run(runs, "c", "tracking", A).run_id == "r0"
    assert cached_run([row(A, "", "failed")], "c", "tracking", A) is None


def test_a_paused_run_is_reused_as_paused():
    """A human task with nothing new answered stays paused, doing no work."""
    hit = cached_run([row(A, "waits", "paused", stage="cad_selection")], "c", "cad_selection", A)
    assert hit is not None and hit.status == "paused"
    report = report_of(hit, cached=True)
    assert (report.state, report.rows_written, report.message) == ("paused", 3, "run 0")
