"""Room geometry of the synthetic benchmark: the room box, windows and doors, floor footprints, meshes.

Frames (see :mod:`cadestate.geometry`): world metres, +Y up, the floor at y = 0, the room box
``x in [-width/2, width/2]``, ``z in [-depth/2, depth/2]``, ``y in [0, height]``. Walls are numbered
0 = z min (faces +z), 1 = x max, 2 = z max, 3 = x min; ``u`` runs along a wall from its centre.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bench.textures import ceiling_texture, door_texture, tile_texture, wall_texture, window_texture, wood_texture
from cadestate.render import Material, RenderMesh


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


def inward_normal(wall: int) -> np.ndarray:
    return np.array([[0.0, 1.0], [-1.0, 0.0], [0.0, -1.0], [1.0, 0.0]][wall])


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


def wall_point(wall: int, u: float, width: float, depth: float, inset: float) -> np.ndarray:
    centre, along, _, _ = wall_frame(wall, width, depth)
    return centre + along * u + inward_normal(wall) * inset


def build_room(rng: np.random.Generator, width: float, depth: float, height: float,
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
        n = inward_normal(w)
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
        n = inward_normal(o.wall)
        axis = 0 if abs(n[0]) > 0.5 else 2
        sign = 1 if n[axis if axis == 0 else 1] > 0 else -1

        def panel(u0: float, u1: float, y0: float, y1: float, d0: float, d1: float, mat: int,
                  front: int | None = None) -> None:
            pts = [wall_point(o.wall, u, width, depth, d) for u in (u0, u1) for d in (d0, d1)]
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


def make_openings(rng: np.random.Generator, width: float, depth: float, height: float) -> list[Opening]:
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
