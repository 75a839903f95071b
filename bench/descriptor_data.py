"""Training crops for the retrieval descriptor: objects of rendered rooms, cropped as detections are.

Each training room is a furnished room of :func:`bench.scene.generate_scene` seen along a camera
walk of :func:`bench.walkthrough.camera_path`, rendered exactly as the benchmark renders its
clips (:class:`cadestate.render.Renderer`, Lambert + ambient, textures, 2x2 supersampling).
Every object visible enough in a frame gives one crop: the bounding box of its visible pixels in
the instance-id mask, jittered as a detector's box would be, cut from the frame after a random
JPEG round trip (the benchmark's frames come through H.264), and embedded by the pipeline's own
embedder (:class:`tasks.detection.models.embedder.Embedder`): the raw backbone descriptor that
:mod:`bench.descriptor_train` learns to project.

Seeds: room ``r`` of training seed ``s`` is scene seed ``TRAIN_SEED_BASE + s * 1_000_000 + r``
(:func:`room_seed`). A benchmark's clip ``i`` of seed ``S`` is scene seed ``S * 1000 + i``
(:mod:`bench.benchmark`), below ``TRAIN_SEED_BASE`` for every benchmark seed under 10^9, so no
training room is a benchmark room (:func:`is_training_seed` states it, a test holds it).
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from bench.scene import generate_scene
from bench.walkthrough import ROOM_INSTANCE_ID, WalkthroughSpec, camera_path, load_mesh, random_lighting
from cadestate.atomic import atomic_write_bytes
from cadestate.geometry import hfov_intrinsics, intrinsics_matrix
from cadestate.render import Camera, Instance, Renderer
from tasks.detection.models.embedder import Embedder

TRAIN_SEED_BASE = 10**12
"""Scene seeds of training rooms start here; benchmark scene seeds (seed * 1000 + i) stay below."""
MIN_VISIBLE_PX = 400
"""An object gives a crop in a frame when at least this many of its pixels are visible..."""
MIN_BOX_SIDE_PX = 16
"""... and its visible box is at least this many pixels on each side."""
BOX_JITTER = 0.06
"""Standard deviation of each box side's shift, as a fraction of the box's size."""
JPEG_QUALITY = (40, 95)
"""Range of the JPEG quality each frame is round-tripped at."""


def room_seed(seed: int, room: int) -> int:
    """The scene seed of training room ``room`` of training seed ``seed`` (both >= 0, room < 10^6)."""
    if seed < 0 or not 0 <= room < 1_000_000:
        raise ValueError(f"training seed {seed} and room {room}: need seed >= 0 and 0 <= room < 1000000")
    return TRAIN_SEED_BASE + seed * 1_000_000 + room


def is_training_seed(scene_seed: int) -> bool:
    """True for the scene seeds of training rooms (:func:`room_seed`)."""
    return scene_seed >= TRAIN_SEED_BASE


@dataclass(frozen=True)
class CropSet:
    """Raw descriptors of object crops: ``vectors`` float32[N, D] (unit norm, the embedder's
    output), ``cad_ids`` object[N] (the model each crop shows), ``rooms`` int64[N] (the room index
    it was rendered in), ``visible_px`` int64[N]."""

    vectors: np.ndarray
    cad_ids: np.ndarray
    rooms: np.ndarray
    visible_px: np.ndarray

    def take(self, mask: np.ndarray) -> CropSet:
        """The crops where ``mask`` bool[N] is true."""
        return CropSet(self.vectors[mask], self.cad_ids[mask], self.rooms[mask], self.visible_px[mask])

    @staticmethod
    def concatenate(parts: list[CropSet]) -> CropSet:
        if not parts:
            return CropSet(np.zeros((0, 0), np.float32), np.zeros(0, object), np.zeros(0, np.int64), np.zeros(0, np.int64))
        return CropSet(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("vectors", "cad_ids", "rooms", "visible_px")))

    def save(self, path: Path) -> None:
        """Write the set to ``path`` atomically (folders made as needed)."""
        buf = io.BytesIO()
        np.savez(buf, vectors=self.vectors, cad_ids=self.cad_ids.astype(str), rooms=self.rooms, visible_px=self.visible_px)
        atomic_write_bytes(path, buf.getvalue())

    @staticmethod
    def load(path: Path) -> CropSet:
        with np.load(path) as f:
            return CropSet(f["vectors"], f["cad_ids"].astype(object), f["rooms"], f["visible_px"])


def jitter_boxes(boxes: np.ndarray, rng: np.random.Generator, sigma: float = BOX_JITTER) -> np.ndarray:
    """Pixel boxes float[K,4] (x1, y1, x2, y2), each side shifted by N(0, sigma * size); a box
    keeps at least 4 px a side."""
    b = np.asarray(boxes, np.float64).reshape(-1, 4)
    w, h = b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]
    size = np.stack([w, h, w, h], axis=1)
    out = b + rng.normal(0.0, sigma, b.shape) * size
    out[:, 2:] = np.maximum(out[:, 2:], out[:, :2] + 4)
    return out


def jpeg_round_trip(rgb: np.ndarray, quality: int) -> np.ndarray:
    """uint8[H,W,3] -> the same image after JPEG compression at ``quality``."""
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="JPEG", quality=int(quality))
    return np.asarray(Image.open(io.BytesIO(buf.getvalue())).convert("RGB"))


def visible_boxes(instance_id: np.ndarray, count: int) -> list[tuple[int, np.ndarray, int]]:
    """(object index k, pixel box float64[4] x1 y1 x2 y2, visible pixels) of the objects
    (instance ``k + 1``, k < ``count``) visible enough in an instance-id mask int[H,W]."""
    out = []
    ids = instance_id.ravel()
    counts = np.bincount(ids[ids > ROOM_INSTANCE_ID], minlength=count + 1)
    for k in np.flatnonzero(counts[1:count + 1] >= MIN_VISIBLE_PX):
        mask = instance_id == k + 1
        rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
        box = np.array([cols[0], rows[0], cols[-1] + 1, rows[-1] + 1], np.float64)
        if min(box[2] - box[0], box[3] - box[1]) >= MIN_BOX_SIDE_PX:
            out.append((int(k), box, int(counts[k + 1])))
    return out


def room_crops(seed: int, room: int, models: list[dict], wh_root: Path, embedder: Embedder, renderer: Renderer,
               frames: int, spec: WalkthroughSpec = WalkthroughSpec()) -> CropSet:
    """The crops of training room ``room`` (scene seed :func:`room_seed`): ``frames`` frames evenly
    spaced along its camera walk, every object visible enough in each (see the module docstring).
    Deterministic in (seed, room, models, spec, frames)."""
    scene_seed = room_seed(seed, room)
    scene = generate_scene(scene_seed, models)
    rng = np.random.default_rng([scene_seed, 0xDE5C])
    lighting = random_lighting(rng)
    poses = camera_path(scene, spec, rng)
    K = intrinsics_matrix(hfov_intrinsics(spec.hfov_deg, spec.width, spec.height), spec.width, spec.height)
    instances = [Instance(m, np.eye(4), ROOM_INSTANCE_ID) for m in scene.room.meshes] + [
        Instance(load_mesh(Path(wh_root) / o.mesh_path), o.object_to_world(), k + 1) for k, o in enumerate(scene.objects)]
    vectors, cad_ids, visible = [], [], []
    for i in np.linspace(0, len(poses) - 1, frames).round().astype(int):
        result = renderer.render(instances, Camera(K, poses[i, :, :3], poses[i, :, 3], spec.width, spec.height),
                                 lighting, (0.9, 0.9, 0.9))
        found = visible_boxes(result.instance_id, len(scene.objects))
        if not found:
            continue
        rgb = jpeg_round_trip(result.rgb, int(rng.integers(JPEG_QUALITY[0], JPEG_QUALITY[1] + 1)))
        boxes = jitter_boxes(np.stack([b for _, b, _ in found]), rng)
        vectors.append(embedder.embed(rgb, boxes))
        cad_ids += [scene.objects[k].cad_id for k, _, _ in found]
        visible += [px for _, _, px in found]
    if not vectors:
        return CropSet.concatenate([])
    return CropSet(np.concatenate(vectors), np.array(cad_ids, dtype=object), np.full(len(cad_ids), room, np.int64),
                   np.array(visible, np.int64))
