"""Stage ``cad_embed``: one appearance descriptor per CAD view render, and the library's whitening.

Reads: ``cad_views`` of one library (renders on a white background). Each render is cropped to the
rendered model (pixels that differ from the background; the whole render when none do) and
embedded exactly like a detection crop (``[embed]`` crop size and context, :mod:`tasks.detection.models.embedder`).
Writes: ``cad_embeddings`` (raw unit-norm descriptors), ``embedding_whitening`` (the
``[cad_embed] whitening`` fitted on them, :mod:`tasks.retrieval.whitening`) and ``cad_model_embeddings``
(per model, the mean of its whitened view descriptors: what retrieval compares tracks with).
With ``whitening = "learned"`` the whitening is the projection `make models` trained
(:mod:`tasks.retrieval.descriptor`), centred on the mean stored with it (one map for every library).
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa
from threadpoolctl import threadpool_limits

from cadestate.config import CadEmbedConfig, EmbedConfig
from cadestate.lineage import digest, table_digest
from cadestate.progress import progress
from schemas.retrieval import CAD_MODEL_EMBEDDINGS
from tasks.cad.views import BACKGROUND
from cadestate.prefetch import prefetch
from tasks.detection.detect import load_rgb
from tasks.detection.embed import vectors_array
from tasks.detection.models.embedder import load_embedder
from tasks.retrieval.descriptor import descriptor_inputs, load_descriptor
from tasks.retrieval.whitening import Whitening, fit_whitening, whitening_table
from tasks.stage import StageContext, StageDef, StageOutput
from warehouse import Warehouse

BACKGROUND_TOLERANCE = 4  # 0-255: a pixel further than this from the background colour is the model


def object_box(rgb: np.ndarray, background: tuple[float, float, float] = BACKGROUND) -> np.ndarray:
    """Pixel box float64[1,4] (x1, y1, x2, y2) of what differs from the background in a render."""
    bg = np.round(np.asarray(background) * 255)
    mask = (np.abs(rgb.astype(np.int16) - bg) > BACKGROUND_TOLERANCE).any(-1)
    if not mask.any():
        return np.array([[0.0, 0.0, rgb.shape[1], rgb.shape[0]]])
    ys, xs = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    return np.array([[xs[0], ys[0], xs[-1] + 1, ys[-1] + 1]], np.float64)


def model_embeddings(library: str, classes: dict[str, str], cad_ids: list[str], whitened: np.ndarray) -> pa.Table:
    """``cad_model_embeddings`` rows, one per model (sorted by cad_id): the mean of its views'
    whitened descriptors float32[N, k] (rows aligned with ``cad_ids``); ``classes``: cad_id -> class."""
    models, index = np.unique(np.asarray(cad_ids, dtype=object), return_inverse=True)
    sums = np.zeros((len(models), whitened.shape[1] if whitened.ndim == 2 else 0), np.float64)
    np.add.at(sums, index, whitened)
    counts = np.bincount(index, minlength=len(models))
    return pa.table({
        "library": [library] * len(models), "cad_id": models.tolist(), "class": [classes[m] for m in models],
        "vector": vectors_array((sums / np.maximum(counts, 1)[:, None]).astype(np.float32)),
        "views": pa.array(counts, pa.int32()),
    }, schema=CAD_MODEL_EMBEDDINGS.schema)


def library_whitening(vectors: np.ndarray, cfg: CadEmbedConfig) -> Whitening:
    """The ``[cad_embed] whitening`` of a library whose raw view descriptors are ``vectors``
    float[N, D]: fitted on them, or for 'learned' the trained file's (its projection and mean:
    one map for every library, so scores of different libraries compare)."""
    if cfg.whitening == "learned":
        projection, _, mean = load_descriptor()
        return fit_whitening(vectors, "learned", cfg.whitening_dims, projection, mean)
    return fit_whitening(vectors, cfg.whitening, cfg.whitening_dims)


def whitened(vectors: np.ndarray, cfg: CadEmbedConfig) -> tuple[Whitening, np.ndarray]:
    """:func:`library_whitening` of ``vectors`` float[N, D] and the vectors it maps, on one BLAS
    thread, as retrieval's products: their last bits depend on the threads, and another core count
    (another machine, a Dask worker) changed every clip's candidates and CAD-selection task id."""
    with threadpool_limits(1, user_api="blas"):
        fitted = library_whitening(vectors, cfg)
        return fitted, fitted.apply(vectors)


def embed_library(wh: Warehouse, embed_cfg: EmbedConfig, cfg: CadEmbedConfig, library: str, run_id: str,
                  show_progress: bool = True) -> StageOutput:
    """Embed every view of ``library``, fit the whitening, write both tables."""
    views = wh.read("cad_views", partitions=[library], columns=["cad_id", "view", "image_path"]).to_pylist()
    views.sort(key=lambda v: (v["cad_id"], v["view"]))
    embedder = load_embedder(embed_cfg)
    chunk = max(embed_cfg.batch_size, 1)
    batches = [views[i:i + chunk] for i in range(0, len(views), chunk)]

    def crops(batch: list[dict]) -> np.ndarray:
        images = [load_rgb(wh.root / v["image_path"]) for v in batch]
        return np.concatenate([embedder.crops(im, object_box(im)) for im in images])

    parts = [embedder.embed_inputs(x) for _, x in progress(prefetch(batches, crops), total=len(batches),
                                                           description=f"embed views {library}", enabled=show_progress)]
    vectors = np.concatenate(parts) if parts else np.zeros((0, 768), np.float32)
    table = pa.table({
        "library": [library] * len(views), "cad_id": [v["cad_id"] for v in views],
        "view": pa.array([v["view"] for v in views], pa.int32()), "vector": vectors_array(vectors),
        "model_sha256": [embedder.sha256] * len(views),
    }, schema=wh.spec("cad_embeddings").schema)
    fitted, projected = whitened(vectors, cfg)
    whitening = whitening_table(library, fitted, len(views)).cast(wh.spec("embedding_whitening").schema)
    classes = {r["cad_id"]: r["class"] for r in wh.read("cad_models", partitions=[library], columns=["cad_id", "class"]).to_pylist()}
    per_model = model_embeddings(library, classes, [v["cad_id"] for v in views], projected)
    written = (wh.write("cad_embeddings", library, table) + wh.write("embedding_whitening", library, whitening)
               + wh.write("cad_model_embeddings", library, per_model))
    return StageOutput(written, digest(table_digest(table), table_digest(whitening), table_digest(per_model)),
                       f"{len(views)} view descriptors, whitening '{whitening['method'][0].as_py()}'")


def _run(ctx: StageContext) -> StageOutput:
    return embed_library(ctx.wh, ctx.config.embed, ctx.cfg, ctx.unit, ctx.run_id, ctx.show_progress)


STAGE = StageDef(
    name="cad_embed", section="cad_embed", scope="library", upstream=("cad_ingest", "cad_views"),
    tables=("cad_embeddings", "embedding_whitening", "cad_model_embeddings"),
    description="embed every CAD view, fit the descriptor whitening",
    extra_sections=("embed",), run=_run, config_inputs=descriptor_inputs,
)
