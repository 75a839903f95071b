"""`cadestate ingest` checks every camera file, video and the [detect] model before it starts a run:
a bad input is one `error:` line and nothing is written; a suspicious one is a warning."""

from __future__ import annotations

import pytest

from fuzz.harness import assert_clean_error, run_cli, warehouse_digest


@pytest.fixture
def started(monkeypatch) -> list:
    """The clip lists `cadestate ingest` handed to a run (the run itself is not started)."""
    calls: list = []
    monkeypatch.setattr("cadestate.cli.pipeline.run_sources", lambda state, items, progress: calls.append(items))
    return calls


def test_bad_camera_file_is_refused_before_the_run(tmp_path, small_clip, started):
    lines = small_clip.cameras_path.read_text().splitlines()
    cams = tmp_path / "c.txt"
    cams.write_text("\n".join(lines[1:]) + "\n")  # the URL line left out
    w = tmp_path / "w"
    result = run_cli("-w", str(w), "ingest", str(small_clip.video_path), str(cams))
    assert assert_clean_error(result) == f"error: {cams}:1: line 1 is a camera line (19 numbers), not the video URL: the URL line is missing"
    assert started == [] and warehouse_digest(w) == {}


def test_bad_detect_config_is_refused_before_the_run(tmp_path, small_clip, started):
    config = tmp_path / "c.toml"
    config.write_text('[detect]\nclasses = ["sofa"]\n')
    result = run_cli("-c", str(config), "-w", str(tmp_path / "w"), "ingest", str(small_clip.video_path),
                     str(small_clip.cameras_path))
    assert_clean_error(result, mentions=f"{config}: [detect] classes: 'sofa' not in the default COCO-80 label map")
    assert started == []


def test_suspicious_intrinsics_are_a_warning(tmp_path, small_clip, started):
    lines = small_clip.cameras_path.read_text().splitlines()
    fields = lines[3].split()
    fields[2] = repr(float(fields[2]) * 1.05)  # fy of the third camera 5 % off the video's aspect
    lines[3] = " ".join(fields)
    cams = tmp_path / "c.txt"
    cams.write_text("\n".join(lines) + "\n")
    result = run_cli("-w", str(tmp_path / "w"), "ingest", str(small_clip.video_path), str(cams))
    assert result.code == 0 and len(started) == 1
    assert result.stderr.startswith(f"warning: {cams}:4: fy/fx = 1.75 fits frames of aspect 1.75 (width/height) but ")
    assert "(differ by 5.0%: non-square pixels or a cropped video?)" in result.stderr
