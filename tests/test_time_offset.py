"""RealEstate10K timestamp offsets: a camera file that counts from the start of a longer video."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from PIL import Image

from bench.demo_clip import decode_index
from cadestate.config import FramesConfig, IngestConfig
from cadestate.lineage import file_sha256
from tasks.video.camera_file import CameraFileError, parse_camera_file, write_camera_file
from tasks.video.frames import extract_frames
from tasks.video.ingest import ClipSource, check_clip_inputs, ingest_clip, ingest_inputs_hash

OFFSET = 65_233_333


@pytest.fixture
def shifted(small_clip, tmp_path):
    """The small clip's camera file with every timestamp OFFSET µs later (as cut from a longer video)."""
    cams = parse_camera_file(small_clip.cameras_path)
    path = tmp_path / "shifted.txt"
    write_camera_file(path, dataclasses.replace(cams, timestamps_us=cams.timestamps_us + OFFSET))
    return path


def test_timestamps_past_the_end_name_the_options(small_clip, shifted):
    with pytest.raises(CameraFileError, match=r"shifted.txt:2: timestamp 65233333 µs is past the end .*all cameras lie "
                                              r"past its end.*--time-offset-us N, or --align-start"):
        check_clip_inputs(small_clip.video_path, shifted)


def test_align_start_maps_the_first_timestamp_to_the_first_frame(small_clip, shifted):
    assert check_clip_inputs(small_clip.video_path, shifted, align_start=True).time_offset_us == OFFSET
    assert check_clip_inputs(small_clip.video_path, shifted, OFFSET).time_offset_us == OFFSET
    with pytest.raises(CameraFileError, match="--align-start: the first timestamp .* lies within"):
        check_clip_inputs(small_clip.video_path, small_clip.cameras_path, align_start=True)  # never guessed
    with pytest.raises(CameraFileError, match=r"minus the time offset 62033333 µs is past the end .* \(30 of the 30"):
        check_clip_inputs(small_clip.video_path, shifted, OFFSET - 3_200_000)  # a wrong offset
    with pytest.raises(CameraFileError, match="before the start"):
        check_clip_inputs(small_clip.video_path, small_clip.cameras_path, 1_000_000)


def test_frames_with_an_offset_are_the_same_pictures_at_the_written_timestamps(wh, small_clip, shifted):
    video = small_clip.video_path
    ingest_clip(wh, IngestConfig(), ClipSource("small", video, shifted, time_offset_us=OFFSET), file_sha256(video),
                file_sha256(shifted), "r0")
    extract_frames(wh, FramesConfig(), "small", "r1", show_progress=False)
    rows = wh.read("frames").to_pylist()
    assert wh.read("clips").to_pylist()[0]["time_offset_us"] == OFFSET
    assert [r["timestamp_us"] for r in rows] == parse_camera_file(shifted).timestamps_us.tolist()  # as written
    for row, index in zip(rows, small_clip.frame_indices):
        assert decode_index(np.asarray(Image.open(wh.root / row["image_path"]))) == index
        assert row["video_time_us"] == row["timestamp_us"] - OFFSET and row["timestamp_error_us"] == 0


def test_the_offset_is_part_of_ingests_inputs():
    assert ingest_inputs_hash("c", "v", "k", "train", 0) == ingest_inputs_hash("c", "v", "k", "train")  # old digests kept
    assert ingest_inputs_hash("c", "v", "k", "train", 5) != ingest_inputs_hash("c", "v", "k", "train", 0)
