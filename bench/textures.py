"""Procedural textures of the synthetic rooms: uint8[H, W, 3] images, row 0 = top.

``rng`` makes them vary per scene; everything is numpy (no image files).
"""

from __future__ import annotations

import numpy as np


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
