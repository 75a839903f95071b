"""Shared fixtures. Prefect's environment is set here, before anything imports Prefect:
one temporary PREFECT_HOME for the whole session (its ephemeral API starts once, ~20 s)."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

_PREFECT_HOME = Path(os.environ.get("CADESTATE_TEST_PREFECT_HOME") or tempfile.mkdtemp(prefix="cadestate-prefect-"))
os.environ["CADESTATE_TEST_PREFECT_HOME"] = str(_PREFECT_HOME)  # a process a test spawns imports this module too: it shares the session's
os.environ["PREFECT_HOME"] = str(_PREFECT_HOME)
os.environ["PREFECT_LOGGING_LEVEL"] = "WARNING"
os.environ.pop("PREFECT_API_URL", None)
os.environ.pop("CADESTATE_CONFIG", None)
os.environ.pop("CADESTATE_WAREHOUSE", None)
os.environ["CADESTATE_PROGRESS"] = "0"

import pytest  # noqa: E402

from bench.demo_clip import DemoClipSpec, make_demo_clip  # noqa: E402
from warehouse import Warehouse  # noqa: E402

def pytest_unconfigure(config) -> None:
    """The session's Prefect home goes with the session (else every run leaves a folder in /tmp)."""
    shutil.rmtree(_PREFECT_HOME, ignore_errors=True)


SMALL_CLIP = DemoClipSpec(name="small", width=320, height=192, num_video_frames=90, sample_every=3, seed=1)
"""A 3-second clip with 30 camera lines, small enough for many tests."""


@pytest.fixture(scope="session")
def small_clip(tmp_path_factory):
    """The SMALL_CLIP files (generate once per session; tests copy before changing them)."""
    return make_demo_clip(tmp_path_factory.mktemp("clips"), SMALL_CLIP)


@pytest.fixture
def wh(tmp_path) -> Warehouse:
    return Warehouse(tmp_path / "warehouse")


SMALL_LIBRARY = {  # class -> Sweet Home 3D models (cad_id); others of the class fill in if one is absent
    "chair": ["sh3d-blendswap-cc-0.armchair", "sh3d-blendswap-cc-0.oakchair", "sh3d-blendswap-cc-0.plasticchair"],
    "table": ["sh3d-blendswap-cc-0.oaktable", "sh3d-blendswap-cc-0.tablewithtablecloth"],
    "sofa": ["sh3d-blendswap-cc-0.sofa", "sh3d-blendswap-cc-0.couch"],
    "bed": ["sh3d-blendswap-cc-0.bed1"],
    "plant": ["sh3d-blendswap-cc-0.littleplant", "sh3d-blendswap-cc-0.decorativeplant"],
    "display": ["sh3d-blendswap-cc-0.led-tv", "sh3d-scopia.tv"],
    "cabinet": ["sh3d-blendswap-cc-0.televisioncabinet", "sh3d-blendswap-cc-0.cupboard"],
    "bookshelf": ["sh3d-blendswap-cc-0.bookcase"],
}


def small_library_items() -> list:
    """The Sweet Home 3D items of SMALL_LIBRARY (about 15 models of 8 classes). Skips the test when
    the library is not fetched (`make cad-library`, which `make test` runs)."""
    from tasks.cad.sources import default_source, sweethome3d_items

    source = default_source()
    if not source.is_dir():
        pytest.skip(f"Sweet Home 3D furniture not found at {source} (run `make cad-library`)")
    items = list(sweethome3d_items(source))
    by_id = {i.cad_id: i for i in items}
    pick = []
    for cls, ids in SMALL_LIBRARY.items():
        chosen = [by_id[i] for i in ids if i in by_id]
        pick += chosen + [i for i in items if i.cls == cls and i not in chosen][:len(ids) - len(chosen)]
    return pick


@pytest.fixture(scope="session")
def small_cad_library(tmp_path_factory):
    """(warehouse, cad_models rows): SMALL_LIBRARY canonicalised (cad_ingest only), once per session."""
    from cadestate.config import CadIngestConfig
    from tasks.cad.ingest import ingest_library

    pick = small_library_items()
    wh = Warehouse(tmp_path_factory.mktemp("small_cad_wh"))
    ingest_library(wh, CadIngestConfig(samples=512, workers=1), "sh3d-small", pick, "r", show_progress=False)
    return wh, wh.read("cad_models").to_pylist()


def _filler(field):
    """A placeholder value of ``field``'s type, for columns a test does not care about."""
    import datetime as dt

    import pyarrow as pa

    t = field.type
    if pa.types.is_fixed_size_list(t):
        return [0.0] * t.list_size
    if pa.types.is_timestamp(t):
        return dt.datetime(2026, 1, 1, tzinfo=dt.timezone.utc)
    if pa.types.is_string(t):
        return "x"
    if pa.types.is_boolean(t):
        return False
    if pa.types.is_list(t):
        return []
    return 1


def table_rows(table: str, rows: list[dict]):
    """``rows`` as a pyarrow table of the warehouse table ``table``, unset columns filled in."""
    import pyarrow as pa

    from schemas import TABLES

    schema = TABLES[table].schema
    return pa.Table.from_pylist([{f.name: r.get(f.name, _filler(f)) for f in schema} for r in rows], schema=schema)


@pytest.fixture(scope="session")
def small_library_warehouse(tmp_path_factory):
    """A Config whose warehouse holds SMALL_LIBRARY with every library stage (views, descriptors,
    label similarity) run by the real flow, once per session; tests copy it (:func:`warehouse_copy`)."""
    from cadestate.config import CadIngestConfig, CadViewsConfig, Config, WarehouseConfig
    from flows.cad_library import run_cad_library

    root = tmp_path_factory.mktemp("library")
    config = Config(warehouse=WarehouseConfig(root=str(root)), cad_ingest=CadIngestConfig(samples=512, workers=1),
                    cad_views=CadViewsConfig(views=4, size=96))
    reports = run_cad_library(small_library_items(), config, show_progress=False)
    assert {r.state for r in reports} == {"completed"}, [r.message for r in reports if r.state != "completed"]
    return config


def warehouse_copy(config, to):
    """``config`` with its warehouse copied to the folder ``to``."""
    import dataclasses
    import shutil

    from cadestate.config import WarehouseConfig

    shutil.copytree(config.warehouse.root, to)
    return dataclasses.replace(config, warehouse=WarehouseConfig(root=str(to)))


def pytest_terminal_summary(terminalreporter):
    """How many generated cases the fuzz suite (tests/fuzz) ran, per suite."""
    from fuzz.harness import CASES

    if CASES:
        per = ", ".join(f"{k} {v}" for k, v in sorted(CASES.items()))
        terminalreporter.write_line(f"fuzz: {sum(CASES.values())} generated cases ran ({per})")


@pytest.fixture(scope="session")
def coco_model():
    """NanoDet-m as `make models` built it (an onnx.ModelProto); skips when it is not built."""
    import onnx

    from tasks.detection.models import nanodet

    source = nanodet.default_cache_dir()
    if not nanodet.is_built(source):
        pytest.skip("the NanoDet-m model is not built (run `make models`)")
    return onnx.load(str(source / nanodet.ONNX_NAME))


@pytest.fixture
def models_dir(tmp_path, monkeypatch):
    """A models folder holding the verified NanoDet-m of `make models` (linked) and nothing else,
    set as $CADESTATE_MODELS for the test."""
    from tasks.detection.models import nanodet

    source = nanodet.default_cache_dir()
    if not nanodet.is_built(source):
        pytest.skip("the NanoDet-m model is not built (run `make models`)")
    out = tmp_path / "models"
    out.mkdir()
    for name in (nanodet.ONNX_NAME, nanodet.NOTICE_NAME, nanodet.LICENSE_NAME):
        f = source / name
        os.link(f, out / name) if f.stat().st_dev == out.stat().st_dev else shutil.copy2(f, out / name)
    monkeypatch.setenv("CADESTATE_MODELS", str(out))
    return out
