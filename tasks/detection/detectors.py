"""Pluggable ONNX object detectors: one adapter per output layout, letterboxed input, NMS within and across classes.

Every detector sees an aspect-preserving letterbox of the image (:mod:`tasks.detection.letterbox`):
on the resized image padded only up to a multiple of 32 on each side (``[detect] canvas = "fit"``,
the default, where the model takes it: a 640x360 frame at S = 480 runs on 480 x 288), or on an
S x S canvas (``"square"``, what the built-in detectors were trained on at S = 416). NanoDet graphs are made to take any such
size (:func:`tasks.detection.models.nanodet.size_free`); other models only when their input leaves
height and width open. An adapter turns the canvas into the network input and the raw outputs of
one image into candidate boxes (x1, y1, x2, y2 in canvas pixels), scores and label indices; the
rest (score threshold, NMS, maximum count, back to image pixels) is shared.

Layouts (``[detect] adapter``):

``nanodet``
    NanoDet(-m/-plus) as exported by its authors (the default model, see
    :mod:`tasks.detection.models.nanodet`): input float32[B,3,S,S] BGR, ``(x - MEAN) / STD`` on 0-255,
    black padding; per stride 8/16/32 sigmoid class scores [B, (S/s)^2, C] and Generalized Focal
    Loss box distributions [B, (S/s)^2, 44].
``yolov8``
    Ultralytics YOLOv8/YOLO11 ``export(format="onnx")``: input float32[B,3,S,S] RGB in [0, 1],
    padding grey (114); one output float32[B, 4 + C, N]: rows cx, cy, w, h in canvas pixels,
    then C class scores in [0, 1] (no objectness). A transposed [B, N, 4 + C] output is accepted.

Models whose input batch is fixed to B run B images per call (a last, shorter batch padded with copies
of its last image, whose outputs are dropped); others get ``batch_size`` images.
A model's declared output shapes must fit its layout and label map (:func:`output_problem`):
:func:`check_detect_config` checks that from the file before a run, :class:`Detector` from its session.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cadestate.config import ConfigError, DetectConfig
from cadestate.lineage import file_sha256
from cadestate.prefetch import prefetch
from tasks.detection.letterbox import Letterbox, letterbox, network_input, resize_bilinear  # noqa: F401  (imported from here too)
from tasks.detection.model_inputs import built_in, detector_labels, detector_path
from tasks.detection.models import furniture_files, nanodet
from tasks.detection.models.nanodet_files import default_cache_dir
from tasks.detection.onnx_session import MeasuredSession

Shape = tuple[int | None, ...]
"""A tensor shape as a model declares it: None for a dimension it leaves open (named or unknown)."""


def _overlaps(boxes: np.ndarray, area: np.ndarray, i: int, rest: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(IoU, share of each box's own area inside box ``i``) of boxes ``rest`` with box ``i``; boxes
    float[N,4] (x1, y1, x2, y2), ``area`` float[N]."""
    wh = np.clip(np.minimum(boxes[i, 2:], boxes[rest, 2:]) - np.maximum(boxes[i, :2], boxes[rest, :2]), 0, None)
    inter = wh[:, 0] * wh[:, 1]
    return inter / np.maximum(area[i] + area[rest] - inter, 1e-9), inter / np.maximum(area[rest], 1e-9)


def nms(boxes: np.ndarray, scores: np.ndarray, labels: np.ndarray, iou: float, containment: float = 1.0,
        agnostic_iou: float = 1.0) -> np.ndarray:
    """Greedy NMS of boxes float[N,4] (x1, y1, x2, y2) with scores float[N] and class indices
    int[N]; returns kept indices int64[K] by decreasing score. A box is dropped when it overlaps a
    kept box of its class above ``iou`` (IoU), when more than ``containment`` of its own area lies
    inside that box (a part of an object boxed again; 1.0: never), or when it overlaps a kept box of
    any class above ``agnostic_iou`` (one object boxed under two names; 1.0: never)."""
    off = boxes + labels[:, None] * (np.abs(boxes).max(initial=0) + 1) * 2  # classes never overlap
    area = (off[:, 2] - off[:, 0]) * (off[:, 3] - off[:, 1])
    plain_area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    order = np.argsort(-scores, kind="stable")
    keep: list[int] = []
    while order.size:
        i, rest = order[0], order[1:]
        keep.append(int(i))
        overlap, inside = _overlaps(off, area, i, rest)
        kept = (overlap <= iou) & (inside <= containment)
        if agnostic_iou < 1.0:
            kept &= _overlaps(boxes, plain_area, i, rest)[0] <= agnostic_iou
        order = rest[kept]
    return np.array(keep, np.int64)


@dataclass(frozen=True)
class Detections:
    """K detections of one image, by decreasing score: boxes float32[K,4] (x1, y1, x2, y2) in
    image pixels, scores float32[K], labels int64[K] (indices into the label map), names [K]."""

    boxes: np.ndarray
    scores: np.ndarray
    labels: np.ndarray
    names: tuple[str, ...]

    def __len__(self) -> int:
        return len(self.scores)


Candidates = tuple[np.ndarray, np.ndarray, np.ndarray]  # boxes [K,4] canvas xyxy, scores [K], labels [K]


@dataclass(frozen=True)
class Layout:
    """How one family of detectors is fed and read."""

    fill: float  # canvas padding, 0-255
    prepare: Callable[[np.ndarray], np.ndarray]  # canvas float32[h,w,3] RGB -> input float32[3,h,w]
    # (outputs of one image, canvas (h, w), C, threshold) -> candidates in canvas pixels
    candidates: Callable[[list[np.ndarray], tuple[int, int], int, float], Candidates]
    # (resized image float32[h,w,3] RGB, out float32[3,ch,cw], pad (x, y), fill) -> None: writes what
    # prepare makes of the canvas without making it; None: the canvas is made
    prepare_into: Callable[[np.ndarray, np.ndarray, tuple[int, int], float], None] | None = None


def _yolov8_prepare(canvas: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray((canvas / 255.0).transpose(2, 0, 1), dtype=np.float32)


def _yolov8_candidates(outputs: list[np.ndarray], canvas: tuple[int, int], num_labels: int, threshold: float) -> Candidates:
    if len(outputs) != 1:
        raise ValueError(f"yolov8 layout: expected 1 output, got {len(outputs)}")
    out = np.asarray(outputs[0])
    if out.ndim != 2 or 4 + num_labels not in out.shape:
        raise ValueError(f"yolov8 layout: output of shape {out.shape} is neither [4+C, N] nor [N, 4+C] with C = {num_labels} labels")
    if out.shape[0] != 4 + num_labels:
        out = out.T
    cls = out[4:].T
    label = cls.argmax(1)
    score = cls[np.arange(len(label)), label]
    keep = np.flatnonzero(score >= threshold)
    cx, cy, w, h = out[:4, keep].astype(np.float64)
    boxes = np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], 1)
    return boxes, score[keep], label[keep].astype(np.int64)


LAYOUTS: dict[str, Layout] = {
    "nanodet": Layout(0.0, nanodet.prepare, nanodet.candidates, nanodet.prepare_into),
    "yolov8": Layout(114.0, _yolov8_prepare, _yolov8_candidates),
}


def _nanodet_problem(outputs: Sequence[Shape], num_labels: int) -> tuple[str, str] | None:
    box = 4 * (nanodet.REG_MAX + 1)
    if len(outputs) != 2 * len(nanodet.STRIDES):
        return "adapter", (f"the model has {len(outputs)} outputs; the nanodet layout reads "
                           f"{2 * len(nanodet.STRIDES)} (class scores and box distributions per stride)")
    classes = sorted({s[-1] for s in outputs if s and s[-1] is not None} - {box, num_labels})
    if classes:
        return "labels", f"the model scores {classes[0]} classes but [detect] labels has {num_labels} names"
    return None


def _yolov8_problem(outputs: Sequence[Shape], num_labels: int) -> tuple[str, str] | None:
    if len(outputs) != 1 or len(outputs[0]) != 3:
        shapes = ", ".join(str(list(s)) for s in outputs)
        return "adapter", f"the model's outputs {shapes} are not the yolov8 layout's one [B, 4 + C, N]"
    dims = outputs[0][1:]
    if None not in dims and 4 + num_labels not in dims:
        return "labels", (f"the model's output [B, {dims[0]}, {dims[1]}] has no axis of 4 + C = {4 + num_labels} "
                          f"for the C = {num_labels} names of [detect] labels")
    return None


def output_problem(adapter: str, outputs: Sequence[Shape], num_labels: int) -> tuple[str, str] | None:
    """(``[detect]`` key, what is wrong) when a model with these declared output shapes cannot be
    read by ``adapter`` with ``num_labels`` labels; None when they fit or open dimensions leave it open."""
    return {"nanodet": _nanodet_problem, "yolov8": _yolov8_problem}[adapter](outputs, num_labels)


def _shape(dims: Sequence) -> Shape:
    """A declared shape with every dimension that is not a positive int as None."""
    return tuple(d if isinstance(d, int) and d > 0 else None for d in dims)


def onnx_shapes(path: Path) -> tuple[list[Shape], list[Shape]]:
    """Input and output shapes of an ONNX file, read with ``onnx`` (no session: cheap): as declared,
    and where an output leaves a non-batch dimension open, as ONNX shape inference finds them.

    Raises:
      ValueError: the file is not an ONNX model (naming it).
    """
    import onnx
    from google.protobuf.message import DecodeError

    try:
        model = onnx.load(str(path), load_external_data=False)
    except (DecodeError, OSError) as e:
        raise ValueError(f"{path}: not an ONNX model ({type(e).__name__}: {e})") from None
    if not model.ir_version or not model.graph.input or not model.graph.output:
        raise ValueError(f"{path}: not an ONNX model (no IR version, graph inputs or outputs)")

    def shapes(values) -> list[Shape]:
        return [_shape([d.dim_value for d in v.type.tensor_type.shape.dim]) for v in values]

    outputs = shapes(model.graph.output)
    if any(None in s[1:] for s in outputs):
        try:
            outputs = shapes(onnx.shape_inference.infer_shapes(model).graph.output)
        except onnx.shape_inference.InferenceError:
            pass  # the declared shapes, open dimensions and all
    return shapes(model.graph.input), outputs


def _label_map_problem(cfg: DetectConfig) -> tuple[str, str] | None:
    """(key, what is wrong) with ``[detect] labels`` and ``classes`` on their own, or None."""
    labels = detector_labels(cfg)
    blank = [i for i, name in enumerate(labels, start=1) if not name.strip()]
    if blank:
        return "labels", f"label {blank[0]} is blank"
    twice = sorted(name for name, n in Counter(labels).items() if n > 1)
    if twice:
        return "labels", f"{twice[0]!r} appears more than once"
    unknown = sorted(set(cfg.classes) - set(labels))
    if unknown:
        which = "[detect] labels" if cfg.labels else f"the label map of [detect] model = {cfg.model!r}"
        return "classes", f"{', '.join(map(repr, unknown))} not in {which}"
    return None


def check_detect_config(cfg: DetectConfig, source: str | None) -> None:
    """Check ``[detect]`` against its label map and model file before a run (``cadestate config
    check`` and ``cadestate ingest`` call it): classes in the label map, no empty or repeated label,
    the model an ONNX file whose declared input size and outputs fit ``input_size``, ``adapter`` and
    ``labels``. A missing default model is left to the detect stage (which asks for `make models`).

    Raises:
      ConfigError: ``"{source}: [detect] {key}: {what is wrong}"``.
    """
    where = source or "built-in defaults"
    problem = _label_map_problem(cfg)
    path = detector_path(cfg)
    if problem is None and (not built_in(cfg) or path.is_file()):
        if not path.is_file():
            problem = "model", f"{path}: no such file"
        else:
            try:
                inputs, outputs = onnx_shapes(path)
            except ValueError as e:
                problem = "model", str(e)
            else:
                problem = output_problem(cfg.adapter, outputs, len(detector_labels(cfg))) or _input_problem(
                    inputs[0], cfg.input_size, cfg.canvas == "fit" and cfg.adapter == "nanodet")
    if problem:
        raise ConfigError(f"{where}: [detect] {problem[0]}: {problem[1]}")


def _input_problem(shape: Shape, input_size: int, size_free: bool = False) -> tuple[str, str] | None:
    """(key, what is wrong) when a model input of ``shape`` [B, 3, S, S] does not take ``input_size``
    (``size_free``: it is made to take any size, :func:`tasks.detection.models.nanodet.size_free`)."""
    side = shape[2:4]
    if not size_free and len(side) == 2 and None not in side and side != (input_size, input_size):
        return "input_size", f"the model's input is {side[0]}x{side[1]} but [detect] input_size is {input_size}"
    return None


CANVAS_MULTIPLE = 32
"""A fitted canvas's sides are multiples of this: NanoDet's and YOLOv8's coarsest stride."""


def fit_model(path: Path, adapter: str) -> bytes | None:
    """The model to run on fitted canvases: a NanoDet graph made size-free
    (:func:`tasks.detection.models.nanodet.size_free`, in memory: the file stays as verified), any
    other model as it is (None: the file itself; it takes fitted canvases if its input leaves
    height and width open)."""
    if adapter != "nanodet":
        return None
    import onnx
    from google.protobuf.message import DecodeError

    try:
        model = onnx.load(str(path))
    except (DecodeError, OSError):  # not an ONNX file: the session says so, naming it
        return None
    try:
        return nanodet.size_free(model).SerializeToString()
    except ValueError:  # not a graph whose sizes can be freed: it runs on the square canvas
        return None


def _missing_model_hint(path: Path) -> str:
    """What to do about a detector file that is not there: build the built-in ones, or name a file
    that is (a relative ``[detect] model`` is taken from the folder the command runs in)."""
    if path.parent == default_cache_dir():
        return "the built-in detectors are built by `make models`"
    return "[detect] model names an ONNX file; a relative path is taken from the folder the command runs in"


class Detector:
    """An ONNX detector with its layout and label map; :meth:`detect` takes RGB uint8 images."""

    def __init__(self, model_path: Path, adapter: str, labels: Sequence[str], input_size: int, *,
                 score_threshold: float = 0.35, nms_iou: float = 0.45, nms_containment: float = 0.8, nms_agnostic_iou: float = 1.0,
                 max_detections: int = 100, batch_size: int = 8, threads: int = 2, canvas: str = "square",
                 classes: Sequence[str] = ()) -> None:
        if adapter not in LAYOUTS:
            raise ValueError(f"unknown detector adapter {adapter!r} (known: {', '.join(LAYOUTS)})")
        if not Path(model_path).is_file():
            raise FileNotFoundError(f"detector model {model_path} not found ({_missing_model_hint(Path(model_path))})")
        self.layout, self.labels, self.size = LAYOUTS[adapter], tuple(labels), input_size
        self.score_threshold, self.nms_iou, self.max_detections = score_threshold, nms_iou, max_detections
        self.nms_containment, self.nms_agnostic_iou = nms_containment, nms_agnostic_iou
        # label ids kept (None: every label): boxes of other labels neither suppress a kept one nor count to the cap
        self.kept = np.array([k for k, name in enumerate(self.labels) if name in classes], np.int64) if classes else None
        graph = fit_model(Path(model_path), adapter) if canvas == "fit" else None
        self.session = MeasuredSession(Path(model_path) if graph is None else graph, threads)
        self.sha256 = file_sha256(Path(model_path))
        shape = self.session.get_inputs()[0].shape
        self.fixed_batch = isinstance(shape[0], int)  # the model takes batches of exactly batch_size images
        self.batch_size = shape[0] if self.fixed_batch else batch_size
        # canvas sides are rounded up to this (None: the canvas is input_size square), Letterbox.of
        self.multiple = CANVAS_MULTIPLE if canvas == "fit" and None in _shape(shape)[2:4] else None
        problem = output_problem(adapter, [_shape(o.shape) for o in self.session.get_outputs()], len(self.labels)) or \
            _input_problem(_shape(shape), input_size)
        if problem:
            raise ValueError(f"{model_path}: {problem[1]} ([detect] {problem[0]})")

    def _run(self, batch: np.ndarray) -> list[list[np.ndarray]]:
        """Network on float32[B,3,h,w] (``batch_size`` images per call; a model with a fixed batch
        gets a shorter last one padded with copies of its last image) -> per image, its outputs
        without the batch axis."""
        name, per_image = self.session.get_inputs()[0].name, []
        for start in range(0, len(batch), self.batch_size):
            part = batch[start:start + self.batch_size]
            images = len(part)
            if self.fixed_batch and images < self.batch_size:
                part = np.concatenate([part, np.repeat(part[-1:], self.batch_size - images, axis=0)])
            outs = self.session.run(None, {name: part})
            per_image += [[o[b] for o in outs] for b in range(images)]
        return per_image

    def canvas(self, image_size: tuple[int, int]) -> tuple[int, int]:
        """(height, width) of the network input of an (H, W) image (:meth:`Letterbox.of` with :attr:`multiple`)."""
        return Letterbox.of(image_size, self.size, self.multiple).canvas

    def inputs(self, images: Sequence[np.ndarray]) -> tuple[np.ndarray, list[Letterbox]]:
        """The network input float32[B,3,h,w] of B RGB uint8[H,W,3] images of one size, and their
        letterboxes (canvas (h, w): :meth:`canvas`)."""
        batch = np.empty((len(images), 3, *self.canvas(images[0].shape[:2])), np.float32)
        return batch, [network_input(im, self.layout, self.size, out, self.multiple) for im, out in zip(images, batch)]

    def detect_inputs(self, batch: np.ndarray, boxes: Sequence[Letterbox]) -> list[Detections]:
        """Detections for each image of an :meth:`inputs` batch."""
        return [self.finish(outs, lb) for lb, outs in zip(boxes, self._run(batch))]

    def detect(self, images: Sequence[np.ndarray]) -> list[Detections]:
        """Detections for each RGB uint8[H,W,3] image; the next ``batch_size`` images (of one size)
        are letterboxed on a thread while the network runs."""
        chunks, start = [], 0
        for end in range(1, len(images) + 1):  # a chunk ends at batch_size images or where the size changes
            if end == len(images) or end - start == self.batch_size or images[end].shape[:2] != images[start].shape[:2]:
                chunks.append(images[start:end])
                start = end
        return [d for _, inputs in prefetch(chunks, self.inputs) for d in self.detect_inputs(*inputs)]

    def finish(self, outputs: list[np.ndarray], lb: Letterbox) -> Detections:
        """Raw outputs of one image -> thresholded, NMS-ed Detections in image pixels, of the kept
        ``classes`` only (dropped before NMS and the cap); a box less than a pixel high or wide on
        the image (one on the letterbox's padding) is dropped."""
        boxes, scores, labels = self.layout.candidates(outputs, lb.canvas, len(self.labels), self.score_threshold)
        if self.kept is not None:
            mine = np.isin(labels, self.kept)
            boxes, scores, labels = boxes[mine], scores[mine], labels[mine]
        k = nms(boxes, scores, labels, self.nms_iou, self.nms_containment, self.nms_agnostic_iou)
        image = lb.to_image(boxes[k])
        on_image = np.flatnonzero((image[:, 2] - image[:, 0] >= 1) & (image[:, 3] - image[:, 1] >= 1))[: self.max_detections]
        k = k[on_image]
        return Detections(image[on_image], scores[k].astype(np.float32), labels[k], tuple(self.labels[i] for i in labels[k]))


def load_detector(cfg) -> Detector:  # cfg: cadestate.config.DetectConfig
    """The detector ``[detect]`` describes: its model (:func:`detector_path`), adapter and label
    map (:func:`detector_labels`). A built-in model must be the one `make models` built and checked
    (NanoDet-m against its pinned SHA-256, the furniture detector against its JSON file's)."""
    model = detector_path(cfg)
    name = built_in(cfg)
    verified = {"coco": nanodet.is_built, "furniture": furniture_files.is_built}
    if name and not verified[name](model.parent):
        raise FileNotFoundError(f"the {name} detector {model} is missing or not verified: run `make models`")
    problem = _label_map_problem(cfg)
    if problem:
        raise ValueError(f"[detect] {problem[0]}: {problem[1]}")
    labels = detector_labels(cfg)
    return Detector(model, cfg.adapter, labels, cfg.input_size, score_threshold=cfg.score_threshold,
                    nms_iou=cfg.nms_iou, nms_containment=cfg.nms_containment, nms_agnostic_iou=cfg.nms_agnostic_iou,
                    max_detections=cfg.max_detections, batch_size=cfg.batch_size, threads=cfg.threads, canvas=cfg.canvas,
                    classes=cfg.classes)
