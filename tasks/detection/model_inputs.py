"""The configured detector as the stages' inputs digest it: its model file and its label map.

``detect`` reruns when the model file's bytes change; ``label_similarity`` and ``manual_tracks``
when the label map does. Light on purpose (no numpy): ``cadestate status`` computes these digests
for every clip.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

from cadestate.atomic import atomic_write_bytes
from cadestate.config import Config, DetectConfig
from cadestate.lineage import digest, file_sha256
from tasks.detection.models import furniture_files, nanodet_files
from tasks.detection.models.nanodet_files import COCO_LABELS, default_cache_dir

BUILT_IN: dict[str, tuple[str, tuple[str, ...]]] = {
    "furniture": (furniture_files.ONNX_NAME, furniture_files.FURNITURE_LABELS),
    "coco": (nanodet_files.ONNX_NAME, COCO_LABELS),
}
"""``[detect] model`` names of the detectors `make models` builds -> (file name in the models cache, label map)."""


def built_in(cfg: DetectConfig) -> str | None:
    """The built-in detector ``[detect] model`` names ('furniture' when empty), or None for a file."""
    name = cfg.model or "furniture"
    return name if name in BUILT_IN else None


def detector_path(cfg: DetectConfig) -> Path:
    """The ONNX file ``[detect] model`` names: a built-in one in the models cache, or the file."""
    name = built_in(cfg)
    return default_cache_dir() / BUILT_IN[name][0] if name else Path(cfg.model).expanduser()


def model_fingerprint(cfg: DetectConfig) -> str:
    """SHA-256 of the detector file ``cfg`` names (empty when it is missing: the stage then fails clearly)."""
    path = detector_path(cfg).resolve()
    if not path.is_file():
        return ""
    return cached_sha256(path)


def cached_sha256(path: Path) -> str:
    """``file_sha256(path)``, kept in ``<models cache>/.digests/`` with the file's inode, size,
    modification and change times: hashed again only when one of them differs (15 MB cost
    ``cadestate status`` about 20 ms per call). Not kept where the cache cannot be written."""
    st = path.stat()
    stamp = f"{st.st_ino} {st.st_size} {st.st_mtime_ns} {st.st_ctime_ns}"
    kept = default_cache_dir() / ".digests" / f"{digest(str(path))}.txt"
    with contextlib.suppress(OSError, ValueError):
        saved, sha = kept.read_text(encoding="utf-8").split("\n")[:2]
        if saved == stamp and len(sha) == 64:
            return sha
    sha = file_sha256(path)
    with contextlib.suppress(OSError):
        atomic_write_bytes(kept, f"{stamp}\n{sha}\n".encode())
    return sha


def detector_labels(cfg: DetectConfig) -> tuple[str, ...]:
    """The detector's label map: ``[detect] labels``, else the built-in model's, else COCO-80."""
    name = built_in(cfg)
    return tuple(cfg.labels) or (BUILT_IN[name][1] if name else COCO_LABELS)


def labels_digest(cfg: DetectConfig) -> str:
    """Digest of the label map."""
    return digest(*detector_labels(cfg))


def model_file_inputs(config: Config) -> list[str]:
    """``config_inputs`` of ``detect``: the detector's model file."""
    return [model_fingerprint(config.detect)]


def label_map_inputs(config: Config) -> list[str]:
    """``config_inputs`` of the stages that read the detector's label map (the classes people may
    draw, the labels whose similarity to the CAD classes is computed)."""
    return [labels_digest(config.detect)]
