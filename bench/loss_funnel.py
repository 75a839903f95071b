"""Where the objects in view went: the step of the pipeline at which each one left the dataset.

Every expected object (:func:`bench.dataset_yield.expected_objects`) gets one fate, the first of
:data:`FATES` read from the end that holds for it:

- ``yielded``: exactly one accepted pose on it, correct, in the yield's headline mode (the yield's
  numerator, so the two always agree);
- ``accepted twice``: more than one accepted pose on its tracks, or credited to it by the headline
  mode (duplicates);
- ``accepted, wrong``: one accepted pose on its tracks, not correct in the headline mode (a wrong
  pose, or a model of another class);
- ``rejected``: a pose was solved on one of its tracks (status ok) and none was accepted;
- ``not solved``: a model was chosen for one of its tracks, no pose was solved (too few clicks,
  no parallax, ...);
- ``no model chosen``: tracks follow it, none got a model (CAD selection said "none of these" for
  each, or called it a fragment of another track);
- ``detected, not tracked``: no track follows it, though detector boxes (of any label) fall on it,
  matched as the track map matches them: tracking did not keep them (too few for a track, or most
  of a track that follows another object);
- ``not detected``: no track follows it and no detector box falls on it (on train clips nobody
  draws it), a loss of detection alone.

"On its tracks": the tracks the report's track map puts on the object
(:func:`bench.retrieval_bench.track_truth`). Read from the end, a later step's failure hides the
earlier ones: an object rejected in verification had a track and a model.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Mapping

from bench.scoring import Key, Outcome

FATES = ("not detected", "detected, not tracked", "no model chosen", "not solved", "rejected", "accepted, wrong",
         "accepted twice", "yielded")
"""The fates in pipeline order (the report's columns)."""


def fate(tracks: set[Key], chosen: set[Key], solved: set[Key], accepted: int, yielded: bool, detected: bool) -> str:
    """The fate of one object (module docstring): ``tracks`` follow it, of which ``chosen`` got a
    model and ``solved`` a pose; ``accepted`` poses on those tracks; ``yielded`` in the headline mode;
    ``detected``: a detector box falls on it."""
    if yielded:
        return "yielded"
    if accepted > 1:
        return "accepted twice"
    if accepted == 1:
        return "accepted, wrong"
    if tracks & solved:
        return "rejected"
    if tracks & chosen:
        return "not solved"
    if tracks:
        return "no model chosen"
    return "detected, not tracked" if detected else "not detected"


def object_fates(expected: set[Key], track_objects: Mapping[Key, Key], chosen: set[Key], solved: set[Key],
                 accepted: Iterable[Key], headline: Iterable[Outcome], detected: set[Key]) -> dict[Key, str]:
    """The fate of every ``expected`` object (clip, ground-truth id). ``track_objects``: (clip, track)
    -> the object it follows; ``chosen``, ``solved``: tracks with a chosen model, with a solved pose;
    ``accepted``: the tracks of the accepted poses; ``headline``: their outcomes in the yield's mode;
    ``detected``: the objects (clip, ground-truth id) at least one detector box falls on."""
    tracks: dict[Key, set[Key]] = {}
    for track, obj in track_objects.items():
        tracks.setdefault(obj, set()).add(track)
    on_tracks = Counter(track_objects[t] for t in accepted if t in track_objects)
    credited: dict[Key, list[Outcome]] = {}
    for o in headline:
        if o.on_object is not None:
            credited.setdefault(o.on_object, []).append(o)
    return {k: fate(tracks.get(k, set()), chosen, solved, max(on_tracks[k], len(credited.get(k, []))),
                    len(credited.get(k, [])) == 1 and credited[k][0].correct, k in detected) for k in expected}


def fate_counts(fates: Mapping[Key, str]) -> dict[str, int]:
    """Objects per fate, every fate listed (0 when none), in pipeline order."""
    counted = Counter(fates.values())
    return {f: counted[f] for f in FATES}


def funnel_markdown(splits: Mapping[str, Mapping[str, int]]) -> list[str]:
    """The report's table: one row per split, one column per fate."""
    lines = ["Where the objects in view went (each at the last step it reached, `bench/loss_funnel.py`):", "",
             "| split | " + " | ".join(FATES) + " |", "|---|" + "---:|" * len(FATES)]
    for split, counts in splits.items():
        lines.append(f"| {split} | " + " | ".join(str(counts[f]) for f in FATES) + " |")
    return lines + [""]
