"""Tests of tasks.video.camera_file: RealEstate10K camera files."""

from __future__ import annotations

import os
import pickle

import numpy as np
import pytest

from cadestate.geometry import look_at, quaternion_to_matrix, rotation_error
from tasks.video import camera_file as cameras
from tasks.video.camera_file import (
    FOCAL_RANGE,
    PRINCIPAL_POINT_MARGIN,
    ROTATION_TOLERANCE,
    TRANSLATION_MAX,
    CameraFileError,
    CameraTrack,
    format_camera_track,
    parse_camera_file,
    parse_camera_text,
    write_camera_file,
)

URL = "https://www.youtube.com/watch?v=abc123XYZ_-"
EYE, TARGET = np.array([1.0, 2.0, 3.0]), np.array([-0.5, 0.25, -1.0])
R0, T0 = look_at(EYE, TARGET)
INTRINSICS = (0.9, 1.6, 0.5, 0.5)


def camera_line(timestamp: object, intrinsics=INTRINSICS, R=R0, t=T0, unused=(0, 0)) -> str:
    """One camera line written independently of format_camera_track."""
    rt = np.concatenate([np.asarray(R, float), np.asarray(t, float)[:, None]], axis=1)
    return " ".join(str(v) for v in [timestamp, *intrinsics, *unused, *rt.ravel().tolist()])


def random_track(n: int, seed: int = 0) -> CameraTrack:
    """A valid track: random unit quaternions, translations over many magnitudes, intrinsics in range."""
    rng = np.random.default_rng(seed)
    R = quaternion_to_matrix(rng.normal(size=(n, 4)))
    t = rng.normal(size=(n, 3)) * 10.0 ** rng.integers(-8, 5, size=(n, 1))
    intrinsics = np.concatenate([rng.uniform(0.2, 5.0, size=(n, 2)), rng.uniform(0.0, 1.0, size=(n, 2))], axis=1)
    intrinsics[0, 2:] = [-0.0, 1.0 / 3.0]
    timestamps = np.cumsum(rng.integers(1, 10**6, size=n)).astype(np.int64)
    return CameraTrack(URL, timestamps, intrinsics, np.concatenate([R, t[:, :, None]], axis=2))


def assert_identical(a: CameraTrack, b: CameraTrack) -> None:
    """Same URL and bit-for-bit the same arrays (dtype, shape and bytes)."""
    assert a.url == b.url
    for name in ("timestamps_us", "intrinsics", "world_to_camera"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes(), name


def test_parses_known_file_with_world_to_camera_convention():
    R1, t1 = look_at([0.0, 1.5, -4.0], [0.0, 1.0, 0.0])
    text = "\n".join([URL, camera_line(0, unused=(7, -2.5)), camera_line(33367, (0.5, 0.75, 0.25, 0.625), R1, t1)])
    track = parse_camera_text(text)

    assert track.url == URL and len(track) == 2
    assert track.timestamps_us.dtype == np.int64 and track.timestamps_us.tolist() == [0, 33367]
    assert track.intrinsics.dtype == np.float64 and track.intrinsics.shape == (2, 4)
    assert track.intrinsics[1].tolist() == [0.5, 0.75, 0.25, 0.625]  # fx, fy, cx, cy in file order
    assert track.world_to_camera.shape == (2, 3, 4)
    assert track.world_to_camera[0, 1, 3] == T0[1]  # column 15 (t2): row-major [R|t]
    np.testing.assert_array_equal(track.R[0], R0)
    np.testing.assert_array_equal(track.t[1], t1)
    # X_cam = R @ X_world + t: the look-at target lies on the optical axis, in front of the camera,
    # and the camera centre maps to the origin. (R0 is not symmetric, so R.T would fail this.)
    target_cam = track.R[0] @ TARGET + track.t[0]
    np.testing.assert_allclose(target_cam[:2], 0.0, atol=1e-12)
    assert target_cam[2] == pytest.approx(np.linalg.norm(TARGET - EYE))
    np.testing.assert_allclose(track.R[0] @ EYE + track.t[0], 0.0, atol=1e-12)
    assert not np.allclose(R0, R0.T)


def test_format_then_parse_is_bit_exact():
    track = random_track(50)
    text = format_camera_track(track)
    assert text.startswith(URL + "\n") and text.endswith("\n") and len(text.splitlines()) == 51
    assert all(line.split()[5:7] == ["0.0", "0.0"] for line in text.splitlines()[1:])
    again = parse_camera_text(text)
    assert_identical(again, track)
    assert again == track
    assert np.signbit(again.intrinsics[0, 2])  # -0.0 survives


def test_url_keeps_inner_whitespace_and_drops_outer():
    track = random_track(2)
    odd = CameraTrack("clip 1\tx", track.timestamps_us, track.intrinsics, track.world_to_camera)
    assert parse_camera_text(format_camera_track(odd)).url == "clip 1\tx"
    assert parse_camera_text(" \t" + URL + " \r\n" + camera_line(0)).url == URL
    with pytest.raises(ValueError, match="one-line text"):  # a CR ends a line: no URL holds one
        CameraTrack("clip 1\rx", track.timestamps_us, track.intrinsics, track.world_to_camera)


def test_a_lone_cr_after_the_url_ends_its_line_in_a_file_of_lf_lines():
    """An editor's CR after line 1 of an LF file glued the first camera onto the URL: one camera
    lost, and the clip named after 19 numbers."""
    lines = [URL, camera_line(10), camera_line(20)]
    assert_identical(parse_camera_text(lines[0] + "\r" + "\n".join(lines[1:])), parse_camera_text("\n".join(lines)))


def test_write_then_parse_is_bit_exact_and_overwrites(tmp_path):
    path = tmp_path / "clip.txt"
    write_camera_file(path, random_track(5, seed=1))
    track = random_track(20, seed=2)
    write_camera_file(str(path), track)
    assert_identical(parse_camera_file(path), track)
    assert os.listdir(tmp_path) == ["clip.txt"]


def test_crlf_and_trailing_blank_lines_accepted():
    lines = [URL, camera_line(10), camera_line(20)]
    expected = parse_camera_text("\n".join(lines))
    crlf, lf, cr = "\r\n".join(lines), "\n".join(lines), "\r".join(lines)
    for text in [crlf + "\r\n", lf + "\n\n   \n\t\n", crlf + "\r\n \r\n\r\n", cr + "\r", cr,
                 "\r\r\n".join(lines)]:  # CRLF written in text mode on Windows
        assert_identical(parse_camera_text(text), expected)


def test_bom_is_dropped():
    text = "\n".join([URL, camera_line(10)])
    assert_identical(parse_camera_text("\ufeff" + text), parse_camera_text(text))


def test_bom_is_dropped_from_a_file(tmp_path):
    path = tmp_path / "clip.txt"
    path.write_bytes(b"\xef\xbb\xbf" + "\n".join([URL, camera_line(10)]).encode())
    assert parse_camera_file(path).url == URL


def test_range_boundaries_are_accepted():
    lo, hi = FOCAL_RANGE
    assert lo == pytest.approx(0.5 / np.tan(np.radians(89.5))) and hi == pytest.approx(0.5 / np.tan(np.radians(0.5)))
    m, big = PRINCIPAL_POINT_MARGIN, TRANSLATION_MAX
    lines = [camera_line(0, (lo, hi, -m, 1 + m), t=(big, -big, 0.0)), camera_line(1, (hi, lo, 1 + m, -m))]
    track = parse_camera_text("\n".join([URL, *lines]))
    assert track.intrinsics[0].tolist() == [lo, hi, -m, 1 + m] and track.t[0, 0] == big


def test_rotation_tolerance_boundary():
    noise = np.full((3, 3), ROTATION_TOLERANCE / 10)
    assert 0 < rotation_error(R0 + noise) <= ROTATION_TOLERANCE
    parse_camera_text("\n".join([URL, camera_line(0, R=R0 + noise)]))
    with pytest.raises(CameraFileError, match="not a rotation"):
        parse_camera_text("\n".join([URL, camera_line(0, R=R0 + 10 * noise)]))


GOOD = [camera_line(100), camera_line(200), camera_line(300)]


def replaced(index: int, line: str) -> list[str]:
    """GOOD with camera line ``index`` (0-based; file line index + 2) replaced."""
    return [line if i == index else g for i, g in enumerate(GOOD)]


def replaced_column(index: int, column: int, value: str) -> list[str]:
    """GOOD with the 1-based ``column`` of camera line ``index`` set to ``value``."""
    fields = GOOD[index].split()
    fields[column - 1] = value
    return replaced(index, " ".join(fields))


MALFORMED = [
    pytest.param(GOOD[:1] + [" ".join(GOOD[1].split()[:18])] + GOOD[2:], 3, "expected 19 columns, found 18",
                 id="18-columns"),
    pytest.param(replaced(2, GOOD[2] + " 0"), 4, "expected 19 columns, found 20", id="20-columns"),
    pytest.param(replaced_column(0, 2, "abc"), 2, "column 2 (fx) is not a finite number: 'abc'", id="non-numeric"),
    pytest.param(replaced_column(1, 8, "1,0"), 3, "column 8 (r11) is not a finite number: '1,0'", id="comma"),
    pytest.param(replaced_column(0, 3, "nan"), 2, "column 3 (fy) is not a finite number: 'nan'", id="nan"),
    pytest.param(replaced_column(1, 19, "inf"), 3, "column 19 (t3) is not a finite number: 'inf'", id="inf"),
    pytest.param(replaced_column(2, 11, "1e999"), 4, "column 11 (t1) is not a finite number: '1e999'",
                 id="overflow"),
    pytest.param(replaced_column(0, 6, "-nan"), 2, "column 6 (unused1) is not a finite number", id="nan-unused"),
    pytest.param(replaced_column(1, 1, "150.5"), 3, "column 1 (timestamp) is not a non-negative integer: '150.5'",
                 id="fractional-timestamp"),
    pytest.param(replaced_column(0, 1, "-3"), 2, "column 1 (timestamp) is not a non-negative integer: '-3'",
                 id="negative-timestamp"),
    pytest.param(replaced_column(2, 1, "1e6"), 4, "column 1 (timestamp) is not a non-negative integer: '1e6'",
                 id="exponent-timestamp"),
    pytest.param(replaced_column(2, 1, str(2**63)), 4, "does not fit in int64", id="huge-timestamp"),
    pytest.param(replaced_column(2, 1, "100"), 4, "duplicate timestamp 100 (also on line 2)", id="duplicate"),
    pytest.param(replaced_column(2, 1, "150"), 4, "timestamp 150 is not after 200 on line 3", id="decreasing"),
    pytest.param(replaced(1, camera_line(200, R=1.01 * R0)), 3, "not a rotation: rotation error 0.0303",
                 id="scaled-rotation"),
    pytest.param(replaced(2, camera_line(300, R=R0 * [[-1], [1], [1]])), 4, "(det -1)", id="reflection"),
    pytest.param(replaced_column(0, 2, "0"), 2, "column 2 (fx) must be > 0, found 0.0", id="zero-fx"),
    pytest.param(replaced_column(1, 3, "-1.5"), 3, "column 3 (fy) must be > 0, found -1.5", id="negative-fy"),
    pytest.param(replaced_column(1, 2, "1e300"), 3, "column 2 (fx) = 1e+300 is not a field of view of 1 to 179 "
                 "degrees (normalised focal length in [0.004363, 57.29])", id="huge-fx"),
    pytest.param(replaced_column(2, 3, "0.004"), 4, "column 3 (fy) = 0.004 is not a field of view", id="tiny-fy"),
    pytest.param(replaced_column(0, 4, "-40"), 2, "column 4 (cx) = -40.0 puts the principal point outside the "
                 "image (normalised, must be in [-0.1, 1.1])", id="cx-outside"),
    pytest.param(replaced_column(1, 5, "1.2"), 3, "column 5 (cy) = 1.2 puts the principal point outside",
                 id="cy-outside"),
    pytest.param(replaced_column(2, 11, "1e200"), 4, "column 11 (t1) = 1e+200 is too far from the origin "
                 "(|t| must be <= 1e+06)", id="huge-t1"),
    pytest.param(replaced_column(0, 19, "-2e6"), 2, "column 19 (t3) = -2000000.0 is too far", id="far-t3"),
    pytest.param(replaced_column(0, 2, "x" * 100), 2, "column 2 (fx) is not a finite number: '" + "x" * 39 + "...",
                 id="long-field-cut"),
    pytest.param(replaced(1, ""), 3, "blank line before more camera lines", id="blank-middle"),
    pytest.param(replaced(1, " \t"), 3, "blank line before more camera lines", id="whitespace-middle"),
]


@pytest.mark.parametrize("camera_lines, line, message", MALFORMED)
def test_malformed_camera_lines(tmp_path, camera_lines, line, message):
    path = tmp_path / "clip.txt"
    path.write_text("\n".join([URL, *camera_lines]) + "\n", encoding="utf-8")
    with pytest.raises(CameraFileError) as info:
        parse_camera_file(path)
    assert (info.value.path, info.value.line) == (str(path), line)
    assert message in info.value.message
    assert str(info.value) == f"{path}:{line}: {info.value.message}"


@pytest.mark.parametrize("text, line, message", [
    pytest.param("", 0, "empty file", id="empty"),
    pytest.param(" \n\r\n\t", 0, "empty file", id="whitespace-only"),
    pytest.param("\n" + GOOD[0], 1, "line 1 (the URL) is empty", id="empty-url"),
    pytest.param(URL, 2, "no camera lines after the URL (line 1)", id="url-only"),
    pytest.param(URL + "\n\n  \n", 2, "no camera lines", id="url-and-blank-lines"),
    pytest.param("\n".join(GOOD), 1, "line 1 is a camera line (19 numbers), not the video URL: the URL line is "
                 "missing", id="missing-url"),
    pytest.param("\n".join(GOOD).replace("100", "nan", 1), 1, "the URL line is missing", id="missing-url-nan"),
    pytest.param("\ufeff" + "\n".join(GOOD), 1, "the URL line is missing", id="missing-url-after-bom"),
    pytest.param("\n".join([GOOD[0].rsplit(" ", 1)[0], *GOOD[1:]]), 1, "line 1 holds 18 numbers, not the video URL: "
                 "the URL line is missing (and a camera line has 19 numbers)", id="missing-url-broken-line"),
    pytest.param("\n".join([GOOD[0] + " 0", *GOOD[1:]]), 1, "line 1 holds 20 numbers", id="missing-url-long-line"),
    pytest.param("\ufeff", 0, "empty file", id="bom-only"),
])
def test_malformed_whole_file(text, line, message):
    with pytest.raises(CameraFileError) as info:
        parse_camera_text(text, source="mem.txt")
    assert (info.value.path, info.value.line) == ("mem.txt", line)
    assert message in str(info.value) and str(info.value).startswith(f"mem.txt:{line}: " if line else "mem.txt: ")


def test_default_source_name():
    with pytest.raises(CameraFileError, match=r"^<string>: empty file$"):  # the whole file: no line
        parse_camera_text("")


def test_non_utf8_file(tmp_path):
    path = tmp_path / "clip.txt"
    path.write_bytes(URL.encode() + b"\n" + GOOD[0].encode() + b"\n" + GOOD[1].encode() + b" \xff\n")
    with pytest.raises(CameraFileError, match="not valid UTF-8") as info:
        parse_camera_file(path)
    assert (info.value.path, info.value.line) == (str(path), 3)  # the line of the bad byte
    for end in ("\r", "\r\n", "\r\r\n"):  # counted as the parser splits lines (\r alone: classic Mac)
        path.write_bytes(end.join([URL, GOOD[0], GOOD[1] + " \xff"]).encode("latin-1") + end.encode())
        with pytest.raises(CameraFileError, match=r":3: not valid UTF-8"):
            parse_camera_file(path)


def test_missing_file(tmp_path):
    with pytest.raises(CameraFileError, match="cannot read file") as info:
        parse_camera_file(tmp_path / "absent.txt")
    assert info.value.line == 0 and str(info.value).startswith(f"{tmp_path / 'absent.txt'}: cannot read file")


def test_camera_file_error_is_value_error_and_pickles():
    error = pickle.loads(pickle.dumps(CameraFileError("a.txt", 3, "bad")))
    assert isinstance(error, ValueError)
    assert (error.path, error.line, error.message, str(error)) == ("a.txt", 3, "bad", "a.txt:3: bad")


def test_track_properties_and_equality():
    track = random_track(4)
    assert len(track) == 4
    assert track.R.shape == (4, 3, 3) and track.t.shape == (4, 3)
    np.testing.assert_array_equal(track.R[2], track.world_to_camera[2, :, :3])
    np.testing.assert_array_equal(track.t[2], track.world_to_camera[2, :, 3])
    assert track == random_track(4) and track != random_track(4, seed=9)
    assert track != CameraTrack("other", track.timestamps_us, track.intrinsics, track.world_to_camera)


@pytest.mark.parametrize("change, message", [
    pytest.param(dict(url=""), "url", id="empty-url"),
    pytest.param(dict(url="a\nb"), "url", id="multi-line-url"),
    pytest.param(dict(url=" a"), "url", id="padded-url"),
    pytest.param(dict(timestamps_us=np.arange(3, dtype=np.int32)), r"timestamps_us must be int64\[N\]",
                 id="int32"),
    pytest.param(dict(intrinsics=np.ones((3, 4), np.float32)), r"intrinsics must be float64\[N, 4\]",
                 id="float32"),
    pytest.param(dict(world_to_camera=np.zeros((3, 4, 4))), r"float64\[N, 3, 4\].*got float64\[3, 4, 4\]",
                 id="shape"),
    pytest.param(dict(intrinsics=np.ones((2, 4))), "same N", id="mismatched-n"),
    pytest.param(dict(timestamps_us=np.zeros(0, np.int64), intrinsics=np.ones((0, 4)),
                      world_to_camera=np.zeros((0, 3, 4))), "N >= 1", id="empty"),
    pytest.param(dict(timestamps_us=np.array([0, 5, 5])), "strictly increasing", id="duplicate-timestamps"),
    pytest.param(dict(timestamps_us=np.array([-1, 5, 6])), "non-negative", id="negative-timestamp"),
    pytest.param(dict(intrinsics=np.array([[1.0, 1, 0, 0]] * 2 + [[1.0, 0, 0, 0]])),
                 r"camera 2: column 3 \(fy\) must be > 0", id="zero-fy"),
    pytest.param(dict(intrinsics=np.array([[1.0, 1, 0, 0]] * 2 + [[1.0, 1, 2, 0]])),
                 r"camera 2: column 4 \(cx\) = 2.0 puts the principal point outside", id="cx-outside"),
    pytest.param(dict(intrinsics=np.array([[1.0, np.nan, 0, 0]] * 3)), "camera 0: .*finite", id="nan"),
    pytest.param(dict(world_to_camera=np.stack([np.eye(3, 4)] * 3) * 2), "camera 0: R is not a rotation",
                 id="scaled"),
])
def test_track_validation(change, message):
    track = random_track(3)
    fields = dict(url=track.url, timestamps_us=track.timestamps_us, intrinsics=track.intrinsics,
                  world_to_camera=track.world_to_camera) | change
    with pytest.raises(ValueError, match=message):
        CameraTrack(**fields)


def test_write_fsyncs_before_replacing(tmp_path, monkeypatch):
    calls = []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(cameras.os, "fsync", lambda fd: (calls.append("fsync"), real_fsync(fd))[1])
    monkeypatch.setattr(cameras.os, "replace", lambda a, b: (calls.append("replace"), real_replace(a, b))[1])
    write_camera_file(tmp_path / "clip.txt", random_track(2))
    assert calls == ["fsync", "replace"]


def fail(*args, **kwargs):
    raise RuntimeError("boom")


@pytest.mark.parametrize("target", ["format_camera_track", "fsync", "replace"])
def test_failed_write_keeps_old_file_and_leaves_no_temp_file(tmp_path, monkeypatch, target):
    path = tmp_path / "clip.txt"
    write_camera_file(path, random_track(3, seed=1))
    before = path.read_bytes()
    monkeypatch.setattr(cameras if target == "format_camera_track" else cameras.os, target, fail)
    with pytest.raises(RuntimeError, match="boom"):
        write_camera_file(path, random_track(3, seed=2))
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["clip.txt"]
