"""bench/loss_funnel.py: each object in view gets the fate of the last step it reached, and the
yielded ones are exactly the yield's numerator."""

from __future__ import annotations

from bench.dataset_yield import pose_yield
from bench.loss_funnel import FATES, fate_counts, funnel_markdown, object_fates
from bench.scoring import Outcome


def test_every_object_gets_the_fate_of_the_last_step_it_reached():
    c = "clip"
    expected = {(c, g) for g in ("missed", "dropped", "none", "unsolved", "rejected", "wrong", "twice", "good", "other")}
    track_objects = {(c, "1"): (c, "none"), (c, "2"): (c, "unsolved"), (c, "3"): (c, "rejected"), (c, "4"): (c, "wrong"),
                     (c, "5"): (c, "twice"), (c, "6"): (c, "twice"), (c, "7"): (c, "good"), (c, "8"): (c, "good"),
                     (c, "9"): (c, "other")}
    chosen = {(c, t) for t in ("2", "3", "4", "5", "6", "7", "9")}
    solved = {(c, t) for t in ("3", "4", "5", "6", "7", "9")}
    accepted = [(c, t) for t in ("4", "5", "6", "7", "9")]
    headline = [Outcome((c, "4"), None, False),  # a wrong pose: on no object in a Scan2CAD mode
                Outcome((c, "5"), (c, "twice"), True), Outcome((c, "6"), (c, "twice"), True),
                Outcome((c, "7"), (c, "good"), True),
                Outcome((c, "9"), (c, "good"), True)]  # track 9 follows "other" but aligns "good": a duplicate there
    detected = {(c, g) for g in ("dropped", "none", "good")}  # a detector box on each (the others: drawn)
    fates = object_fates(expected, track_objects, chosen, solved, accepted, headline, detected)
    assert fates == {(c, "missed"): "not detected", (c, "dropped"): "detected, not tracked",
                     (c, "none"): "no model chosen", (c, "unsolved"): "not solved", (c, "rejected"): "rejected",
                     (c, "wrong"): "accepted, wrong", (c, "twice"): "accepted twice",
                     (c, "good"): "accepted twice", (c, "other"): "accepted, wrong"}
    headline = headline[:4]  # without the pose that doubled "good"
    fates = object_fates(expected, track_objects, chosen, solved, accepted[:4], headline, detected)
    assert fates[(c, "good")] == "yielded" and fates[(c, "other")] == "rejected"
    assert sum(f == "yielded" for f in fates.values()) == pose_yield(headline, expected).yielded
    counts = fate_counts(fates)
    assert list(counts) == list(FATES) and sum(counts.values()) == len(expected)
    table = funnel_markdown({"all": counts})
    assert table[2] == "| split | " + " | ".join(FATES) + " |"
    assert table[4] == "| all | 1 | 1 | 1 | 1 | 2 | 1 | 1 | 1 |"
