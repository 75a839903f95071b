"""Stage ``detect``: run the configured ONNX detector (:mod:`tasks.detection.detectors`) on every frame of a clip.

Reads: the clip's ``frames`` (images). Writes: its ``detections`` partition, one row per kept box
with the box normalised as in CAD-Estate, (ymin, xmin, ymax, xmax) in [0, 1] of the image (origin
top-left, y down), and ``det_id = frame_index * 10000 + rank`` (rank by score within the frame).
Boxes whose label is not in ``[detect] classes`` (when set) are dropped before ranking. With
``[detect] temporal_weight`` > 0 the network keeps boxes down to ``candidate_threshold``, the clip's
boxes are rescored over time (:mod:`tasks.detection.temporal`) and those whose new score reaches
``score_threshold`` are kept: ``score`` is the new score, ``frame_score`` the network's on its frame.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pyarrow as pa
from PIL import Image

from cadestate.config import DetectConfig
from cadestate.lineage import table_digest
from cadestate.prefetch import prefetch
from cadestate.progress import progress
from tasks.detection.detectors import Detections, load_detector
from tasks.detection.temporal import FrameDetections, temporal_scores
from tasks.detection.model_inputs import model_file_inputs
from tasks.stage import StageContext, StageDef, StageOutput
from warehouse import Warehouse

DET_ID_STRIDE = 10_000  # det_id = frame_index * DET_ID_STRIDE + rank


def load_rgb(path: Path) -> np.ndarray:
    """An image file as RGB uint8[H,W,3]."""
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"))


def detection_rows(clip: str, frame: dict, det: Detections, model_sha256: str, classes: tuple[str, ...],
                   final: np.ndarray, threshold: float) -> list[dict]:
    """``detections`` rows of one frame (``frame``: a ``frames`` row with width, height, index,
    timestamp): its boxes ranked by their final scores float[K] (``det.scores`` are the network's),
    those under ``threshold`` dropped."""
    w, h = frame["width"], frame["height"]
    keep = [k for k in np.argsort(-final, kind="stable").tolist()
            if final[k] >= threshold and (not classes or det.names[k] in classes)]
    return [{
        "clip": clip, "det_id": frame["frame_index"] * DET_ID_STRIDE + rank,
        "timestamp_us": frame["timestamp_us"], "frame_index": frame["frame_index"],
        "box": [float(y1 / h), float(x1 / w), float(y2 / h), float(x2 / w)],
        "label": det.names[k], "label_id": int(det.labels[k]), "score": float(final[k]),
        "frame_score": float(det.scores[k]), "model_sha256": model_sha256,
    } for rank, k in enumerate(keep) for x1, y1, x2, y2 in [det.boxes[k].tolist()]]


def network_config(cfg: DetectConfig) -> DetectConfig:
    """The ``[detect]`` the network runs with: down to ``candidate_threshold`` when boxes are
    rescored over time (they are kept by ``score_threshold`` afterwards)."""
    if cfg.temporal_weight == 0:
        return cfg
    return replace(cfg, score_threshold=min(cfg.candidate_threshold, cfg.score_threshold))


def detect_clip(wh: Warehouse, cfg: DetectConfig, clip: str, run_id: str, show_progress: bool = True) -> StageOutput:
    """Detect objects in every frame of ``clip`` and write its ``detections`` partition."""
    frames = wh.read("frames", partitions=[clip], columns=["timestamp_us", "frame_index", "image_path", "width", "height"])
    frames = sorted(frames.to_pylist(), key=lambda f: f["frame_index"])
    if not frames:
        raise LookupError(f"clip {clip} has no frames: run its frames stage first")
    detector = load_detector(network_config(cfg))
    found: list[Detections] = []
    batches = [frames[i:i + cfg.batch_size] for i in range(0, len(frames), cfg.batch_size)]
    # decoding and letterboxing the next batch overlap the network's run on this one
    loaded = prefetch(batches, lambda b: detector.inputs([load_rgb(wh.root / f["image_path"]) for f in b]))
    for _, inputs in progress(loaded, total=len(batches), description=f"detect {clip}", enabled=show_progress):
        found += detector.detect_inputs(*inputs)
    scores = temporal_scores([FrameDetections(d.boxes, d.scores, d.labels) for d in found],
                             cfg.temporal_weight, cfg.temporal_link_iou, cfg.temporal_frames)
    rows = [r for frame, det, s in zip(frames, found, scores)
            for r in detection_rows(clip, frame, det, detector.sha256, cfg.classes, s, cfg.score_threshold)]
    table = pa.Table.from_pylist(rows, schema=wh.spec("detections").schema)
    written = wh.write("detections", clip, table)
    labels = sorted({r["label"] for r in rows})
    shown = f" ({', '.join(labels[:8])}{'…' if len(labels) > 8 else ''})" if labels else ""
    rescored = f"; {sum(len(d) for d in found)} candidates rescored over time" if cfg.temporal_weight else ""
    return StageOutput(written, table_digest(table), f"{written} boxes in {len(frames)} frames{shown}{rescored}")


def _run(ctx: StageContext) -> StageOutput:
    return detect_clip(ctx.wh, ctx.cfg, ctx.unit, ctx.run_id, ctx.show_progress)


STAGE = StageDef(
    name="detect", section="detect", scope="clip", upstream=("frames",), tables=("detections",),
    description="detect objects in every frame (ONNX detector)",
    run=_run, config_inputs=model_file_inputs,
)
