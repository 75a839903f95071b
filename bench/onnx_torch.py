"""An ONNX graph run by torch, its weights trainable: how the furniture detector is fine-tuned whole.

:class:`OnnxNet` executes the nodes of an ONNX model in graph order with torch operations, each
float initializer of more than one value (convolution weights and biases) a ``Parameter``; the
other initializers (shapes, pads, split sizes) stay constants. Its outputs equal onnxruntime's to
float rounding (``tests/test_detector_train.py``). :func:`with_weights` writes the trained
parameters back into a copy of the model, so the result is the same graph with new weights, which
the ``nanodet`` adapter reads unchanged; no exporter is involved.

Only the operators NanoDet-m's graph uses are known (:data:`OPS`); another raises ``ValueError``
naming it. Layout is the graph's: NCHW.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import onnx
from onnx import numpy_helper

if TYPE_CHECKING:
    import torch

OPS = ("Add", "Concat", "Conv", "Identity", "LeakyRelu", "MaxPool", "Pad", "Reshape", "Resize", "Sigmoid", "Split", "Transpose")


def _is_weight(array: np.ndarray) -> bool:
    return array.dtype == np.float32 and array.size > 1


def _net_type():
    import torch
    import torch.nn.functional as F

    def symmetric(pads: list[int]) -> list[int]:
        if pads[: len(pads) // 2] != pads[len(pads) // 2:]:
            raise ValueError(f"asymmetric pads {pads} (NanoDet pads with explicit Pad nodes)")
        return pads[: len(pads) // 2]

    def run(node: onnx.NodeProto, ins: list, attrs: dict) -> list:
        op = node.op_type
        if op == "Conv":
            return [F.conv2d(ins[0], ins[1], ins[2] if len(ins) > 2 else None, attrs.get("strides", [1, 1]),
                             symmetric(attrs.get("pads", [0, 0, 0, 0])), attrs.get("dilations", [1, 1]), attrs.get("group", 1))]
        if op == "Pad":  # ONNX: all begins then all ends; torch: (begin, end) from the last axis back
            p, value = ins[1].tolist(), float(ins[2]) if len(ins) > 2 and ins[2] is not None else 0.0
            half = len(p) // 2
            return [F.pad(ins[0], [v for d in reversed(range(half)) for v in (p[d], p[d + half])],
                          mode=attrs.get("mode", b"constant").decode(), value=value)]
        if op == "LeakyRelu":
            return [F.leaky_relu(ins[0], attrs.get("alpha", 0.01))]
        if op == "MaxPool":
            return [F.max_pool2d(ins[0], attrs["kernel_shape"], attrs.get("strides"), symmetric(attrs.get("pads", [0, 0, 0, 0])))]
        if op == "Resize":  # NanoDet's FPN: bilinear, half-pixel centres, to given sizes
            mode = attrs.get("mode", b"nearest").decode()
            if mode != "linear" or attrs.get("coordinate_transformation_mode", b"half_pixel") != b"half_pixel":
                raise ValueError(f"Resize {mode} {attrs.get('coordinate_transformation_mode')}: only linear half_pixel is known")
            return [F.interpolate(ins[0], size=ins[3].tolist()[2:], mode="bilinear", align_corners=False)]
        if op == "Split":
            return list(torch.split(ins[0], ins[1].tolist(), attrs.get("axis", 0)))
        if op == "Reshape":  # the batch axis stays the input's (the graph was exported for batch 1)
            return [ins[0].reshape([ins[0].shape[0], *ins[1].tolist()[1:]])]
        if op == "Transpose":
            return [ins[0].permute(attrs["perm"])]
        if op == "Concat":
            return [torch.cat(ins, attrs["axis"])]
        if op == "Add":
            return [ins[0] + ins[1]]
        if op == "Sigmoid":
            return [torch.sigmoid(ins[0])]
        return [ins[0]]  # Identity

    class OnnxNet(torch.nn.Module):
        """``model`` (its operators among :data:`OPS`) as a torch module: ``forward(x)`` takes the
        graph's input with any batch size and returns its outputs, in the graph's order."""

        def __init__(self, model: onnx.ModelProto):
            super().__init__()
            unknown = sorted({n.op_type for n in model.graph.node} - set(OPS))
            if unknown:
                raise ValueError(f"ONNX operators torch does not run here: {', '.join(unknown)}")
            self.nodes = list(model.graph.node)
            self.attrs = [{a.name: onnx.helper.get_attribute_value(a) for a in n.attribute} for n in self.nodes]
            self.input = model.graph.input[0].name
            self.outputs = [o.name for o in model.graph.output]
            self.weights = torch.nn.ParameterList()
            self.slot: dict[str, int] = {}  # initializer name -> index in ``weights``
            self.constants: dict[str, torch.Tensor] = {}
            for t in model.graph.initializer:
                array = numpy_helper.to_array(t)
                if _is_weight(array):
                    self.slot[t.name] = len(self.weights)
                    self.weights.append(torch.nn.Parameter(torch.from_numpy(array.copy())))
                else:
                    self.constants[t.name] = torch.from_numpy(array.copy())

        def value(self, env: dict, name: str):
            if name in env:
                return env[name]
            return self.weights[self.slot[name]] if name in self.slot else self.constants[name]

        def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
            env = {self.input: x}
            for node, attrs in zip(self.nodes, self.attrs):
                ins = [self.value(env, i) if i else None for i in node.input]
                env.update(zip(node.output, run(node, ins, attrs)))
            return [env[o] for o in self.outputs]

    return OnnxNet


def onnx_net(model: onnx.ModelProto) -> torch.nn.Module:
    """A :class:`OnnxNet` of ``model`` (module docstring)."""
    return _net_type()(model)


def with_weights(model: onnx.ModelProto, net: torch.nn.Module) -> onnx.ModelProto:
    """A copy of ``model`` whose weight initializers are ``net``'s parameters (``net`` an
    :func:`onnx_net` of ``model`` or of a model with the same initializers)."""
    new = onnx.ModelProto()
    new.CopyFrom(model)
    for i, t in enumerate(new.graph.initializer):
        if t.name in net.slot:
            array = net.weights[net.slot[t.name]].detach().numpy().astype(np.float32)
            new.graph.initializer[i].CopyFrom(numpy_helper.from_array(array, t.name))
    return new
