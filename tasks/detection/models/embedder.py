"""Appearance embedder: the detector's own backbone (NanoDet-m), average-pooled, as an ONNX model.

Descriptors come from the COCO-trained NanoDet-m backbone that `make models` builds and verifies
(no registry package ships CLIP or DINO weights; an ImageNet MobileNetV2 that one does ship was
measured under the same trained projection and tied, at 30x the cost: README, detection section).
The embedder graph is cut out of that verified ONNX at load time (deterministically, so its own
SHA-256 is fixed) and made size-agnostic:

    input  float32[B,3,S,S]   a letterboxed crop, BGR, (x - MEAN) / STD (as the detector); S % 32 == 0
    stride-16 backbone map [B,256,S/16,S/16] -> global average -> L2-normalise -> 256
    stride-32 backbone map [B,512,S/32,S/32] -> global average -> L2-normalise -> 512
    output float32[B,768] "embedding" = concat / sqrt(2): unit L2 norm

Every backbone stride-2 convolution pads (0, 1) for any even input side, which is why any S
divisible by 32 runs the same computation as the detector's 416. A crop is the box grown by
``context`` times its size on every side (clipped to the image), letterboxed onto an S x S canvas
padded with the normalisation mean (zero input), so the detection crops of a clip and the CAD
view renders go through exactly the same function.
"""
from __future__ import annotations

import hashlib
import math
import os
import threading
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from tasks.detection.detectors import letterbox
from tasks.detection.models import nanodet
from tasks.detection.models.tfjs_to_onnx import serialize
from tasks.detection.onnx_session import MeasuredSession

FEATURES = (  # backbone outputs of the pinned NanoDet-m ONNX (those its FPN reads)
    "PartitionedCall/onnx_tf_prefix_Concat_42__193",  # stride 16, 256 channels
    "PartitionedCall/onnx_tf_prefix_Concat_62__284",  # stride 32, 512 channels
)
DIM = 768
FILL_RGB = tuple(float(v) for v in nanodet.MEAN[::-1])  # padding that normalises to zero


def _ancestors(graph: onnx.GraphProto, outputs: tuple[str, ...]) -> tuple[list[onnx.NodeProto], list[onnx.TensorProto]]:
    """The nodes (in graph order) and initializers that ``outputs`` depend on."""
    producer = {o: n for n in graph.node for o in n.output}
    needed, stack = set(), list(outputs)
    while stack:
        name = stack.pop()
        node = producer.get(name)
        if node is not None and id(node) not in needed:
            needed.add(id(node))
            stack += [i for i in node.input if i]
    nodes = [n for n in graph.node if id(n) in needed]
    used = {i for n in nodes for i in n.input}
    return nodes, [t for t in graph.initializer if t.name in used]


def build_graph(detector_onnx: Path) -> onnx.ModelProto:
    """The embedder graph cut out of the NanoDet-m ONNX (see module docstring)."""
    model = onnx.load(str(detector_onnx))
    input_name = model.graph.input[0].name
    nodes, initializers = _ancestors(model.graph, FEATURES)
    outs = []
    for k, name in enumerate(FEATURES):
        nodes += [helper.make_node("GlobalAveragePool", [name], [f"gap{k}"]),
                  helper.make_node("Flatten", [f"gap{k}"], [f"flat{k}"], axis=1),
                  helper.make_node("LpNormalization", [f"flat{k}"], [f"norm{k}"], axis=1, p=2)]
        outs.append(f"norm{k}")
    half = numpy_helper.from_array(np.array(1 / math.sqrt(2), np.float32), "inv_sqrt2")
    nodes += [helper.make_node("Concat", outs, ["concat"], axis=1),
              helper.make_node("Mul", ["concat", "inv_sqrt2"], ["embedding"])]
    x = helper.make_tensor_value_info(input_name, TensorProto.FLOAT, ["batch", 3, "height", "width"])
    y = helper.make_tensor_value_info("embedding", TensorProto.FLOAT, ["batch", DIM])
    graph = helper.make_graph(nodes, "nanodet_m_backbone_embedder", [x], [y], [*initializers, half])
    out = helper.make_model(graph, opset_imports=list(model.opset_import), producer_name="cadestate")
    out.ir_version = model.ir_version
    onnx.checker.check_model(out)
    return out


def crop_boxes(boxes: np.ndarray, image_size: tuple[int, int], context: float) -> np.ndarray:
    """Boxes float[K,4] (x1, y1, x2, y2, pixels) grown by ``context`` x size per side, clipped to
    the (H, W) image and rounded outwards to whole pixels (at least 1 px wide): int[K,4]."""
    b = np.asarray(boxes, np.float64).reshape(-1, 4)
    h, w = image_size
    size = b[:, 2:] - b[:, :2]
    grown = np.concatenate([b[:, :2] - context * size, b[:, 2:] + context * size], 1)
    lo = np.clip(np.floor(grown[:, :2]), 0, [w - 1, h - 1])
    hi = np.clip(np.ceil(grown[:, 2:]), lo + 1, [w, h])
    return np.concatenate([lo, hi], 1).astype(np.int64)


class Embedder:
    """Descriptors of image regions: :meth:`embed` returns float32[K, 768], unit L2 norm."""

    def __init__(self, detector_onnx: Path, crop_size: int = 128, context: float = 0.1,
                 batch_size: int = 32, threads: int = 2) -> None:
        if crop_size % 32:
            raise ValueError(f"[embed] crop_size must be a multiple of 32 (the backbone's stride), got {crop_size}")
        data = serialize(build_graph(detector_onnx))
        self.sha256 = hashlib.sha256(data).hexdigest()
        self.session = MeasuredSession(data, threads)
        self.crop_size, self.context, self.batch_size = crop_size, context, batch_size

    def crops(self, rgb: np.ndarray, boxes: np.ndarray) -> np.ndarray:
        """Network inputs float32[K,3,S,S] of the boxes float[K,4] (x1, y1, x2, y2 px) of an RGB image."""
        out = np.empty((len(boxes), 3, self.crop_size, self.crop_size), np.float32)
        for k, (x1, y1, x2, y2) in enumerate(crop_boxes(boxes, rgb.shape[:2], self.context)):
            canvas, _ = letterbox(rgb[y1:y2, x1:x2], self.crop_size, FILL_RGB)
            out[k] = nanodet.prepare(canvas)
        return out

    def embed_inputs(self, inputs: np.ndarray) -> np.ndarray:
        """Descriptors float32[K,768] of network inputs float32[K,3,S,S], ``batch_size`` per call."""
        name = self.session.get_inputs()[0].name
        parts = [self.session.run(None, {name: inputs[i:i + self.batch_size]})[0]
                 for i in range(0, len(inputs), self.batch_size)]
        return np.concatenate(parts) if parts else np.zeros((0, DIM), np.float32)

    def embed(self, rgb: np.ndarray, boxes: np.ndarray) -> np.ndarray:
        """Descriptors float32[K,768] of the boxes float[K,4] (x1, y1, x2, y2 px) of one RGB uint8 image."""
        return self.embed_inputs(self.crops(rgb, np.asarray(boxes).reshape(-1, 4)))


_KEPT = threading.local()
"""Each thread's last embedder, with what it was loaded from (:func:`load_embedder`)."""


def load_embedder(cfg) -> Embedder:  # cfg: cadestate.config.EmbedConfig
    """The embedder ``[embed]`` describes, cut from the verified NanoDet-m of `make models`.

    Kept for the thread's next call while the model file (path, inode, size, modification and change
    times) and ``cfg`` stay the same: a long-lived process (the annotation app, ``cadestate serve``)
    loads it once, not at every stage run (cutting the graph, two onnxruntime sessions and the
    model's SHA-256 cost ~100 ms, two thirds of a manual-track stage run on the demo clip). Per thread, because an
    embedder's session takes calls from one thread at a time."""
    cache = nanodet.default_cache_dir()
    path = cache / nanodet.ONNX_NAME
    try:
        st = os.stat(path)
        file_id = (str(path), st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)
        key = (*file_id, cfg.crop_size, cfg.context, cfg.batch_size, cfg.threads)
    except OSError:
        key = None
    kept = getattr(_KEPT, "embedder", None)
    if key is not None and kept is not None and kept[0] == key:
        return kept[1]
    if not nanodet.is_built(cache):
        raise FileNotFoundError(f"the NanoDet-m model in {cache} is missing or not verified: run `make models`")
    embedder = Embedder(path, cfg.crop_size, cfg.context, cfg.batch_size, cfg.threads)
    _KEPT.embedder = (key, embedder)
    return embedder
