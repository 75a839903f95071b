"""Stage ``detect``: run the configured ONNX detector (:mod:`tasks.detection.detectors`) on every frame of a clip.

Reads: the clip's ``frames`` (images). Writes: its ``detections`` partition, one row per kept box
with the box normalised as in CAD-Estate, (ymin, xmin, ymax, xmax) in [0, 1] of the image (origin
top-left, y down), and ``det_id = frame_index * 10000 + rank`` (rank by score within the frame).
Boxes whose label is not in ``[detect] classes`` (when set) are dropped by the detector before its
NMS and its cap of ``max_detections`` (:class:`tasks.detection.detectors.Detector`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
from PIL import Image

from cadestate.config import DetectConfig
from cadestate.lineage import table_digest
from cadestate.prefetch import prefetch
from cadestate.progress import progress
from tasks.detection.detectors import Detections, load_detector
from tasks.detection.model_inputs import model_file_inputs
from tasks.stage import StageContext, StageDef, StageOutput
from warehouse import Warehouse

DET_ID_STRIDE = 10_000  # det_id = frame_index * DET_ID_STRIDE + rank


def load_rgb(path: Path) -> np.ndarray:
    """An image file as RGB uint8[H,W,3].

    Raises:
      OSError: the file is missing, cut short or not an image; the message names it (PIL's
        "Truncated File Read" does not).
    """
    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB"))
    except OSError as e:
        raise OSError(f"{path}: not a readable image ({e.strerror or e})") from None


def detection_rows(clip: str, frame: dict, det: Detections, model_sha256: str) -> list[dict]:
    """``detections`` rows of one frame (``frame``: a ``frames`` row with width, height, index, timestamp)."""
    w, h = frame["width"], frame["height"]
    return [{
        "clip": clip, "det_id": frame["frame_index"] * DET_ID_STRIDE + rank,
        "timestamp_us": frame["timestamp_us"], "frame_index": frame["frame_index"],
        "box": [float(y1 / h), float(x1 / w), float(y2 / h), float(x2 / w)],
        "label": det.names[rank], "label_id": int(det.labels[rank]), "score": float(det.scores[rank]),
        "model_sha256": model_sha256,
    } for rank, (x1, y1, x2, y2) in enumerate(det.boxes.tolist())]


def detect_clip(wh: Warehouse, cfg: DetectConfig, clip: str, run_id: str, show_progress: bool = True) -> StageOutput:
    """Detect objects in every frame of ``clip`` and write its ``detections`` partition."""
    frames = wh.read("frames", partitions=[clip], columns=["timestamp_us", "frame_index", "image_path", "width", "height"])
    frames = sorted(frames.to_pylist(), key=lambda f: f["frame_index"])
    if not frames:
        raise LookupError(f"clip {clip} has no frames: run its frames stage first")
    detector = load_detector(cfg)
    rows: list[dict] = []
    batches = [frames[i:i + cfg.batch_size] for i in range(0, len(frames), cfg.batch_size)]
    # decoding and letterboxing the next batch overlap the network's run on this one
    loaded = prefetch(batches, lambda b: detector.inputs([load_rgb(wh.root / f["image_path"]) for f in b]))
    for batch, inputs in progress(loaded, total=len(batches), description=f"detect {clip}", enabled=show_progress):
        for frame, det in zip(batch, detector.detect_inputs(*inputs)):
            rows += detection_rows(clip, frame, det, detector.sha256)
    table = pa.Table.from_pylist(rows, schema=wh.spec("detections").schema)
    written = wh.write("detections", clip, table)
    labels = sorted({r["label"] for r in rows})
    shown = f" ({', '.join(labels[:8])}{'…' if len(labels) > 8 else ''})" if labels else ""
    return StageOutput(written, table_digest(table), f"{written} boxes in {len(frames)} frames{shown}")


def _run(ctx: StageContext) -> StageOutput:
    return detect_clip(ctx.wh, ctx.cfg, ctx.unit, ctx.run_id, ctx.show_progress)


STAGE = StageDef(
    name="detect", section="detect", scope="clip", upstream=("frames",), tables=("detections",),
    description="detect objects in every frame (ONNX detector)",
    run=_run, config_inputs=model_file_inputs,
)
