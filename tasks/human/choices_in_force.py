"""Which CAD choice answers each item of a clip's cad_selection task, when the task changed under
it (another detector, another retrieval config): a choice given on an earlier task still holds.

The cad_selection task id is a digest of the clip's candidates, so any change upstream makes a new
task. An item (a track, its key-frames with the track's box there, its candidates) is answered by

1. the answer in force under the task's own id (:func:`tasks.human.answers_in_force.current_answers`),
   else
2. its ``previous``: the newest choice given on an earlier cad_selection task of the clip on the
   same object, whatever id its track had then (a detector or tracking change remakes the tracks
   and renumbers them), carried by the stage (:func:`held_choices`) when

   - it chose a model (an answer of "none fits", or "a fragment of track N", is asked again: the
     candidates, or the other track, may have changed),
   - that model is among the item's candidates now, and
   - it speaks of the same object: on every key-frame the earlier task showed a box on where the
     track has boxes now, one of them overlaps it (IoU >= :data:`tasks.human.clicks_in_force.SAME_OBJECT_IOU`),
     and there is at least one such key-frame. An answer speaks of one object: where it holds for
     several tracks, the best matched takes it (:func:`tasks.human.clicks_in_force.taken_answers`).
     The newest answer on the object decides (of equally new ones, from one label file, the one
     given on a track of the same id).

The stages, the web app's queue and the simulated annotators count both alike
(:func:`tasks.human.answers_in_force.answered_items`), and :func:`tasks.human.cad_selection.selected_models`
reads both. Boxes: (ymin, xmin, ymax, xmax), normalised.
"""

from __future__ import annotations

from collections.abc import Mapping

import pyarrow as pa

from tasks.human.clicks_in_force import Box, Match, earlier_answers, item_boxes, match, taken_answers


def same_object(then: Mapping[int, Box], now: Mapping[int, list[Box]]) -> Match | None:
    """Whether (and how well: :func:`tasks.human.clicks_in_force.match`) the track whose boxes are
    ``now`` (timestamp -> its boxes there) is the object an earlier task showed with the boxes
    ``then``: where both have boxes, one overlaps; on one frame at least."""
    m = match([ts for ts in then if now.get(ts)], then, now)
    return m if m is not None and m[0] > 0 else None


def held_choices(task_id: str, candidates: Mapping[int, set[str]], now: Mapping[int, Mapping[int, list[Box]]],
                 answers: pa.Table, tasks: pa.Table) -> dict[int, str]:
    """Per track of ``candidates`` (track -> its candidates' cad_ids) without an answer under
    ``task_id``, the model chosen on an earlier task that still holds (see the module). ``now``: the
    boxes by timestamp of the clip's tracks, all of them (an answer goes to the track that matches
    it best, asked about or not); ``answers``: the clip's cad_selection answers in force over all
    tasks; ``tasks``: its ``label_tasks`` rows. Tracks without are absent."""
    answered = {int(r["track_id"]) for r in answers.to_pylist() if r["task_id"] == task_id}
    taken = taken_answers(earlier_answers(answers, tasks, "cad_selection", task_id), set(now) | set(candidates),
                          lambda t, e: same_object(item_boxes(e[1]), now.get(t, {})))
    out = {}
    for t, cads in candidates.items():
        if t in answered or t not in taken:
            continue
        newest = taken[t][0][0][0]  # the newest answer's row decides
        if newest["cad_id"] is not None and newest["cad_id"] in cads:
            out[t] = newest["cad_id"]
    return out
