"""Fine-tune every weight of the furniture detector on the rendered rooms (``make models``, after its rows).

Class rows on NanoDet-m's frozen hidden maps (:mod:`bench.detector_train`) stop at about 0.38
recall at COCO's precision on held-out rooms: stronger heads on the same maps gain little, the
features are the limit. So the whole network (3.8 M weights) is trained on the same frames, run
by torch from its own ONNX graph (:mod:`bench.onnx_torch`) and written back into it.

Start and teacher: the detector with its trained rows. Loss per batch of ``finetune_batch`` frames
(:class:`bench.detector_data.FrameSet`, the held-out rooms never drawn):

- Quality Focal Loss on the furniture classes' scores: a cell asked for a class (the rows'
  targets) should score it with the IoU of its own box, as it is now, with its object's box;
- ``box_giou`` times the generalised-IoU loss and ``box_dfl`` times the Distribution Focal Loss
  (NanoDet's own box losses) of those cells' boxes towards their object's box
  (:func:`assigned_boxes`), each cell weighted by its target IoU: the teacher's boxes fit COCO's
  objects, and on held-out rooms half of the false boxes overlapped an object by only 0.2-0.5;
- ``box_distill`` times the KL divergence of every other cell's box distributions (4 sides x 11
  bins) from the teacher's, so the cells that should score nothing keep the teacher's boxes;
- binary cross-entropy of the COCO labels kept beside them towards the teacher's scores, so they
  keep their meaning (a cat stays a cat).

With ``box_giou`` 0 the boxes are not trained: every cell's box is held to the teacher's and the
scores' targets are the rows' (the IoU of the teacher's box).

AdamW on :data:`THREADS` threads with deterministic algorithms, batches drawn by a generator of
the spec's seed: the same frames give the same bytes (for a given thread count, which is why it is
fixed, not the machine's).

Operating point (:func:`calibrate`): as for the rows (:func:`bench.detector_train.operating_threshold`),
on the held-out rooms run through the fine-tuned ONNX by onnxruntime (the detect stage's runtime);
the furniture rows' biases are then shifted so that ``[detect] score_threshold`` is that point.
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING

import numpy as np
import onnx
from onnx import numpy_helper

from bench.detector_data import FrameSet, cell_centres, pairwise_iou
from bench.detector_train import OPERATING_THRESHOLDS, kept, logit, operating_threshold, score_found
from cadestate.progress import progress
from tasks.detection.models import nanodet
from tasks.detection.models.furniture_files import FURNITURE_CLASSES, FURNITURE_LABELS

if TYPE_CHECKING:
    from bench.detector_train import TrainSpec

BINS = nanodet.REG_MAX + 1
THREADS = 2
"""Torch's threads while fine-tuning: two runs of the same batches gave the same weights, and the
default 800 steps of 8 frames took 19 minutes against 32 on one thread (2 cores)."""


def network_input(canvas: np.ndarray) -> np.ndarray:
    """Letterboxed frames uint8[B, S, S, 3] RGB -> the network's input float32[B, 3, S, S]
    (:func:`tasks.detection.models.nanodet.prepare` of each)."""
    return np.stack([nanodet.prepare(c.astype(np.float32)) for c in canvas])


def finetune(model: onnx.ModelProto, frames: FrameSet, train_idx: np.ndarray, spec: TrainSpec,
             show_progress: bool = True) -> tuple[onnx.ModelProto, dict]:
    """``model`` (the detector of the whole label map) fine-tuned on the frames ``train_idx``
    (module docstring), and the mean losses of its first and last 50 steps (of halves, when fewer)."""
    import torch

    threads, deterministic = torch.get_num_threads(), torch.are_deterministic_algorithms_enabled()
    torch.set_num_threads(THREADS)
    torch.use_deterministic_algorithms(True)
    try:
        return _finetune(torch, model, frames, train_idx, spec, show_progress)
    finally:
        torch.set_num_threads(threads)
        torch.use_deterministic_algorithms(deterministic)


def _split(outputs: list) -> tuple:
    """The six outputs of a batch -> (scores [B, 3549, L], box distributions [B, 3549, 44]), strides in order."""
    import torch

    return (torch.cat([o for o in outputs if o.shape[-1] != 4 * BINS], 1),
            torch.cat([o for o in outputs if o.shape[-1] == 4 * BINS], 1))


def _finetune(torch, model: onnx.ModelProto, frames: FrameSet, train_idx: np.ndarray, spec: TrainSpec, show_progress: bool):
    from bench.onnx_torch import onnx_net, with_weights

    F = torch.nn.functional
    torch.manual_seed(spec.seed)
    student, teacher = onnx_net(model), onnx_net(model)
    teacher.requires_grad_(False)
    optimiser = torch.optim.AdamW(student.parameters(), lr=spec.finetune_lr, weight_decay=spec.weight_decay)
    generator = torch.Generator().manual_seed(spec.seed)
    k, losses = len(FURNITURE_CLASSES), []
    centres = torch.from_numpy(cell_centres().astype(np.float32))[None]
    strides = torch.cat([torch.full(((nanodet.SIZE // s) ** 2,), float(s)) for s in nanodet.STRIDES])[None]
    for _ in progress(range(spec.finetune_steps), total=spec.finetune_steps, description="fine-tuning", enabled=show_progress):
        pick = np.sort(train_idx[torch.randint(len(train_idx), (spec.finetune_batch,), generator=generator).numpy()])
        x = torch.from_numpy(network_input(frames.canvas[pick]))
        target = torch.from_numpy(frames.target[pick].astype(np.int64))
        quality = torch.from_numpy(frames.quality[pick].astype(np.float32))
        truth = torch.from_numpy(np.stack([assigned_boxes(frames, f) for f in pick]))
        scores, dists = _split(student(x))
        with torch.no_grad():
            t_scores, t_dists = _split(teacher(x))
        p = scores[..., :k].clamp(1e-6, 1 - 1e-6)  # the graph ends in a sigmoid: scores, not logits
        pos = target >= 0
        log_q = torch.log_softmax(dists.reshape(*dists.shape[:2], 4, BINS), -1)
        boxes = cell_boxes(log_q[pos].exp(), centres.expand(len(pick), -1, -1)[pos], strides.expand(len(pick), -1)[pos])
        with torch.no_grad():
            live_iou = box_iou(boxes, truth[pos]).clamp(min=0.0)
        wanted = torch.zeros_like(p)
        wanted[pos, target[pos]] = live_iou if spec.box_giou else quality[pos]
        qfl = F.binary_cross_entropy(p, wanted, reduction="none") * (wanted - p).abs() ** spec.beta
        qfl = (qfl * (target != -2)[..., None]).sum() / max(int(pos.sum()), 1)
        rest = F.binary_cross_entropy(scores[..., k:].clamp(1e-6, 1 - 1e-6), t_scores[..., k:])
        log_t = torch.log_softmax(t_dists.reshape(*t_dists.shape[:2], 4, BINS), -1)
        kl = F.kl_div(log_q, log_t, log_target=True, reduction="none").sum(-1).mean(-1)  # [B, cells]
        held = ~pos if spec.box_giou else torch.ones_like(pos)
        box = (kl * held).sum() / max(int(held.sum()), 1)
        weight = quality[pos]
        giou = ((1 - box_iou(boxes, truth[pos], generalized=True)) * weight).sum() / max(float(weight.sum()), 1e-6)
        dfl = (distribution_focal(log_q[pos], truth[pos], centres.expand(len(pick), -1, -1)[pos],
                                  strides.expand(len(pick), -1)[pos]) * weight).sum() / max(float(weight.sum()), 1e-6)
        loss = qfl + rest + spec.box_distill * box + spec.box_giou * giou + spec.box_dfl * dfl
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        losses.append([float(qfl.detach()), float(rest.detach()), float(box.detach()), float(giou.detach()), float(dfl.detach())])
    n = max(1, min(50, len(losses) // 2))  # 50 steps, or half of fewer
    first, last = np.mean(losses[:n], 0), np.mean(losses[-n:], 0)
    names = ("focal", "coco_distill", "box_distill", "giou", "dfl")
    return with_weights(model, student), {
        "finetune_loss_first_50": {n: round(float(v), 4) for n, v in zip(names, first)},
        "finetune_loss_last_50": {n: round(float(v), 4) for n, v in zip(names, last)}}


def assigned_boxes(frames: FrameSet, f: int) -> np.ndarray:
    """float32[3549, 4]: for each cell of frame ``f`` asked for a class (``target >= 0``), the box
    (x1, y1, x2, y2, letterbox pixels) of the object it was assigned to (:func:`bench.detector_data.assign`:
    of the objects whose box holds the cell's centre, the one its stored box overlaps most); NaN elsewhere."""
    out = np.full((len(frames.target[f]), 4), np.nan, np.float32)
    pos = frames.target[f] >= 0
    gt = frames.gt_boxes[frames.gt_frame == f]
    if pos.any():
        c = cell_centres()[pos]
        inside = ((c[:, None, 0] >= gt[None, :, 0]) & (c[:, None, 0] <= gt[None, :, 2])
                  & (c[:, None, 1] >= gt[None, :, 1]) & (c[:, None, 1] <= gt[None, :, 3]))
        out[pos] = gt[np.where(inside, pairwise_iou(frames.boxes[f][pos], gt), -1.0).argmax(1)]
    return out


def cell_boxes(probs, centres, strides):
    """Bin probabilities [P, 4, 11] of cells at ``centres`` [P, 2] with ``strides`` [P] -> boxes [P, 4]
    (x1, y1, x2, y2): the expected distance to each side, as the detect stage decodes them."""
    import torch

    d = (probs * torch.arange(BINS, dtype=probs.dtype)).sum(-1) * strides[:, None]
    return torch.cat([centres - d[:, :2], centres + d[:, 2:]], 1)


def box_iou(a, b, generalized: bool = False):
    """IoU (or generalised IoU) of paired boxes [P, 4] and [P, 4] (x1, y1, x2, y2) -> [P]."""
    import torch

    wh = (torch.minimum(a[:, 2:], b[:, 2:]) - torch.maximum(a[:, :2], b[:, :2])).clamp(min=0)
    inter = wh[:, 0] * wh[:, 1]
    area = lambda x: (x[:, 2] - x[:, 0]).clamp(min=0) * (x[:, 3] - x[:, 1]).clamp(min=0)  # noqa: E731
    union = area(a) + area(b) - inter
    iou = inter / union.clamp(min=1e-6)
    if not generalized:
        return iou
    hull = (torch.maximum(a[:, 2:], b[:, 2:]) - torch.minimum(a[:, :2], b[:, :2])).clamp(min=0)
    hull_area = (hull[:, 0] * hull[:, 1]).clamp(min=1e-6)
    return iou - (hull_area - union) / hull_area


def distribution_focal(log_probs, truth, centres, strides):
    """Distribution Focal Loss [P] of bin log-probabilities [P, 4, 11] towards the distances of
    boxes ``truth`` [P, 4] from the cells' ``centres`` [P, 2], in units of ``strides`` [P]: the two
    bins around each distance get weights by how near it lies (NanoDet's box loss)."""
    import torch

    target = torch.cat([centres - truth[:, :2], truth[:, 2:] - centres], 1) / strides[:, None]
    target = target.clamp(0, BINS - 1 - 0.01)
    left = target.floor().long()
    w_right = target - left
    pick = lambda i: log_probs.gather(-1, i[..., None])[..., 0]  # noqa: E731
    return -((1 - w_right) * pick(left) + w_right * pick(left + 1)).mean(-1)


def cell_outputs(model: onnx.ModelProto, frames: FrameSet) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per frame, ``model``'s (scores float32[3549, L], boxes float32[3549, 4] letterbox pixels) of
    every cell, run by onnxruntime."""
    from tasks.detection.onnx_session import load_session

    session = load_session(model.SerializeToString())
    name = session.get_inputs()[0].name
    out = []
    for f in range(len(frames)):
        per = nanodet.split_outputs(session.run(None, {name: network_input(frames.canvas[f:f + 1])}),
                                    num_labels=len(FURNITURE_LABELS))
        out.append((np.concatenate([s for s, _ in per.values()]),
                    np.concatenate([nanodet.distance_boxes(d, s, np.arange(len(d))) for s, (_, d) in per.items()]).astype(np.float32)))
    return out


def shift_rows(model: onnx.ModelProto, shift: float) -> onnx.ModelProto:
    """A copy of ``model`` whose furniture rows' biases (the first ``len(FURNITURE_CLASSES)`` of each
    head's class rows) are ``shift`` higher."""
    from tasks.detection.models.nanodet_head import head_parts

    new = onnx.ModelProto()
    new.CopyFrom(model)
    biases = {part.bias for part in head_parts(model)}
    for i, t in enumerate(new.graph.initializer):
        if t.name in biases:
            b = numpy_helper.to_array(t).astype(np.float32)
            b[:len(FURNITURE_CLASSES)] += np.float32(shift)
            new.graph.initializer[i].CopyFrom(numpy_helper.from_array(b, t.name))
    return new


def calibrate(model: onnx.ModelProto, held: FrameSet, spec: TrainSpec, precision: float) -> tuple[onnx.ModelProto, dict]:
    """``model`` with its furniture rows moved to the operating point (module docstring), and its
    held-out results: per threshold before the move, the point and shift, and after it at
    ``spec.score_threshold``. ``precision``: the COCO rows' held-out precision."""
    score = functools.partial(_score, held, nms_iou=spec.nms_iou, containment=spec.nms_containment)
    cells = cell_outputs(model, held)
    by_threshold = {t: score(cells, t) for t in OPERATING_THRESHOLDS}
    operating = operating_threshold(by_threshold, precision)
    shift = logit(spec.score_threshold) - logit(operating)
    moved = shift_rows(model, shift)
    return moved, {
        "finetune_heldout_by_threshold": {str(t): {k: v for k, v in r.items() if k != "per_class_recall"}
                                          for t, r in by_threshold.items()},
        "finetune_operating_threshold": operating, "finetune_bias_shift": round(shift, 4),
        "heldout_after": score(cell_outputs(moved, held), spec.score_threshold)}


def _score(held: FrameSet, cells: list[tuple[np.ndarray, np.ndarray]], threshold: float, nms_iou: float, containment: float) -> dict:
    return score_found(held, [kept(s, b, threshold, nms_iou, containment) for s, b in cells])
