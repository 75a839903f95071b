"""Which benchmark seeds have been looked at while choosing something, and which one is fresh.

A number measured on a benchmark that a knob was chosen on flatters the knob. So the benchmark's
report says, for its seed, whether it is in :data:`USED_SEEDS` (seen while tuning, fitting or
deciding: its numbers may flatter) or is :data:`FRESH_SEED`, the seed ``make bench`` generates
with the same command as every other benchmark (``cadestate bench generate --seed S --clips 8``)
and that nothing has been chosen on. Whoever tunes on the fresh seed adds it here with what was
chosen, and picks a new :data:`FRESH_SEED` (a test holds that it is not among the used ones, and
that it is the Makefile's ``FRESH_SEED``). The detector's and descriptor's training rooms have
scene seeds from ``bench.descriptor_data.TRAIN_SEED_BASE`` on, far from any benchmark's.
"""

from __future__ import annotations

DEFAULT_SEED = 20261123
"""The default benchmark's seed (``make bench``, ``cadestate bench generate`` without ``--seed``)."""

FRESH_SEED = 3000017
"""The benchmark seed ``make bench`` reports beside the default one: never used while tuning."""

USED_SEEDS: dict[int, str] = {
    DEFAULT_SEED: "the default benchmark: most knobs were measured on it since the first stop",
    60606: "world-up tolerance, the simulated verifier's rule (its failures studied), NMS across classes, "
           "retrieval's max_per_class, the detector's fine-tuning steps, "
           "the shadow rule's score condition",
    424242: "world-up tolerance, retrieval's class_exponent",
    271828: "world-up tolerance, retrieval's class_exponent, the narrow-axis prior, retrieval's max_per_class",
    314159: "world-up tolerance, retrieval's class_exponent",
    8675309: "world-up and tracking checks, the narrow-axis prior, retrieval's max_per_class",
    1729: "reported fresh by stop 41, then the narrow-axis prior and retrieval's max_per_class",
    4711: "hard axis ties against the narrow-axis prior",
    8128: "reported fresh by stop 42; its yield was one reason the narrow-axis prior is off by default",
    30307: "fresh until its misnamed bathtub and kitchen island suggested retrieval's class cap (max_per_class)",
    4242: "reported fresh for the pose solver's support prior",
    5150: "reported fresh for the 3D joining of track fragments",
    101: "tracking cue and fragment-joining fits, the shadow-track rule, retrieval's max_per_class, "
         "the detector's fine-tuning steps, the shadow rule's score condition (its lost bed and table studied)",
    31: "tracking cue and fragment-joining fits, the shadow-track rule, retrieval's max_per_class",
    77: "tracking cue and fragment-joining fits, the shadow-track rule, retrieval's max_per_class",
    9137: "tracking cue and fragment-joining fits, the shadow-track rule, retrieval's max_per_class",
    65537: "the detector's rare-class training rooms (not adopted on its yield, stop 54)",
    52711: "make bench's fresh seed until stop 57: its retrieval misses studied, then the descriptor's 6,000 "
           "training steps adopted on its yield",
    90125: "generated in stop 57: its retrieval misses studied, then the descriptor's 6,000 training steps "
           "adopted on its yield",
    8191: "make bench's fresh seed until stop 58: the detector's input canvas (fitted, long side 480) chosen "
          "on its detection curves among 416 square and fitted 416, 448, 480, 512 and 544; since stop 59 a tuning "
          "seed (the fine-tuning's rates and schedules, NMS, shadow thresholds, the weak-track rule, temporal "
          "rescoring; stop 66: the fitted 480 canvas made the default on the yield of seven seeds, this one among them)",
    131071: "generated in stop 58 after the fitted-canvas pick: the square, fitted 416 and fitted 480 canvases "
            "measured end to end on it, and the square kept as the default; since stop 59 a tuning seed (as 8191; "
            "stop 65: the pose solver's proportion prior weighed on both; stop 66: the fitted 480 canvas chosen "
            "on the yield of seven seeds, this one among them)",
    524287: "make bench's fresh seed until stop 65: its wrong poses studied (a wardrobe accepted 0 cm deep) "
            "before the pose solver's proportion prior was chosen on the tuning seeds; stop 66: one of the seven "
            "seeds the fitted 480 canvas was chosen on",
    6700417: "generated in stop 63 to judge temporal rescoring of detections (not adopted); its lost bookshelf studied; "
             "stop 65: its wrong poses studied for the pose solver's proportion prior; stop 66: one of the seven "
             "seeds the fitted 480 canvas was chosen on",
    2147483647: "generated in stop 63 to judge temporal rescoring of detections (not adopted); stop 64 judged "
                "the drawn class exponent and the descriptor's training rooms on it; stop 65: its wrong poses studied "
                "for the pose solver's proportion prior; stop 66: one of the seven seeds the fitted 480 canvas "
                "was chosen on",
    5550001: "generated in stop 72 at 1920 x 1080 to judge an antialiased shrink of the detector's input (not adopted)",
    3000101: "generated in stop 78 (2 clips): SfM's world scale measured on it, and the room depth that brings it "
             "to metres (tasks.video.sfm.ROOM_DEPTH_M) chosen with it; stop 79: its focal length 18 % off studied "
             "for SfM's remapping ([cameras] focal_remaps)",
    3000201: "generated in stop 79 (8 clips): SfM's focal length on each, one 38 % off studied for SfM's remapping "
             "([cameras] focal_remaps, its cap of 2 remaps)",
    3000301: "generated in stop 79 (8 clips): SfM's focal length before and after its remapping, measured once, "
             "not tuned on",
    999983: "generated in stop 64 to judge the drawn class exponent and the descriptor's training rooms; stop 65: "
            "its wrong poses studied for the pose solver's proportion prior; stop 66: one of the seven seeds the "
            "fitted 480 canvas was chosen on",
}
"""Benchmark seeds whose numbers were seen while something was chosen, and what."""


def seed_note(seed: int) -> str:
    """One line for a benchmark report: whether numbers on ``seed`` may flatter."""
    if seed in USED_SEEDS:
        return f"Seed {seed} was used while tuning ({USED_SEEDS[seed]}): its numbers may flatter; seed {FRESH_SEED} is the fresh one."
    if seed == FRESH_SEED:
        return f"Seed {seed} is the fresh seed: nothing was chosen on it (bench/seeds.py)."
    return f"Seed {seed} is not in bench/seeds.py's record of used seeds: fresh, unless you tuned on it."
