"""What the furniture detector buys: both built-in detectors on the same benchmark frames and ground truth.

Each detector of :data:`DETECTORS` (``[detect] model = "coco"`` and ``"furniture"``, every other
``[detect]`` setting at its default (the fitted canvas, 480 on its longer side), and the furniture
detector on the 416 x 416 square canvas it was trained on, the default until 2026-12-05) runs on the camera-line frames of every clip of each
benchmark folder, decoded from the clip's video as the pipeline decodes them, and is scored as
``cadestate bench report`` scores the ``detections`` table
(:func:`bench.eval_detection.evaluate_detections`, the ignore rule of :mod:`bench.ignore`): recall
and precision at IoU 0.5 on the furniture classes, per class, and class-agnostic recall. No
warehouse is needed, so the detectors are compared without running the pipeline for each.

    python -m bench.detector_eval BENCH_DIR [BENCH_DIR ...] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from bench.benchmark import CLASS_NAMES, ignore_rule, read_manifest
from bench.eval_detection import FrameBoxes, evaluate_detections
from cadestate.config import DetectConfig
from schemas.official import read_frames, read_objects
from tasks.detection.detectors import Detector, load_detector
from tasks.video.decode import decode_at

DETECTORS = {"coco": DetectConfig(model="coco"), "furniture": DetectConfig(model="furniture"),
             "furniture, square canvas": DetectConfig(model="furniture", canvas="square", input_size=416)}
"""The detectors compared, by the name their row of the report has."""


def clip_frames(bench_dir: Path, clip: str, detector: Detector) -> list[FrameBoxes]:
    """Ground truth (ignore rule applied) and ``detector``'s boxes on every camera-line frame of ``clip``."""
    frames = read_frames(bench_dir / clip / "frames.json")
    objects = read_objects(bench_dir / clip / "objects.json").objects
    ignored = ignore_rule(bench_dir, clip)
    stamps = np.array([f.timestamp for f in frames.frames], np.int64)
    out = []
    for stamp, decoded in zip(stamps.tolist(), decode_at(bench_dir / f"{clip}.mp4", stamps)):
        h, w = decoded.rgb.shape[:2]
        gt = [(e.box, CLASS_NAMES.get(o.cls, "other"), ignored(o, e)) for o in objects for e in o.track if e.timestamp == stamp]
        det = detector.detect([decoded.rgb])[0]
        boxes = det.boxes.astype(np.float64)[:, [1, 0, 3, 2]] / [h, w, h, w]  # (ymin, xmin, ymax, xmax) normalised
        out.append(FrameBoxes(np.array([b for b, _, _ in gt], np.float64).reshape(-1, 4), [c for _, c, _ in gt],
                              np.array([i for _, _, i in gt], bool), boxes, list(det.names)))
    return out


def run(bench_dirs: list[Path]) -> dict:
    """{benchmark folder: {detector name: evaluate_detections result}} for the :data:`DETECTORS`."""
    result: dict = {}
    for bench_dir in bench_dirs:
        clips = read_manifest(bench_dir).clips
        for name, cfg in DETECTORS.items():
            detector = load_detector(cfg)
            frames = [f for clip in clips for f in clip_frames(Path(bench_dir), clip, detector)]
            result.setdefault(str(bench_dir), {})[name] = evaluate_detections(frames)
    return result


def markdown(result: dict) -> list[str]:
    """One table per benchmark: each detector's recall, precision, class-agnostic recall, and the per-class recall."""
    lines = []
    for bench_dir, by_model in result.items():
        classes = sorted({c for r in by_model.values() for c, v in r["per_class"].items() if v["ground_truth"]})
        lines += [f"Detection on {bench_dir} (IoU 0.5, furniture classes)", "",
                  "| detector | recall | precision | class-agnostic recall | " + " | ".join(classes) + " |",
                  "|---|---:|---:|---:|" + "---:|" * len(classes)]
        for model, r in by_model.items():
            per = [r["per_class"].get(c, {}).get("recall") for c in classes]
            lines.append(f"| {model} | {r['recall']} | {r['precision']} | {r['class_agnostic_recall']} | "
                         + " | ".join("-" if v is None else f"{v:.2f}" for v in per) + " |")
        lines.append("")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("bench_dirs", nargs="+", type=Path)
    parser.add_argument("--json", action="store_true", help="print the results as JSON")
    args = parser.parse_args(argv)
    result = run(args.bench_dirs)
    print(json.dumps(result, indent=1) if args.json else "\n".join(markdown(result)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
