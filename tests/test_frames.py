"""Ingest and frame extraction as plain functions: exact frames, clear failures, nothing half-written."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from bench.demo_clip import DemoClipSpec, decode_index, make_demo_clip
from cadestate.config import FramesConfig, IngestConfig
from cadestate.geometry import project, quaternion_to_matrix
from cadestate.lineage import file_sha256
from tasks.video.camera_file import CameraFileError, CameraTrack, parse_camera_file, write_camera_file
from tasks.video.decode import VideoError, decode_at, probe_video, write_video
from tasks.video.frames import extract_frames
from tasks.video.ingest import ASPECT_ERROR, ClipSource, check_clip_inputs, discover_clips, ingest_clip, official_clip_name
from warehouse import WarehouseError, connect


def ingest(wh, video: Path, cameras: Path, clip: str = "small", tolerance_us: int = FramesConfig().max_timestamp_error_us):
    # up forced to +Y: the demo world is built +Y up, and these tests compare the frames with the camera file exactly
    return ingest_clip(wh, IngestConfig(up="+y"), ClipSource(clip, video, cameras), file_sha256(video), file_sha256(cameras),
                       "r0", tolerance_us)


def test_extracted_frames_are_exactly_the_camera_frames(wh, small_clip):
    ingest(wh, small_clip.video_path, small_clip.cameras_path)
    out = extract_frames(wh, FramesConfig(), "small", "run1", show_progress=False)
    frames = wh.read("frames").to_pylist()
    assert out.rows_written == len(frames) == len(small_clip.frame_indices) == 30
    for row, index in zip(frames, small_clip.frame_indices):
        image = np.asarray(Image.open(wh.root / row["image_path"]))
        assert image.shape == (192, 320, 3) and (row["width"], row["height"]) == (320, 192)
        assert decode_index(image) == index  # the very frame the camera line names
        assert row["timestamp_error_us"] == 0
    (version,) = {p.parent.name for p in (wh.root / "media" / "frames" / "small").glob("*/*")}
    assert len(version) == 16  # the images' digest: a rerun that decodes the same images keeps their paths
    again = extract_frames(wh, FramesConfig(max_timestamp_error_us=2_999), "small", "run2", show_progress=False)
    assert again.output_hash == out.output_hash and wh.read("frames").column("image_path").to_pylist() == \
        [r["image_path"] for r in frames]  # task files written before still name images that are there
    assert [p.name for p in (wh.root / "media" / "frames" / "small").iterdir()] == [version]


def test_frames_table_geometry_matches_the_camera_file(wh, small_clip):
    ingest(wh, small_clip.video_path, small_clip.cameras_path)
    extract_frames(wh, FramesConfig(), "small", "run1", show_progress=False)
    cams = parse_camera_file(small_clip.cameras_path)
    row = wh.read("frames").to_pylist()[7]
    R, t = np.reshape(row["world_to_camera_R"], (3, 3)), np.asarray(row["world_to_camera_t"])
    np.testing.assert_array_equal(R, cams.R[7])
    np.testing.assert_array_equal(t, cams.t[7])
    np.testing.assert_allclose(np.reshape(row["camera_to_world_R"], (3, 3)), R.T)
    centre = np.asarray(row["camera_center"])
    np.testing.assert_allclose(R @ centre + t, 0, atol=1e-12)
    assert abs(centre[1] - 1.5) < 1e-9  # the demo camera walks at 1.5 m, world +Y up
    K = np.reshape(row["K"], (3, 3))
    assert K[0, 2] == pytest.approx(160) and K[1, 2] == pytest.approx(96)
    uv, depth = project(K, R, t, (centre + 2.0 * R[2])[None])  # 2 m along the optical axis
    np.testing.assert_allclose(uv[0], [160, 96]) and depth[0] == pytest.approx(2)
    # The same numbers through SQL on the catalog: DuckDB arrays, 1-based.
    con = connect(wh)
    assert con.execute("SELECT camera_center[2] FROM frames WHERE frame_index = 7").fetchone()[0] == pytest.approx(1.5)
    con.close()


def test_sparse_timestamps_are_reached_by_seeking(small_clip):
    ts = parse_camera_file(small_clip.cameras_path).timestamps_us
    pick = ts[[0, 4, 11, 29]]
    frames = list(decode_at(small_clip.video_path, pick, seek_threshold_us=100_000))
    assert [f.time_us for f in frames] == list(pick)
    assert [decode_index(f.rgb) for f in frames] == list(small_clip.frame_indices[[0, 4, 11, 29]])


def shifted_inside(src: Path, dst: Path, shift_us: int = 15_000) -> Path:
    """A copy of the camera file ``src`` whose cameras but the first and the last are ``shift_us`` late
    (half a frame at 30 fps)."""
    cams = parse_camera_file(src)
    times = cams.timestamps_us.copy()
    times[1:-1] += shift_us
    write_camera_file(dst, CameraTrack(cams.url, times, cams.intrinsics, cams.world_to_camera))
    return dst


def test_timestamp_discrepancy_past_tolerance_fails_and_writes_nothing(wh, small_clip, tmp_path):
    """Ingested under a looser tolerance than the frames stage's (ingest refuses it under the same)."""
    shifted = shifted_inside(small_clip.cameras_path, tmp_path / "shifted.txt")
    ingest(wh, small_clip.video_path, shifted, tolerance_us=20_000)
    step = int(parse_camera_file(small_clip.cameras_path).timestamps_us[1])
    with pytest.raises(VideoError, match=rf"^{shifted}:3: clip small \(.*small.mp4\): camera line 3 asks for {step + 15_000} µs "
                                         rf"but the nearest video frame is at {step} µs \(-15000 µs"):
        extract_frames(wh, FramesConfig(), "small", "run1", show_progress=False)
    assert wh.read("frames").num_rows == 0
    assert not list((wh.root / "media").rglob("*.jpg")) and not list((wh.root / "_staging").iterdir())
    # A looser tolerance accepts it and records the discrepancy per frame.
    extract_frames(wh, FramesConfig(max_timestamp_error_us=20_000), "small", "run2", show_progress=False)
    assert set(wh.read("frames").column("timestamp_error_us").to_pylist()) == {0, -15_000}  # the earlier frame is always nearer


def test_cameras_off_the_frames_at_either_end_fail_at_ingest(small_clip, tmp_path):
    """A video of another frame rate, or a truncated one, is refused before anything starts, naming the line."""
    cams = parse_camera_file(small_clip.cameras_path)
    late = tmp_path / "late.txt"
    write_camera_file(late, CameraTrack(cams.url, cams.timestamps_us + 15_000, cams.intrinsics, cams.world_to_camera))
    with pytest.raises(CameraFileError, match=rf"^{late}:2: timestamp 15000 µs has no frame in .*small.mp4: the nearest is "
                                              r"at 0 µs \(-15000 µs; \[frames\] max_timestamp_error_us = 3000\)"):
        check_clip_inputs(small_clip.video_path, late)
    assert check_clip_inputs(small_clip.video_path, late, tolerance_us=20_000).time_offset_us == 0
    last = tmp_path / "last.txt"
    times = cams.timestamps_us.copy()
    times[-1] += 15_000
    write_camera_file(last, CameraTrack(cams.url, times, cams.intrinsics, cams.world_to_camera))
    with pytest.raises(CameraFileError, match=rf"^{last}:{len(times) + 1}: timestamp {times[-1]} µs has no frame"):
        check_clip_inputs(small_clip.video_path, last)


def test_cameras_between_the_frames_inside_the_clip_fail_at_ingest(wh, small_clip, tmp_path):
    """A camera file of another frame rate lines up with the video at its ends (a 60 fps file on a
    30 fps video): every camera is checked against the video's frame times before anything is
    written, not only the first and the last (the clip was registered and its frames stage failed)."""
    shifted = shifted_inside(small_clip.cameras_path, tmp_path / "shifted.txt")
    step = int(parse_camera_file(small_clip.cameras_path).timestamps_us[1])
    with pytest.raises(CameraFileError, match=rf"^{shifted}:3: timestamp {step + 15_000} µs has no frame in .*small.mp4: "
                                              rf"the nearest is at {step} µs \(-15000 µs"):
        ingest(wh, small_clip.video_path, shifted)
    assert wh.read("clips").num_rows == 0 and not (wh.root / "inputs" / "small").exists()


def test_cameras_on_one_frame_fail_at_ingest(wh, small_clip, tmp_path):
    """A camera file in milliseconds (0, 67, 133, ...): every camera lay within 3 ms of the first
    frame, so the clip was ingested with every pose on one image."""
    cams = parse_camera_file(small_clip.cameras_path)
    ms = tmp_path / "ms.txt"
    write_camera_file(ms, CameraTrack(cams.url, cams.timestamps_us // 1000, cams.intrinsics, cams.world_to_camera))
    with pytest.raises(CameraFileError, match=rf"^{ms}:3: timestamp {cams.timestamps_us[1] // 1000} µs falls on the same "
                                              r"frame of .*small.mp4 as line 2's \(0 µs\): each camera needs a frame of "
                                              r"its own \(timestamps in milliseconds, not µs\?\)"):
        ingest(wh, small_clip.video_path, ms)
    assert wh.read("clips").num_rows == 0 and not (wh.root / "inputs" / "small").exists()


def test_corrupt_video_fails_clearly_at_ingest(wh, small_clip, tmp_path):
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(np.random.default_rng(0).bytes(50_000))
    with pytest.raises(VideoError, match="junk.mp4: cannot"):
        ingest(wh, junk, small_clip.cameras_path)
    assert wh.read("clips").num_rows == 0 and not (wh.root / "inputs").exists()


def test_truncated_video_fails_and_keeps_previous_frames(wh, small_clip, tmp_path):
    ingest(wh, small_clip.video_path, small_clip.cameras_path)
    extract_frames(wh, FramesConfig(), "small", "run1", show_progress=False)
    before = wh.read("frames")
    cut = tmp_path / "cut.mp4"
    data = small_clip.video_path.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(VideoError, match="cut.mp4"):
        ingest(wh, cut, small_clip.cameras_path)
        extract_frames(wh, FramesConfig(), "small", "run2", show_progress=False)
    assert wh.read("frames").equals(before)
    assert all((wh.root / p).exists() for p in before.column("image_path").to_pylist())


def test_cameras_past_the_end_of_the_video_fail_at_ingest(wh, small_clip, tmp_path):
    cams = parse_camera_file(small_clip.cameras_path)
    late = tmp_path / "late.txt"  # cameras from 2.8 s: the first one past the 3 s video (+0.1 s) is the 5th
    write_camera_file(late, CameraTrack(cams.url, cams.timestamps_us + 2_800_000, cams.intrinsics, cams.world_to_camera))
    with pytest.raises(CameraFileError, match=r"late.txt:6: timestamp 3200000 µs is past the end of .*small.mp4, "
                                              r"which lasts 3000000 µs \(26 of the 30 cameras are past it\)$"):
        ingest(wh, small_clip.video_path, late)
    assert wh.read("clips").num_rows == 0 and not (wh.root / "inputs").exists()


def with_intrinsics(src: Path, dst: Path, fx: float, fy: float) -> Path:
    """A copy of the camera file ``src`` at ``dst`` with every camera's fx and fy replaced."""
    cams = parse_camera_file(src)
    intrinsics = cams.intrinsics.copy()
    intrinsics[:, :2] = fx, fy
    write_camera_file(dst, CameraTrack(cams.url, cams.timestamps_us, intrinsics, cams.world_to_camera))
    return dst


def test_intrinsics_of_another_aspect_fail_at_ingest(wh, small_clip, tmp_path):
    video = tmp_path / "four_three.mp4"  # 4:3, one second
    write_video(video, (np.zeros((48, 64, 3), np.uint8) for _ in range(30)), 64, 48, 30)
    wide = with_intrinsics(small_clip.cameras_path, tmp_path / "wide.txt", 0.8, 0.8 * 16 / 9)
    lines = wide.read_text().splitlines()
    wide.write_text("\n".join(lines[:11]) + "\n")  # 10 cameras within the second
    with pytest.raises(CameraFileError, match=r"wide.txt:2: fy/fx = 1.778 fits frames of aspect 1.778 \(width/height\) "
                                              r"but .*four_three.mp4 is 64x48 \(1.333\): the intrinsics are another "
                                              r"video's \(differ by 33%, more than 10%\)$"):
        ingest(wh, video, wide)
    assert wh.read("clips").num_rows == 0 and not (wh.root / "inputs").exists()


def test_slightly_other_aspect_is_a_warning(wh, small_clip, tmp_path):
    aspect = 320 / 192
    assert check_clip_inputs(small_clip.video_path, small_clip.cameras_path).warnings == ()
    near = with_intrinsics(small_clip.cameras_path, tmp_path / "near.txt", 0.8, 0.8 * aspect * 1.05)
    checked = check_clip_inputs(small_clip.video_path, near)
    assert checked.warnings == (f"{near}:2: fy/fx = 1.75 fits frames of aspect 1.75 (width/height) but "
                                f"{small_clip.video_path} is 320x192 (1.667) (differ by 5.0%: non-square pixels "
                                f"or a cropped video?)",)
    assert ingest(wh, small_clip.video_path, near).message == checked.warnings[0]  # the stage reports it
    far = with_intrinsics(small_clip.cameras_path, tmp_path / "far.txt", 0.8, 0.8 * aspect * (1 + ASPECT_ERROR) * 1.01)
    with pytest.raises(CameraFileError, match="far.txt:2: .*differ by 11%, more than 10%"):
        check_clip_inputs(small_clip.video_path, far)


def test_malformed_camera_file_fails_at_ingest_naming_the_line(wh, small_clip, tmp_path):
    bad = tmp_path / "bad.txt"
    lines = small_clip.cameras_path.read_text().splitlines()
    lines[5] = lines[5].replace(" ", " nan ", 1)
    bad.write_text("\n".join(lines) + "\n")
    with pytest.raises(CameraFileError, match=r"bad.txt:6: "):
        ingest(wh, small_clip.video_path, bad)
    assert wh.read("clips").num_rows == 0


def test_a_youtube_id_that_starts_with_a_dash_names_a_clip_end_to_end(wh, small_clip, tmp_path):
    """1 in 64 YouTube ids starts with '-', and CAD-Estate names the clip by it: such names were
    refused, so those RealEstate10K clips could not be ingested. Now its frames are extracted and
    queried by name."""
    lines = small_clip.cameras_path.read_text().splitlines()
    cameras = tmp_path / "c.txt"
    cameras.write_text("\n".join(["https://www.youtube.com/watch?v=-0AK9iy8y0c", *lines[1:]]) + "\n")
    clip = official_clip_name(parse_camera_file(cameras), cameras)
    assert clip == f"-0AK9iy8y0c_{lines[1].split()[0]}"
    ingest(wh, small_clip.video_path, cameras, clip)
    extract_frames(wh, FramesConfig(), clip, "run1", show_progress=False)
    con = connect(wh)
    assert con.execute("SELECT DISTINCT clip FROM frames").fetchall() == [(clip,)]
    assert con.execute("SELECT count(*) FROM frames WHERE clip = ?", [clip]).fetchone() == (30,)


def test_png_frames_are_lossless(wh, small_clip):
    ingest(wh, small_clip.video_path, small_clip.cameras_path)
    extract_frames(wh, FramesConfig(image_format="png"), "small", "run1", show_progress=False)
    first = wh.read("frames").to_pylist()[0]
    assert first["image_path"].endswith(".png")
    decoded = next(decode_at(small_clip.video_path, np.array([first["timestamp_us"]])))
    np.testing.assert_array_equal(np.asarray(Image.open(wh.root / first["image_path"])), decoded.rgb)


def test_ingest_keeps_inputs_and_probe(wh, small_clip):
    out = ingest(wh, small_clip.video_path, small_clip.cameras_path)
    row = wh.read("clips").to_pylist()[0]
    assert (row["num_cameras"], row["width"], row["height"], row["codec"]) == (30, 320, 192, "h264")
    assert row["fps"] == pytest.approx(30) and row["url"] == "synthetic://demo/small"
    assert file_sha256(wh.root / row["video_path"]) == row["video_sha256"] == file_sha256(small_clip.video_path)
    assert out.rows_written == 1
    info = probe_video(small_clip.video_path)
    assert info.duration_us == 3_000_000


def test_discover_clips_pairs_videos_with_camera_files(tmp_path, small_clip):
    shutil.copy(small_clip.video_path, tmp_path / "living room é.mp4")  # named by its camera file: any file name
    shutil.copy(small_clip.cameras_path, tmp_path / "living room é.txt")
    assert discover_clips(tmp_path) == [(tmp_path / "living room é.mp4", tmp_path / "living room é.txt")]
    shutil.copy(small_clip.video_path, tmp_path / "b.mp4")
    with pytest.raises(FileNotFoundError, match="b.mp4: no camera file b.txt"):
        discover_clips(tmp_path)
    (tmp_path / "b.mp4").rename(tmp_path / "b.m4v")  # a suffix not read: its camera file was skipped without a word
    shutil.copy(small_clip.cameras_path, tmp_path / "b.txt")
    (tmp_path / "notes.txt").write_text("not a camera file\n1 2 3\n")
    with pytest.raises(FileNotFoundError, match=r"b.txt: a camera file with no video beside it \(b.mp4, b.mkv"):
        discover_clips(tmp_path)
    (tmp_path / "b.txt").unlink()
    assert discover_clips(tmp_path) == [(tmp_path / "living room é.mp4", tmp_path / "living room é.txt")]
    with pytest.raises(WarehouseError, match="invalid clip name"):
        ClipSource("bad name", tmp_path / "a.mp4", tmp_path / "a.txt")


def remux(src: Path, dst: Path) -> None:
    """Copy the video stream into another container (no re-encoding)."""
    import av

    with av.open(str(src)) as inp, av.open(str(dst), "w") as out:
        stream = out.add_stream_from_template(inp.streams.video[0])
        for packet in inp.demux(inp.streams.video[0]):
            if packet.dts is not None:
                packet.stream = stream
                out.mux(packet)


def test_a_reingest_from_another_container_that_fails_keeps_the_video_in_force(wh, small_clip, tmp_path, monkeypatch):
    """A clip ingested again from an .mkv, whose copy fails (a full disk): the .mp4 the clip's row
    names stays (it was deleted before the copy, leaving the row naming no video); once a copy
    succeeds, the row names the .mkv and the .mp4 goes."""
    cfg = IngestConfig(up="+y", link_inputs=False)

    def again(video: Path):
        return ingest_clip(wh, cfg, ClipSource("small", video, small_clip.cameras_path), file_sha256(video),
                           file_sha256(small_clip.cameras_path), "r0")

    again(small_clip.video_path)
    mkv = tmp_path / "small.mkv"
    remux(small_clip.video_path, mkv)

    def full_disk(src, dst, *args, **kwargs):
        Path(dst).write_bytes(b"part")
        raise OSError(28, "No space left on device")

    with monkeypatch.context() as m:
        m.setattr("tasks.video.ingest.shutil.copyfile", full_disk)
        with pytest.raises(OSError, match="No space left"):
            again(mkv)
    (row,) = wh.read("clips").to_pylist()
    assert row["video_path"].endswith("video.mp4") and file_sha256(wh.root / row["video_path"]) == row["video_sha256"]
    assert sorted(p.name for p in wh.inputs_dir("small").iterdir()) == ["cameras.txt", "placed.json", "video.mp4"]
    again(mkv)
    (row,) = wh.read("clips").to_pylist()
    assert row["video_path"].endswith("video.mkv") and file_sha256(wh.root / row["video_path"]) == file_sha256(mkv)
    assert sorted(p.name for p in wh.inputs_dir("small").iterdir()) == ["cameras.txt", "placed.json", "video.mkv"]


def test_video_that_opens_but_ends_early_fails_at_ingest(wh, small_clip, tmp_path):
    mkv = tmp_path / "full.mkv"
    remux(small_clip.video_path, mkv)
    cut = tmp_path / "cut.mkv"
    cut.write_bytes(mkv.read_bytes()[: int(mkv.stat().st_size * 0.6)])
    n = len(parse_camera_file(small_clip.cameras_path))  # the header still promises 3 s: the packets say how long it is
    with pytest.raises(CameraFileError, match=rf":\d+: timestamp \d+ µs is past the end of .*cut.mkv, which lasts \d+ µs "
                                              rf"\(\d+ of the {n} cameras are past it\)"):
        ingest(wh, cut, small_clip.cameras_path)
    assert wh.read("clips").num_rows == 0


def test_aspect_check_honours_non_square_pixels(small_clip, tmp_path):
    import av
    from fractions import Fraction

    video = tmp_path / "anamorphic.mp4"  # 64x48 pixels, each 4:3 wide: shown as 16:9
    with av.open(str(video), "w") as container:
        stream = container.add_stream("libx264", rate=30)
        stream.width, stream.height, stream.pix_fmt = 64, 48, "yuv420p"
        stream.codec_context.sample_aspect_ratio = Fraction(4, 3)
        for i in range(30):
            frame = av.VideoFrame.from_ndarray(np.zeros((48, 64, 3), np.uint8), format="rgb24")
            frame.pts = i
            container.mux(stream.encode(frame))
        container.mux(stream.encode())
    assert probe_video(video).pixel_aspect == pytest.approx(4 / 3)
    wide = with_intrinsics(small_clip.cameras_path, tmp_path / "wide.txt", 0.8, 0.8 * 16 / 9)
    wide.write_text("\n".join(wide.read_text().splitlines()[:11]) + "\n")
    assert check_clip_inputs(video, wide).warnings == ()
    square = with_intrinsics(wide, tmp_path / "square.txt", 0.8, 0.8 * 4 / 3)
    with pytest.raises(CameraFileError, match=r"fits frames of aspect 1 \(width/height\) but .* is 64x48 "
                                              r"\(1.333, pixel aspect 1.333\)"):
        check_clip_inputs(video, square)


def _write(path: Path, frames: list[np.ndarray], fmt: str | None = None, codec: str = "libx264", gop: int = 30,
           pts: list[int] | None = None, sar=None) -> Path:
    """Encode ``frames`` (30 fps) with PyAV: ``pts`` per frame (default its index), ``sar`` the pixel aspect."""
    import av

    with av.open(str(path), "w", format=fmt) as container:
        stream = container.add_stream(codec, rate=30)
        stream.height, stream.width = frames[0].shape[:2]
        stream.pix_fmt = "yuv420p" if codec == "libx264" else "yuvj420p"
        stream.codec_context.gop_size = gop
        if sar is not None:
            stream.codec_context.sample_aspect_ratio = sar
        for i, image in enumerate(frames):
            frame = av.VideoFrame.from_ndarray(image, format="rgb24")
            frame.pts = i if pts is None else pts[i]
            container.mux(stream.encode(frame))
        container.mux(stream.encode())
    return path


def _corner(height: int, width: int, value: int = 0) -> np.ndarray:
    """A grey picture with a white block in its top-left corner."""
    image = np.full((height, width, 3), 100 + value, np.uint8)
    image[:32, :32] = 255
    return image


def test_a_video_stored_sideways_is_decoded_upright(small_clip, tmp_path):
    """A phone's portrait video: stored 320x192 with a display matrix that turns it 90 degrees
    clockwise (ffprobe: rotation -90). Its size, frames and camera file are those of the upright picture."""
    import struct

    stored = _write(tmp_path / "stored.mp4", [_corner(192, 320)] * 30)
    data = bytearray(stored.read_bytes())
    at = data.find(b"tkhd")
    end = at - 4 + struct.unpack(">I", data[at - 4:at])[0]  # the matrix lies 44 bytes before the box's end
    data[end - 44:end - 8] = struct.pack(">9i", 0, 65536, 0, -65536, 0, 0, 0, 0, 1 << 30)
    video = tmp_path / "portrait.mp4"
    video.write_bytes(bytes(data))
    info = probe_video(video)
    assert (info.width, info.height, info.rotation) == (192, 320, 270)
    [frame] = decode_at(video, np.array([0]))
    assert frame.rgb.shape == (320, 192, 3)
    assert frame.rgb[5, 187].min() > 240 and frame.rgb[5, 5].max() < 150  # top-left turned clockwise: top-right
    portrait = with_intrinsics(small_clip.cameras_path, tmp_path / "portrait.txt", 0.9, 0.9 * 192 / 320)
    portrait.write_text("\n".join(portrait.read_text().splitlines()[:11]) + "\n")
    assert check_clip_inputs(video, portrait).warnings == ()


def test_a_seek_that_lands_after_its_target_is_taken_again_from_further_back(tmp_path):
    """MPEG-TS has no exact index: a backward seek may land after the frame asked for."""
    video = _write(tmp_path / "long.ts", [_corner(96, 160, i % 100) for i in range(300)], fmt="mpegts", gop=250)
    wanted = np.array([0, 3_333_333, 6_666_667, 9_000_000])
    assert [f.time_us for f in decode_at(video, wanted)] == wanted.tolist()


def test_a_matroska_video_starting_late_lasts_its_own_length(tmp_path):
    """Matroska states no stream duration, and its container's can be the end time: a 3 s clip cut
    at 60 s (``-copyts``) read as 63 s long, so --align-start was refused as 'within the video'."""
    import av

    path = tmp_path / "late.mkv"
    with av.open(str(path), "w", format="matroska") as c:
        s = c.add_stream("libx264", rate=30)
        s.width, s.height, s.pix_fmt = 64, 48, "yuv420p"
        for i in range(90):
            f = av.VideoFrame.from_ndarray(np.full((48, 64, 3), i, np.uint8), format="rgb24")
            f.pts = 1800 + i  # from 60 s, at 1/30 s
            c.mux(s.encode(f))
        c.mux(s.encode())
    assert abs(probe_video(path).duration_us - 3_000_000) <= 34_000


def test_an_avi_with_b_frames_is_refused_naming_the_file(tmp_path):
    """AVI states no presentation times: FFmpeg times the decoded frames of a stream with B-frames
    in decode order (x264: out of order; MPEG-4 part 2: one frame late), the packets' times look
    regular, and every camera got another frame's picture with a timestamp error of 0. Refused at
    the probe; an AVI without B-frames is decoded frame for frame."""
    frames = [np.full((48, 64, 3), 8 * i, np.uint8) for i in range(30)]  # frame i: grey level 8 i
    with pytest.raises(VideoError, match=r"^\S+b\.avi: an AVI whose h264 stream has B-frames: AVI states no presentation "
                                         r"times, so its frames' times are not known; convert it to MP4 or MKV first$"):
        probe_video(_write(tmp_path / "b.avi", frames, fmt="avi"))
    plain = _write(tmp_path / "plain.avi", frames, fmt="avi", codec="mjpeg")
    wanted = np.array([round(i * 1e6 / 30) for i in range(1, 29)])
    assert [round(int(f.rgb[0, 0, 0]) / 8) for f in decode_at(plain, wanted)] == list(range(1, 29))


def test_mpeg_ts_frames_before_the_first_keyframe_after_the_start_are_reached(tmp_path):
    """A seek to 0 in MPEG-TS (no index) landed on the keyframe at 0.5 s: with seeks on every
    target (threshold 0) frames 7 and 14 came out as frame 15. The start is decoded from the file
    opened again."""
    import av

    path = tmp_path / "open.ts"
    with av.open(str(path), "w", format="mpegts") as c:
        s = c.add_stream("libx264", rate=30)
        s.width, s.height, s.pix_fmt = 64, 48, "yuv420p"
        s.codec_context.gop_size = 15
        s.codec_context.options = {"x264-params": "open-gop=1:bframes=3:keyint=15:min-keyint=15:scenecut=0"}
        for i in range(60):
            f = av.VideoFrame.from_ndarray(np.full((48, 64, 3), 4 * i, np.uint8), format="rgb24")
            f.pts = i
            c.mux(s.encode(f))
        c.mux(s.encode())
    wanted = [7, 14, 40]
    got = [f.time_us for f in decode_at(path, np.array([i * 1_000_000 // 30 for i in wanted]), seek_threshold_us=0)]
    assert [round(t * 30 / 1e6) for t in got] == wanted


def test_a_given_camera_file_has_no_interpolated_camera_whatever_an_earlier_sfm_ingest_left(wh, small_clip):
    """A clip first ingested from its video alone (SfM) leaves its report of interpolated cameras;
    re-ingested with a given camera file of as many lines, its frames took that report's flags."""
    import json

    from tasks.video.ingest import SFM_REPORT_FILE

    n = len(parse_camera_file(small_clip.cameras_path))
    folder = wh.inputs_dir("small")
    folder.mkdir(parents=True)
    (folder / SFM_REPORT_FILE).write_text(json.dumps({"interpolated": [i % 2 == 1 for i in range(n)]}))
    ingest(wh, small_clip.video_path, small_clip.cameras_path)
    extract_frames(wh, FramesConfig(), "small", "run1", show_progress=False)
    assert not any(wh.read("frames").column("camera_interpolated").to_pylist())
