"""Fixtures of the fuzz suites."""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import pytest

from cadestate.config import IngestConfig
from cadestate.lineage import file_sha256
from fuzz.harness import warehouse_digest
from tasks.video.ingest import ClipSource, ingest_clip
from warehouse import Warehouse


@dataclass(frozen=True)
class SmallWarehouse:
    """A warehouse holding the small clip (ingested by the ingest stage itself, no run), the clip's
    video and camera file, and the warehouse's digest, which no fuzz case may change."""

    root: Path
    video: Path
    cameras: Path
    digest: dict[str, str]


@pytest.fixture(scope="session")
def small_warehouse(small_clip, tmp_path_factory) -> SmallWarehouse:
    folder = tmp_path_factory.mktemp("fuzz_warehouse")
    video, cameras = folder / "small.mp4", folder / "small.txt"
    shutil.copy(small_clip.video_path, video)
    shutil.copy(small_clip.cameras_path, cameras)
    wh = Warehouse(folder / "warehouse")
    ingest_clip(wh, IngestConfig(link_inputs=False), ClipSource("small", video, cameras), file_sha256(video),
                file_sha256(cameras), "r0")
    return SmallWarehouse(wh.root, video, cameras, warehouse_digest(wh.root))


@pytest.fixture(scope="module")
def no_runs():
    """Fail the case if `cadestate ingest` starts a run: bad input must be refused before that."""

    def run_sources(*args, **kwargs):
        raise AssertionError("`cadestate ingest` started a run on a bad input")

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("cadestate.cli.pipeline.run_sources", run_sources)
        yield
