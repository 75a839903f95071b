"""What the human-task stages read besides their upstream outputs, as digests.

People's answers in force (:func:`tasks.human.answers_in_force.answers_digest`): ingesting labels makes
the stage stale, and a rerun resumes it. After ``manual_tracks``, also the tracks its answer leaves
out (said to be no object, or another track: :func:`tasks.tracking.relations.left_out_digest`).
Kept apart from the stages' modules so that ``cadestate status``, which computes them for every
clip, imports none of the stages' dependencies (:mod:`tasks.registry` imports a declared function
from where the stage's module imports it).
"""

from __future__ import annotations

from cadestate.lineage import digest
from tasks.human.answers_in_force import answers_digest
from tasks.retrieval.label_similarity import similarity_labels
from tasks.tracking.relations import left_out_digest
from warehouse import Warehouse


def manual_track_inputs(wh: Warehouse, clip: str) -> list[str]:
    """The classes of the label similarities, and the answers in force."""
    return [digest(*similarity_labels(wh)), answers_digest(wh, "manual_track", clip)]


def cad_selection_inputs(wh: Warehouse, clip: str) -> list[str]:
    return [answers_digest(wh, "cad_selection", clip), left_out_digest(wh, clip)]


def correspondence_inputs(wh: Warehouse, clip: str) -> list[str]:
    return [answers_digest(wh, "correspondences", clip), left_out_digest(wh, clip)]


def verification_inputs(wh: Warehouse, clip: str) -> list[str]:
    return [answers_digest(wh, "verification", clip), left_out_digest(wh, clip)]
