"""Detection and embedding throughput on the paper's average clip (138 frames, 640x360).

Detection: the ``[detect]`` default detector over the 138 frames of :mod:`bench.frames_throughput`'s
clip, batched as the stage runs it (ms per frame, median of ``repeats``), beside, in the same
rounds on the same frames, a bare onnxruntime session with onnxruntime's default options on the
network inputs the detector makes of them (prepared beforehand, outside the timing) and the
detector's own session on those inputs (both run the graph the detector runs: on its fitted canvas,
``[detect] canvas``, the size-free one): ``ratio_to_bare_session`` is detection against the bare
session, ``ratio_to_own_session`` against the network alone with the pipeline's options (what
letterbox, input preparation, decoding and NMS add). ``thread_options``: per round, what the
detector's :class:`~tasks.detection.onnx_session.MeasuredSession` measured of its threads sleeping
and spinning, and which it chose (a new detector each round, as the stage loads one per clip). Embedding: crops of every detected box,
tiled to ``crops`` crops, through the ``[embed]`` default embedder (descriptors per second, crop
preparation included). ``coco_detect_ms_per_frame``: the COCO NanoDet-m (``[detect] model = "coco"``)
in the same rounds, so ``ratio_to_coco`` says what the default furniture detector costs against it;
``other_canvas_ms_per_frame``: the default detector on the square canvas it was trained on
(:data:`SQUARE`: a 640x360 frame on 416 x 416 instead of the default fitted 480 x 288), in the same
rounds, so ``other_canvas_ratio`` says what it costs against the default.
"""

from __future__ import annotations

import dataclasses
import json
import statistics
import time
from pathlib import Path

import numpy as np
import onnxruntime

from bench.demo_clip import make_demo_clip
from bench.frames_throughput import SPEC
from cadestate.config import DetectConfig, EmbedConfig
from tasks.detection.detectors import Detector, detector_path, fit_model, load_detector
from tasks.detection.letterbox import letterbox
from tasks.detection.models.embedder import load_embedder
from tasks.video.camera_file import parse_camera_file
from tasks.video.decode import decode_at


SQUARE = dataclasses.replace(DetectConfig(), canvas="square", input_size=416)
"""The default detector on the square canvas the built-in detectors were trained on (the default
``[detect]`` until 2026-12-05)."""


def canvas_name(detector: Detector, image: np.ndarray) -> str:
    """``"WxH"`` of the network input ``detector`` makes of ``image``."""
    height, width = detector.canvas(image.shape[:2])
    return f"{width}x{height}"


def run(cache_dir: Path, repeats: int = 3, crops: int = 1000) -> dict:
    video, cameras = cache_dir / f"{SPEC.name}.mp4", cache_dir / f"{SPEC.name}.txt"
    if not (video.exists() and cameras.exists()):
        make_demo_clip(cache_dir, SPEC)
    images = [f.rgb for f in decode_at(video, parse_camera_file(cameras).timestamps_us)]
    detector, cfg = load_detector(DetectConfig()), DetectConfig()
    coco = load_detector(DetectConfig(model="coco"))
    other = load_detector(SQUARE)
    graph = fit_model(detector_path(cfg), cfg.adapter) if detector.multiple else None
    bare = onnxruntime.InferenceSession(graph or str(detector_path(cfg)), providers=["CPUExecutionProvider"])
    name = bare.get_inputs()[0].name
    inputs = [np.stack([detector.layout.prepare(letterbox(im, detector.size, detector.layout.fill, detector.multiple)[0])
                        for im in images[i:i + detector.batch_size]]) for i in range(0, len(images), detector.batch_size)]
    fresh: list = []  # the stage loads its detector per clip: each round times a new one (loaded untimed)
    timed = {"detect": lambda: fresh[-1].detect(images), "coco": lambda: coco.detect(images),
             "other": lambda: other.detect(images),
             "bare": lambda: [bare.run(None, {name: x}) for x in inputs],
             "own": lambda: [detector.session.run(None, {name: x}) for x in inputs]}
    seconds: dict[str, list[float]] = {k: [] for k in timed}
    results, options = {}, []
    for _ in range(repeats):  # interleaved: all see the same load of the machine
        fresh.append(load_detector(cfg))
        for key, call in timed.items():
            t0 = time.perf_counter()
            results[key] = call()
            seconds[key].append(time.perf_counter() - t0)
        options.append(fresh.pop().session.summary())
    detections = results["detect"]
    ms = {k: 1000 * statistics.median(v) / len(images) for k, v in seconds.items()}
    embedder = load_embedder(EmbedConfig())
    pairs = [(im, box) for im, det in zip(images, detections) for box in det.boxes]
    if not pairs:  # nothing detected: time crops of the central quarter instead
        pairs = [(im, np.array([160, 90, 480, 270], np.float32)) for im in images]
    pairs = (pairs * (crops // len(pairs) + 1))[:crops]
    t0 = time.perf_counter()
    for start in range(0, crops, 32):
        chunk = pairs[start:start + 32]
        embedder.embed_inputs(np.concatenate([embedder.crops(im, box[None]) for im, box in chunk]))
    embed_s = time.perf_counter() - t0
    return {
        "frames": len(images), "size": f"{SPEC.width}x{SPEC.height}", "detector_threads": cfg.threads,
        "detect_ms_per_frame": round(ms["detect"], 1), "bare_session_ms_per_frame": round(ms["bare"], 1),
        "own_session_ms_per_frame": round(ms["own"], 1), "ratio_to_bare_session": round(ms["detect"] / ms["bare"], 3),
        "ratio_to_own_session": round(ms["detect"] / ms["own"], 3), "thread_options": options,
        "coco_detect_ms_per_frame": round(ms["coco"], 1), "ratio_to_coco": round(ms["detect"] / ms["coco"], 3),
        "canvas": canvas_name(detector, images[0]), "other_canvas": canvas_name(other, images[0]),
        "other_canvas_ms_per_frame": round(ms["other"], 1), "other_canvas_ratio": round(ms["other"] / ms["detect"], 3),
        "boxes_per_frame": round(sum(len(d) for d in detections) / len(images), 2),
        "embeddings_per_s": round(crops / embed_s, 1), "crop_size": EmbedConfig().crop_size,
    }


if __name__ == "__main__":
    from bench.script_args import no_arguments

    no_arguments(__doc__)
    print(json.dumps(run(Path("data/bench/perf")), indent=2))
