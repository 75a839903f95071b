"""Detector adapters on tiny torch models exported to ONNX here, letterbox geometry, NMS, config."""

from __future__ import annotations

import io
import warnings

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from cadestate.config import ConfigError, DetectConfig, config_from_dict  # noqa: E402
from tasks.detection.detectors import (  # noqa: E402
    LAYOUTS, Detector, Letterbox, check_detect_config, letterbox, load_detector, network_input, nms, output_problem,
    resize_bilinear,
)
from tasks.detection.models import nanodet as nd  # noqa: E402


class FixedOutputs(torch.nn.Module):
    """Returns constant tensors (one per output) for every image of the batch, whatever it shows,
    plus 0 x the image mean so the graph depends on its input."""

    def __init__(self, outputs: list[np.ndarray]) -> None:
        super().__init__()
        self.values = torch.nn.ParameterList([torch.nn.Parameter(torch.from_numpy(o), requires_grad=False) for o in outputs])

    def forward(self, x):
        zero = x.mean(dim=(1, 2, 3)) * 0
        return tuple(v.unsqueeze(0) + zero.view(-1, *([1] * v.dim())) for v in self.values)


def export(module: torch.nn.Module, path, size: int, dynamic_batch: bool, n_outputs: int) -> None:
    names = [f"out{i}" for i in range(n_outputs)]
    axes = {"images": {0: "batch"}, **{n: {0: "batch"} for n in names}} if dynamic_batch else None
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript exporter is deprecated but needs no onnxscript
        torch.onnx.export(module, torch.zeros(1, 3, size, size), buf, dynamo=False, input_names=["images"],
                          output_names=names, dynamic_axes=axes, opset_version=17)
    path.write_bytes(buf.getvalue())


# ---- YOLOv8 layout --------------------------------------------------------------------------------
LABELS = ("chair", "sofa", "table")


def yolo_outputs(size: int = 64, transposed: bool = False) -> np.ndarray:
    """[4 + 3, N] with N = 6 anchors: (cx, cy, w, h) in canvas px, then 3 class scores."""
    rows = [  # cx, cy, w, h, chair, sofa, table
        (20, 32, 10, 20, 0.9, 0.1, 0.0),   # chair 0.9
        (21, 32, 10, 20, 0.8, 0.0, 0.0),   # chair 0.8, IoU 0.82 with the first: suppressed
        (21, 32, 10, 20, 0.0, 0.7, 0.0),   # sofa on the same spot: another class, kept
        (50, 40, 8, 8, 0.0, 0.0, 0.5),     # table 0.5
        (10, 10, 4, 4, 0.2, 0.0, 0.0),     # below the threshold
        (40, 20, 6, 6, 0.0, 0.0, 0.36),    # table 0.36
    ]
    out = np.array(rows, np.float32).T
    return np.ascontiguousarray(out.T if transposed else out)


@pytest.mark.parametrize("transposed", [False, True])
def test_yolov8_adapter_on_exported_model(tmp_path, transposed):
    path = tmp_path / "yolo.onnx"
    export(FixedOutputs([yolo_outputs(transposed=transposed)]), path, 64, dynamic_batch=True, n_outputs=1)
    det = Detector(path, "yolov8", LABELS, 64, score_threshold=0.3, nms_iou=0.6, batch_size=2)
    assert det.batch_size == 2
    images = [np.zeros((32, 64, 3), np.uint8), np.zeros((64, 32, 3), np.uint8), np.zeros((64, 64, 3), np.uint8)]
    wide, tall, square = det.detect(images)  # two network calls: a batch of 2, then 1
    assert square.names == ("chair", "sofa", "table", "table")
    np.testing.assert_allclose(square.scores, [0.9, 0.7, 0.5, 0.36], atol=1e-6)
    np.testing.assert_allclose(square.boxes[0], [15, 22, 25, 42], atol=1e-4)
    # a 32 x 64 image sits at pad_y = 16 of the 64 x 64 canvas, scale 1: boxes shift up and clip
    np.testing.assert_allclose(wide.boxes[0], [15, 6, 25, 26], atol=1e-4)
    np.testing.assert_allclose(wide.boxes[3], [37, 1, 43, 7], atol=1e-4)
    # a 64 x 32 image: pad_x = 16
    np.testing.assert_allclose(tall.boxes[0], [0, 22, 9, 42], atol=1e-4)
    assert square.labels.tolist() == [0, 1, 2, 2]
    few = Detector(path, "yolov8", LABELS, 64, score_threshold=0.3, max_detections=2).detect(images[2:])[0]
    assert few.names == ("chair", "sofa")
    # [detect] classes: other labels are dropped before the cap and NMS, so they take no place of a kept box
    tables = Detector(path, "yolov8", LABELS, 64, score_threshold=0.3, max_detections=2, classes=("table",)).detect(images[2:])[0]
    assert tables.names == ("table", "table")
    np.testing.assert_allclose(tables.scores, [0.5, 0.36], atol=1e-6)


def test_a_model_with_a_fixed_batch_of_two_takes_an_odd_number_of_images(tmp_path):
    path = tmp_path / "yolo_b2.onnx"
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(FixedOutputs([yolo_outputs()]), torch.zeros(2, 3, 64, 64), buf, dynamo=False,
                          input_names=["images"], output_names=["out0"], opset_version=17)
    path.write_bytes(buf.getvalue())
    det = Detector(path, "yolov8", LABELS, 64, score_threshold=0.3, batch_size=8)
    assert det.batch_size == 2
    found = det.detect([np.zeros((64, 64, 3), np.uint8)] * 3)  # a batch of 2, then 1 padded to 2
    assert [d.names for d in found] == [("chair", "sofa", "table", "table")] * 3


def test_yolov8_adapter_rejects_a_wrong_label_map(tmp_path):
    path = tmp_path / "yolo.onnx"
    export(FixedOutputs([yolo_outputs()]), path, 64, dynamic_batch=True, n_outputs=1)
    with pytest.raises(ValueError, match=r"yolo.onnx: the model's output \[B, 7, 6\] has no axis of 4 \+ C = 9 for "
                                         r"the C = 5 names of \[detect\] labels \(\[detect\] labels\)"):
        Detector(path, "yolov8", ("a", "b", "c", "d", "e"), 64)  # at load, not mid-run


# ---- NanoDet layout ---------------------------------------------------------------------------------
def nanodet_outputs(size: int = 64, num_labels: int = 3, width: int | None = None) -> list[np.ndarray]:
    """Six outputs [N, C] / [N, 44] per stride of a ``size`` x ``width`` (default ``size``) input with
    one confident cell: stride 16, row 1, col 2, class 1 at 0.9, one-hot distance bins (left 3, top
    2, right 1, bottom 0)."""
    width = width or size
    outs = []
    for s in nd.STRIDES:
        n = (size // s) * (width // s)
        cls = np.full((n, num_labels), 0.01, np.float32)
        box = np.zeros((n, 44), np.float32)
        if s == 16:
            cell = 1 * (width // s) + 2
            cls[cell, 1] = 0.9
            logits = np.zeros((4, 11), np.float32)
            logits[np.arange(4), [3, 2, 1, 0]] = 60.0
            box[cell] = logits.reshape(44)
        outs += [cls, box]
    return outs


def test_nanodet_adapter_on_exported_model(tmp_path):
    path = tmp_path / "nanodet.onnx"
    export(FixedOutputs(nanodet_outputs()), path, 64, dynamic_batch=False, n_outputs=6)
    det = Detector(path, "nanodet", LABELS, 64, score_threshold=0.3, batch_size=8)
    assert det.batch_size == 1  # fixed batch: one image per call
    a, b = det.detect([np.zeros((64, 64, 3), np.uint8), np.zeros((32, 64, 3), np.uint8)])
    # cell centre ((2 + 0.5) * 16, (1 + 0.5) * 16) = (40, 24); distances 48, 32, 16, 0
    assert a.names == ("sofa",) and a.scores[0] == pytest.approx(0.9)
    np.testing.assert_allclose(a.boxes[0], [0, 0, 56, 24], atol=1e-3)  # x1 = -8 clipped
    np.testing.assert_allclose(b.boxes[0], [0, 0, 56, 8], atol=1e-3)  # pad_y 16
    strip, = det.detect([np.zeros((8, 64, 3), np.uint8)])  # pad_y 28: the box (y -8 .. 24) lies on the padding
    assert strip.boxes.shape == (0, 4) and strip.names == () and len(strip.scores) == len(strip.labels) == 0
    # a batch of inputs (what the detect stage prefetches) runs one image per call too
    both = det.detect_inputs(*det.inputs([np.zeros((64, 64, 3), np.uint8), np.zeros((32, 64, 3), np.uint8)]))
    assert [np.array_equal(x.boxes, y.boxes) for x, y in zip(both, (a, b))] == [True, True]
    with pytest.raises(ValueError, match="input is 64x64"):
        Detector(path, "nanodet", LABELS, 416)


def test_nanodet_adapter_rejects_a_wrong_label_map_or_layout(tmp_path):
    path = tmp_path / "nanodet.onnx"
    export(FixedOutputs(nanodet_outputs()), path, 64, dynamic_batch=False, n_outputs=6)
    with pytest.raises(ValueError, match=r"the model scores 3 classes but \[detect\] labels has 80 names"):
        Detector(path, "nanodet", nd.COCO_LABELS, 64)
    with pytest.raises(ValueError, match=r"not the yolov8 layout's one \[B, 4 \+ C, N\] \(\[detect\] adapter\)"):
        Detector(path, "yolov8", LABELS, 64)


@pytest.mark.parametrize("outputs, num_labels, problem", [
    ([(1, 84, 8400)], 80, None),
    ([(1, 8400, 84)], 80, None),
    ([(None, 84, None)], 3, None),  # open dimensions: nothing to say
    ([(1, 84, 8400)], 3, "labels"),
    ([(1, 84)], 80, "adapter"),
    ([(1, 84, 8400)] * 2, 80, "adapter"),
])
def test_yolov8_output_problem(outputs, num_labels, problem):
    found = output_problem("yolov8", outputs, num_labels)
    assert (found and found[0]) == problem


@pytest.mark.parametrize("canvas", [(64, 64), (32, 64), (64, 96), (128, 64)])
def test_nanodet_candidates_use_cell_centres(canvas):
    """On a square and on rectangular canvases (height, width): cells are row-major, width/stride a row."""
    boxes, scores, labels = nd.candidates(nanodet_outputs(canvas[0], width=canvas[1]), canvas, 3, 0.3)
    assert labels.tolist() == [1] and scores.tolist() == pytest.approx([0.9])
    np.testing.assert_allclose(boxes[0], [-8, -8, 56, 24], atol=1e-3)
    with pytest.raises(ValueError, match="unexpected NanoDet output shape"):
        nd.candidates(nanodet_outputs(canvas[0], width=canvas[1]), (canvas[0] + 32, canvas[1]), 3, 0.3)


# ---- shared pieces ------------------------------------------------------------------------------------
def test_letterbox_geometry_and_round_trip():
    img = np.zeros((300, 451, 3), np.uint8)
    img[..., 0] = 255  # red
    canvas, lb = letterbox(img, 416, fill=7.0)
    assert canvas.shape == (416, 416, 3) and lb.scale == pytest.approx(416 / 451)
    assert lb.pad == (0, (416 - round(300 * lb.scale)) // 2) == Letterbox.of((300, 451), 416).pad
    np.testing.assert_allclose(canvas[lb.pad[1] + 5, 10], [255, 0, 0], atol=1e-3)
    np.testing.assert_allclose(canvas[0, 0], [7, 7, 7])
    x = nd.prepare(canvas)
    np.testing.assert_allclose(x[:, lb.pad[1] + 5, 10], (np.array([0, 0, 255], np.float32) - nd.MEAN) / nd.STD, atol=1e-4)
    boxes = np.array([[10, 20, 200, 290], [0, 0, 451, 300]], np.float32)
    np.testing.assert_allclose(lb.to_image(lb.to_canvas(boxes)), boxes, atol=1e-3)


def test_a_sliver_keeps_a_pixel_on_the_canvas():
    """A crop one pixel high and 300 wide letterboxed to 128 (0.43 px high scaled) keeps one row."""
    sliver = np.full((1, 300, 3), 200, np.uint8)
    canvas, lb = letterbox(sliver, 128)
    assert canvas.shape == (128, 128, 3) and lb.pad == (0, 63)
    np.testing.assert_allclose(canvas[63], 200.0)
    np.testing.assert_allclose(canvas[62], 0.0)
    assert Letterbox.of((300, 1), 128, multiple=32).canvas == (128, 32)


@pytest.mark.parametrize("image, canvas, pad", [
    ((360, 640), (256, 416), (0, 11)),  # 16:9 -> 416 x 234, padded to 256 rows: 0.62 of the square
    ((640, 360), (416, 256), (11, 0)),  # portrait
    ((300, 451), (288, 416), (0, 5)),  # 416 x 277
    ((416, 416), (416, 416), (0, 0)),
    ((100, 50), (416, 224), (8, 0)),  # upscaled: 208 columns -> 224
])
def test_a_fitted_letterbox_pads_only_to_a_multiple_of_32(image, canvas, pad):
    """Image pixel (x, y) -> canvas (x * scale + pad_x, y * scale + pad_y) on both canvases; the
    fitted one keeps the square's scale, and is the scaled image rounded up to 32 on each side."""
    rgb = np.full((*image, 3), 200, np.uint8)
    fitted, lb = letterbox(rgb, 416, fill=7.0, multiple=32)
    square = Letterbox.of(image, 416)
    assert lb.canvas == fitted.shape[:2] == canvas and lb.pad == pad and lb.scale == square.scale
    assert square.canvas == (416, 416)
    h, w = round(image[0] * lb.scale), round(image[1] * lb.scale)
    inside = fitted[pad[1]:pad[1] + h, pad[0]:pad[0] + w]
    assert inside.shape[:2] == (h, w) and np.allclose(inside, 200, atol=1e-3)
    outside = np.ones(fitted.shape[:2], bool)
    outside[pad[1]:pad[1] + h, pad[0]:pad[0] + w] = False
    assert np.all(fitted[outside] == 7.0)
    boxes = np.array([[0, 0, image[1], image[0]], [3, 4, 20, 30]], np.float32)
    np.testing.assert_allclose(lb.to_image(lb.to_canvas(boxes)), boxes, atol=1e-3)
    np.testing.assert_allclose(lb.to_canvas(boxes[:1]), [[pad[0], pad[1], pad[0] + w, pad[1] + h]], atol=1e-3)


@pytest.mark.parametrize("image", [(2160, 4096), (333, 1000), (997, 101), (360, 640)])
@pytest.mark.parametrize("multiple", [None, 32])
def test_the_canvas_block_of_the_image_is_the_whole_image(image, multiple):
    """Each side is resized to a whole number of pixels, so by a factor a little off ``scale``:
    boxes were mapped back with ``scale``, and one at the bottom of a 4096x2160 frame came back
    3.7 px short of it (ymax 0.998 of the height)."""
    lb = Letterbox.of(image, 416, multiple)
    h, w = image
    nh, nw = round(h * lb.scale), round(w * lb.scale)
    block = np.array([[lb.pad[0], lb.pad[1], lb.pad[0] + nw, lb.pad[1] + nh]], np.float32)
    np.testing.assert_allclose(lb.to_image(block), [[0, 0, w, h]], atol=2e-3)


def four_neighbour_resize(rgb: np.ndarray, nh: int, nw: int) -> np.ndarray:
    """The previous resize_bilinear: every output pixel blends its four source neighbours at once."""
    h, w = rgb.shape[:2]
    ys = np.clip((np.arange(nh) + 0.5) * (h / nh) - 0.5, 0, h - 1)
    xs = np.clip((np.arange(nw) + 0.5) * (w / nw) - 0.5, 0, w - 1)
    y0, x0 = np.floor(ys).astype(int), np.floor(xs).astype(int)
    y1, x1 = np.minimum(y0 + 1, h - 1), np.minimum(x0 + 1, w - 1)
    fy, fx = (ys - y0)[:, None, None].astype(np.float32), (xs - x0)[None, :, None].astype(np.float32)
    im = rgb.astype(np.float32)
    top = im[y0][:, x0] * (1 - fx) + im[y0][:, x1] * fx
    bot = im[y1][:, x0] * (1 - fx) + im[y1][:, x1] * fx
    return top * (1 - fy) + bot * fy


@pytest.mark.parametrize("shape,out", [((360, 640), (234, 416)), ((1080, 1920), (234, 416)), ((50, 37), (416, 308)),
                                       ((13, 200), (27, 416)), ((1, 1), (4, 4)), ((300, 451), (277, 416))])
def test_separable_resize_equals_the_four_neighbour_blend(shape, out):
    rng = np.random.default_rng(sum(shape))
    img = rng.integers(0, 256, (*shape, 3), np.uint8)
    got = resize_bilinear(img, *out)
    assert got.dtype == np.float32 and np.array_equal(got, four_neighbour_resize(img, *out))
    crop = rng.integers(0, 256, (100, 200, 3), np.uint8)[10:60, 20:90]  # a crop: a strided view, as the embedder cuts
    assert np.array_equal(resize_bilinear(crop, 128, 90), four_neighbour_resize(crop, 128, 90))
    floats = img.astype(np.float64) + 0.25
    assert np.array_equal(resize_bilinear(floats, *out), four_neighbour_resize(floats, *out))


def test_prepare_equals_the_transposed_normalisation():
    canvas, _ = letterbox(np.random.default_rng(0).integers(0, 256, (300, 451, 3), np.uint8), 416)
    expected = np.ascontiguousarray(((canvas[..., ::-1] - nd.MEAN) / nd.STD).transpose(2, 0, 1), dtype=np.float32)
    got = nd.prepare(canvas)
    assert got.flags.c_contiguous and got.dtype == np.float32 and np.array_equal(got, expected)


@pytest.mark.parametrize("shape", [(360, 640, 3), (640, 360, 3), (416, 416, 3), (17, 900, 3), (1080, 1920, 3)])
@pytest.mark.parametrize("adapter", sorted(LAYOUTS))
def test_network_input_is_the_prepared_letterbox_bit_for_bit(shape, adapter):
    """The detector writes its input without making the canvas (nanodet): the same bits as
    preparing the letterboxed canvas, padding included, so detections do not move."""
    image = np.random.default_rng(sum(shape)).integers(0, 256, shape, np.uint8)
    layout, out = LAYOUTS[adapter], np.full((3, 416, 416), np.nan, np.float32)
    lb = network_input(image, layout, 416, out)
    canvas, expected_lb = letterbox(image, 416, layout.fill)
    assert lb == expected_lb and np.array_equal(out.view(np.uint32), layout.prepare(canvas).view(np.uint32))


def test_class_aware_nms():
    boxes = np.array([[0, 0, 10, 10], [1, 0, 11, 10], [1, 0, 11, 10], [50, 50, 60, 60]], np.float64)
    scores = np.array([0.9, 0.8, 0.7, 0.6])
    labels = np.array([0, 0, 1, 0])
    assert nms(boxes, scores, labels, 0.6).tolist() == [0, 2, 3]
    assert nms(boxes, scores, labels, 0.9).tolist() == [0, 1, 2, 3]
    assert nms(boxes[:0], scores[:0], labels[:0], 0.5).tolist() == []


def test_nms_across_classes_drops_one_object_boxed_under_two_names_and_keeps_objects_that_overlap_less():
    table = [0.0, 0.0, 100.0, 60.0]
    table_as_bed = [2.0, 0.0, 100.0, 62.0]  # IoU 0.93 with the table
    chair_under = [40.0, 20.0, 100.0, 60.0]  # IoU 0.4 with the table, all of it inside: another object
    boxes = np.array([table, table_as_bed, chair_under], np.float64)
    scores, labels = np.array([0.6, 0.5, 0.4]), np.array([0, 1, 2])
    assert nms(boxes, scores, labels, 0.45, 0.8).tolist() == [0, 1, 2]  # within classes only, as before
    assert nms(boxes, scores, labels, 0.45, 0.8, agnostic_iou=0.7).tolist() == [0, 2]
    assert nms(boxes, scores, labels, 0.45, 0.8, agnostic_iou=0.3).tolist() == [0]
    assert nms(boxes, scores, labels, 0.45, 0.8, agnostic_iou=1.0).tolist() == [0, 1, 2]
    # a box dropped across classes drops nothing of its own class: the better box of the other class does
    boxes = np.array([table, table_as_bed, table_as_bed], np.float64)
    assert nms(boxes, np.array([0.6, 0.5, 0.45]), np.array([0, 1, 1]), 0.45, 0.8, agnostic_iou=0.7).tolist() == [0]
    # at a higher score the other name wins
    assert nms(boxes[:2], np.array([0.5, 0.6]), np.array([0, 1]), 0.45, 0.8, agnostic_iou=0.7).tolist() == [1]


def test_detect_config_label_map_and_errors(tmp_path):
    cfg = config_from_dict({"detect": {"adapter": "yolov8", "labels": ["a", "b"], "input_size": 640}})
    assert cfg.detect.labels == ("a", "b")
    with pytest.raises(ConfigError, match=r"\[detect\] labels: expected a list of strings"):
        config_from_dict({"detect": {"labels": "chair"}})
    with pytest.raises(ConfigError, match="adapter"):
        config_from_dict({"detect": {"adapter": "ssd"}})
    with pytest.raises(FileNotFoundError, match="nothere.onnx"):
        load_detector(DetectConfig(model=str(tmp_path / "nothere.onnx")))
    (tmp_path / "junk.onnx").write_bytes(b"not a model")
    with pytest.raises(ValueError, match="junk.onnx: not a loadable ONNX model"):
        load_detector(DetectConfig(model=str(tmp_path / "junk.onnx")))
    (tmp_path / "empty.onnx").write_bytes(b"")  # parses as an empty graph: the session names the file
    for canvas in ("fit", "square"):
        with pytest.raises(ValueError, match="empty.onnx: not a loadable ONNX model"):
            load_detector(DetectConfig(model=str(tmp_path / "empty.onnx"), canvas=canvas))
    with pytest.raises(ValueError, match=r"\[detect\] classes: 'sofa' not in \[detect\] labels"):
        load_detector(DetectConfig(model=str(tmp_path / "junk.onnx"), labels=("a",), classes=("sofa",)))


def check(tmp_path, **detect) -> str:
    """The ConfigError of check_detect_config on a [detect] section."""
    with pytest.raises(ConfigError) as e:
        check_detect_config(DetectConfig(**detect), str(tmp_path / "c.toml"))
    assert str(e.value).startswith(f"{tmp_path / 'c.toml'}: [detect] ")
    return str(e.value).split(": [detect] ", 1)[1]


def test_check_detect_config_reads_the_model_file(tmp_path):
    yolo = tmp_path / "yolo.onnx"
    export(FixedOutputs([yolo_outputs()]), yolo, 64, dynamic_batch=True, n_outputs=1)
    ok = dict(model=str(yolo), adapter="yolov8", labels=LABELS, input_size=64)
    check_detect_config(DetectConfig(**ok), "c.toml")
    assert check(tmp_path, **ok | dict(labels=LABELS + ("bed",))) == (  # shapes inferred: the graph leaves them open
        "labels: the model's output [B, 7, 6] has no axis of 4 + C = 8 for the C = 4 names of [detect] labels")
    assert check(tmp_path, **ok | dict(input_size=640)) == (
        "input_size: the model's input is 64x64 but [detect] input_size is 640")
    assert check(tmp_path, **ok | dict(adapter="nanodet")).startswith(
        "adapter: the model has 1 outputs; the nanodet layout reads 6")
    assert check(tmp_path, **ok | dict(model=str(tmp_path / "nothere.onnx"))) == f"model: {tmp_path}/nothere.onnx: no such file"
    (tmp_path / "junk.onnx").write_bytes(b"not a model")
    assert check(tmp_path, **ok | dict(model=str(tmp_path / "junk.onnx"))).startswith(
        f"model: {tmp_path}/junk.onnx: not an ONNX model (DecodeError")
    (tmp_path / "empty.onnx").write_bytes(b"")
    assert check(tmp_path, **ok | dict(model=str(tmp_path / "empty.onnx"))) == (
        f"model: {tmp_path}/empty.onnx: not an ONNX model (no IR version, graph inputs or outputs)")
    assert check(tmp_path, **ok | dict(model=str(tmp_path))).startswith(f"model: {tmp_path}: no such file")


def test_check_detect_config_label_map(tmp_path):
    assert check(tmp_path, model="coco", classes=("sofa",)) == "classes: 'sofa' not in the label map of [detect] model = 'coco'"
    assert check(tmp_path, classes=("couch",)) == "classes: 'couch' not in the label map of [detect] model = 'furniture'"
    assert check(tmp_path, labels=("a", "b"), classes=("b", "c")) == "classes: 'c' not in [detect] labels"
    assert check(tmp_path, labels=("a", " ")) == "labels: label 2 is blank"
    assert check(tmp_path, labels=("a", "b", "a")) == "labels: 'a' appears more than once"


def test_check_detect_config_on_the_default_model(tmp_path):
    from tasks.detection.detectors import detector_path

    for model, classes in (("coco", 80), ("furniture", 89)):
        if not detector_path(DetectConfig(model=model)).is_file():
            pytest.skip(f"the {model} detector is not built (`make models`)")
        check_detect_config(DetectConfig(model=model), None)  # its label map fits it
        assert check(tmp_path, model=model, labels=("chair", "sofa")) == (
            f"labels: the model scores {classes} classes but [detect] labels has 2 names")
        assert check(tmp_path, model=model, adapter="yolov8").startswith(f"adapter: the model's outputs [1, 2704, {classes}], ")


def test_nms_drops_a_part_boxed_again_inside_a_better_box_of_its_class():
    whole = [0.0, 0.0, 100.0, 100.0]
    seat = [10.0, 50.0, 90.0, 100.0]  # IoU 0.4 with the whole, all of it inside
    shelf = [60.0, 60.0, 140.0, 140.0]  # a quarter of it inside the whole
    boxes = np.array([whole, seat, shelf, seat])
    scores, labels = np.array([0.9, 0.8, 0.7, 0.6]), np.array([0, 0, 0, 1])
    assert nms(boxes, scores, labels, 0.45).tolist() == [0, 1, 2, 3]  # IoU alone keeps the part
    assert nms(boxes, scores, labels, 0.45, containment=0.8).tolist() == [0, 2, 3]  # another class's part stays
    assert nms(boxes, scores, labels, 0.45, containment=1.0).tolist() == [0, 1, 2, 3]
    assert nms(boxes, scores, labels, 0.45, containment=0.2).tolist() == [0, 3]
