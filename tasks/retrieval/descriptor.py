"""The learned retrieval descriptor: a linear projection of the backbone descriptor, trained by
``make models`` (:mod:`bench.descriptor_train`) on crops of rendered rooms against the CAD
library's own views.

File: ``<models cache>/descriptor-projection.npz`` (``$CADESTATE_MODELS``, as the detector), with
``projection`` float32[k, D] (D = the embedder's 768), ``mean`` float32[D] (the mean view
descriptor of the library it was trained on, which the training centred on) and ``meta`` (a JSON
string: the training spec and seed, the library it was trained on, held-out accuracy). Its SHA-256 versions it: the
``cad_embed`` stage digests the file as an input (:func:`descriptor_inputs`), so a retrained
projection re-embeds the libraries and reruns retrieval.

``[cad_embed] whitening = "learned"`` applies it as a :class:`tasks.retrieval.whitening.Whitening`
whose mean and projection are the file's: ``w = normalise(P (v - mean))``, the same map the
training optimised, for every library alike (a library centred on its own mean would score on
another scale: a small one's models would come out near the top for any object).

Light on purpose (numpy only inside the functions that read or write the file): ``cadestate
status`` digests the file through :func:`descriptor_inputs`.
"""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import TYPE_CHECKING

from cadestate.atomic import atomic_write_bytes
from cadestate.config import Config
from tasks.detection.model_inputs import cached_sha256
from tasks.detection.models.nanodet_files import default_cache_dir

if TYPE_CHECKING:
    import numpy as np

DESCRIPTOR_NAME = "descriptor-projection.npz"


class DescriptorMissing(FileNotFoundError):
    """The learned descriptor file is not there (``make models`` builds it)."""


def descriptor_path() -> Path:
    """Where `make models` writes the learned projection."""
    return default_cache_dir() / DESCRIPTOR_NAME


def save_descriptor(path: Path, projection: np.ndarray, mean: np.ndarray, meta: dict) -> Path:
    """Write ``projection`` float32[k, D], ``mean`` float32[D] and ``meta`` to ``path`` atomically;
    the bytes depend on the values only (numpy's archive entries carry a fixed date)."""
    import numpy as np

    buf = io.BytesIO()
    np.savez(buf, projection=np.ascontiguousarray(projection, np.float32), mean=np.ascontiguousarray(mean, np.float32),
             meta=np.array(json.dumps(meta, sort_keys=True)))
    atomic_write_bytes(path, buf.getvalue())
    return path


def load_descriptor(path: Path | None = None) -> tuple[np.ndarray, dict, np.ndarray]:
    """(projection float32[k, D], meta, mean float32[D]) of the descriptor file (default
    :func:`descriptor_path`)."""
    import zipfile

    import numpy as np

    path = path or descriptor_path()
    if not path.is_file():
        raise DescriptorMissing(f"{path}: no learned descriptor; run `make models` (or set [cad_embed] whitening "
                                f"to 'whiten')")
    try:
        with np.load(path, allow_pickle=False) as f:
            projection, meta = f["projection"], json.loads(str(f["meta"]))
            mean = f["mean"] if "mean" in f.files else None
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as e:  # BadZipFile: a file cut short
        raise DescriptorMissing(f"{path}: not a descriptor file ({e}); run `make models` again") from None
    if projection.ndim != 2 or projection.dtype != np.float32:
        raise DescriptorMissing(f"{path}: projection must be float32[k, D], got {projection.dtype}{list(projection.shape)}")
    if mean is None or mean.dtype != np.float32 or mean.shape != projection.shape[1:]:
        shape = "none" if mean is None else f"{mean.dtype}{list(mean.shape)}"
        raise DescriptorMissing(f"{path}: mean must be float32[{projection.shape[1]}], got {shape} (a file made before "
                                "the mean was kept); run `make models` again")
    if not (np.isfinite(projection).all() and np.isfinite(mean).all()):  # every score NaN: no track had a candidate
        raise DescriptorMissing(f"{path}: holds values that are not finite (a training that diverged?); run `make models` "
                                "again")
    return projection, meta, mean


def descriptor_inputs(config: Config) -> list[str]:
    """``config_inputs`` of ``cad_embed``: the descriptor file's SHA-256 when the whitening is
    'learned' (empty when the file is missing: the stage then fails clearly)."""
    if config.cad_embed.whitening != "learned":
        return []
    path = descriptor_path()
    return [cached_sha256(path) if path.is_file() else ""]
