"""NanoDet-m's per-stride class rows, cut open and put back: the graph surgery of the furniture detector.

Per stride s (8, 16, 32) the NanoDet-m ONNX ends in

    hidden float32[1,128,S/s,S/s] (3x3 conv + LeakyReLU) -> 1x1 Conv [80 + 44, 128] -> Split [80, 44]
        -> class rows: Sigmoid -> Reshape [1, 80, -1] -> Transpose -> output [1, N, 80]
        -> box rows:   Reshape [1, 44, -1] -> Transpose -> output [1, N, 44]   (N = (S/s)^2 cells)

:func:`head_parts` finds those nodes by walking up from the class outputs (no name is assumed),
:func:`trunk_model` adds the hidden maps to the outputs (what the class rows are trained on) and
:func:`with_class_rows` swaps in K new class rows per stride, keeping the 44 box rows and every
other weight bit-identical: the result is a NanoDet model of K classes that the ``nanodet``
adapter reads unchanged (K must not be 44, the width the adapter tells box outputs by).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import onnx
from onnx import numpy_helper

BOX_ROWS = 44


@dataclass(frozen=True)
class HeadPart:
    """One stride's head in the graph: ``hidden`` the 1x1 conv's input (its hidden map, [1,128,h,w]),
    ``weight``/``bias`` the conv's initializer names ([C + 44, 128, 1, 1], [C + 44]), ``split`` the
    Split sizes' initializer ([C, 44]), ``reshape`` the class Reshape's shape initializer ([1, C, -1]),
    ``output`` the class output's name ([1, N, C])."""

    hidden: str
    weight: str
    bias: str
    split: str
    reshape: str
    output: str


def _producers(graph: onnx.GraphProto) -> dict[str, onnx.NodeProto]:
    return {o: n for n in graph.node for o in n.output}


def head_parts(model: onnx.ModelProto) -> list[HeadPart]:
    """The heads of a NanoDet model, in output order (strides 8, 16, 32).

    Raises:
      ValueError: the graph does not end in the layout of the module docstring.
    """
    graph = model.graph
    producer, inits = _producers(graph), {t.name for t in graph.initializer}
    parts = []
    for out in graph.output:
        if out.type.tensor_type.shape.dim[-1].dim_value == BOX_ROWS:
            continue
        chain, name = {}, out.name
        while name in producer and len(chain) < 8:
            node = producer[name]
            chain.setdefault(node.op_type, node)
            if node.op_type == "Conv":
                break
            name = next(i for i in node.input if i not in inits)
        if not {"Reshape", "Split", "Conv"} <= set(chain):
            raise ValueError(f"class output {out.name}: no Conv -> Split -> Reshape chain above it")
        conv, split, reshape = chain["Conv"], chain["Split"], chain["Reshape"]
        parts.append(HeadPart(conv.input[0], conv.input[1], conv.input[2], split.input[1], reshape.input[1], out.name))
    return parts


def _initializer(model: onnx.ModelProto, name: str) -> onnx.TensorProto:
    return next(t for t in model.graph.initializer if t.name == name)


def class_rows(model: onnx.ModelProto) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per stride, the class rows (weight float32[C, 128], bias float32[C]) of the 1x1 conv."""
    out = []
    for part in head_parts(model):
        w = numpy_helper.to_array(_initializer(model, part.weight))
        b = numpy_helper.to_array(_initializer(model, part.bias))
        out.append((w[:-BOX_ROWS, :, 0, 0].astype(np.float32), b[:-BOX_ROWS].astype(np.float32)))
    return out


def trunk_model(model: onnx.ModelProto) -> onnx.ModelProto:
    """A copy of ``model`` that also outputs each stride's hidden map float32[1,128,h,w] (after its
    six outputs, in stride order)."""
    trunk = onnx.ModelProto()
    trunk.CopyFrom(model)
    for part in head_parts(model):
        trunk.graph.output.append(onnx.helper.make_tensor_value_info(part.hidden, onnx.TensorProto.FLOAT, None))
    return trunk


def with_class_rows(model: onnx.ModelProto, rows: list[tuple[np.ndarray, np.ndarray]]) -> onnx.ModelProto:
    """A copy of ``model`` whose class rows are ``rows`` (per stride: weight float32[K, 128], bias
    float32[K]); box rows and every other weight unchanged; outputs declared [1, N, K].

    Raises:
      ValueError: a stride's rows are missing or misshapen, or K is 44.
    """
    parts = head_parts(model)
    if len(rows) != len(parts):
        raise ValueError(f"{len(rows)} sets of class rows for {len(parts)} strides")
    k = {w.shape[0] for w, _ in rows}
    if len(k) != 1 or k == {BOX_ROWS}:
        raise ValueError(f"class rows of {sorted(k)} classes: every stride needs the same count, not {BOX_ROWS}")
    (k,) = k
    new = onnx.ModelProto()
    new.CopyFrom(model)
    replace = {}
    for part, (w, b) in zip(parts, rows):
        old_w = numpy_helper.to_array(_initializer(model, part.weight))
        old_b = numpy_helper.to_array(_initializer(model, part.bias))
        if w.shape != (k, old_w.shape[1]) or b.shape != (k,):
            raise ValueError(f"class rows {w.shape}, {b.shape} do not fit the head's {old_w.shape[1]} channels")
        replace[part.weight] = np.concatenate([w[:, :, None, None], old_w[-BOX_ROWS:]]).astype(np.float32)
        replace[part.bias] = np.concatenate([b, old_b[-BOX_ROWS:]]).astype(np.float32)
        replace[part.split] = np.array([k, BOX_ROWS], np.int64)
        replace[part.reshape] = np.array([1, k, -1], np.int64)
    for i, t in enumerate(new.graph.initializer):
        if t.name in replace:
            new.graph.initializer[i].CopyFrom(numpy_helper.from_array(replace[t.name], t.name))
    outputs = {p.output for p in parts}
    for out in new.graph.output:
        if out.name in outputs:
            out.type.tensor_type.shape.dim[-1].dim_value = k
    return new
