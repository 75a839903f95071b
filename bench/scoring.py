"""Scoring modes of ``bench report``: what "correct" means, each named for what it is.

Every mode scores *every* prediction it is given (each accepted track of the pipeline; a clip
may have several tracks on one object) against the posed ground-truth objects of the same clip,
with the Scan2CAD thresholds (translation <= 0.20 m, rotation <= 20 degrees, scale <= 20 %; world
frame, metres; rotations (w, x, y, z) CAD -> world; scales along the CAD axes). A ground-truth
object is credited at most once; accuracy = credited objects / all posed ground-truth objects
(instance mean) and the mean over classes of the per-class accuracy (class mean).

``pose``
    The pose alone. Each prediction belongs to the ground-truth object its track follows (a map
    from the 2D track match, :func:`bench.retrieval_bench.track_truth`); the object is credited
    when *any* of its tracks is correct by :func:`bench.eval_pose.is_correct` (mirror flags
    equal; 4-way models turned by 90 degrees compare x/z-swapped scales). Further tracks on an
    object are ``duplicates``; tracks on no object are ``false_positives``. Neither the class
    nor the CAD model is checked.
``scan2cad-class``
    The Scan2CAD benchmark as its paper states it: a prediction counts only against ground-truth
    objects of its class, in 3D (no track map): in prediction order, each takes the first
    not-yet-credited object of its class that it aligns within the thresholds. Symmetry: the
    ground-truth model's order (rotation error minimised over ``q_gt · R_y(2πi/m)``); scales are
    compared as they are (no swap); the mirror flag is not looked at.
``scan2cad-exact``
    Scan2CAD's evaluation script (``Routines/Script/EvaluateBenchmark.py``): as
    ``scan2cad-class``, but a prediction whose CAD model (a mirrored model is a CAD model of its
    own: :func:`tasks.dataset.export_scan2cad.scan2cad_cad_id`) does not appear among the clip's ground-truth
    objects is dropped, and each model is used by at most as many predictions as the ground truth
    has objects of it; the symmetry is the predicted model's (as the script reads it).

In the Scan2CAD modes, an unmatched prediction that aligns an object already credited is a
``duplicate`` (in ``scan2cad-exact``, only with that object's model, by its own symmetry: a model
the mode dropped came back as a correct duplicate), any other unmatched one a
``false_positive``. The dataset's yield scores them *by track* (``by_track``): a prediction whose track follows an object is matched against that object
alone, as the dataset publishes it (that track's pose); in 3D alone a chair's pose that landed on
the chair beside it credited that one, though its own track had none.

Scales: a pose's scale multiplies its own model's size (the library's models are in metres, where
Scan2CAD's ShapeNet models are normalised, so that a scale there is the object's size). A
prediction of another model than the ground truth's is compared by the sizes it gives in the
world: its scale is first brought to the ground-truth model's units, ``s * extent_pred /
extent_gt`` (``extents``: cad_id -> bounding-box size; the same model is compared as it is).

Every mode also says, per prediction, which ground-truth object it is *on* and whether it is
correct (:class:`Outcome`, the input of the dataset's yield, :mod:`bench.dataset_yield`): in
``pose`` the object its track follows (correct or not); in the Scan2CAD modes the object it is
credited with, or for a duplicate the credited object it aligns (both correct); a false positive
is on the object its track follows (not correct: a wrong second pose on an object leaves the
object unyielded and is a duplicate of the dataset, not a false annotation), or on no object
when its track follows none.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import dataclasses

import numpy as np

from bench.eval_pose import (MAX_ROTATION_DEG, MAX_SCALE_PCT, MAX_TRANSLATION_M, PosedObject, is_correct,
                             rotation_error_deg, scale_error_pct, translation_error)
from tasks.dataset.export_scan2cad import scan2cad_cad_id

MODES = ("pose", "scan2cad-class", "scan2cad-exact")

Key = tuple[str, str]
"""(clip, track id): a prediction's or a ground-truth object's."""


@dataclass(frozen=True)
class Outcome:
    """One prediction scored: the ground-truth object it is on (None: none) and whether it is correct."""

    prediction: Key
    on_object: Key | None
    correct: bool


@dataclass(frozen=True)
class ModeResult:
    """One mode's score. Accuracies in [0, 1] (nan without ground truth); ``per_class`` maps a
    class to (ground-truth objects, credited objects)."""

    mode: str
    num_gt: int
    num_predictions: int
    num_correct: int
    duplicates: int
    false_positives: int
    per_class: dict[str, tuple[int, int]]
    outcomes: tuple[Outcome, ...] = ()

    @property
    def instance_accuracy(self) -> float:
        return self.num_correct / self.num_gt if self.num_gt else float("nan")

    @property
    def class_accuracy(self) -> float:
        return float(np.mean([c / n for n, c in self.per_class.values()])) if self.per_class else float("nan")

    def as_dict(self) -> dict:
        pct = lambda v: None if v != v else round(100 * v, 1)  # noqa: E731
        return {"ground_truth": self.num_gt, "predictions": self.num_predictions, "correct": self.num_correct,
                "instance_accuracy_pct": pct(self.instance_accuracy), "class_accuracy_pct": pct(self.class_accuracy),
                "duplicates": self.duplicates, "false_positives": self.false_positives}


def _result(mode: str, gts: list[PosedObject], credited: set[tuple[str, str]], predictions: int, duplicates: int,
            false_positives: int, outcomes: list[Outcome]) -> ModeResult:
    per_class: dict[str, tuple[int, int]] = {}
    for g in gts:
        n, c = per_class.get(g.cls, (0, 0))
        per_class[g.cls] = (n + 1, c + (g.key in credited))
    return ModeResult(mode, len(gts), predictions, len(credited), duplicates, false_positives,
                      dict(sorted(per_class.items())), tuple(outcomes))


def _symmetry(symmetries: Mapping[str, int], cad_id: str | None) -> int:
    return int(symmetries.get(cad_id, 1)) if cad_id is not None else 1


def in_truth_units(p: PosedObject, g: PosedObject, extents: Mapping[str, tuple] | None) -> PosedObject:
    """``p`` with its scale in the units of ``g``'s model (module docstring: scales); as it is for
    the same model, or when an extent is unknown."""
    if not extents or p.cad_id == g.cad_id:
        return p
    mine, theirs = extents.get(p.cad_id), extents.get(g.cad_id)
    if mine is None or theirs is None or min(theirs) <= 0:
        return p
    return dataclasses.replace(p, scale=tuple(float(s) * a / b for s, a, b in zip(p.scale, mine, theirs)))


def score_pose(predictions: Iterable[PosedObject], ground_truth: Iterable[PosedObject], truth: Mapping[tuple[str, str], str],
               symmetries: Mapping[str, int], extents: Mapping[str, tuple] | None = None) -> ModeResult:
    """Mode ``pose``. ``truth``: (clip, predicted track id) -> ground-truth track id of that clip."""
    preds, gts = list(predictions), list(ground_truth)
    by_key = {g.key: g for g in gts}
    credited: set[tuple[str, str]] = set()
    on_object: Counter[tuple[str, str]] = Counter()
    false_positives = 0
    outcomes = []
    for p in preds:
        g = by_key.get((p.clip, truth.get(p.key, "")))
        if g is None:
            false_positives += 1
            outcomes.append(Outcome(p.key, None, False))
            continue
        on_object[g.key] += 1
        p = in_truth_units(p, g, extents)
        ok = is_correct(p.translation, p.rotation, p.scale, g.translation, g.rotation, g.scale,
                        _symmetry(symmetries, g.cad_id), mirrored=p.is_mirrored, mirrored_gt=g.is_mirrored)
        if ok:
            credited.add(g.key)
        outcomes.append(Outcome(p.key, g.key, ok))
    duplicates = sum(n - 1 for n in on_object.values())
    return _result("pose", gts, credited, len(preds), duplicates, false_positives, outcomes)


def _aligns(p: PosedObject, g: PosedObject, symmetry: int, extents: Mapping[str, tuple] | None = None) -> bool:
    """Scan2CAD's test: translation, symmetric rotation and unswapped scale errors within thresholds."""
    p = in_truth_units(p, g, extents)
    return (translation_error(p.translation, g.translation) <= MAX_TRANSLATION_M
            and rotation_error_deg(p.rotation, g.rotation, symmetry) <= MAX_ROTATION_DEG
            and scale_error_pct(p.scale, g.scale) <= MAX_SCALE_PCT)


def _model(o: PosedObject) -> str:
    """The CAD model of ``o`` as Scan2CAD names it (a mirrored model is one of its own)."""
    return scan2cad_cad_id(o.cad_id or "", o.is_mirrored)


def score_scan2cad(predictions: Iterable[PosedObject], ground_truth: Iterable[PosedObject], symmetries: Mapping[str, int],
                   exact: bool, truth: Mapping[tuple[str, str], str] | None = None,
                   extents: Mapping[str, tuple] | None = None, by_track: bool = False) -> ModeResult:
    """Mode ``scan2cad-exact`` (``exact``) or ``scan2cad-class``; predictions in the order given;
    ``truth`` (the track map of :func:`score_pose`) places a false positive on its track's object.
    ``by_track``: a prediction whose track follows an object is matched against that object alone
    (the dataset's record of a track: the yield), not the first of its class it aligns in 3D."""
    preds, gts = list(predictions), list(ground_truth)
    open_gt: dict[tuple[str, str], list[PosedObject]] = {}
    for g in gts:
        open_gt.setdefault((g.clip, g.cls), []).append(g)
    allowed = Counter((g.clip, g.cls, _model(g)) for g in gts)
    used: Counter[tuple[str, str, str]] = Counter()
    credited_objects: list[PosedObject] = []
    unmatched: list[PosedObject] = []
    outcomes = []
    for p in preds:
        model = (p.clip, p.cls, _model(p))
        if exact:
            if used[model] >= allowed[model]:
                unmatched.append(p)
                continue
            used[model] += 1
        candidates = open_gt.get((p.clip, p.cls), [])
        followed = _followed(p, truth, by_track)
        hit = next((g for g in candidates if (followed is None or g.key == followed)
                    and _aligns(p, g, _symmetry(symmetries, p.cad_id if exact else g.cad_id), extents)), None)
        if hit is None:
            unmatched.append(p)
            continue
        candidates.remove(hit)
        credited_objects.append(hit)
        outcomes.append(Outcome(p.key, hit.key, True))
    duplicates = 0
    known = {g.key for g in gts}
    for p in unmatched:
        followed = _followed(p, truth, by_track)
        aligned = next((g for g in credited_objects if g.clip == p.clip and g.cls == p.cls
                        and (followed is None or g.key == followed)
                        and (not exact or _model(p) == _model(g))
                        and _aligns(p, g, _symmetry(symmetries, p.cad_id if exact else g.cad_id), extents)), None)
        duplicates += aligned is not None
        tracked = (p.clip, (truth or {}).get(p.key, ""))
        on = aligned.key if aligned is not None else (tracked if tracked in known else None)
        outcomes.append(Outcome(p.key, on, aligned is not None))
    return _result("scan2cad-exact" if exact else "scan2cad-class", gts, {g.key for g in credited_objects}, len(preds),
                   duplicates, len(unmatched) - duplicates, outcomes)


def _followed(p: PosedObject, truth: Mapping[tuple[str, str], str] | None, by_track: bool) -> Key | None:
    """The object ``p``'s track follows, when matching ``by_track`` (None: any object of its class)."""
    gt_id = (truth or {}).get(p.key) if by_track else None
    return (p.clip, gt_id) if gt_id else None


def score_all(predictions: list[PosedObject], ground_truth: list[PosedObject], truth: Mapping[tuple[str, str], str],
              symmetries: Mapping[str, int], extents: Mapping[str, tuple] | None = None,
              by_track: bool = False) -> dict[str, ModeResult]:
    """Every mode of :data:`MODES` on the same predictions (ordered by clip, then track id);
    ``by_track``: the Scan2CAD modes match a prediction on a track that follows an object against
    that object alone (:func:`score_scan2cad`)."""
    ordered = sorted(predictions, key=lambda p: (p.clip, int(p.track_id) if p.track_id.isdigit() else 0, p.track_id))
    return {"pose": score_pose(ordered, ground_truth, truth, symmetries, extents),
            "scan2cad-class": score_scan2cad(ordered, ground_truth, symmetries, False, truth, extents, by_track),
            "scan2cad-exact": score_scan2cad(ordered, ground_truth, symmetries, True, truth, extents, by_track)}
