"""Train the retrieval descriptor: a linear projection of the backbone descriptor, learned so that
an object's crops in rendered rooms rank its own CAD model first (``make models``).

Model. With raw unit descriptors x float[768] (:mod:`tasks.detection.models.embedder`), the
library's mean view descriptor mu and the learned matrix W float32[k, 768], a descriptor is
``z(x) = normalise(W (x - mu))`` and a CAD model m with views v_m1..v_mV is
``p_m = mean_j z(v_mj)``: exactly what ``[cad_embed] whitening = "learned"`` computes
(:mod:`tasks.retrieval.descriptor`), and what retrieval compares a track's detections with.
W starts as the library's PCA whitening (``whitening = "whiten"``, k = 128) and is trained with
the cross-entropy of ``z(x) . p_m / TAU`` over all models of the library against the crop's own
model (contrastive: every other model is a negative), Adam, on one thread (reproducible).

Data: the crops of :mod:`bench.descriptor_data` (training rooms only, seeds disjoint from any
benchmark's; rendered on every core, :mod:`bench.room_pool`); the CAD views' raw descriptors
from a warehouse where the library is ingested. Rooms are split by index into training and
held-out rooms; the held-out top-1/top-10 are reported, and the number of steps is fixed, chosen
on the held-out rooms (never on a benchmark): top-10 0.784 at 1,500 steps, 0.815 at 3,000, 0.828
at 6,000 (the default; 128 or 256 dimensions at 3,000 gave 0.815 and 0.825). So was the number of
rooms: on the 240 rooms held out of 1,440 (10,256 crops), top-1 / top-10 0.487 / 0.810 from 240
rooms, 0.565 / 0.858 from 720, 0.591 / 0.874 from 1,440 (the default): the projection overfits
fewer rooms (top-1 on its own training crops 0.945 from 240, 0.707 from 1,440). On 1,440 rooms,
12,000 steps (the default) gave 0.620 / 0.889 against 0.591 / 0.874 at 6,000.

The training warehouse gets the embedded CAD library when it has none (the library flow with
``whitening = "whiten"``: the learned one does not exist yet). The file's ``meta.recipe`` digests
what made it (the spec, this code and the room generator's, the embedder, the library): a run
whose recipe equals the file's returns at once, so ``make models`` retrains only when one changed.

    python -m bench.descriptor_train --warehouse W --out MODELS_DIR [--seed 1] [--rooms 240]
"""

from __future__ import annotations

import functools
import hashlib
import json
import sys
import time
from collections.abc import Sequence
from contextlib import ExitStack
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from bench.descriptor_data import CropSet, room_crops
from bench.detector_train import sources_digest
from bench.room_pool import default_workers, map_rooms
from bench.training_cli import training_main
from cadestate.atomic import atomic_write_bytes
from cadestate.lineage import digest, file_sha256
from cadestate.progress import progress
from tasks.retrieval.descriptor import DESCRIPTOR_NAME, save_descriptor
from tasks.retrieval.index import list_matrix
from tasks.retrieval.whitening import fit_whitening
from warehouse import Warehouse

TAU = 0.05
"""Softmax temperature of the contrastive loss (cosines are in [-1, 1])."""


@dataclass(frozen=True)
class TrainSpec:
    """What to train: ``rooms`` rendered rooms (every ``holdout_every``-th held out), ``frames``
    frames each, ``dims`` output dimensions, ``steps`` Adam steps of ``batch`` crops at ``lr``."""

    seed: int = 1
    rooms: int = 1440
    frames: int = 8
    holdout_every: int = 6
    dims: int = 128
    steps: int = 12000
    batch: int = 256
    lr: float = 3e-3
    weight_decay: float = 1e-4


@dataclass(frozen=True)
class LibraryViews:
    """The library's raw view descriptors: ``vectors`` float32[V, D], ``model`` int64[V] (index into
    ``cad_ids``), ``cad_ids`` object[M] sorted."""

    vectors: np.ndarray
    model: np.ndarray
    cad_ids: np.ndarray


def library_views(wh: Warehouse) -> LibraryViews:
    """Every ingested library's raw view descriptors (``cad_embeddings``)."""
    table = wh.read("cad_embeddings", columns=["cad_id", "view", "vector"]).sort_by([("cad_id", "ascending"), ("view", "ascending")])
    if not table.num_rows:
        raise SystemExit(f"{wh.root}: no CAD view descriptors; run `cadestate cad ingest` on it first")
    ids = np.asarray(table.column("cad_id").to_pylist(), dtype=object)
    cad_ids, model = np.unique(ids, return_inverse=True)
    return LibraryViews(list_matrix(table.column("vector")), model.astype(np.int64), cad_ids)


def _room_state(wh_root: Path, stack: ExitStack) -> tuple:
    """One process's (library rows, warehouse root, embedder, renderer) for :func:`_room`."""
    from cadestate.config import EmbedConfig
    from cadestate.render import Renderer
    from tasks.detection.models.embedder import load_embedder

    models = Warehouse(wh_root).read("cad_models").to_pylist()
    return models, wh_root, load_embedder(EmbedConfig()), stack.enter_context(Renderer(640, 360, 2))


NO_WALK = "no collision-free camera path"
"""How :func:`bench.walkthrough.camera_path` says that a room has no walk (room 865 of seed 1)."""


def _room(spec: TrainSpec, state: tuple, room: int) -> CropSet | None:
    """The crops of one room; None for a room without a camera walk (as the detector's rooms skip it)."""
    models, wh_root, embedder, renderer = state
    try:
        return room_crops(spec.seed, room, models, wh_root, embedder, renderer, spec.frames)
    except RuntimeError as e:
        if NO_WALK not in str(e):
            raise
        return None


def render_crops(wh: Warehouse, spec: TrainSpec, show_progress: bool = True, workers: int | None = None,
                 rooms: Sequence[int] | None = None) -> CropSet:
    """The crops of the training rooms ``rooms`` (default: all ``spec.rooms``;
    :func:`bench.descriptor_data.room_crops`), rendered on ``workers`` processes (default: one per
    core; :mod:`bench.room_pool`); rooms without a walk or without a crop add none."""
    rooms = range(spec.rooms) if rooms is None else rooms
    parts = map_rooms(functools.partial(_room_state, wh.root), functools.partial(_room, spec), rooms,
                      default_workers() if workers is None else workers, "training rooms", show_progress)
    return CropSet.concatenate([p for p in parts if p is not None and len(p.cad_ids)])


def _ranks(z: np.ndarray, prototypes: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Rank (0 = first) of each crop's own model among all models."""
    scores = z @ prototypes.T
    own = scores[np.arange(len(z)), target]
    return (scores > own[:, None]).sum(1)


def evaluate(W: np.ndarray, mu: np.ndarray, views: LibraryViews, crops: CropSet) -> dict:
    """Top-1 and top-10 accuracy of crops against the library with projection W."""
    def z(x: np.ndarray) -> np.ndarray:
        y = (x - mu) @ W.T
        return y / np.maximum(np.linalg.norm(y, axis=1, keepdims=True), 1e-12)

    sums = np.zeros((len(views.cad_ids), W.shape[0]))
    np.add.at(sums, views.model, z(views.vectors))
    prototypes = sums / np.bincount(views.model, minlength=len(views.cad_ids))[:, None]
    target = np.searchsorted(views.cad_ids, crops.cad_ids)
    ranks = _ranks(z(crops.vectors), prototypes, target)
    return {"crops": int(len(ranks)), "top1": round(float(np.mean(ranks < 1)), 4), "top10": round(float(np.mean(ranks < 10)), 4)}


def train(views: LibraryViews, crops: CropSet, spec: TrainSpec, show_progress: bool = True) -> tuple[np.ndarray, dict]:
    """The projection float32[dims, D] trained on ``crops`` of the non-held-out rooms, and a
    report: held-out and training top-1/top-10 before and after. Runs torch on one thread with
    deterministic algorithms (restored afterwards), so the same inputs give the same bytes."""
    import torch

    threads, deterministic = torch.get_num_threads(), torch.are_deterministic_algorithms_enabled()
    torch.set_num_threads(1)
    torch.use_deterministic_algorithms(True)
    try:
        return _train(torch, views, crops, spec, show_progress)
    finally:
        torch.set_num_threads(threads)
        torch.use_deterministic_algorithms(deterministic)


def _train(torch, views: LibraryViews, crops: CropSet, spec: TrainSpec, show_progress: bool) -> tuple[np.ndarray, dict]:
    torch.manual_seed(spec.seed)
    mu = views.vectors.mean(0)
    W0 = fit_whitening(views.vectors, "whiten", spec.dims).projection
    known = np.isin(crops.cad_ids, views.cad_ids)
    held = (crops.rooms % spec.holdout_every) == spec.holdout_every - 1
    train_set, held_set = crops.take(known & ~held), crops.take(known & held)

    W = torch.nn.Parameter(torch.tensor(W0, dtype=torch.float32))
    V = torch.tensor(views.vectors - mu, dtype=torch.float32)
    counts = torch.tensor(np.bincount(views.model, minlength=len(views.cad_ids)), dtype=torch.float32)
    view_model = torch.tensor(views.model)
    X = torch.tensor(train_set.vectors - mu, dtype=torch.float32)
    Y = torch.tensor(np.searchsorted(views.cad_ids, train_set.cad_ids))
    optimiser = torch.optim.AdamW([W], lr=spec.lr, weight_decay=spec.weight_decay)
    generator = torch.Generator().manual_seed(spec.seed)
    losses = []
    for _ in progress(range(spec.steps), total=spec.steps, description="training", enabled=show_progress):
        pick = torch.randint(len(X), (spec.batch,), generator=generator)
        z = torch.nn.functional.normalize(X[pick] @ W.T, dim=1)
        zv = torch.nn.functional.normalize(V @ W.T, dim=1)
        prototypes = torch.zeros(len(counts), W.shape[0]).index_add(0, view_model, zv) / counts[:, None]
        loss = torch.nn.functional.cross_entropy(z @ prototypes.T / TAU, Y[pick])
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        losses.append(float(loss.detach()))
    trained = W.detach().numpy().astype(np.float32)
    report = {"train_crops": int(len(train_set.vectors)), "heldout_crops": int(len(held_set.vectors)),
              "heldout_before": evaluate(W0, mu, views, held_set), "heldout_after": evaluate(trained, mu, views, held_set),
              "train_after": evaluate(trained, mu, views, train_set),
              "loss_first_100": round(float(np.mean(losses[:100])), 4), "loss_last_100": round(float(np.mean(losses[-100:])), 4)}
    return trained, report


DATA_SOURCES = ("bench/descriptor_data.py", "bench/scene.py", "bench/room.py", "bench/textures.py", "bench/walkthrough.py",
                "cadestate/render.py", "tasks/detection/models/embedder.py")
"""The code that makes the training crops (its bytes key the crops kept beside the descriptor)."""
RECIPE_SOURCES = (*DATA_SOURCES, "bench/descriptor_train.py")
"""The code whose bytes enter the recipe digest (relative to the repository root)."""


def recipe(spec: TrainSpec, library: str, embedder_sha256: str) -> str:
    """Digest of what makes the descriptor: the spec, :data:`RECIPE_SOURCES`, the embedder
    graph's SHA-256 and the library's digest."""
    return digest(json.dumps(asdict(spec), sort_keys=True), sources_digest(RECIPE_SOURCES), embedder_sha256, library, str(TAU))


def crops_path(out_dir: Path, spec: TrainSpec, library: str) -> Path:
    """Where the training crops of ``spec``'s rooms of ``library`` (its digest) are kept: keyed by
    what makes them (seed, rooms, frames, the library, :data:`DATA_SOURCES`' bytes), not by the
    training's knobs, so a retraining alone reuses them."""
    key = digest(library, str(spec.seed), str(spec.rooms), str(spec.frames), sources_digest(DATA_SOURCES))
    return out_dir / f"descriptor-crops-{key[:16]}.npz"


def build(wh: Warehouse, out_dir: Path, spec: TrainSpec, show_progress: bool = True) -> Path:
    """Render the training crops (kept beside the output, per spec and library), train, write the
    descriptor file into ``out_dir``; returns its path. Returns at once when the file there was
    made by the same recipe (:func:`recipe`)."""
    from cadestate.config import EmbedConfig
    from tasks.detection.models.embedder import load_embedder
    from tasks.retrieval.descriptor import DescriptorMissing, load_descriptor

    views = library_views(wh)
    library = digest(*views.cad_ids.tolist())
    embedder = load_embedder(EmbedConfig())
    made_by = recipe(spec, library, embedder.sha256)
    try:
        if load_descriptor(out_dir / DESCRIPTOR_NAME)[1].get("recipe") == made_by:
            return out_dir / DESCRIPTOR_NAME
    except DescriptorMissing:
        pass
    crops_file = crops_path(out_dir, spec, library)
    t0 = time.perf_counter()
    if crops_file.is_file():
        crops = CropSet.load(crops_file)
    else:
        minutes = max(1, round(spec.rooms / 130))  # 1,440 rooms took 11 minutes (2026-12-05)
        print(f"descriptor: rendering {spec.rooms} training rooms, {spec.frames} frames each (about {minutes} minutes on "
              f"2 cores; kept in {crops_file.name})", file=sys.stderr, flush=True)
        crops = render_crops(wh, spec, show_progress)
        crops.save(crops_file)
    t1 = time.perf_counter()
    print(f"descriptor: training on {len(crops.vectors)} crops (every {spec.holdout_every}th room's held out), {spec.steps} steps "
          f"(about {max(1, round(spec.steps / 1500))} minutes)", file=sys.stderr, flush=True)
    W, report = train(views, crops, spec, show_progress)
    meta = {"spec": asdict(spec), "recipe": made_by, "library_digest": library, "models": int(len(views.cad_ids)), "tau": TAU,
            "crops_sha256": hashlib.sha256(crops.vectors.tobytes()).hexdigest(), **report}
    path = save_descriptor(out_dir / DESCRIPTOR_NAME, W, views.vectors.mean(0), meta)
    timings = {"render_s": round(t1 - t0, 1), "train_s": round(time.perf_counter() - t1, 1)}
    atomic_write_bytes(out_dir / "descriptor-report.json", json.dumps({**meta, **timings, "sha256": file_sha256(path)}, indent=1).encode())
    return path


def main(argv: list[str] | None = None) -> int:
    return training_main(__doc__, TrainSpec, build, "the descriptor file", argv)


if __name__ == "__main__":
    sys.exit(main())
