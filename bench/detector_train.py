"""Train the furniture detector: NanoDet-m with class rows for the CAD vocabulary (``make models``).

Two phases: class rows on NanoDet-m's frozen hidden maps (below), then every weight fine-tuned from
there (:mod:`bench.detector_finetune`), which moves the operating point once more.

Rows. NanoDet-m is frozen up to each stride's hidden map, and its box rows stay as they are (its
boxes already fit furniture: for every object of the training rooms some cell's box has IoU >= 0.5
with it). Per stride a new 1x1 class row per furniture class (:data:`FURNITURE_CLASSES`) reads the
hidden map: ``score = sigmoid(w . h + b)``. Rows of classes COCO has start from COCO's row
("sofa" from "couch"), the others at zero with the prior bias. They are trained with Quality Focal
Loss (the loss NanoDet was trained with): a cell on an object should score the object's class
with the IoU of its box, every other score 0 (:mod:`bench.detector_data`). AdamW on one thread
with deterministic algorithms, so the same frames give the same bytes.

Export (:func:`tasks.detection.models.nanodet_head.with_class_rows`): the learned rows, then COCO's
rows for the COCO labels that stand for none of the classes, form the label map
:data:`FURNITURE_LABELS`; every other weight is NanoDet-m's until the fine-tuning. The file goes
beside NanoDet-m with a JSON file: label map, SHA-256 (the detector is checked against it before
use), the recipe digest, and the held-out reports (rows, then fine-tuned): recall and precision on
every sixth room (never trained on), matched as the benchmark matches (IoU 0.5; NMS as
``[detect]`` does it).

Operating point: of :data:`OPERATING_THRESHOLDS`, the lowest score threshold at which the detector
is at least as precise on the held-out rooms as NanoDet-m's own rows are there at
``[detect] score_threshold`` (:func:`operating_threshold`) is moved onto that threshold (0.35) by
shifting the learned rows' biases by ``logit(0.35) - logit(threshold)``: one default threshold
serves both built-in detectors, and the new rows buy recall, not false boxes.

Data: frames of :mod:`bench.detector_data`, rendered on every core (:mod:`bench.room_pool`) and kept
beside the model per (seed, rooms, frames, library) since they take ~10 minutes to render. A run
whose recipe equals the file's returns at once.

    python -m bench.detector_train --warehouse W --out MODELS_DIR [--seed 1] [--rooms 400]

Time on 2 cores, the first time: rendering ~10 minutes, rows ~5, fine-tuning 19-26 (by CPU).
"""

from __future__ import annotations

import functools
import json
import sys
import time
from contextlib import ExitStack
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from bench.detector_data import FrameSet, room_frames
from bench.room_pool import default_workers, map_rooms
from bench.training_cli import training_main
from cadestate.atomic import atomic_write_bytes
from cadestate.lineage import digest, file_sha256
from cadestate.progress import progress
from tasks.detection.models.furniture_files import COCO_SOURCE, FURNITURE_CLASSES, FURNITURE_LABELS, META_NAME, ONNX_NAME
from tasks.detection.models.nanodet_files import COCO_LABELS
from warehouse import Warehouse

PRIOR_BIAS = -4.595
"""Bias of a row without a COCO source: sigmoid = 0.01, NanoDet's prior."""
OPERATING_THRESHOLDS = (0.3, 0.35, 0.4, 0.45, 0.5, 0.55, 0.6)
"""Score thresholds tried on the held-out rooms for the operating point (:func:`operating_threshold`)."""


@dataclass(frozen=True)
class TrainSpec:
    """What to train: ``rooms`` rendered rooms (every ``holdout_every``-th held out) of ``frames``
    frames, ``steps`` AdamW steps of ``batch`` frames at ``lr`` for the rows, then
    ``finetune_steps`` of ``finetune_batch`` frames at ``finetune_lr`` for every weight (boxes of
    cells on objects trained towards them with weights ``box_giou`` and ``box_dfl``, the other
    cells' box distributions held to the start's with weight ``box_distill``:
    :mod:`bench.detector_finetune`); ``score_threshold``, ``nms_iou``
    and ``nms_containment``: the ``[detect]`` defaults the detector is evaluated and calibrated at."""

    seed: int = 1
    rooms: int = 400
    frames: int = 8
    holdout_every: int = 6
    steps: int = 3000
    batch: int = 16
    lr: float = 3e-3
    weight_decay: float = 1e-4
    beta: float = 2.0
    finetune_steps: int = 800
    finetune_batch: int = 8
    finetune_lr: float = 1e-4
    box_distill: float = 1.0
    box_giou: float = 2.0
    box_dfl: float = 0.25
    score_threshold: float = 0.35
    nms_iou: float = 0.45
    nms_containment: float = 0.8


def _room_state(wh_root: Path, coco_onnx: Path, stack: ExitStack) -> tuple:
    """One process's (library rows, warehouse root, trunk session, renderer) for :func:`_room`."""
    import onnx

    from cadestate.render import Renderer
    from tasks.detection.models.nanodet_head import trunk_model
    from tasks.detection.onnx_session import load_session

    models = Warehouse(wh_root).read("cad_models").to_pylist()
    trunk = load_session(trunk_model(onnx.load(str(coco_onnx))).SerializeToString())
    return models, wh_root, trunk, stack.enter_context(Renderer(640, 360, 2))


def _room(spec: TrainSpec, state: tuple, room: int) -> FrameSet:
    models, wh_root, trunk, renderer = state
    return room_frames(spec.seed, room, models, wh_root, trunk, renderer, spec.frames)


def render_frames(wh: Warehouse, coco_onnx: Path, spec: TrainSpec, show_progress: bool = True,
                  workers: int | None = None) -> FrameSet:
    """The frames of every training room (:func:`bench.detector_data.room_frames`), rendered on
    ``workers`` processes (default: one per core; :mod:`bench.room_pool`)."""
    parts = map_rooms(functools.partial(_room_state, wh.root, coco_onnx), functools.partial(_room, spec),
                      range(spec.rooms), default_workers() if workers is None else workers, "detector rooms", show_progress)
    return FrameSet.concatenate(parts)


def stride_slices() -> list[slice]:
    """The cells of strides 8, 16 and 32 in a frame's 3549 cells."""
    from tasks.detection.models import nanodet

    sizes = [(nanodet.SIZE // s) ** 2 for s in nanodet.STRIDES]
    ends = np.cumsum(sizes)
    return [slice(int(e - n), int(e)) for e, n in zip(ends, sizes)]


def initial_rows(coco_rows: list[tuple[np.ndarray, np.ndarray]]) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per stride, the furniture rows to start from: COCO's row of the class's source, else zero
    weights and the prior bias."""
    out = []
    for w, b in coco_rows:
        W = np.zeros((len(FURNITURE_CLASSES), w.shape[1]), np.float32)
        B = np.full(len(FURNITURE_CLASSES), PRIOR_BIAS, np.float32)
        for i, c in enumerate(FURNITURE_CLASSES):
            if c in COCO_SOURCE:
                j = COCO_LABELS.index(COCO_SOURCE[c])
                W[i], B[i] = w[j], b[j]
        out.append((W, B))
    return out


def full_rows(furniture: list[tuple[np.ndarray, np.ndarray]], coco_rows: list[tuple[np.ndarray, np.ndarray]]
              ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per stride, the rows of the whole label map :data:`FURNITURE_LABELS`: furniture, then COCO's rest."""
    rest = [COCO_LABELS.index(label) for label in FURNITURE_LABELS[len(FURNITURE_CLASSES):]]
    return [(np.concatenate([fw, cw[rest]]), np.concatenate([fb, cb[rest]])) for (fw, fb), (cw, cb) in zip(furniture, coco_rows)]


def kept(scores: np.ndarray, boxes: np.ndarray, threshold: float, nms_iou: float, containment: float
         ) -> tuple[np.ndarray, np.ndarray]:
    """One frame's cells (scores float[3549, L] over the whole label map, boxes float[3549, 4]) ->
    the (boxes float[K,4], label indices int[K]) the detector keeps: each cell's best label at or
    above ``threshold``, class-aware NMS (:func:`tasks.detection.detectors.nms`), at most 100."""
    from tasks.detection.detectors import nms

    label = scores.argmax(1)
    best = scores[np.arange(len(label)), label]
    keep = np.flatnonzero(best >= threshold)
    k = keep[nms(boxes[keep].astype(np.float64), best[keep], label[keep], nms_iou, containment)][:100]
    return boxes[k], label[k]


def detections(frames: FrameSet, rows: list[tuple[np.ndarray, np.ndarray]], threshold: float, nms_iou: float,
               containment: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per frame, what the detector with ``rows`` (the whole label map) on the frozen hidden maps
    keeps (:func:`kept`)."""
    out = []
    for f in range(len(frames)):
        scores = np.concatenate([1 / (1 + np.exp(-(frames.hidden[f, sl].astype(np.float32) @ w.T + b)))
                                 for sl, (w, b) in zip(stride_slices(), rows)])
        out.append(kept(scores, frames.boxes[f], threshold, nms_iou, containment))
    return out


def score_found(frames: FrameSet, found: list[tuple[np.ndarray, np.ndarray]]) -> dict:
    """Recall and precision at IoU 0.5 on the furniture classes of what was ``found`` per frame
    (:func:`kept`): the benchmark's matching, :func:`bench.eval_detection.evaluate_detections`
    (ignore regions: objects seen too little)."""
    from bench.eval_detection import FrameBoxes, evaluate_detections

    xyxy_to_yxyx = [1, 0, 3, 2]
    boxes = [FrameBoxes(frames.gt_boxes[frames.gt_frame == f][:, xyxy_to_yxyx],
                        [FURNITURE_CLASSES[c] for c in frames.gt_class[frames.gt_frame == f]],
                        frames.gt_ignore[frames.gt_frame == f], b[:, xyxy_to_yxyx], [FURNITURE_LABELS[i] for i in lab])
             for f, (b, lab) in enumerate(found)]
    result = evaluate_detections(boxes)
    return {k: result[k] for k in ("recall", "precision", "class_agnostic_recall")} | {
        "per_class_recall": {c: v["recall"] for c, v in result["per_class"].items() if v["recall"] is not None}}


def evaluate(frames: FrameSet, rows: list[tuple[np.ndarray, np.ndarray]], threshold: float, nms_iou: float,
             containment: float) -> dict:
    """:func:`score_found` of the detector with ``rows`` on the frozen hidden maps."""
    return score_found(frames, detections(frames, rows, threshold, nms_iou, containment))


def train(frames: FrameSet, coco_rows: list[tuple[np.ndarray, np.ndarray]], spec: TrainSpec, show_progress: bool = True
          ) -> tuple[list[tuple[np.ndarray, np.ndarray]], dict]:
    """The furniture rows per stride trained on the non-held-out rooms, and a report (held-out
    recall and precision of COCO's rows and of the trained ones). Torch on one thread with
    deterministic algorithms (restored afterwards): the same inputs give the same bytes."""
    import torch

    threads, deterministic = torch.get_num_threads(), torch.are_deterministic_algorithms_enabled()
    torch.set_num_threads(1)
    torch.use_deterministic_algorithms(True)
    try:
        return _train(torch, frames, coco_rows, spec, show_progress)
    finally:
        torch.set_num_threads(threads)
        torch.use_deterministic_algorithms(deterministic)


def held_out(frames: FrameSet, spec: TrainSpec) -> np.ndarray:
    """bool[F]: the frames of every ``holdout_every``-th room, never trained on."""
    return (frames.rooms % spec.holdout_every) == spec.holdout_every - 1


def _train(torch, frames: FrameSet, coco_rows, spec: TrainSpec, show_progress: bool):
    torch.manual_seed(spec.seed)
    held = held_out(frames, spec)
    train_idx, held_idx = np.flatnonzero(~held), np.flatnonzero(held)
    start = initial_rows(coco_rows)
    params = [(torch.nn.Parameter(torch.tensor(w)), torch.nn.Parameter(torch.tensor(b))) for w, b in start]
    optimiser = torch.optim.AdamW([p for pair in params for p in pair], lr=spec.lr, weight_decay=spec.weight_decay)
    generator = torch.Generator().manual_seed(spec.seed)
    slices, k = stride_slices(), len(FURNITURE_CLASSES)
    losses = []
    for _ in progress(range(spec.steps), total=spec.steps, description="training", enabled=show_progress):
        pick = np.sort(train_idx[torch.randint(len(train_idx), (spec.batch,), generator=generator).numpy()])
        hidden = torch.from_numpy(frames.hidden[pick].astype(np.float32))
        target = torch.from_numpy(frames.target[pick].astype(np.int64))
        quality = torch.from_numpy(frames.quality[pick].astype(np.float32))
        logits = torch.cat([hidden[:, sl] @ w.T + b for sl, (w, b) in zip(slices, params)], 1)  # [B, 3549, k]
        wanted = torch.zeros_like(logits)
        pos = target >= 0
        wanted[pos, target[pos]] = quality[pos]
        p = torch.sigmoid(logits)
        loss = torch.nn.functional.binary_cross_entropy_with_logits(logits, wanted, reduction="none") * (wanted - p).abs() ** spec.beta
        loss = (loss * (target != -2)[..., None]).sum() / max(int(pos.sum()), 1)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        losses.append(float(loss.detach()))
    trained = [(w.detach().numpy().astype(np.float32), b.detach().numpy().astype(np.float32)) for w, b in params]
    held_set = frames.take(held_idx)
    at = functools.partial(evaluate, held_set, nms_iou=spec.nms_iou, containment=spec.nms_containment)
    coco = at(full_rows(start, coco_rows), spec.score_threshold)
    by_threshold = {t: at(full_rows(trained, coco_rows), t) for t in OPERATING_THRESHOLDS}
    operating = operating_threshold(by_threshold, coco["precision"] or 0.0)
    shift = logit(spec.score_threshold) - logit(operating)
    calibrated = [(w, (b + shift).astype(np.float32)) for w, b in trained]
    report = {
        "train_frames": int(len(train_idx)), "heldout_frames": int(len(held_idx)),
        "heldout_objects": int((~held_set.gt_ignore).sum()),
        "heldout_start": coco,
        "heldout_by_threshold": {str(t): {k: v for k, v in r.items() if k != "per_class_recall"} for t, r in by_threshold.items()},
        "operating_threshold": operating, "bias_shift": round(shift, 4),
        "heldout_after": at(full_rows(calibrated, coco_rows), spec.score_threshold),
        "loss_first_100": round(float(np.mean(losses[:100])), 4), "loss_last_100": round(float(np.mean(losses[-100:])), 4),
    }
    return calibrated, report


def operating_threshold(by_threshold: dict[float, dict], precision: float) -> float:
    """The lowest threshold whose result (:func:`evaluate`) is at least as precise as ``precision``
    (the COCO rows' on the same rooms: never more false boxes per true one than the detector it
    replaces), else the most precise threshold."""
    precise = [t for t, r in sorted(by_threshold.items()) if (r["precision"] or 0.0) >= precision]
    return precise[0] if precise else max(by_threshold, key=lambda t: (by_threshold[t]["precision"] or 0.0, t))


def logit(p: float) -> float:
    """log(p / (1 - p)) for p in (0, 1)."""
    return float(np.log(p / (1 - p)))


DATA_SOURCES = ("bench/detector_data.py", "bench/descriptor_data.py", "bench/scene.py", "bench/room.py", "bench/textures.py",
                "bench/walkthrough.py", "cadestate/render.py", "tasks/detection/models/nanodet_head.py",
                "tasks/detection/models/furniture_files.py")
"""The code that makes the training frames (its bytes key the frames kept beside the model)."""
RECIPE_SOURCES = (*DATA_SOURCES, "bench/detector_train.py", "bench/detector_finetune.py", "bench/onnx_torch.py")
"""The code whose bytes enter the recipe digest (relative to the repository root)."""


def sources_digest(sources: tuple[str, ...]) -> str:
    """Digest of the bytes of ``sources`` (paths relative to the repository root)."""
    root = Path(__file__).resolve().parents[1]
    return digest(*(file_sha256(root / f) for f in sources))


def recipe(spec: TrainSpec, library: str, coco_sha256: str) -> str:
    """Digest of what makes the detector: the spec, :data:`RECIPE_SOURCES`, NanoDet-m's SHA-256 and
    the library's digest."""
    return digest(json.dumps(asdict(spec), sort_keys=True), sources_digest(RECIPE_SOURCES), coco_sha256, library)


def build(wh: Warehouse, out_dir: Path, spec: TrainSpec, show_progress: bool = True) -> Path:
    """Render the training frames (kept beside the output), train, write the detector and its JSON
    file into ``out_dir``; returns the detector's path. Returns at once when the JSON file there
    names the same recipe and the detector's SHA-256."""
    import onnx

    from bench.detector_finetune import calibrate, finetune
    from tasks.detection.models import furniture_files as furniture
    from tasks.detection.models import nanodet
    from tasks.detection.models.nanodet_head import class_rows, with_class_rows
    from tasks.detection.models.tfjs_to_onnx import serialize

    coco_onnx = out_dir / nanodet.ONNX_NAME
    if not nanodet.is_built(out_dir):
        raise SystemExit(f"NanoDet-m is not built in {out_dir}: run `python -m tasks.detection.models.nanodet {out_dir}` first")
    cad_ids = sorted(wh.read("cad_models", columns=["cad_id"]).column("cad_id").to_pylist())
    library = digest(*cad_ids)
    made_by = recipe(spec, library, nanodet.ONNX_SHA256)
    if furniture.is_built(out_dir) and furniture.read_meta(out_dir).get("recipe") == made_by:
        return out_dir / ONNX_NAME
    frames_file = out_dir / f"detector-frames-{digest(library, str(spec.seed), str(spec.rooms), str(spec.frames), sources_digest(DATA_SOURCES))[:16]}.npz"
    t0 = time.perf_counter()
    if frames_file.is_file():
        frames = FrameSet.load(frames_file)
    else:
        print(f"detector: rendering {spec.rooms} training rooms, {spec.frames} frames each (about 10 minutes on 2 cores; "
              f"kept in {frames_file.name})", file=sys.stderr, flush=True)
        frames = render_frames(wh, coco_onnx, spec, show_progress)
        frames.save(frames_file)
    t1 = time.perf_counter()
    print(f"detector: training {len(FURNITURE_CLASSES)} class rows per stride on {len(frames)} frames "
          f"(every {spec.holdout_every}th room held out), {spec.steps} steps (a few minutes)", file=sys.stderr, flush=True)
    model = onnx.load(str(coco_onnx))
    coco_rows = class_rows(model)
    rows, report = train(frames, coco_rows, spec, show_progress)
    report["heldout_rows"] = report.pop("heldout_after")
    t2 = time.perf_counter()
    print(f"detector: fine-tuning every weight, {spec.finetune_steps} steps of {spec.finetune_batch} frames "
          "(about 20 minutes on 2 cores)", file=sys.stderr, flush=True)
    held = held_out(frames, spec)
    tuned, losses = finetune(with_class_rows(model, full_rows(rows, coco_rows)), frames, np.flatnonzero(~held), spec, show_progress)
    final, calibration = calibrate(tuned, frames.take(np.flatnonzero(held)), spec, report["heldout_start"]["precision"] or 0.0)
    data = serialize(final)
    path = out_dir / ONNX_NAME
    atomic_write_bytes(path, data)
    meta = {"labels": list(FURNITURE_LABELS), "sha256": file_sha256(path), "recipe": made_by, "spec": asdict(spec),
            "library_digest": library, "source": f"{nanodet.ONNX_NAME} sha256 {nanodet.ONNX_SHA256}",
            "render_s": round(t1 - t0, 1), "train_s": round(t2 - t1, 1), "finetune_s": round(time.perf_counter() - t2, 1),
            **report, **losses, **calibration}
    atomic_write_bytes(out_dir / furniture.NOTICE_NAME, furniture.NOTICE.encode())
    atomic_write_bytes(out_dir / META_NAME, json.dumps(meta, indent=1).encode())
    return path


def main(argv: list[str] | None = None) -> int:
    return training_main(__doc__, TrainSpec, build, "the detector", argv)


if __name__ == "__main__":
    sys.exit(main())
