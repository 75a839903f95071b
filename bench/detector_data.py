"""Training frames for the furniture detector: rendered rooms, randomised, as the frozen NanoDet trunk sees them.

Each training room is a furnished room of :func:`bench.scene.generate_scene` seen along a camera
walk (:func:`bench.walkthrough.camera_path`) through a camera of random field of view, rendered as
the benchmark renders its clips, then randomised so that the class rows do not learn one
renderer's look (:func:`randomise`): colour gains, brightness, contrast and gamma, blur, sensor
noise, a JPEG round trip and a mirror flip. Room seeds are the descriptor's training seeds
(:func:`bench.descriptor_data.room_seed`, offset by :data:`SEED_OFFSET`): never a benchmark room.

Every frame goes through the NanoDet-m trunk (its graph with the heads' hidden maps as outputs,
:func:`tasks.detection.models.nanodet_head.trunk_model`) and keeps, per cell of the three strides
(2704 + 676 + 169 = 3549 cells, row-major per stride, strides 8, 16, 32):

- ``hidden`` float16[3549, 128]: the hidden map the class rows read;
- ``boxes`` float32[3549, 4]: the frozen box rows' box (x1, y1, x2, y2, letterbox pixels);
- ``target`` int8[3549]: the furniture class (index into ``FURNITURE_CLASSES``) the cell should
  score, -1 for background, -2 for "neither" (it lies on an object seen too little to ask for);
- ``quality`` float16[3549]: the score it should give that class: the IoU of its box with the
  object's box (Quality Focal Loss's target);

and the letterboxed frame itself, ``canvas`` uint8[416, 416, 3] RGB (what the whole network is
fine-tuned on, :mod:`bench.detector_finetune`).

A cell is assigned to the object whose box holds its centre and whose IoU with the cell's box is
the largest, when that IoU is at least :data:`MIN_POSITIVE_IOU`. Object boxes are the boxes of their
visible pixels (as the benchmark's ground truth).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageFilter

from bench.descriptor_data import MIN_BOX_SIDE_PX, MIN_VISIBLE_PX, jpeg_round_trip, room_seed
from bench.scene import generate_scene
from bench.walkthrough import ROOM_INSTANCE_ID, WalkthroughSpec, camera_path, load_mesh, random_lighting
from cadestate.atomic import atomic_writer
from cadestate.geometry import hfov_intrinsics, intrinsics_matrix
from cadestate.render import Camera, Instance, Renderer
from tasks.detection.detectors import letterbox
from tasks.detection.models import nanodet
from tasks.detection.models.furniture_files import FURNITURE_CLASSES

SEED_OFFSET = 500_000
"""Detector rooms are training rooms ``SEED_OFFSET + r`` (the descriptor's are 0 .. 239)."""
MIN_POSITIVE_IOU = 0.3
"""A cell's box must overlap an object's box at least this much to be asked for its class."""
HFOV_DEG = (50.0, 80.0)
"""Range of the horizontal field of view of each room's camera (the benchmark's is 65)."""
JPEG_QUALITY = (40, 95)
CELLS = sum((nanodet.SIZE // s) ** 2 for s in nanodet.STRIDES)
CLASS_INDEX = {c: i for i, c in enumerate(FURNITURE_CLASSES)}


@dataclass(frozen=True)
class FrameSet:
    """F frames: ``hidden`` float16[F, 3549, 128], ``boxes`` float32[F, 3549, 4], ``target``
    int8[F, 3549], ``quality`` float16[F, 3549], ``canvas`` uint8[F, 416, 416, 3] (module docstring);
    ``rooms`` int64[F]; the ground
    truth ``gt_frame`` int64[G], ``gt_boxes`` float32[G, 4] (letterbox pixels), ``gt_class``
    int64[G] (furniture class index), ``gt_ignore`` bool[G] (seen too little)."""

    hidden: np.ndarray
    boxes: np.ndarray
    target: np.ndarray
    quality: np.ndarray
    canvas: np.ndarray
    rooms: np.ndarray
    gt_frame: np.ndarray
    gt_boxes: np.ndarray
    gt_class: np.ndarray
    gt_ignore: np.ndarray

    FIELDS = ("hidden", "boxes", "target", "quality", "canvas", "rooms", "gt_frame", "gt_boxes", "gt_class", "gt_ignore")

    def __len__(self) -> int:
        return len(self.rooms)

    @staticmethod
    def empty() -> FrameSet:
        z = np.zeros
        return FrameSet(z((0, CELLS, 128), np.float16), z((0, CELLS, 4), np.float32), z((0, CELLS), np.int8),
                        z((0, CELLS), np.float16), z((0, nanodet.SIZE, nanodet.SIZE, 3), np.uint8), z(0, np.int64), z(0, np.int64), z((0, 4), np.float32), z(0, np.int64),
                        z(0, bool))

    @staticmethod
    def concatenate(parts: list[FrameSet]) -> FrameSet:
        offsets = np.cumsum([0] + [len(p) for p in parts])
        fields = {f: np.concatenate([getattr(p, f) for p in parts]) for f in FrameSet.FIELDS if f != "gt_frame"}
        gt_frame = np.concatenate([p.gt_frame + o for p, o in zip(parts, offsets)])
        return FrameSet(gt_frame=gt_frame, **fields)

    def take(self, frames: np.ndarray) -> FrameSet:
        """The frames whose indices are ``frames`` int[F'] (increasing)."""
        keep = np.isin(self.gt_frame, frames)
        renumber = np.searchsorted(frames, self.gt_frame[keep])
        return FrameSet(self.hidden[frames], self.boxes[frames], self.target[frames], self.quality[frames],
                        self.canvas[frames], self.rooms[frames], renumber, self.gt_boxes[keep], self.gt_class[keep], self.gt_ignore[keep])

    def save(self, path: Path) -> None:
        """Write the set to ``path`` (uncompressed .npz, atomically, streamed: it holds gigabytes)."""
        with atomic_writer(path) as f:
            np.savez(f, **{k: getattr(self, k) for k in self.FIELDS})

    @staticmethod
    def load(path: Path) -> FrameSet:
        with np.load(path) as f:
            return FrameSet(**{k: f[k] for k in FrameSet.FIELDS})


def randomise(rgb: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, bool]:
    """uint8[H,W,3] -> (the image with random colour gains, brightness, contrast, gamma, blur,
    noise and JPEG quality, and whether it was also mirrored left-right)."""
    x = rgb.astype(np.float32) / 255.0
    x = x * rng.uniform(0.85, 1.15, 3) * rng.uniform(0.7, 1.3)
    mean = x.mean()
    x = np.clip((x - mean) * rng.uniform(0.7, 1.3) + mean, 0.0, 1.0) ** rng.uniform(0.7, 1.4)
    img = Image.fromarray((x * 255).round().astype(np.uint8))
    if rng.uniform() < 0.4:
        img = img.filter(ImageFilter.GaussianBlur(float(rng.uniform(0.3, 1.5))))
    out = np.asarray(img).astype(np.float32) + rng.normal(0.0, rng.uniform(0.0, 6.0), (rgb.shape[0], rgb.shape[1], 3))
    out = jpeg_round_trip(np.clip(out, 0, 255).round().astype(np.uint8), int(rng.integers(JPEG_QUALITY[0], JPEG_QUALITY[1] + 1)))
    flip = bool(rng.uniform() < 0.5)
    return (np.ascontiguousarray(out[:, ::-1]) if flip else out), flip


def object_boxes(instance_id: np.ndarray, count: int) -> list[tuple[int, np.ndarray, bool]]:
    """(object index k, pixel box float64[4] x1 y1 x2 y2, seen too little) of every object with a
    visible pixel in an instance-id mask int[H,W] (object k is instance k + 1): "too little" is
    fewer than MIN_VISIBLE_PX pixels or a side under MIN_BOX_SIDE_PX."""
    ids = instance_id.ravel()
    counts = np.bincount(ids[ids > ROOM_INSTANCE_ID], minlength=count + 1)
    out = []
    for k in np.flatnonzero(counts[1:count + 1]):
        mask = instance_id == k + 1
        rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
        box = np.array([cols[0], rows[0], cols[-1] + 1, rows[-1] + 1], np.float64)
        little = counts[k + 1] < MIN_VISIBLE_PX or min(box[2] - box[0], box[3] - box[1]) < MIN_BOX_SIDE_PX
        out.append((int(k), box, bool(little)))
    return out


def cell_centres() -> np.ndarray:
    """float64[3549, 2] (x, y) letterbox pixels of every cell, strides 8, 16, 32, row-major."""
    out = []
    for s in nanodet.STRIDES:
        n = nanodet.SIZE // s
        iy, ix = np.divmod(np.arange(n * n), n)
        out.append(np.stack([(ix + 0.5) * s, (iy + 0.5) * s], 1))
    return np.concatenate(out)


def pairwise_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU float64[N, M] of boxes float[N,4] and float[M,4] (x1, y1, x2, y2)."""
    wh = np.clip(np.minimum(a[:, None, 2:], b[None, :, 2:]) - np.maximum(a[:, None, :2], b[None, :, :2]), 0, None)
    inter = wh[..., 0] * wh[..., 1]
    area = lambda x: np.clip(x[:, 2] - x[:, 0], 0, None) * np.clip(x[:, 3] - x[:, 1], 0, None)  # noqa: E731
    return inter / np.maximum(area(a)[:, None] + area(b)[None, :] - inter, 1e-9)


def assign(cell_boxes: np.ndarray, gt_boxes: np.ndarray, gt_class: np.ndarray, gt_ignore: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray]:
    """Per cell: (target int8[C], quality float32[C]) for cell boxes float[C,4] and objects'
    boxes float[G,4], classes int[G], ignore bool[G] (module docstring)."""
    target = np.full(len(cell_boxes), -1, np.int8)
    quality = np.zeros(len(cell_boxes), np.float32)
    if not len(gt_boxes):
        return target, quality
    c = cell_centres()
    inside = ((c[:, None, 0] >= gt_boxes[None, :, 0]) & (c[:, None, 0] <= gt_boxes[None, :, 2])
              & (c[:, None, 1] >= gt_boxes[None, :, 1]) & (c[:, None, 1] <= gt_boxes[None, :, 3]))
    iou = np.where(inside, pairwise_iou(cell_boxes, gt_boxes), 0.0)
    best = iou.argmax(1)
    top = iou[np.arange(len(iou)), best]
    hit = top >= MIN_POSITIVE_IOU
    ignored = gt_ignore[best]
    target[hit & ignored] = -2
    pos = hit & ~ignored
    target[pos] = gt_class[best[pos]]
    quality[pos] = top[pos]
    return target, quality


def cell_boxes_of(outputs: list[np.ndarray]) -> np.ndarray:
    """The trunk's six NanoDet outputs of one image -> the box of every cell float32[3549, 4]."""
    per = nanodet.split_outputs([o[0] for o in outputs])
    return np.concatenate([nanodet.distance_boxes(dist, s, np.arange(len(dist))) for s, (_, dist) in per.items()]).astype(np.float32)


def room_frames(seed: int, room: int, models: list[dict], wh_root: Path, trunk, renderer: Renderer, frames: int,
                spec: WalkthroughSpec = WalkthroughSpec()) -> FrameSet:
    """The frames of detector training room ``room`` (scene seed ``room_seed(seed, SEED_OFFSET + room)``):
    ``frames`` frames evenly spaced along its camera walk, randomised, through ``trunk`` (an
    onnxruntime session of the trunk model). Deterministic in (seed, room, models, spec, frames)."""
    scene_seed = room_seed(seed, SEED_OFFSET + room)
    scene = generate_scene(scene_seed, models)
    rng = np.random.default_rng([scene_seed, 0xDE7EC7])
    lighting = random_lighting(rng)
    hfov = float(rng.uniform(*HFOV_DEG))
    try:
        poses = camera_path(scene, dataclasses.replace(spec, hfov_deg=hfov), rng)
    except RuntimeError:  # no collision-free walk through this room (rare): it gives no frames
        return FrameSet.empty()
    K = intrinsics_matrix(hfov_intrinsics(hfov, spec.width, spec.height), spec.width, spec.height)
    instances = [Instance(m, np.eye(4), ROOM_INSTANCE_ID) for m in scene.room.meshes] + [
        Instance(load_mesh(Path(wh_root) / o.mesh_path), o.object_to_world(), k + 1) for k, o in enumerate(scene.objects)]
    name = trunk.get_inputs()[0].name
    parts: dict[str, list] = {f: [] for f in FrameSet.FIELDS}
    for n, i in enumerate(np.linspace(0, len(poses) - 1, frames).round().astype(int)):
        result = renderer.render(instances, Camera(K, poses[i, :, :3], poses[i, :, 3], spec.width, spec.height),
                                 lighting, (0.9, 0.9, 0.9))
        rgb, flip = randomise(result.rgb, rng)
        found = object_boxes(result.instance_id, len(scene.objects))
        canvas, lb = letterbox(rgb, nanodet.SIZE)
        canvas = np.clip(np.round(canvas), 0, 255).astype(np.uint8)  # kept as the fine-tuning sees it
        outs = trunk.run(None, {name: nanodet.prepare(canvas.astype(np.float32))[None]})
        boxes = np.array([b for _, b, _ in found], np.float64).reshape(-1, 4)
        if flip:
            boxes[:, [0, 2]] = spec.width - boxes[:, [2, 0]]
        gt = lb.to_canvas(boxes)
        cls = np.array([CLASS_INDEX.get(scene.objects[k].cls, -1) for k, _, _ in found], np.int64)
        ignore = np.array([little or c < 0 for (_, _, little), c in zip(found, cls)], bool)
        cell_boxes = cell_boxes_of(outs[:6])
        target, quality = assign(cell_boxes, gt, cls, ignore)
        parts["hidden"].append(np.concatenate([h[0].reshape(h.shape[1], -1).T for h in outs[6:9]]).astype(np.float16))
        parts["boxes"].append(cell_boxes)
        parts["target"].append(target)
        parts["quality"].append(quality.astype(np.float16))
        parts["canvas"].append(canvas)
        parts["rooms"].append(room)
        parts["gt_frame"].append(np.full(len(gt), n, np.int64))
        parts["gt_boxes"].append(gt.astype(np.float32))
        parts["gt_class"].append(cls)
        parts["gt_ignore"].append(ignore)
    stack = {"hidden", "boxes", "target", "quality", "canvas"}
    return FrameSet(**{f: (np.stack(v) if f in stack else np.asarray(v, np.int64) if f == "rooms" else np.concatenate(v))
                       for f, v in parts.items()})
