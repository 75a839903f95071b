"""Fine-tuning the whole furniture detector: torch runs NanoDet's ONNX graph as onnxruntime does,
trained weights go back into the graph, the fine-tuning learns its targets while boxes and COCO
labels stay the teacher's, the same seed gives the same bytes, and the operating-point shift moves
only the furniture rows."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from bench.detector_data import CELLS, FrameSet
from bench.detector_train import TrainSpec, stride_slices
from tasks.detection.models import nanodet
from tasks.detection.models.furniture_files import FURNITURE_CLASSES, FURNITURE_LABELS

onnx = pytest.importorskip("onnx")
torch = pytest.importorskip("torch")


@pytest.fixture(scope="module")
def furniture_start(coco_model):
    """NanoDet-m with furniture rows taken from COCO's where COCO has the class (the fine-tuning's start)."""
    from bench.detector_train import full_rows, initial_rows
    from tasks.detection.models.nanodet_head import class_rows, with_class_rows

    rows = class_rows(coco_model)
    return with_class_rows(coco_model, full_rows(initial_rows(rows), rows))


def _ort(model, x):
    from tasks.detection.onnx_session import load_session

    session = load_session(model.SerializeToString())
    return [np.concatenate(o) for o in zip(*[session.run(None, {session.get_inputs()[0].name: x[i:i + 1]}) for i in range(len(x))])]


def test_torch_runs_the_graph_as_onnxruntime_and_trained_weights_go_back(furniture_start):
    from bench.onnx_torch import onnx_net, with_weights

    x = np.random.default_rng(0).normal(size=(2, 3, 416, 416)).astype(np.float32)
    net = onnx_net(furniture_start)
    with torch.no_grad():
        mine = [o.numpy() for o in net(torch.from_numpy(x))]
    for a, b in zip(mine, _ort(furniture_start, x)):
        np.testing.assert_allclose(a, b, atol=2e-5)
    assert with_weights(furniture_start, net).SerializeToString() == furniture_start.SerializeToString()
    with torch.no_grad():
        for p in net.parameters():
            p.mul_(1.01)
        changed = [o.numpy() for o in net(torch.from_numpy(x))]
    written = _ort(with_weights(furniture_start, net), x)
    assert not np.allclose(written[3], mine[3], atol=1e-3)  # the weights did change the boxes
    for a, b in zip(changed, written):
        np.testing.assert_allclose(a, b, atol=2e-5)
    broken = onnx.ModelProto()
    broken.CopyFrom(furniture_start)
    broken.graph.node[0].op_type = "Softplus"
    with pytest.raises(ValueError, match="Softplus"):
        onnx_net(broken)


def square_frames(n: int = 4) -> FrameSet:
    """Frames of noise with one bright square each (a cabinet's box); the stride-16 cells inside it should say 'cabinet'."""
    rng = np.random.default_rng(5)
    canvas = rng.integers(60, 120, (n, nanodet.SIZE, nanodet.SIZE, 3)).astype(np.uint8)
    target = np.full((n, CELLS), -1, np.int8)
    quality = np.zeros((n, CELLS), np.float16)
    sl, side = stride_slices()[1], nanodet.SIZE // 16
    squares = np.zeros((n, 4), np.float32)
    for f in range(n):
        y, x = rng.integers(4, side - 10, 2)
        canvas[f, y * 16:(y + 6) * 16, x * 16:(x + 6) * 16] = (230, 40, 40)
        squares[f] = [x * 16, y * 16, (x + 6) * 16, (y + 6) * 16]
        cells = [sl.start + (y + i) * side + x + j for i in range(1, 5) for j in range(1, 5)]
        target[f, cells] = FURNITURE_CLASSES.index("cabinet")
        quality[f, cells] = 0.9
    z = np.zeros
    return FrameSet(z((n, CELLS, 128), np.float16), z((n, CELLS, 4), np.float32), target, quality, canvas,
                    np.arange(n, dtype=np.int64), np.arange(n, dtype=np.int64), squares,
                    np.full(n, FURNITURE_CLASSES.index("cabinet"), np.int64), z(n, bool))


def test_finetuning_learns_its_targets_keeps_the_teachers_boxes_and_repeats_bit_for_bit_whatever_the_callers_threads(
        furniture_start):
    from bench.detector_finetune import finetune
    from bench.onnx_torch import onnx_net

    frames = square_frames()
    spec = TrainSpec(finetune_steps=12, finetune_batch=2, finetune_lr=1e-3)
    tuned, report = finetune(furniture_start, frames, np.arange(len(frames)), spec, show_progress=False)
    x = torch.from_numpy(np.stack([nanodet.prepare(c.astype(np.float32)) for c in frames.canvas]))
    with torch.no_grad():
        before, after = onnx_net(furniture_start)(x), onnx_net(tuned)(x)
    cabinet, pos = FURNITURE_CLASSES.index("cabinet"), torch.from_numpy(frames.target[:, stride_slices()[1]] >= 0)
    assert float(after[1][..., cabinet][pos].mean()) > float(before[1][..., cabinet][pos].mean()) + 0.2, report
    assert report["finetune_loss_last_50"]["focal"] < report["finetune_loss_first_50"]["focal"]
    free, _ = finetune(furniture_start, frames, np.arange(len(frames)), dataclasses.replace(spec, box_distill=0.0), show_progress=False)
    with torch.no_grad():
        undistilled = onnx_net(free)(x)
    sides = lambda d: (torch.softmax(d.reshape(*d.shape[:2], 4, 11), -1) * torch.arange(11.0)).sum(-1)  # noqa: E731
    drift = lambda out: np.mean([float((sides(a) - sides(b)).abs().mean()) for b, a in zip(before[3:], out[3:])])  # noqa: E731
    assert drift(after) < 0.75 * drift(undistilled), (drift(after), drift(undistilled))  # box sides held to the teacher's
    again, _ = finetune(furniture_start, frames, np.arange(len(frames)), dataclasses.replace(spec, finetune_steps=3), show_progress=False)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # a caller (a machine) with another thread count: fine-tuning runs on its own fixed count
    try:
        same, _ = finetune(furniture_start, frames, np.arange(len(frames)), dataclasses.replace(spec, finetune_steps=3), show_progress=False)
        assert torch.get_num_threads() == 1  # and gives the caller's count back
    finally:
        torch.set_num_threads(threads)
    assert again.SerializeToString() == same.SerializeToString()


def test_the_operating_point_shift_moves_only_the_furniture_rows(furniture_start):
    from bench.detector_finetune import shift_rows

    x = np.random.default_rng(2).normal(size=(1, 3, 416, 416)).astype(np.float32)
    before, after = _ort(furniture_start, x), _ort(shift_rows(furniture_start, 1.5), x)
    k = len(FURNITURE_CLASSES)
    logit = lambda p: np.log(p / (1 - p))  # noqa: E731
    for b, a in zip(before[:3], after[:3]):
        assert b.shape[-1] == len(FURNITURE_LABELS)
        np.testing.assert_allclose(logit(a[..., :k].astype(np.float64)), logit(b[..., :k].astype(np.float64)) + 1.5, atol=1e-3)
        assert np.array_equal(a[..., k:], b[..., k:])
    assert all(np.array_equal(a, b) for a, b in zip(after[3:], before[3:]))
