"""9-DoF pose accuracy, Scan2CAD style (skanti/Scan2CAD ``Routines/Script/EvaluateBenchmark.py``).

An alignment is **correct** when translation error <= 0.20 m, rotation error <= 20 degrees and
scale error <= 20 %, where

- rotation error = 2·arccos(|<q, q_gt>|) in degrees, minimised over ``R_gt · R_y(2πi/m)``,
  i = 0..m-1, m = the ground-truth CAD model's symmetry order about its up axis +Y (1, 2, 4, 36);
- scale error = 100·|mean(s / s_gt) − 1| (per-axis ratios, averaged), with s_gt taken in the
  symmetric version that minimised the rotation error: a 4-way model turned by 90 or 270
  degrees has its x and z scales swapped (:func:`symmetric_scale`);
- translation error = Euclidean distance in metres.

Decisions (not fixed by Scan2CAD, documented and tested here):

- **Mirror flag**: a prediction whose ``is_mirrored`` differs from the ground truth's is
  *incorrect* whatever its errors: a mirrored CAD model has the other chirality, and we do not
  know per model whether it is mirror-symmetric. Its errors are still reported.
- **Class**: the predicted class must equal the ground truth's (Scan2CAD matches per category);
  in ``match="track"`` a wrong class makes the pair incorrect.
- ``match="track"``: our pipeline poses each annotated track, so a prediction is paired with the
  ground-truth object of the same (clip, track_id). ``match="greedy"``: Scan2CAD's rule;
  predictions, by descending score, each take the nearest (in translation) not yet matched
  ground-truth object of their class in their clip *that they align correctly*; a prediction
  that aligns none stays unmatched. Either way each ground-truth object is matched at most once,
  and accuracy = correct ground-truth objects / all posed ground-truth objects.
- Instance mean: over all ground-truth objects. Class mean: mean over classes (with at least one
  ground-truth object) of the per-class accuracy.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np

from schemas.official import ObjectsFile

MAX_TRANSLATION_M = 0.20
MAX_ROTATION_DEG = 20.0
MAX_SCALE_PCT = 20.0

_SCAN2CAD_TAGS = {"__SYM_NONE": 1, "__SYM_ROTATE_UP_2": 2, "__SYM_ROTATE_UP_4": 4, "__SYM_ROTATE_UP_INF": 36}


def symmetry_order(symmetry: int | str | None) -> int:
    """Rotational symmetry order m about +Y: an int (1, 2, 4, 36; <= 1 means none) or a Scan2CAD tag."""
    if symmetry is None:
        return 1
    if isinstance(symmetry, str):
        if symmetry not in _SCAN2CAD_TAGS:
            raise ValueError(f"unknown symmetry tag {symmetry!r}; expected one of {sorted(_SCAN2CAD_TAGS)}")
        return _SCAN2CAD_TAGS[symmetry]
    return max(1, int(symmetry))


def _normalise(q) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64).reshape(4)
    n = np.linalg.norm(q)
    if not n > 0:
        raise ValueError(f"not a quaternion: {q}")
    return q / n


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products of quaternions (w, x, y, z): float[..., 4] x float[..., 4] -> float[..., 4]."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], -1)


def symmetric_rotation_error(q, q_gt, symmetry: int | str | None = 1) -> tuple[float, int]:
    """(angle in degrees, i): the angle between rotations q and q_gt (float[4], (w, x, y, z)),
    minimised over the symmetric versions ``q_gt · q_y(2πi/m)`` of the ground truth (rotation
    about the object's +Y), and the i that attains it."""
    q, q_gt = _normalise(q), _normalise(q_gt)
    m = symmetry_order(symmetry)
    half = np.pi * np.arange(m) / m  # half of 2πi/m
    q_sym = np.stack([np.cos(half), np.zeros(m), np.sin(half), np.zeros(m)], -1)  # float[m, 4]
    candidates = _qmul(q_gt[None], q_sym)
    dots = np.clip(np.abs(candidates @ q), 0.0, 1.0)
    i = int(dots.argmax())
    return float(np.degrees(2.0 * np.arccos(dots[i]))), i


def rotation_error_deg(q, q_gt, symmetry: int | str | None = 1) -> float:
    """Angle in degrees between rotations q and q_gt, minimised over the ground truth's symmetric
    versions (see :func:`symmetric_rotation_error`)."""
    return symmetric_rotation_error(q, q_gt, symmetry)[0]


def symmetric_scale(s_gt, symmetry: int | str | None, index: int) -> np.ndarray:
    """The ground-truth scale float[3] (sx, sy, sz) expressed in the symmetric version ``index`` of
    :func:`symmetric_rotation_error`: for a 4-way model turned by 90 or 270 degrees about +Y the CAD
    x and z axes trade places, so (sx, sy, sz) -> (sz, sy, sx) (R_y(90) diag(a, b, c) R_y(-90) =
    diag(c, b, a)); unchanged otherwise (2-way: 180 degrees keeps the axes; 36-way: sx = sz)."""
    s_gt = np.asarray(s_gt, dtype=np.float64).reshape(3)
    return s_gt[[2, 1, 0]] if symmetry_order(symmetry) == 4 and index % 2 == 1 else s_gt


def translation_error(t, t_gt) -> float:
    """Euclidean distance (metres) between float[3] translations."""
    return float(np.linalg.norm(np.asarray(t, dtype=np.float64) - np.asarray(t_gt, dtype=np.float64)))


def scale_error_pct(s, s_gt) -> float:
    """100·|mean(s / s_gt) − 1| for float[3] scales (per-axis ratios, averaged)."""
    ratio = np.asarray(s, dtype=np.float64) / np.asarray(s_gt, dtype=np.float64)
    return float(100.0 * abs(ratio.mean() - 1.0))


def is_correct(t, q, s, t_gt, q_gt, s_gt, symmetry: int | str | None = 1, *, mirrored: bool = False,
               mirrored_gt: bool = False, max_translation: float = MAX_TRANSLATION_M,
               max_rotation: float = MAX_ROTATION_DEG, max_scale: float = MAX_SCALE_PCT) -> bool:
    """Scan2CAD criterion (all three errors within threshold) plus an equal mirror flag."""
    re, i = symmetric_rotation_error(q, q_gt, symmetry)
    return (mirrored == mirrored_gt and translation_error(t, t_gt) <= max_translation
            and re <= max_rotation and scale_error_pct(s, symmetric_scale(s_gt, symmetry, i)) <= max_scale)


@dataclass(frozen=True)
class PosedObject:
    """One posed object (prediction or ground truth): pose translation float[3] (m), rotation
    float[4] (w, x, y, z), scale float[3]; ``score`` orders predictions in greedy matching."""

    track_id: str
    cls: str
    translation: tuple[float, float, float]
    rotation: tuple[float, float, float, float]
    scale: tuple[float, float, float]
    is_mirrored: bool = False
    cad_id: str | None = None
    clip: str = ""
    score: float = 1.0

    @property
    def key(self) -> tuple[str, str]:
        return (self.clip, self.track_id)


def posed_objects(objects: ObjectsFile) -> list[PosedObject]:
    """The posed objects of an official ``objects.json`` (objects without a pose are left out)."""
    return [PosedObject(o.track_id, o.cls, o.translation, o.rotation, o.scale, o.is_mirrored, o.cad_id,
                        objects.clip_name) for o in objects.objects if o.translation is not None]


@dataclass(frozen=True)
class PoseMatch:
    """A (ground truth, prediction) pair with its errors; ``correct`` per the module's rules."""

    gt: PosedObject
    pred: PosedObject
    translation_error: float
    rotation_error_deg: float
    scale_error_pct: float
    mirror_ok: bool
    class_ok: bool
    correct: bool


@dataclass(frozen=True)
class ClassRow:
    cls: str
    num_gt: int
    num_correct: int

    @property
    def accuracy(self) -> float:
        return self.num_correct / self.num_gt if self.num_gt else float("nan")


@dataclass(frozen=True)
class PoseReport:
    """Accuracies in [0, 1]; ``per_class`` sorted by class; ``unmatched_predictions`` = false positives."""

    instance_accuracy: float
    class_accuracy: float
    num_gt: int
    num_predictions: int
    num_correct: int
    per_class: tuple[ClassRow, ...]
    matches: tuple[PoseMatch, ...] = field(repr=False)
    unmatched_predictions: tuple[PosedObject, ...] = field(repr=False)

    def as_dict(self) -> dict:
        return {"instance_accuracy": self.instance_accuracy, "class_accuracy": self.class_accuracy,
                "num_gt": self.num_gt, "num_predictions": self.num_predictions, "num_correct": self.num_correct,
                "false_positives": len(self.unmatched_predictions),
                "per_class": {r.cls: {"num_gt": r.num_gt, "num_correct": r.num_correct, "accuracy": r.accuracy}
                              for r in self.per_class}}

    def markdown(self) -> str:
        rows = ["| class | GT objects | correct | accuracy |", "|---|---:|---:|---:|"]
        rows += [f"| {r.cls} | {r.num_gt} | {r.num_correct} | {100 * r.accuracy:.1f} % |" for r in self.per_class]
        rows.append(f"| **class mean** | {self.num_gt} | {self.num_correct} | {100 * self.class_accuracy:.1f} % |")
        rows.append(f"| **instance mean** | {self.num_gt} | {self.num_correct} | {100 * self.instance_accuracy:.1f} % |")
        return "\n".join(rows)


Symmetries = Mapping[str, int | str] | Callable[[PosedObject], int | str | None] | None


def _symmetry_of(gt: PosedObject, symmetries: Symmetries) -> int:
    if symmetries is None:
        return 1
    if callable(symmetries):
        return symmetry_order(symmetries(gt))
    return symmetry_order(symmetries.get(gt.cad_id, 1) if gt.cad_id is not None else 1)


def _pair(gt: PosedObject, pred: PosedObject, symmetry: int, require_class: bool) -> PoseMatch:
    te = translation_error(pred.translation, gt.translation)
    re, i = symmetric_rotation_error(pred.rotation, gt.rotation, symmetry)
    se = scale_error_pct(pred.scale, symmetric_scale(gt.scale, symmetry, i))
    mirror_ok = pred.is_mirrored == gt.is_mirrored
    class_ok = pred.cls == gt.cls or not require_class
    ok = mirror_ok and class_ok and te <= MAX_TRANSLATION_M and re <= MAX_ROTATION_DEG and se <= MAX_SCALE_PCT
    return PoseMatch(gt, pred, te, re, se, mirror_ok, class_ok, ok)


def match_and_score(predictions: Iterable[PosedObject], ground_truth: Iterable[PosedObject],
                    symmetries: Symmetries = None, match: str = "track", require_class: bool = True) -> PoseReport:
    """Match predictions to ground-truth objects and score them (see the module docstring).

    ``symmetries``: the ground-truth CAD model's symmetry order, as a mapping cad_id -> order
    (1/2/4/36 or Scan2CAD tag; missing = 1) or a function of the ground-truth object.
    ``match``: "track" (by (clip, track_id)) or "greedy" (Scan2CAD).
    """
    preds, gts = list(predictions), list(ground_truth)
    if len({g.key for g in gts}) != len(gts):
        raise ValueError("ground truth has duplicate (clip, track_id) keys")
    matches: list[PoseMatch] = []
    used_preds: set[int] = set()
    if match == "track":
        by_key: dict[tuple[str, str], int] = {}
        for i, p in enumerate(preds):
            if p.key in by_key:
                raise ValueError(f"two predictions for track {p.key}; match='track' needs one per track")
            by_key[p.key] = i
        for g in gts:
            if g.key in by_key:
                used_preds.add(by_key[g.key])
                matches.append(_pair(g, preds[by_key[g.key]], _symmetry_of(g, symmetries), require_class))
    elif match == "greedy":
        taken: set[int] = set()
        for i in sorted(range(len(preds)), key=lambda i: -preds[i].score):
            p = preds[i]
            best: PoseMatch | None = None
            best_j = -1
            for j, g in enumerate(gts):
                if j in taken or g.clip != p.clip or g.cls != p.cls:
                    continue
                pair = _pair(g, p, _symmetry_of(g, symmetries), True)
                if pair.correct and (best is None or pair.translation_error < best.translation_error):
                    best, best_j = pair, j
            if best is not None:
                taken.add(best_j)
                used_preds.add(i)
                matches.append(best)
    else:
        raise ValueError(f"match must be 'track' or 'greedy', not {match!r}")
    correct_keys = {m.gt.key for m in matches if m.correct}
    classes = sorted({g.cls for g in gts})
    per_class = tuple(ClassRow(c, sum(g.cls == c for g in gts), sum(g.cls == c and g.key in correct_keys for g in gts))
                      for c in classes)
    num_correct = len(correct_keys)
    return PoseReport(
        instance_accuracy=num_correct / len(gts) if gts else float("nan"),
        class_accuracy=float(np.mean([r.accuracy for r in per_class])) if per_class else float("nan"),
        num_gt=len(gts), num_predictions=len(preds), num_correct=num_correct, per_class=per_class,
        matches=tuple(matches), unmatched_predictions=tuple(p for i, p in enumerate(preds) if i not in used_preds))

