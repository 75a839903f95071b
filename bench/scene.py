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

from bench.room import Footprint, Room, build_room, inward_normal, make_openings, wall_frame, wall_point
from cadestate.render import object_to_world

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


def yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) of a rotation by ``yaw`` radians about +Y."""
    return (math.cos(yaw / 2), 0.0, math.sin(yaw / 2), 0.0)


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
            p = centre + along * u + inward_normal(wall) * (size[2] / 2 + WALL_GAP_M + 0.01)
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
    openings = make_openings(rng, width, depth, height)
    keepouts = []
    for o in openings:
        if o.kind == "door":
            c = wall_point(o.wall, o.u, width, depth, 0.5)
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
                build_room(rng, width, depth, height, openings))
    return Scene(int(seed), room, tuple(placer.objects))


__all__ = ["PlacedObject", "Footprint", "Opening", "Room", "Scene", "generate_scene", "usable_models",
           "wall_frame", "yaw_quaternion", "EXCLUDED_CLASSES", "WALL_CLASSES"]
