"""Stage ``embed``: one appearance descriptor per detection crop (:mod:`tasks.detection.models.embedder`).

Reads: the clip's ``detections`` and ``frames`` (images). Writes: its ``embeddings`` partition,
``owner = 'detection'``, ``owner_id = det_id``, a raw unit-norm float32 descriptor each (the CAD
library's whitening is applied where descriptors are compared, see :mod:`tasks.retrieval.whitening`).
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from cadestate.config import EmbedConfig
from cadestate.lineage import table_digest
from cadestate.progress import progress
from cadestate.prefetch import prefetch
from tasks.detection.detect import load_rgb
from tasks.detection.models.embedder import Embedder, load_embedder
from tasks.stage import StageContext, StageDef, StageOutput
from warehouse import Warehouse


def pixel_boxes(boxes: list[list[float]], width: int, height: int) -> np.ndarray:
    """Normalised (ymin, xmin, ymax, xmax) [K] -> pixel (x1, y1, x2, y2) float64[K,4]."""
    b = np.asarray(boxes, np.float64).reshape(-1, 4)
    return b[:, [1, 0, 3, 2]] * [width, height, width, height]


def vectors_array(vectors: np.ndarray) -> pa.ListArray:
    """float32[N,D] -> an Arrow list<float32> column of N rows (no Python lists in between); N may be 0."""
    v = np.ascontiguousarray(vectors, np.float32)
    v = v.reshape(len(v), -1) if len(v) else v.reshape(0, 0)
    offsets = np.arange(len(v) + 1, dtype=np.int32) * v.shape[1]
    return pa.ListArray.from_arrays(pa.array(offsets), pa.array(v.ravel()),
                                    type=pa.list_(pa.field("item", pa.float32(), nullable=False)))


def embed_frame_boxes(wh: Warehouse, embedder: Embedder, cfg: EmbedConfig, clip: str, boxes: list[tuple[int, list[float]]],
                      show_progress: bool = False, description: str = "") -> np.ndarray:
    """Descriptors float32[N,D] of N boxes of the clip's frames, each (frame_index, normalised
    (ymin, xmin, ymax, xmax)), in the order given; the crops of several frames go through the
    network together (``[embed] batch_size``). The one way every clip box is embedded (detections,
    drawn boxes)."""
    frames = {f["frame_index"]: f for f in wh.read("frames", partitions=[clip], columns=["frame_index", "image_path", "width", "height"]).to_pylist()}
    by_frame: dict[int, list[int]] = {}
    for k, (index, _) in enumerate(boxes):
        if index not in frames:
            raise ValueError(f"clip {clip}: no frame {index} in the frames table (rerun its frames stage)")
        by_frame.setdefault(index, []).append(k)
    order, crops, parts = [], [], []
    loaded = prefetch(sorted(by_frame), lambda i: load_rgb(wh.root / frames[i]["image_path"]))
    for index, rgb in progress(loaded, total=len(by_frame), description=description or f"embed {clip}", enabled=show_progress):
        f = frames[index]
        crops.append(embedder.crops(rgb, pixel_boxes([boxes[k][1] for k in by_frame[index]], f["width"], f["height"])))
        order += by_frame[index]
        if sum(map(len, crops)) >= cfg.batch_size:
            parts.append(embedder.embed_inputs(np.concatenate(crops)))
            crops = []
    if crops:
        parts.append(embedder.embed_inputs(np.concatenate(crops)))
    vectors = np.concatenate(parts) if parts else np.zeros((0, 0), np.float32)
    out = np.empty_like(vectors)
    out[order] = vectors
    return out


def embed_clip(wh: Warehouse, cfg: EmbedConfig, clip: str, run_id: str, show_progress: bool = True) -> StageOutput:
    """Embed every detection of ``clip`` and write its ``embeddings`` partition."""
    dets = wh.read("detections", partitions=[clip], columns=["det_id", "frame_index", "box"]).to_pylist()
    dets.sort(key=lambda d: (d["frame_index"], d["det_id"]))
    embedder = load_embedder(cfg)
    vectors = embed_frame_boxes(wh, embedder, cfg, clip, [(d["frame_index"], d["box"]) for d in dets], show_progress)
    ids = [d["det_id"] for d in dets]
    table = pa.table({
        "clip": [clip] * len(ids), "owner": ["detection"] * len(ids), "owner_id": pa.array(ids, pa.int64()),
        "vector": vectors_array(vectors),
        "model_sha256": [embedder.sha256] * len(ids),
    }, schema=wh.spec("embeddings").schema)
    written = wh.write("embeddings", clip, table)
    return StageOutput(written, table_digest(table), f"{written} descriptors")


def _run(ctx: StageContext) -> StageOutput:
    return embed_clip(ctx.wh, ctx.cfg, ctx.unit, ctx.run_id, ctx.show_progress)


STAGE = StageDef(
    name="embed", section="embed", scope="clip", upstream=("frames", "detect"), tables=("embeddings",),
    description="one appearance descriptor per detection",
    run=_run,
)
