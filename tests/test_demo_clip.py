"""Tests for bench.demo_clip: barcode round trips, exact frame times, camera file, determinism."""

from __future__ import annotations

import dataclasses
import io
from fractions import Fraction
from pathlib import Path

import av
import numpy as np
import pytest
from PIL import Image

from bench.demo_clip import (
    BAND_HEIGHT,
    CAMERA_HEIGHT_M,
    DemoClip,
    DemoClipSpec,
    _make_room,
    decode_index,
    encode_index,
    make_demo_clip,
)
from cadestate.geometry import camera_to_world, intrinsics_matrix, project, rotation_error
from tasks.video.camera_file import parse_camera_file
from tasks.video.decode import frame_timestamp_us, write_video

SPEC = DemoClipSpec(name="small", width=320, height=192, num_video_frames=60, sample_every=3, seed=7)


def decode_frames(path: Path) -> list[tuple[Fraction, np.ndarray]]:
    """Time in seconds and uint8[H, W, 3] RGB pixels of every frame of the video, in decode order."""
    with av.open(str(path)) as container:
        return [(f.pts * f.time_base, f.to_ndarray(format="rgb24")) for f in container.decode(video=0)]


@pytest.fixture(scope="module")
def clip(tmp_path_factory: pytest.TempPathFactory) -> DemoClip:
    return make_demo_clip(tmp_path_factory.mktemp("clip"), SPEC)


@pytest.fixture(scope="module")
def frames(clip: DemoClip) -> list[tuple[Fraction, np.ndarray]]:
    return decode_frames(clip.video_path)


def test_every_decoded_frame_shows_its_index_at_its_exact_time(
    frames: list[tuple[Fraction, np.ndarray]],
) -> None:
    assert len(frames) == SPEC.num_video_frames
    for index, (time_s, image) in enumerate(frames):
        assert image.shape == (SPEC.height, SPEC.width, 3)
        assert decode_index(image) == index
        assert time_s == Fraction(index, SPEC.fps)


def test_camera_file_lists_sampled_frames(clip: DemoClip) -> None:
    track = parse_camera_file(clip.cameras_path)
    assert clip.cameras_path == clip.video_path.with_suffix(".txt")
    assert track.url == "synthetic://demo/small"
    np.testing.assert_array_equal(clip.frame_indices, np.arange(0, 60, 3))
    assert track.timestamps_us.tolist() == [frame_timestamp_us(int(i), SPEC.fps) for i in clip.frame_indices]
    fx = 0.5 / np.tan(np.radians(SPEC.hfov_deg) / 2)
    np.testing.assert_allclose(track.intrinsics, [[fx, fx * 320 / 192, 0.5, 0.5]] * 20)
    assert max(rotation_error(R) for R in track.R) < 1e-9
    R_cw, centres = camera_to_world(track.R, track.t)
    np.testing.assert_allclose(centres[:, 1], CAMERA_HEIGHT_M)
    step_m = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    assert np.all(step_m < 0.5 * 3 / SPEC.fps)  # slower than 0.5 m/s (samples are 3 frames apart)
    assert np.all(R_cw[:, 1, 1] < -0.9)  # image down (+y_cam) is roughly world down (-Y): no roll or flip


def test_pictures_agree_with_cameras(clip: DemoClip, frames: list[tuple[Fraction, np.ndarray]]) -> None:
    """The floor planks (0.25 m wide along x, alternately 90 % and 100 % bright) are where the
    camera file projects them. Points with |x| < 1 m: no furniture (at |x| > 1.1 m) can hide them."""
    room = _make_room(np.random.default_rng(SPEC.seed))
    x, z = np.meshgrid(np.arange(-3.5, 4) / 4, np.linspace(room.lo[2] + 0.2, room.hi[2] - 0.2, 40))
    floor = np.stack([x.ravel(), np.zeros(x.size), z.ravel()], axis=1)  # float[P, 3] plank centres, world
    plank_shade = np.where(np.floor(floor[:, 0] * 4) % 2 == 0, 0.9, 1.0)
    track = parse_camera_file(clip.cameras_path)
    checked = 0
    for k, index in enumerate(clip.frame_indices):
        K = intrinsics_matrix(track.intrinsics[k], SPEC.width, SPEC.height)
        uv, depth = project(K, track.R[k], track.t[k], floor)
        in_image = (uv >= [4, BAND_HEIGHT + 4]) & (uv < [SPEC.width - 4, SPEC.height - 4])
        seen = (depth > 0) & (depth < 6) & in_image.all(axis=1)
        u, v = uv[seen].astype(int).T
        distance_shade = np.clip(1.1 - 0.05 * depth[seen], 0.6, 1.0)
        expected = room.palette[2] * (plank_shade[seen] * distance_shade)[:, None]
        np.testing.assert_allclose(frames[index][1][v, u], expected, atol=8)
        checked += int(seen.sum())
    assert checked >= 100


def drawn_frames(monkeypatch: pytest.MonkeyPatch, out_dir: Path, spec: DemoClipSpec) -> tuple[DemoClip, list[np.ndarray]]:
    """Make a clip and keep every frame as drawn, before encoding."""
    import bench.demo_clip as demo

    drawn: list[np.ndarray] = []

    def keep(path: Path, frames, *args, **kwargs) -> None:
        write_video(path, (drawn.append(f) or f for f in frames), *args, **kwargs)

    monkeypatch.setattr(demo, "write_video", keep)
    return make_demo_clip(out_dir, spec), drawn


def test_same_spec_gives_identical_clip(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Same spec: the same camera file, bit-identical frames and the same H.264 file (libx264
    without macroblock-tree rate control, :data:`tasks.video.decode.X264_REPRODUCIBLE`)."""
    spec = dataclasses.replace(SPEC, num_video_frames=24)
    first, a = drawn_frames(monkeypatch, tmp_path / "a", spec)
    again, b = drawn_frames(monkeypatch, tmp_path / "b", spec)
    assert again.cameras_path.read_bytes() == first.cameras_path.read_bytes()
    assert len(a) == len(b) == 24
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    assert again.video_path.read_bytes() == first.video_path.read_bytes()
    other = make_demo_clip(tmp_path / "other", dataclasses.replace(spec, seed=8))
    assert other.cameras_path.read_bytes() != first.cameras_path.read_bytes()


def test_regenerating_replaces_files_and_leaves_no_temporaries(tmp_path: Path) -> None:
    spec = DemoClipSpec(name="tiny", width=320, height=64, num_video_frames=4, sample_every=2)
    (tmp_path / "tiny.mp4").write_bytes(b"stale")
    first = make_demo_clip(tmp_path, spec)
    make_demo_clip(tmp_path, spec)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tiny.mp4", "tiny.txt"]
    assert [decode_index(image) for _, image in decode_frames(first.video_path)] == [0, 1, 2, 3]


@pytest.mark.parametrize("size", [(360, 640), (192, 320), (240, 426)])
def test_index_survives_jpeg(size: tuple[int, int]) -> None:
    rng = np.random.default_rng(1)
    for index in [0, 1, 2, 255, 256, 0x1234, 0x5555, 0xAAAA, 0x8000, 65535]:
        image = rng.integers(0, 256, (*size, 3), dtype=np.uint8)
        encode_index(image, index)
        buffer = io.BytesIO()
        Image.fromarray(image).save(buffer, format="JPEG", quality=90)
        assert decode_index(np.asarray(Image.open(buffer).convert("RGB"))) == index


def test_barcode_errors() -> None:
    image = np.full((360, 640, 3), 128, np.uint8)
    with pytest.raises(ValueError, match="no frame-index barcode"):
        decode_index(image)
    for index in (-1, 65536):
        with pytest.raises(ValueError, match="16 bits"):
            encode_index(image, index)
    with pytest.raises(ValueError, match="too small"):
        encode_index(np.zeros((360, 300, 3), np.uint8), 0)
    with pytest.raises(ValueError, match="invalid demo clip spec"):
        make_demo_clip(Path("unused"), DemoClipSpec(width=321))


def test_frame_timestamps_are_exact_rounded_microseconds() -> None:
    assert [frame_timestamp_us(i, 30) for i in range(4)] == [0, 33333, 66667, 100000]
    assert frame_timestamp_us(300, 30) == 10_000_000
    assert frame_timestamp_us(1, 24) == 41667
    assert [frame_timestamp_us(i, 128) for i in (1, 3)] == [7812, 23438]  # ties to even, as round()
    assert frame_timestamp_us(10**9, 30) == 10**9 * 100_000 // 3  # no float rounding at large indices
