"""Tests of :mod:`tasks.cad.symmetry`: programmatic meshes with known answers, and a list of
Sweet Home 3D models whose symmetry was decided by looking at them (``data/sh3d_symmetry.csv``)."""

from __future__ import annotations

import csv
import dataclasses
import time
from collections.abc import Callable
from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest
import trimesh

from tasks.cad.ingest import canonicalise
from tasks.cad.sources import CadItem, default_source, load_item, slug, sweethome3d_items
from tasks.cad.symmetry import (
    DEFAULT_TOLERANCE,
    SYMMETRY_ORDERS,
    SymmetryResult,
    detect_symmetry,
    sample_surface,
)

HAND_CHECKED = Path(__file__).parent / "data" / "sh3d_symmetry.csv"
SH3D_DIR = default_source()  # $CADESTATE_SH3D_DIR, or where `make cad-library` unpacks Debian's package
SH3D_SETS = ("BlendSwap-CC-0", "BlendSwap-CC-BY", "KatorLegaz", "Scopia")


# --- programmatic meshes (canonical frame: metres, +Y up, bounding box centred) ---------------

def _canonical(*parts: trimesh.Trimesh) -> trimesh.Trimesh:
    mesh = trimesh.util.concatenate(list(parts))
    lo, hi = mesh.bounds
    mesh.apply_translation(-(lo + hi) / 2)
    return mesh


def _box(extents, centre=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents, transform=trimesh.transformations.translation_matrix(centre))


def _z_to_y(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """trimesh builds round primitives along +Z; turn them to stand along +Y."""
    mesh.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))
    return mesh


def _cylinder(radius, height, centre=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    mesh = _z_to_y(trimesh.creation.cylinder(radius=radius, height=height, sections=64))
    mesh.apply_translation(centre)
    return mesh


def _sphere(radius, centre) -> trimesh.Trimesh:
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=radius)
    mesh.apply_translation(centre)
    return mesh


def _legs(half_x, half_z, height, thickness):
    return [_box((thickness, height, thickness), (sx * half_x, height / 2, sz * half_z))
            for sx in (-1, 1) for sz in (-1, 1)]


def _chair() -> trimesh.Trimesh:
    seat = _box((0.45, 0.04, 0.45), (0, 0.45, 0))
    backrest = _box((0.45, 0.45, 0.04), (0, 0.695, -0.205))
    return _canonical(seat, backrest, *_legs(0.2, 0.2, 0.43, 0.04))


SHAPES: dict[str, tuple[int, Callable[[], trimesh.Trimesh]]] = {
    "box 1.0x0.5x0.6": (2, lambda: _box((1.0, 0.5, 0.6))),
    "box 0.8x0.5x0.8": (4, lambda: _box((0.8, 0.5, 0.8))),
    "cylinder": (36, lambda: _cylinder(0.3, 0.8)),
    "cone": (36, lambda: _canonical(
        _z_to_y(trimesh.creation.cone(radius=0.3, height=0.7, sections=64)))),
    "round table (disc top, stem, foot)": (36, lambda: _canonical(
        _cylinder(0.5, 0.04, (0, 0.73, 0)), _cylinder(0.04, 0.7, (0, 0.36, 0)),
        _cylinder(0.25, 0.02, (0, 0.01, 0)))),
    "chair (seat, backrest, 4 legs)": (1, _chair),
    "L-shape": (1, lambda: _canonical(_box((1.0, 0.4, 0.3)), _box((0.3, 0.4, 0.7), (0.35, 0, 0.5)))),
    "table, rectangular top, 4 legs": (2, lambda: _canonical(
        _box((1.6, 0.04, 0.9), (0, 0.73, 0)), *_legs(0.75, 0.4, 0.71, 0.06))),
    "table, square top, 4 legs": (4, lambda: _canonical(
        _box((0.9, 0.04, 0.9), (0, 0.73, 0)), *_legs(0.4, 0.4, 0.71, 0.06))),
    "bed with headboard and lower footboard": (1, lambda: _canonical(
        _box((1.6, 0.3, 2.0), (0, 0.25, 0)), _box((1.6, 0.9, 0.05), (0, 0.45, -1.0)),
        _box((1.6, 0.5, 0.05), (0, 0.25, 1.0)))),
    # small details must not break symmetry
    "box with a knob on top": (2, lambda: _canonical(
        _box((1.0, 0.5, 0.6)), _sphere(0.02, (0.3, 0.25, 0.2)))),
    "cylinder with a knob on the side": (36, lambda: _canonical(
        _cylinder(0.3, 0.8), _sphere(0.015, (0.3, 0.2, 0)))),
    "cabinet with one door handle": (2, lambda: _canonical(
        _box((0.8, 1.8, 0.6)), _box((0.02, 0.25, 0.02), (0.3, 0.1, 0.31)))),
}


@pytest.fixture(scope="module")
def meshes() -> dict[str, trimesh.Trimesh]:
    return {name: make() for name, (_, make) in SHAPES.items()}


@pytest.mark.parametrize("name", list(SHAPES))
def test_programmatic_meshes(name, meshes):
    result = detect_symmetry(sample_surface(meshes[name]))
    expected = SHAPES[name][0]
    assert result.order == expected, f"{name}: got {result.order}, expected {expected}, errors {result.errors}"


def test_result_fields(meshes):
    result = detect_symmetry(sample_surface(meshes["box 1.0x0.5x0.6"]))
    assert isinstance(result, SymmetryResult) and result.order in SYMMETRY_ORDERS
    assert sorted(result.errors) == [2, 4, 36]
    assert all(isinstance(e, float) and e >= 0.0 for e in result.errors.values())
    assert result.errors[2] <= DEFAULT_TOLERANCE < result.errors[4]
    with pytest.raises(dataclasses.FrozenInstanceError):
        result.order = 4  # type: ignore[misc]


@pytest.mark.parametrize("name", list(SHAPES))
def test_same_answer_for_other_samples(name, meshes):
    """Another seed, a random subset of the samples, more samples, a shuffled order: same order."""
    expected = SHAPES[name][0]
    rng = np.random.default_rng(7)
    points = sample_surface(meshes[name], 4096, seed=0)
    variants = {
        "seed 1": sample_surface(meshes[name], 4096, seed=1),
        "seed 2": sample_surface(meshes[name], 4096, seed=2),
        "random 3000 of 4096": points[rng.choice(len(points), 3000, replace=False)],
        "8192 samples": sample_surface(meshes[name], 8192, seed=3),
        "shuffled": points[rng.permutation(len(points))],
    }
    for variant, pts in variants.items():
        assert detect_symmetry(pts).order == expected, f"{name}, {variant}"


def test_scale_invariant_and_deterministic(meshes):
    points = sample_surface(meshes["table, rectangular top, 4 legs"])
    a, b = detect_symmetry(points), detect_symmetry(points.copy())
    assert a == b
    scaled = detect_symmetry(points * 100.0)  # centimetres instead of metres
    assert scaled.order == a.order
    assert all(abs(scaled.errors[k] - a.errors[k]) < 1e-9 for k in a.errors)


def test_symmetry_is_about_the_up_axis(meshes):
    """Lying on its side, a standing cylinder is only 2-fold symmetric about +Y."""
    cyl = meshes["cylinder"].copy()
    cyl.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 0, 1]))
    assert detect_symmetry(sample_surface(cyl)).order == 2


def test_tolerance_parameter(meshes):
    points = sample_surface(meshes["chair (seat, backrest, 4 legs)"])
    assert detect_symmetry(points).order == 1
    assert detect_symmetry(points, tolerance=10.0).order == 36


def test_degenerate_input():
    assert detect_symmetry(np.zeros((1, 3))).order == 36
    with pytest.raises(ValueError):
        detect_symmetry(np.zeros((10, 2)))


def test_sample_surface_deterministic(meshes):
    mesh = meshes["box 1.0x0.5x0.6"]
    a, b = sample_surface(mesh, 1000, seed=5), sample_surface(mesh, 1000, seed=5)
    assert a.shape == (1000, 3) and a.dtype == np.float64
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, sample_surface(mesh, 1000, seed=6))
    # on the surface: inside the box, on one of its faces
    half = np.array([0.5, 0.25, 0.3])
    assert np.all(np.abs(a) <= half + 1e-9)
    assert np.all(np.isclose(np.abs(a), half, atol=1e-9).any(axis=1))


def test_sample_surface_area_uniform(meshes):
    """Faces are hit in proportion to their area: the top (1.0 x 0.6) gets 0.6 / 2.8 of the samples."""
    points = sample_surface(meshes["box 1.0x0.5x0.6"], 20000, seed=0)
    top = np.isclose(points[:, 1], 0.25).mean()
    assert abs(top - 0.3 / 1.4) < 0.015


# --- the hand-checked Sweet Home 3D list --------------------------------------------------------

def _hand_checked_rows() -> list[dict[str, str]]:
    with HAND_CHECKED.open(newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def test_hand_checked_list_well_formed():
    rows = _hand_checked_rows()
    assert len(rows) >= 30
    assert list(rows[0]) == ["set", "id", "name", "expected_order", "note"]
    assert len({r["id"] for r in rows}) == len(rows)
    for r in rows:
        assert r["set"] in SH3D_SETS and int(r["expected_order"]) in SYMMETRY_ORDERS and r["note"].strip()
    counts = {k: sum(int(r["expected_order"]) == k for r in rows) for k in SYMMETRY_ORDERS}
    assert min(counts.values()) >= 6, counts


@lru_cache(maxsize=None)
def _sh3d_items() -> dict[tuple[str, str], CadItem]:
    """Catalogue items by (library, item id), read by the pipeline's own source reader."""
    return {(i.library, i.item): i for i in sweethome3d_items(SH3D_DIR)}


def load_sh3d_model(set_name: str, item_id: str) -> trimesh.Trimesh:
    """The item in the canonical frame, through the ingest stage's own loading and canonicalisation."""
    item = _sh3d_items()[("sh3d-" + slug(set_name), item_id.split("#", 1)[1])]
    scene, _ = load_item(item)
    return canonicalise(scene, item).mesh


@pytest.mark.skipif(not SH3D_DIR.is_dir(), reason=(
    f"Sweet Home 3D furniture folder {SH3D_DIR} not found (unpack Debian's "
    "sweethome3d-furniture 1.8-1 there or set CADESTATE_SH3D_DIR)"))
def test_hand_checked_sweet_home_3d_models():
    rows = _hand_checked_rows()
    disagreements, seconds = [], []
    for r in rows:
        assert r["set"] in SH3D_SETS
        mesh = load_sh3d_model(r["set"], r["id"])
        points = sample_surface(mesh, 4096, seed=0)
        start = time.process_time()
        result = detect_symmetry(points)
        seconds.append(time.process_time() - start)
        if result.order != int(r["expected_order"]):
            errors = ", ".join(f"{k}: {v:.4f}" for k, v in result.errors.items())
            disagreements.append(f"{r['id']}: expected {r['expected_order']}, got {result.order} "
                                 f"(errors {errors}; {r['note']})")
    agreement = 1.0 - len(disagreements) / len(rows)
    print(f"\nhand-checked Sweet Home 3D models: agreement {agreement:.1%} "
          f"({len(rows) - len(disagreements)}/{len(rows)}); detect_symmetry "
          f"{1000 * np.median(seconds):.0f} ms median, {1000 * max(seconds):.0f} ms max CPU per model")
    for line in disagreements:
        print("  disagreement:", line)
    assert agreement >= 0.9, "\n".join(disagreements)
