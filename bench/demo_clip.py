"""Synthetic walkthrough clips for the demo, the tests and the frame-extraction benchmark.

A clip is an H.264 MP4 of a camera dollying and panning through a ray-cast box room (floor, walls
with windows, ceiling, a few furniture blocks) plus its RealEstate10K camera file. The pictures
are rendered from exactly the poses that the camera file lists (world +Y up, OpenCV cameras,
world->camera ``R, t``; see :mod:`cadestate.geometry`), and every video frame carries its own
index as a 16-bit barcode in a band at the top, so decoded frames can be checked one by one.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from cadestate.geometry import hfov_intrinsics, intrinsics_matrix, look_at
from tasks.video.camera_file import CameraTrack, write_camera_file
from tasks.video.decode import frame_timestamp_us, write_video

BAND_HEIGHT = 32
"""Rows at the top of every frame that hold the frame-index barcode."""
NUM_BITS = 16
_GUARDS = ((1, 0), (0, 1))  # left and right guard blocks (1 = white), around the MSB-first bits
_NUM_CELLS = NUM_BITS + 4
_MIN_CELL_WIDTH = 16  # one H.264 macroblock
CAMERA_HEIGHT_M = 1.5
_RENDER_SCALE = 2  # ray-cast at 1/2 resolution, then upsample bilinearly (pixel centres line up)


@dataclass(frozen=True)
class DemoClipSpec:
    """What to generate. ``width`` and ``height`` must be even (yuv420p), at least 320 x 64."""

    name: str = "demo_0000"
    width: int = 640
    height: int = 360
    fps: int = 30
    num_video_frames: int = 300  # length of the encoded video
    sample_every: int = 2  # the camera file lists every k-th video frame, as RealEstate10K samples
    seed: int = 0
    codec: str = "libx264"
    hfov_deg: float = 65.0  # typical phone camera


@dataclass(frozen=True)
class DemoClip:
    """A generated clip: ``frame_indices`` int64[N] is the video frame index of each camera line."""

    video_path: Path
    cameras_path: Path
    spec: DemoClipSpec
    frame_indices: np.ndarray


def _barcode_layout(image: np.ndarray) -> tuple[int, int]:
    """Left edge and width in pixels of the barcode cells of a uint8[H, W, 3] frame."""
    height, width = image.shape[:2]
    cell = width // _NUM_CELLS
    if image.ndim != 3 or cell < _MIN_CELL_WIDTH or height < 2 * BAND_HEIGHT:
        raise ValueError(f"frame {image.shape} too small for the index barcode (needs W >= 320, H >= 64)")
    return (width - _NUM_CELLS * cell) // 2, cell


def encode_index(image: np.ndarray, index: int) -> None:
    """Draw ``index`` (0..65535) into the top ``BAND_HEIGHT`` rows of uint8[H, W, 3] ``image``, in place.

    The band is grey with 20 full-height black/white blocks of ``W // 20`` px: two guard blocks
    (white, black), the 16 bits MSB first (white = 1), two guard blocks (black, white).
    """
    if not 0 <= index < 2**NUM_BITS:
        raise ValueError(f"frame index {index} does not fit in {NUM_BITS} bits")
    x0, cell = _barcode_layout(image)
    bits = [(index >> (NUM_BITS - 1 - b)) & 1 for b in range(NUM_BITS)]
    cells = np.array([*_GUARDS[0], *bits, *_GUARDS[1]], dtype=np.uint8) * 255
    image[:BAND_HEIGHT] = 128
    image[:BAND_HEIGHT, x0 : x0 + _NUM_CELLS * cell] = np.repeat(cells, cell)[None, :, None]


def decode_index(image: np.ndarray) -> int:
    """Read back the index that :func:`encode_index` drew, from a lossily decoded uint8[H, W, 3] frame.

    Averages the inner half of each block and thresholds halfway between the guard blocks' levels.
    Raises ValueError when the guards do not show a clear black/white pattern (no barcode).
    """
    x0, cell = _barcode_layout(image)
    inner = slice(BAND_HEIGHT // 4, BAND_HEIGHT - BAND_HEIGHT // 4)
    band = image[inner, x0 : x0 + _NUM_CELLS * cell].astype(np.float32).mean(axis=(0, 2))
    levels = band.reshape(_NUM_CELLS, cell)[:, cell // 4 : cell - cell // 4].mean(axis=1)
    whites, blacks = levels[[0, -1]], levels[[1, -2]]
    if whites.min() - blacks.max() < 96:
        raise ValueError("no frame-index barcode in the top band (guard blocks not black/white)")
    bits = levels[2:-2] > (whites.mean() + blacks.mean()) / 2
    return int(sum(int(bit) << (NUM_BITS - 1 - b) for b, bit in enumerate(bits)))


@dataclass(frozen=True)
class _Room:
    """World-frame scene: the room box ``lo``/``hi`` float32[3] (floor at y = 0) and furniture boxes
    float32[B, 2, 3] (min, max corners). ``palette`` float32[7 + 3B, 3] holds the linear 0..255
    colour of each material: the room faces -x, +x, floor, ceiling, -z, +z, then windows, then
    for each box its x sides, top and z sides."""

    lo: np.ndarray
    hi: np.ndarray
    boxes: np.ndarray
    palette: np.ndarray


def _make_room(rng: np.random.Generator) -> _Room:
    """A room of about 7 x 9 x 2.8 m with pastel walls, a wooden floor and three furniture blocks."""
    half_x, half_z, ceiling = rng.uniform(3.0, 4.0), rng.uniform(4.0, 5.0), rng.uniform(2.6, 3.0)
    walls = np.array([[236, 222, 200], [206, 222, 230], [214, 230, 210], [238, 214, 214]])
    walls = np.roll(walls, rng.integers(4), axis=0) + rng.uniform(-12, 12, (4, 3))
    boxes = []
    for side in (-1, 1, -1):  # furniture against the side walls, below the camera's 1.5 m eye line
        size = rng.uniform([0.8, 0.4, 0.8], [1.6, 0.9, 2.0])
        x = side * (half_x - size[0] / 2 - rng.uniform(0.0, 0.3))
        z = rng.uniform(-half_z + size[2], half_z - size[2])
        boxes.append([[x - size[0] / 2, 0.0, z - size[2] / 2], [x + size[0] / 2, size[1], z + size[2] / 2]])
    box_colours = rng.choice([[70, 110, 160], [180, 80, 70], [90, 140, 90], [200, 170, 90]], 3, replace=False)
    box_sides = box_colours[:, None, :] * np.array([0.8, 1.0, 0.65])[None, :, None]  # x sides, top, z sides
    palette = np.concatenate([walls[:2], [[176, 128, 84], [246, 244, 238]], walls[2:], [[150, 200, 240]],
                              box_sides.reshape(-1, 3)])
    lo, hi = np.array([-half_x, 0.0, -half_z], np.float32), np.array([half_x, ceiling, half_z], np.float32)
    return _Room(lo, hi, np.array(boxes, np.float32), palette.astype(np.float32))


def _camera_poses(room: _Room, n: int, fps: int, rng: np.random.Generator) -> np.ndarray:
    """World->camera [R|t] float64[n, 3, 4] of frames ``0..n-1``: a slow periodic dolly along z
    (<= 0.4 m/s), a sideways sway and a pan of about +-30 degrees, eye 1.5 m above the floor."""
    time_s = np.arange(n) / fps
    phase = rng.uniform(0, 2 * np.pi, 3)
    z = 0.5 * (room.lo[2] + room.hi[2]) + 2.0 * np.sin(2 * np.pi * time_s / 31 + phase[0])
    x = 0.5 * np.sin(2 * np.pi * time_s / 17 + phase[1])
    yaw = 0.5 * np.sin(2 * np.pi * time_s / 11 + phase[2])
    poses = np.empty((n, 3, 4))
    for i in range(n):
        eye = np.array([x[i], CAMERA_HEIGHT_M, z[i]])
        R, t = look_at(eye, eye + [np.sin(yaw[i]), -0.2, np.cos(yaw[i])])
        poses[i] = np.concatenate([R, t[:, None]], axis=1)
    return poses


def _render(room: _Room, rays_cam: np.ndarray, pose: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Ray-cast the room from world->camera ``pose`` float[3, 4].

    ``rays_cam`` float32[3, H*W] are the camera-frame rays through the pixel centres (row-major
    pixels); returns uint8[H, W, 3].
    """
    R = pose[:, :3].astype(np.float32)
    # Elementwise products and sums, not BLAS: a BLAS kernel may round differently with the
    # threads it gets, and a pixel on a boundary then flips (the clip must be bit-identical).
    eye = -(R * pose[:, 3:4].astype(np.float32)).sum(axis=0)[:, None]  # -R^T t
    d = (R[:, :, None] * rays_cam[:, None, :]).sum(axis=0)  # R^T rays: world-frame ray directions
    with np.errstate(divide="ignore"):
        inv = 1.0 / d
    exits = np.maximum((room.lo[:, None] - eye) * inv, (room.hi[:, None] - eye) * inv)
    axis = exits.argmin(axis=0)
    depth = exits.min(axis=0)
    material = 2 * axis + (np.take_along_axis(d, axis[None], 0)[0] > 0)
    x, y, z = eye + depth * d
    planks = 0.9 + 0.1 * (np.floor(x * 4) % 2)  # floor boards 0.25 m wide
    shade = np.where(material == 2, planks, 0.82 + 0.18 * y / room.hi[1])  # walls brighter higher up
    window = (axis != 1) & (y > 0.9) & (y < 2.1) & (np.abs(np.where(axis == 0, z, x) % 2.5 - 1.25) < 0.45)
    material[window] = 6
    for b, (b_lo, b_hi) in enumerate(room.boxes):  # slab test
        t0, t1 = (b_lo[:, None] - eye) * inv, (b_hi[:, None] - eye) * inv
        entries = np.minimum(t0, t1)
        near = entries.max(axis=0)
        seen = (near <= np.maximum(t0, t1).min(axis=0)) & (near > 0) & (near < depth)
        depth = np.where(seen, near, depth)
        material[seen] = 7 + 3 * b + entries[:, seen].argmax(axis=0)
        shade[seen] = 1.0
    shade *= np.clip(1.1 - 0.05 * depth, 0.6, 1.0)
    rgb = room.palette[material] * shade[:, None]
    return rgb.clip(0, 255).astype(np.uint8).reshape(*shape, 3)


def make_demo_clip(out_dir: Path, spec: DemoClipSpec = DemoClipSpec()) -> DemoClip:
    """Write ``out_dir/<name>.mp4`` and ``out_dir/<name>.txt`` (RealEstate10K), each replaced atomically.

    Video frame ``i`` is at ``i / fps`` s; the camera file lists frames ``0, k, 2k, ...``
    (``k = sample_every``) at :func:`frame_timestamp_us`. Deterministic in ``spec``.
    Raises ValueError for an odd size, fewer than 1 or more than 65536 frames, or ``sample_every < 1``.
    """
    if spec.width % 2 or spec.height % 2 or spec.sample_every < 1 or not 0 < spec.num_video_frames <= 2**16:
        raise ValueError(f"invalid demo clip spec: {spec}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(spec.seed)
    room = _make_room(rng)
    poses = _camera_poses(room, spec.num_video_frames, spec.fps, rng)
    normalised = hfov_intrinsics(spec.hfov_deg, spec.width, spec.height)
    small = (spec.height // _RENDER_SCALE, spec.width // _RENDER_SCALE)
    u, v = np.meshgrid(np.arange(small[1]) + 0.5, np.arange(small[0]) + 0.5)
    pixels = np.stack([u * _RENDER_SCALE, v * _RENDER_SCALE, np.ones_like(u)]).reshape(3, -1)  # full-size
    K_inv = np.linalg.inv(intrinsics_matrix(normalised, spec.width, spec.height))
    rays_cam = (K_inv[:, :, None] * pixels[None]).sum(axis=1).astype(np.float32)  # K^-1 pixels, no BLAS

    def draw(index: int) -> np.ndarray:
        picture = Image.fromarray(_render(room, rays_cam, poses[index], small))
        image = np.array(picture.resize((spec.width, spec.height), Image.Resampling.BILINEAR))
        encode_index(image, index)
        return image

    video_path = out_dir / f"{spec.name}.mp4"
    write_video(video_path, (draw(i) for i in range(spec.num_video_frames)), spec.width, spec.height, spec.fps,
                spec.codec)

    frame_indices = np.arange(0, spec.num_video_frames, spec.sample_every, dtype=np.int64)
    track = CameraTrack(
        url=f"synthetic://demo/{spec.name}",
        timestamps_us=np.array([frame_timestamp_us(int(i), spec.fps) for i in frame_indices], dtype=np.int64),
        intrinsics=np.tile(normalised, (len(frame_indices), 1)),
        world_to_camera=poses[frame_indices],
    )
    cameras_path = out_dir / f"{spec.name}.txt"
    write_camera_file(cameras_path, track)  # atomic itself
    return DemoClip(video_path, cameras_path, spec, frame_indices)
