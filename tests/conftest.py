"""Shared fixtures. Prefect's environment is set here, before anything imports Prefect:
one temporary PREFECT_HOME for the whole session (its ephemeral API starts once, ~20 s)."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

_PREFECT_HOME = Path(tempfile.mkdtemp(prefix="cadestate-prefect-"))
os.environ["PREFECT_HOME"] = str(_PREFECT_HOME)
os.environ["PREFECT_LOGGING_LEVEL"] = "WARNING"
os.environ.pop("PREFECT_API_URL", None)
os.environ.pop("CADESTATE_CONFIG", None)
os.environ.pop("CADESTATE_WAREHOUSE", None)
os.environ["CADESTATE_PROGRESS"] = "0"

import pytest  # noqa: E402

from bench.demo_clip import DemoClipSpec, make_demo_clip  # noqa: E402
from warehouse import Warehouse  # noqa: E402

SMALL_CLIP = DemoClipSpec(name="small", width=320, height=192, num_video_frames=90, sample_every=3, seed=1)
"""A 3-second clip with 30 camera lines, small enough for many tests."""


@pytest.fixture(scope="session")
def small_clip(tmp_path_factory):
    """The SMALL_CLIP files (generate once per session; tests copy before changing them)."""
    return make_demo_clip(tmp_path_factory.mktemp("clips"), SMALL_CLIP)


@pytest.fixture
def wh(tmp_path) -> Warehouse:
    return Warehouse(tmp_path / "warehouse")
