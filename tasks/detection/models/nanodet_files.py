"""What is known of the NanoDet model without loading it: its file's name, where `make models` puts
it, and its label map (COCO-80). Imports nothing heavy: ``cadestate status`` digests the
detector's file and labels through it (:mod:`tasks.detection.model_inputs`)."""

from __future__ import annotations

import os
from pathlib import Path

ONNX_NAME = "nanodet-m-416.onnx"
COCO_LABELS: tuple[str, ...] = (
    "person", "bicycle", "car", "motorcycle", "airplane", "bus", "train", "truck", "boat",
    "traffic light", "fire hydrant", "stop sign", "parking meter", "bench", "bird", "cat", "dog",
    "horse", "sheep", "cow", "elephant", "bear", "zebra", "giraffe", "backpack", "umbrella",
    "handbag", "tie", "suitcase", "frisbee", "skis", "snowboard", "sports ball", "kite",
    "baseball bat", "baseball glove", "skateboard", "surfboard", "tennis racket", "bottle",
    "wine glass", "cup", "fork", "knife", "spoon", "bowl", "banana", "apple", "sandwich", "orange",
    "broccoli", "carrot", "hot dog", "pizza", "donut", "cake", "chair", "couch", "potted plant",
    "bed", "dining table", "toilet", "tv", "laptop", "mouse", "remote", "keyboard", "cell phone",
    "microwave", "oven", "toaster", "sink", "refrigerator", "book", "clock", "vase", "scissors",
    "teddy bear", "hair drier", "toothbrush",
)


def default_cache_dir() -> Path:
    """$CADESTATE_MODELS (~ expanded, as $CADESTATE_SH3D_DIR's), else ~/.cache/cadestate/models."""
    env = os.environ.get("CADESTATE_MODELS")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "cadestate" / "models"
