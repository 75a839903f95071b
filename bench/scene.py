"""Seeded synthetic furnished rooms for the walkthrough benchmark (:mod:`bench.walkthrough`).

Frames (see :mod:`cadestate.geometry`): world metres, +Y up, the floor at y = 0, the room box
``x in [-width/2, width/2]``, ``z in [-depth/2, depth/2]``, ``y in [0, height]``. CAD models are
in the canonical CAD frame (metres, +Y up, front +Z, bounding box centred at the origin) and are
placed with the official object-to-world mapping: mirror => scale => rotation => translation
(``cadestate.render.object_to_world``). Everything is deterministic in ``(seed, models)``.

Footprints are the oriented rectangles that posed models cover on the floor (x, z); placement
keeps them apart by :data:`FOOTPRINT_MARGIN_M`, inside the room, off door swings, and only
rotates models about +Y so that every model stands upright with its lowest point on the floor
(or, for displays put on a cabinet, on the cabinet's top).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from cadestate.render import Material, RenderMesh, object_to_world

EXCLUDED_CLASSES = frozenset({"other", "vehicle", "door", "window", "laptop", "clock"})
"""Classes never placed: not furniture, not upright (laptop), or hung on walls (clock)."""
WALL_CLASSES = frozenset({"bed", "sofa", "cabinet", "bookshelf", "display", "toilet", "sink", "piano",
                          "refrigerator", "stove", "washer", "radiator", "bathtub", "loudspeaker", "microwave"})
"""Classes placed with their back against a wall, facing into the room."""
CLASS_WEIGHTS = {"chair": 2.0, "sofa": 3.0, "bed": 2.5, "display": 2.5, "plant": 3.0, "toilet": 1.5, "sink": 1.5,
                 "cabinet": 2.0, "bookshelf": 1.5, "lamp": 1.5}
"""Relative frequency of each class among the extra (non table-group) objects; others get 0.25.
COCO-detectable classes (chair, sofa, bed, display, plant, toilet, sink) are favoured."""
MAX_PER_CLASS = {"bed": 1, "toilet": 1, "sink": 1, "sofa": 2, "display": 2, "bathtub": 1, "piano": 1,
                 "refrigerator": 1, "stove": 1, "washer": 1}
FOOTPRINT_MARGIN_M = 0.05
"""Smallest gap between two footprints (and between a footprint and a wall is 0.02 m)."""
WALL_GAP_M = 0.02
MIRROR_PROBABILITY = 0.25
SCALE_JITTER = 0.15


@dataclass(frozen=True)
class PlacedObject:
    """One library model posed in the world.

    ``cls`` is the class name (``class`` in the library table), ``class_id`` its id (ShapeNet synset
    or ``cadestate-<name>``), ``symmetry`` its order about +Y, ``mesh_path`` the canonical GLB
    relative to the warehouse root, ``extent`` float[3] its canonical bounding-box size (x, y, z) m.
    Pose (official order, object -> world: mirror => scale => rotation => translation):
    ``translation`` (x, y, z) metres, ``rotation`` (w, x, y, z) unit quaternion (a rotation about
    +Y only: ``yaw`` radians, so the canonical front +Z faces world (sin yaw, 0, cos yaw)),
    ``scale`` (sx, sy, sz) along the canonical axes, ``mirrored`` (canonical x negated first).
    ``support``: index of the object it stands on in :attr:`Scene.objects`, or -1 for the floor.
    """

    cad_id: str
    cls: str
    class_id: str
    symmetry: int
    mesh_path: str
    extent: tuple[float, float, float]
    translation: tuple[float, float, float]
    rotation: tuple[float, float, float, float]
    scale: tuple[float, float, float]
    mirrored: bool
    yaw: float
    support: int = -1

    def object_to_world(self) -> np.ndarray:
        """float64[4, 4] canonical CAD frame -> world."""
        return object_to_world(self.translation, self.rotation, self.scale, self.mirrored)

    @property
    def size(self) -> np.ndarray:
        """float64[3] posed bounding-box size along the object's own (rotated) x, y, z axes."""
        return np.asarray(self.extent) * np.asarray(self.scale)

    def footprint(self) -> Footprint:
        """The oriented rectangle the posed model covers on the floor."""
        s = self.size
        return Footprint(self.translation[0], self.translation[2], s[0] / 2, s[2] / 2, self.yaw)

    def corners(self) -> np.ndarray:
        """float64[8, 3] world corners of the posed bounding box."""
        e = np.asarray(self.extent) / 2
        c = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * e
        M = self.object_to_world()
        return c @ M[:3, :3].T + M[:3, 3]


@dataclass(frozen=True)
class Footprint:
    """Oriented rectangle on the floor: centre (x, z) metres, half sizes ``hx`` along the object's
    x axis and ``hz`` along its z axis, ``yaw`` radians about +Y (object z -> (sin yaw, cos yaw))."""

    x: float
    z: float
    hx: float
    hz: float
    yaw: float

    def axes(self) -> np.ndarray:
        """float64[2, 2] rows: the object's x and z axes in world (x, z)."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([[c, -s], [s, c]])

    def corners(self) -> np.ndarray:
        """float64[4, 2] world (x, z) corners."""
        a = self.axes()
        return np.array([self.x, self.z]) + np.array([[i * self.hx, j * self.hz] for i, j in
                                                      ((-1, -1), (1, -1), (1, 1), (-1, 1))]) @ a

    def overlaps(self, other: Footprint, margin: float = 0.0) -> bool:
        """Separating-axis test of the two rectangles, each grown by ``margin / 2``."""
        pa, pb = self.corners(), other.corners()
        grow = margin / 2
        for axis in (*self.axes(), *other.axes()):
            a, b = pa @ axis, pb @ axis
            if a.max() + grow <= b.min() - grow or b.max() + grow <= a.min() - grow:
                return False
        return True

    def distance(self, points: np.ndarray) -> np.ndarray:
        """float64[N] distance from world (x, z) points float[N, 2] to the rectangle (0 inside)."""
        local = (np.asarray(points, np.float64) - [self.x, self.z]) @ self.axes().T
        d = np.abs(local) - [self.hx, self.hz]
        return np.linalg.norm(np.maximum(d, 0.0), axis=-1)

    def contains(self, other: Footprint, tolerance: float = 1e-6) -> bool:
        """Whether every corner of ``other`` lies in this rectangle."""
        return bool(np.all(self.distance(other.corners()) <= tolerance))


@dataclass(frozen=True)
class Opening:
    """A window or door panel on a wall. ``wall``: 0 = z min (faces +z), 1 = x max (faces -x),
    2 = z max (faces -z), 3 = x min (faces +x); ``u`` metres along the wall from its centre
    (see :func:`wall_frame`), ``bottom``/``top`` heights, ``width`` metres."""

    kind: str  # "window" | "door"
    wall: int
    u: float
    width: float
    bottom: float
    top: float


@dataclass(frozen=True, eq=False)
class Room:
    """Room box ``width`` (x) x ``depth`` (z) x ``height`` (y) metres centred on x = z = 0, floor
    y = 0. ``openings``: windows and doors (thin panels 2 cm in front of the walls); ``keepouts``:
    floor rectangles kept free of furniture (door swings). ``meshes``: the render meshes (world
    frame; floor, walls, ceiling, skirting, openings) with procedural textures."""

    width: float
    depth: float
    height: float
    openings: tuple[Opening, ...]
    keepouts: tuple[Footprint, ...]
    meshes: tuple[RenderMesh, ...]

    def wall_distance(self, points: np.ndarray) -> np.ndarray:
        """float64[N] distance of world (x, z) points float[N, 2] to the nearest wall (< 0 outside)."""
        p = np.asarray(points, np.float64)
        return np.minimum(self.width / 2 - np.abs(p[:, 0]), self.depth / 2 - np.abs(p[:, 1]))


@dataclass(frozen=True, eq=False)
class Scene:
    """A room and the models placed in it; ``seed`` generated it."""

    seed: int
    room: Room
    objects: tuple[PlacedObject, ...]

    def footprints(self) -> list[Footprint]:
        return [o.footprint() for o in self.objects]

    def clearance(self, points: np.ndarray) -> np.ndarray:
        """float64[N] distance of world (x, z) points to the nearest footprint or wall."""
        p = np.asarray(points, np.float64).reshape(-1, 2)
        d = self.room.wall_distance(p)
        for f in self.footprints():
            d = np.minimum(d, f.distance(p))
        return d


def wall_frame(wall: int, width: float, depth: float) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Wall ``wall``'s (x, z) centre float[2], along-wall unit vector float[2] (u axis), inward
    normal float[2], its length, and the yaw that makes an object's front (+Z) face into the room."""
    if wall == 0:
        return np.array([0.0, -depth / 2]), np.array([1.0, 0.0]), width, 0.0
    if wall == 1:
        return np.array([width / 2, 0.0]), np.array([0.0, 1.0]), depth, -math.pi / 2
    if wall == 2:
        return np.array([0.0, depth / 2]), np.array([-1.0, 0.0]), width, math.pi
    return np.array([-width / 2, 0.0]), np.array([0.0, -1.0]), depth, math.pi / 2


def _inward(wall: int) -> np.ndarray:
    return np.array([[0.0, 1.0], [-1.0, 0.0], [0.0, -1.0], [1.0, 0.0]][wall])


def yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) of a rotation by ``yaw`` radians about +Y."""
    return (math.cos(yaw / 2), 0.0, math.sin(yaw / 2), 0.0)


# ----------------------------------------------------------------------------------------------
# Procedural textures (uint8[H, W, 3], row 0 = top). ``rng`` makes them vary per scene.


def _noise(rng: np.random.Generator, shape: tuple[int, int], cells: int) -> np.ndarray:
    """Smooth value noise float[H, W] in about [-1, 1], ``cells`` lattice cells across."""
    g = rng.uniform(-1, 1, (cells + 1, cells + 1))
    g[-1], g[:, -1] = g[0], g[:, 0]  # tileable
    y, x = np.linspace(0, cells, shape[0], endpoint=False), np.linspace(0, cells, shape[1], endpoint=False)
    yi, xi = y.astype(int), x.astype(int)
    fy, fx = (y - yi)[:, None], (x - xi)[None, :]
    fy, fx = fy * fy * (3 - 2 * fy), fx * fx * (3 - 2 * fx)
    a, b = g[yi][:, xi], g[yi][:, xi + 1]
    c, d = g[yi + 1][:, xi], g[yi + 1][:, xi + 1]
    return (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy


def _to_uint8(img: np.ndarray) -> np.ndarray:
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def wood_texture(rng: np.random.Generator, size: int = 512, planks: int = 8, base=None) -> np.ndarray:
    """Floor boards running along the texture's x: ``planks`` rows, staggered joints, grain."""
    base = np.asarray(base if base is not None else rng.choice(
        [[150, 105, 65], [180, 135, 90], [120, 80, 50], [200, 165, 120], [110, 75, 45]]), np.float64)
    h = size // planks
    img = np.empty((size, size, 3))
    x = np.arange(size)
    grain = _noise(rng, (size, size), 32)
    fine = _noise(rng, (size, size), 128)
    for p in range(planks):
        rows = slice(p * h, (p + 1) * h)
        offset = rng.integers(0, size)
        joints = (x + offset) % (size // 2) < 2
        tint = rng.uniform(0.82, 1.12)
        stripes = 0.08 * np.sin((np.arange(h)[:, None] + 6 * grain[rows]) * rng.uniform(0.6, 1.2))
        shade = tint * (1 + stripes + 0.05 * fine[rows])
        shade[:, joints] *= 0.55
        shade[:2] *= 0.6
        img[rows] = base * shade[..., None]
    return _to_uint8(img)


def tile_texture(rng: np.random.Generator, size: int = 256, tiles: int = 2) -> np.ndarray:
    """``tiles`` x ``tiles`` square tiles with grout lines and slight per-tile tone variation."""
    base = np.asarray(rng.choice([[225, 220, 210], [190, 185, 178], [160, 150, 140], [235, 232, 226],
                                  [120, 125, 130]]), np.float64)
    n = size // tiles
    tone = rng.uniform(0.92, 1.06, (tiles, tiles))
    img = base * np.kron(tone, np.ones((n, n)))[..., None] * (1 + 0.04 * _noise(rng, (size, size), 64))[..., None]
    grout = (np.arange(size) % n < 3)
    img[grout] = img[grout] * 0 + [150, 145, 140]
    img[:, grout] = [150, 145, 140]
    return _to_uint8(img)


def wall_texture(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """Matt paint, or a wallpaper with stripes or a diamond pattern (one texture repeat = 1 m)."""
    paint = np.asarray(rng.choice([[236, 230, 215], [214, 226, 232], [222, 234, 214], [240, 222, 214],
                                   [235, 235, 235], [200, 210, 220], [238, 226, 190], [205, 195, 185]]), np.float64)
    paint = paint + rng.uniform(-10, 10, 3)
    img = np.broadcast_to(paint, (size, size, 3)) * (1 + 0.025 * _noise(rng, (size, size), 48))[..., None]
    kind = rng.choice(["paint", "paint", "stripes", "diamonds"])
    if kind == "stripes":
        n = int(rng.choice([16, 32, 64]))
        img = img * np.where((np.arange(size) // n) % 2, 0.9, 1.0)[None, :, None]
    elif kind == "diamonds":
        y, x = np.mgrid[0:size, 0:size] / (size / 4)
        d = np.abs((x % 1) - 0.5) + np.abs((y % 1) - 0.5)
        img = img * np.where(np.abs(d - 0.35) < 0.03, 0.85, 1.0)[..., None]
    return _to_uint8(img)


def ceiling_texture(rng: np.random.Generator, size: int = 64) -> np.ndarray:
    img = np.full((size, size, 3), 242.0) * (1 + 0.015 * _noise(rng, (size, size), 8))[..., None]
    return _to_uint8(img)


def window_texture(rng: np.random.Generator, size: int = 128) -> np.ndarray:
    """A sky gradient over a band of greenery or buildings, seen through the glass."""
    t = np.linspace(0, 1, size)[:, None, None]
    sky = (1 - t) * np.array([120, 170, 230]) + t * np.array([215, 230, 245])
    img = np.broadcast_to(sky, (size, size, 3)).copy()
    horizon = (0.65 + 0.1 * _noise(rng, (1, size), 6)[0]) * size
    rows = np.arange(size)[:, None]
    ground = rows > horizon[None, :]
    green = np.array(rng.choice([[80, 120, 70], [110, 110, 105], [95, 130, 80]]), np.float64)
    img[ground] = (green * (1 + 0.15 * _noise(rng, (size, size), 16)[..., None]))[ground]
    return _to_uint8(img)


def door_texture(rng: np.random.Generator, size: int = 128) -> np.ndarray:
    """A wooden or painted door leaf with two recessed panels (texture covers the whole leaf)."""
    if rng.uniform() < 0.5:
        img = wood_texture(rng, size, planks=1).astype(np.float64).transpose(1, 0, 2)
    else:
        colour = np.asarray(rng.choice([[245, 245, 240], [230, 225, 210], [90, 100, 115]]), np.float64)
        img = np.broadcast_to(colour, (size, size, 3)).copy()
    y, x = np.mgrid[0:size, 0:size] / size
    for y0, y1 in ((0.08, 0.45), (0.55, 0.92)):
        edge = (x > 0.15) & (x < 0.85) & (y > y0) & (y < y1)
        inner = (x > 0.17) & (x < 0.83) & (y > y0 + 0.01) & (y < y1 - 0.01)
        img[edge & ~inner] *= 0.75
    return _to_uint8(img)


# ----------------------------------------------------------------------------------------------
# Room geometry.


class _MeshBuilder:
    """Collects quads (world frame) into one RenderMesh."""

    def __init__(self) -> None:
        self.positions: list[np.ndarray] = []
        self.normals: list[np.ndarray] = []
        self.uvs: list[np.ndarray] = []
        self.faces: list[np.ndarray] = []
        self.face_material: list[int] = []
        self.materials: list[Material] = []
        self.n = 0

    def material(self, m: Material) -> int:
        self.materials.append(m)
        return len(self.materials) - 1

    def quad(self, corners: np.ndarray, uvs: np.ndarray, material: int) -> None:
        """Corners float[4, 3] in order around the quad, uvs float[4, 2]."""
        corners = np.asarray(corners, np.float64)
        n = np.cross(corners[1] - corners[0], corners[2] - corners[0])
        self.positions.append(corners)
        self.normals.append(np.tile(n / np.linalg.norm(n), (4, 1)))
        self.uvs.append(np.asarray(uvs, np.float64))
        self.faces.append(np.array([[0, 1, 2], [0, 2, 3]]) + self.n)
        self.face_material += [material, material]
        self.n += 4

    def box(self, lo: np.ndarray, hi: np.ndarray, material: int, uv_per_m: float = 1.0,
            front_material: int | None = None, front_axis: tuple[int, int] | None = None) -> None:
        """Axis-aligned box; ``front_axis`` (axis, sign) face gets ``front_material`` with uvs 0..1."""
        lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
        for axis in range(3):
            for sign in (-1, 1):
                a, b = [k for k in range(3) if k != axis]
                c = np.empty((4, 3))
                c[:, axis] = hi[axis] if sign > 0 else lo[axis]
                for i, (ua, ub) in enumerate(((0, 0), (1, 0), (1, 1), (0, 1))):
                    c[i, a] = hi[a] if ua else lo[a]
                    c[i, b] = hi[b] if ub else lo[b]
                front = front_axis == (axis, sign)
                if front:
                    # u along the horizontal axis, v up (uv (0, 0) = bottom-left of the image).
                    horiz = a if a != 1 else b
                    u = (c[:, horiz] - lo[horiz]) / max(hi[horiz] - lo[horiz], 1e-9)
                    if (axis == 2 and sign < 0) or (axis == 0 and sign > 0):
                        u = 1 - u
                    v = (c[:, 1] - lo[1]) / max(hi[1] - lo[1], 1e-9)
                    uv = np.stack([u, v], 1)
                else:
                    uv = np.stack([c[:, a], c[:, b]], 1) * uv_per_m
                self.quad(c, uv, front_material if front else material)

    def build(self) -> RenderMesh:
        return RenderMesh(np.concatenate(self.positions), np.concatenate(self.normals), np.concatenate(self.uvs),
                          np.concatenate(self.faces), np.array(self.face_material), tuple(self.materials))


def _wall_point(wall: int, u: float, width: float, depth: float, inset: float) -> np.ndarray:
    centre, along, _, _ = wall_frame(wall, width, depth)
    return centre + along * u + _inward(wall) * inset


def _build_room(rng: np.random.Generator, width: float, depth: float, height: float,
                openings: list[Opening]) -> tuple[RenderMesh, ...]:
    b = _MeshBuilder()
    if rng.uniform() < 0.7:
        floor_tex, floor_m = wood_texture(rng), rng.uniform(1.6, 2.4)  # metres per texture repeat
    else:
        floor_tex, floor_m = tile_texture(rng), rng.uniform(0.6, 1.2)
    floor = b.material(Material((1, 1, 1), floor_tex))
    ceiling = b.material(Material((1, 1, 1), ceiling_texture(rng)))
    wall_tex = wall_texture(rng)
    accent = rng.integers(4) if rng.uniform() < 0.4 else -1
    walls = [b.material(Material((1, 1, 1), wall_texture(rng) if w == accent else wall_tex)) for w in range(4)]
    x0, x1, z0, z1 = -width / 2, width / 2, -depth / 2, depth / 2
    s = 1.0 / floor_m
    b.quad([[x0, 0, z0], [x1, 0, z0], [x1, 0, z1], [x0, 0, z1]],
           np.array([[x0, z0], [x1, z0], [x1, z1], [x0, z1]]) * s, floor)
    b.quad([[x0, height, z0], [x0, height, z1], [x1, height, z1], [x1, height, z0]],
           np.array([[x0, z0], [x0, z1], [x1, z1], [x1, z0]]), ceiling)
    for w in range(4):
        centre, along, length, _ = wall_frame(w, width, depth)
        p0, p1 = centre - along * length / 2, centre + along * length / 2
        corners = [[p0[0], 0, p0[1]], [p1[0], 0, p1[1]], [p1[0], height, p1[1]], [p0[0], height, p0[1]]]
        b.quad(corners, [[-length / 2, 0], [length / 2, 0], [length / 2, height], [-length / 2, height]], walls[w])
    trim_colour = rng.choice([[0.95, 0.95, 0.93], [0.85, 0.82, 0.78], [0.45, 0.32, 0.22]])
    trim = b.material(Material(trim_colour))
    for w in range(4):  # skirting boards, 8 cm high, 1.5 cm deep
        centre, along, length, _ = wall_frame(w, width, depth)
        n = _inward(w)
        p = [centre - along * length / 2, centre + along * length / 2, centre + along * length / 2 + n * 0.015,
             centre - along * length / 2 + n * 0.015]
        xs, zs = [q[0] for q in p], [q[1] for q in p]
        b.box([min(xs), 0, min(zs)], [max(xs), 0.08, max(zs)], trim)
    frame = b.material(Material(rng.choice([[0.96, 0.96, 0.95], [0.3, 0.3, 0.32], [0.55, 0.4, 0.28]])))
    glass = b.material(Material((1, 1, 1), window_texture(rng)))
    door = b.material(Material((1, 1, 1), door_texture(rng)))
    handle = b.material(Material((0.75, 0.72, 0.6)))
    for o in openings:
        centre, along, _, _ = wall_frame(o.wall, width, depth)
        n = _inward(o.wall)
        axis = 0 if abs(n[0]) > 0.5 else 2
        sign = 1 if n[axis if axis == 0 else 1] > 0 else -1

        def panel(u0: float, u1: float, y0: float, y1: float, d0: float, d1: float, mat: int,
                  front: int | None = None) -> None:
            pts = [_wall_point(o.wall, u, width, depth, d) for u in (u0, u1) for d in (d0, d1)]
            xs, zs = [q[0] for q in pts], [q[1] for q in pts]
            b.box([min(xs), y0, min(zs)], [max(xs), y1, max(zs)], mat, front_material=front,
                  front_axis=(axis, sign) if front is not None else None)

        u0, u1 = o.u - o.width / 2, o.u + o.width / 2
        if o.kind == "window":
            f = 0.06
            panel(u0, u1, o.bottom, o.top, 0.0, 0.02, glass, glass)
            panel(u0 - f, u1 + f, o.bottom - f, o.bottom, 0.0, 0.05, frame)  # sill
            panel(u0 - f, u1 + f, o.top, o.top + f, 0.0, 0.04, frame)
            panel(u0 - f, u0, o.bottom, o.top, 0.0, 0.04, frame)
            panel(u1, u1 + f, o.bottom, o.top, 0.0, 0.04, frame)
            panel(o.u - 0.02, o.u + 0.02, o.bottom, o.top, 0.0, 0.035, frame)  # mullion
        else:
            f = 0.07
            panel(u0, u1, 0.0, o.top, 0.0, 0.025, door, door)
            panel(u0 - f, u0, 0.0, o.top + f, 0.0, 0.035, frame)
            panel(u1, u1 + f, 0.0, o.top + f, 0.0, 0.035, frame)
            panel(u0 - f, u1 + f, o.top, o.top + f, 0.0, 0.035, frame)
            hu = u1 - 0.09
            panel(hu - 0.06, hu + 0.02, 1.0, 1.03, 0.025, 0.07, handle)
    return (b.build(),)


def _make_openings(rng: np.random.Generator, width: float, depth: float, height: float) -> list[Opening]:
    openings: list[Opening] = []
    door_wall = int(rng.integers(4))
    _, _, length, _ = wall_frame(door_wall, width, depth)
    dw = rng.uniform(0.8, 0.95)
    du = rng.uniform(-length / 2 + dw / 2 + 0.2, length / 2 - dw / 2 - 0.2)
    openings.append(Opening("door", door_wall, float(du), float(dw), 0.0, float(rng.uniform(2.0, 2.12))))
    for w in range(4):
        _, _, length, _ = wall_frame(w, width, depth)
        for _ in range(int(rng.choice([0, 1, 1, 2]))):
            ww = rng.uniform(0.8, min(1.8, length / 3))
            bottom = rng.uniform(0.75, 1.0)
            top = min(height - 0.25, bottom + rng.uniform(1.0, 1.5))
            for _attempt in range(10):
                u = rng.uniform(-length / 2 + ww / 2 + 0.3, length / 2 - ww / 2 - 0.3)
                if all(o.wall != w or abs(o.u - u) > (o.width + ww) / 2 + 0.3 for o in openings):
                    openings.append(Opening("window", w, float(u), float(ww), float(bottom), float(top)))
                    break
    return openings


# ----------------------------------------------------------------------------------------------
# Furniture placement.


def usable_models(models: list[dict], room_height: float = 2.5) -> list[dict]:
    """Models that may be placed: an allowed class, not a door or window by name, a plausible size,
    sorted by cad_id."""
    out = []
    for m in models:
        e = np.asarray(m["extent"], np.float64)
        if m["class"] in EXCLUDED_CLASSES or not np.all(np.isfinite(e)) or e.min() < 0.02:
            continue
        if re.search(r"\bdoor\b|\bwindow\b", (m.get("name") or "").lower()):  # e.g. "screen door"
            continue
        if e[1] > room_height - 0.3 or max(e[0], e[2]) > 3.0 or e.max() < 0.15:
            continue
        out.append(m)
    return sorted(out, key=lambda m: m["cad_id"])


class _Placer:
    def __init__(self, rng: np.random.Generator, width: float, depth: float, keepouts: list[Footprint]):
        self.rng, self.width, self.depth = rng, width, depth
        self.keepouts = keepouts
        self.objects: list[PlacedObject] = []

    def pose(self, m: dict) -> tuple[np.ndarray, bool]:
        scale = self.rng.uniform(1 - SCALE_JITTER, 1 + SCALE_JITTER, 3)
        mirrored = bool(self.rng.uniform() < MIRROR_PROBABILITY)
        return scale, mirrored

    def free(self, f: Footprint, ignore: int = -1) -> bool:
        if np.any(np.abs(f.corners()[:, 0]) > self.width / 2 - WALL_GAP_M + 1e-9) or \
                np.any(np.abs(f.corners()[:, 1]) > self.depth / 2 - WALL_GAP_M + 1e-9):
            return False
        if any(f.overlaps(k) for k in self.keepouts):
            return False
        return not any(i != ignore and o.support < 0 and f.overlaps(o.footprint(), FOOTPRINT_MARGIN_M)
                       for i, o in enumerate(self.objects))

    def make(self, m: dict, scale: np.ndarray, mirrored: bool, x: float, z: float, yaw: float,
             floor_y: float = 0.0, support: int = -1) -> PlacedObject:
        e = np.asarray(m["extent"], np.float64)
        y = floor_y + scale[1] * e[1] / 2
        yaw = math.remainder(yaw, 2 * math.pi)
        return PlacedObject(cad_id=m["cad_id"], cls=m["class"], class_id=m["class_id"], symmetry=int(m["symmetry"]),
                            mesh_path=m["mesh_path"], extent=tuple(float(v) for v in e),
                            translation=(float(x), float(y), float(z)), rotation=yaw_quaternion(yaw),
                            scale=tuple(float(v) for v in scale), mirrored=mirrored, yaw=float(yaw), support=support)

    def try_add(self, obj: PlacedObject) -> bool:
        if obj.support < 0 and not self.free(obj.footprint()):
            return False
        self.objects.append(obj)
        return True

    def against_wall(self, m: dict, attempts: int = 40) -> bool:
        scale, mirrored = self.pose(m)
        size = np.asarray(m["extent"]) * scale
        for _ in range(attempts):
            wall = int(self.rng.integers(4))
            centre, along, length, yaw = wall_frame(wall, self.width, self.depth)
            free_len = length / 2 - size[0] / 2 - 0.05
            if free_len <= 0:
                continue
            u = self.rng.uniform(-free_len, free_len)
            p = centre + along * u + _inward(wall) * (size[2] / 2 + WALL_GAP_M + 0.01)
            if self.try_add(self.make(m, scale, mirrored, p[0], p[1], yaw)):
                return True
        return False

    def in_corner(self, m: dict, attempts: int = 20) -> bool:
        scale, mirrored = self.pose(m)
        size = np.asarray(m["extent"]) * scale
        r = max(size[0], size[2]) / 2 * math.sqrt(2)
        for _ in range(attempts):
            sx, sz = self.rng.choice([-1, 1], 2)
            x = sx * (self.width / 2 - r - WALL_GAP_M - self.rng.uniform(0.02, 0.4))
            z = sz * (self.depth / 2 - r - WALL_GAP_M - self.rng.uniform(0.02, 0.4))
            yaw = math.atan2(-x, -z) + self.rng.uniform(-0.4, 0.4)  # roughly facing the room centre
            if self.try_add(self.make(m, scale, mirrored, x, z, yaw)):
                return True
        return False

    def anywhere(self, m: dict, attempts: int = 40, facing: np.ndarray | None = None) -> bool:
        scale, mirrored = self.pose(m)
        size = np.asarray(m["extent"]) * scale
        r = max(size[0], size[2]) / 2
        for _ in range(attempts):
            x = self.rng.uniform(-self.width / 2 + r, self.width / 2 - r)
            z = self.rng.uniform(-self.depth / 2 + r, self.depth / 2 - r)
            target = facing if facing is not None else np.zeros(2)
            yaw = math.atan2(target[0] - x, target[1] - z) + self.rng.uniform(-0.5, 0.5)
            if self.try_add(self.make(m, scale, mirrored, x, z, yaw)):
                return True
        return False

    def on_top(self, m: dict) -> bool:
        """On a cabinet (not covered already) whose top is 0.3-1.1 m high and big enough."""
        scale, mirrored = self.pose(m)
        size = np.asarray(m["extent"]) * scale
        hosts = [i for i, o in enumerate(self.objects) if o.cls == "cabinet" and o.support < 0
                 and 0.3 < o.translation[1] * 2 < 1.1 and o.size[0] > size[0] + 0.02 and o.size[2] > size[2] + 0.02
                 and not any(p.support == i for p in self.objects)]
        if not hosts:
            return False
        host = self.objects[hosts[int(self.rng.integers(len(hosts)))]]
        top = host.translation[1] + host.size[1] / 2
        slack = (host.size[2] - size[2]) / 2
        local_z = -slack + min(slack, 0.03)  # towards the back of the cabinet
        a = host.footprint().axes()
        p = np.array([host.translation[0], host.translation[2]]) + local_z * a[1]
        obj = self.make(m, scale, mirrored, p[0], p[1], host.yaw, floor_y=top, support=self.objects.index(host))
        if not host.footprint().contains(obj.footprint(), 1e-6):
            return False
        self.objects.append(obj)
        return True

    def table_group(self, table: dict, chair: dict, n_chairs: int, attempts: int = 40) -> bool:
        for _ in range(attempts):
            scale, mirrored = self.pose(table)
            tsize = np.asarray(table["extent"]) * scale
            margin = 0.9
            lim_x, lim_z = self.width / 2 - margin - tsize[0] / 2, self.depth / 2 - margin - tsize[2] / 2
            if lim_x <= 0 or lim_z <= 0:
                return False
            x, z = self.rng.uniform(-lim_x, lim_x), self.rng.uniform(-lim_z, lim_z)
            yaw = float(self.rng.choice([0.0, math.pi / 2])) + self.rng.uniform(-0.15, 0.15)
            t = self.make(table, scale, mirrored, x, z, yaw)
            if not self.free(t.footprint()):
                continue
            start = len(self.objects)
            self.objects.append(t)
            a = t.footprint().axes()
            cscale, _ = self.pose(chair)
            csize = np.asarray(chair["extent"]) * cscale
            slots = []
            for axis, half, side_len in ((0, tsize[0] / 2, tsize[2]), (1, tsize[2] / 2, tsize[0])):
                for sign in (-1, 1):
                    offsets = [0.0] if side_len < 2 * csize[0] + 0.15 else [-side_len / 4, side_len / 4]
                    for off in offsets:
                        out = sign * a[axis]
                        along = a[1 - axis]
                        p = np.array([x, z]) + out * (half + FOOTPRINT_MARGIN_M + 0.03 + csize[2] / 2) + along * off
                        slots.append((p, math.atan2(-out[0], -out[1])))
            order = self.rng.permutation(len(slots))
            placed = 0
            for k in order:
                if placed == n_chairs:
                    break
                p, cyaw = slots[k]
                c = self.make(chair, cscale, bool(self.rng.uniform() < MIRROR_PROBABILITY), p[0], p[1],
                              cyaw + self.rng.uniform(-0.12, 0.12))
                placed += self.try_add(c)
            if placed >= 2:
                return True
            del self.objects[start:]
        return False


def generate_scene(seed: int, models: list[dict]) -> Scene:
    """A furnished room with 4-12 library models (``cad_models`` rows: cad_id, class, class_id,
    extent, symmetry, mesh_path), deterministic in ``(seed, models)``; see the module docstring.
    Raises ValueError when the library has no placeable model."""
    rng = np.random.default_rng([int(seed), 0x5CE7E])
    width, depth, height = rng.uniform(3.5, 7.0), rng.uniform(3.5, 7.0), rng.uniform(2.5, 2.9)
    pool = usable_models(models, height)
    if not pool:
        raise ValueError("no placeable model in the library (every class excluded or sizes implausible)")
    by_class: dict[str, list[dict]] = {}
    for m in pool:
        by_class.setdefault(m["class"], []).append(m)
    openings = _make_openings(rng, width, depth, height)
    keepouts = []
    for o in openings:
        if o.kind == "door":
            c = _wall_point(o.wall, o.u, width, depth, 0.5)
            _, _, _, yaw = wall_frame(o.wall, width, depth)
            keepouts.append(Footprint(float(c[0]), float(c[1]), o.width / 2 + 0.1, 0.5, yaw))
    placer = _Placer(rng, width, depth, keepouts)

    def pick(cls: str) -> dict:
        options = by_class[cls]
        return options[int(rng.integers(len(options)))]

    target = int(rng.integers(4, 13))
    area = width * depth
    target = min(target, max(4, int(area / 2.2)))
    counts: dict[str, int] = {}
    wants: list[str] = []
    group = "table" in by_class and "chair" in by_class and rng.uniform() < 0.85
    n_chairs = int(rng.integers(2, 5)) if group else 0
    classes = sorted(by_class)
    weights = np.array([CLASS_WEIGHTS.get(c, 0.25) for c in classes])
    budget = target - (1 + n_chairs if group else 0)
    while len(wants) < max(budget, 0) + 4 and weights.sum() > 0:  # a few spares for failed placements
        c = classes[int(rng.choice(len(classes), p=weights / weights.sum()))]
        counts[c] = counts.get(c, 0) + 1
        if counts[c] >= MAX_PER_CLASS.get(c, 3):
            weights[classes.index(c)] = 0
        wants.append(c)
    # Large wall pieces first, then the table group, then the rest.
    big = [c for c in wants if c in WALL_CLASSES and c not in ("display", "microwave")]
    big.sort(key=lambda c: -float(np.prod(np.asarray(by_class[c][0]["extent"])[[0, 2]])))
    rest = [c for c in wants if c not in big]
    placed_extra = 0
    for c in big[:max(budget, 0)]:
        placed_extra += placer.against_wall(pick(c))
    if group:
        dining = [m for m in by_class["chair"] if m["extent"][0] <= 0.6 and m["extent"][2] <= 0.65]
        chair = dining[int(rng.integers(len(dining)))] if dining else pick("chair")
        placer.table_group(pick("table"), chair, n_chairs)
    for c in rest + big[max(budget, 0):]:
        if len(placer.objects) >= target:
            break
        m = pick(c)
        if c in ("display", "microwave"):
            ok = (rng.uniform() < 0.8 and placer.on_top(m)) or placer.against_wall(m)
        elif c in WALL_CLASSES:
            ok = placer.against_wall(m)
        elif c in ("plant", "lamp", "bin", "jar", "loudspeaker"):
            ok = placer.in_corner(m) or placer.against_wall(m)
        else:
            ok = placer.anywhere(m)
        placed_extra += ok
    # Top up to at least 4 objects with whatever fits.
    for _ in range(40):
        if len(placer.objects) >= 4:
            break
        c = classes[int(rng.integers(len(classes)))]
        placer.anywhere(pick(c), attempts=10) or placer.in_corner(pick(c), attempts=10)
    room = Room(float(width), float(depth), float(height), tuple(openings), tuple(keepouts),
                _build_room(rng, width, depth, height, openings))
    return Scene(int(seed), room, tuple(placer.objects))


__all__ = ["PlacedObject", "Footprint", "Opening", "Room", "Scene", "generate_scene", "usable_models",
           "wall_frame", "yaw_quaternion", "EXCLUDED_CLASSES", "WALL_CLASSES"]
