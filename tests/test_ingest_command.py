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
    config.write_text('[detect]\nclasses = ["couch"]\n')  # COCO's name; the default detector says "sofa"
    result = run_cli("-c", str(config), "-w", str(tmp_path / "w"), "ingest", str(small_clip.video_path),
                     str(small_clip.cameras_path))
    assert_clean_error(result, mentions=f"{config}: [detect] classes: 'couch' not in the label map of [detect] model = 'furniture'")
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


def test_a_video_alone_is_an_sfm_clip_named_after_its_file(tmp_path, small_clip, started):
    result = run_cli("-w", str(tmp_path / "w"), "ingest", str(small_clip.video_path), "--intrinsics", "250,250,160,96")
    assert result.code == 0, result.stderr
    (item,) = started[0]
    assert (item.clip, item.cameras, item.intrinsics, item.time_offset_us) == ("small_0", None, (250.0, 250.0, 160.0, 96.0), 0)


@pytest.mark.parametrize("args, message", [
    (["--intrinsics", "250,250,160"], "--intrinsics must be fx,fy,cx,cy in pixels"),
    (["--intrinsics", "250,250,900,96"], "--intrinsics: principal point (900, 96) px is outside the 320x192 frame"),
    # said after all of SfM's work, as column 2 of a camera file the user never wrote
    (["--intrinsics", "100000,250,160,96"], "--intrinsics: fx = 100000 px is not a field of view of 1 to 179 degrees on "
                                            "the 320x192 frame (1.396 to 1.833e+04 px)"),
    (["--intrinsics", "250,0.5,160,96"], "--intrinsics: fy = 0.5 px is not a field of view"),
    (["--time-offset-us", "5"], "--time-offset-us and --align-start need a camera file"),
])
def test_sfm_options_are_checked(tmp_path, small_clip, started, args, message):
    result = run_cli("-w", str(tmp_path / "w"), "ingest", str(small_clip.video_path), *args)
    assert result.code == 2 and message in result.stderr and started == []


def test_two_videos_or_a_camera_file_first_are_named_as_such(tmp_path, small_clip, started):
    """Two files are VIDEO CAMERAS.txt: two videos (two SfM clips, the user thought) read the second
    as a camera file ("not valid UTF-8")."""
    other = tmp_path / "other.mp4"
    other.write_bytes(small_clip.video_path.read_bytes())
    for args in ([small_clip.video_path, other], [small_clip.cameras_path, small_clip.video_path]):
        result = run_cli("-w", str(tmp_path / "w"), "ingest", *map(str, args))
        assert result.code == 2 and "two files are VIDEO CAMERAS.txt, in that order" in result.stderr, result.stderr
        assert "UTF-8" not in result.stderr and started == []
    # three or more paths, files among them (two clips' pairs): said as such, not "<video>: not a folder"
    result = run_cli("-w", str(tmp_path / "w"), "ingest", *map(str, [small_clip.video_path, small_clip.cameras_path, other]))
    assert result.code == 2 and f"{small_clip.video_path}: a file among 3 paths: give one clip" in result.stderr, result.stderr
    assert "not a folder" not in result.stderr and started == []


def test_align_start_prints_the_offset_and_hands_it_on(tmp_path, small_clip, started):
    import dataclasses

    from tasks.video.camera_file import parse_camera_file, write_camera_file

    cams = parse_camera_file(small_clip.cameras_path)
    shifted = tmp_path / "c.txt"
    write_camera_file(shifted, dataclasses.replace(cams, timestamps_us=cams.timestamps_us + 65_233_333))
    result = run_cli("-w", str(tmp_path / "w"), "ingest", str(small_clip.video_path), str(shifted), "--align-start")
    assert result.code == 0, result.stderr
    assert f"{shifted}: --align-start: time offset 65233333 µs" in result.stderr
    assert started[0][0].time_offset_us == 65_233_333
    refused = run_cli("-w", str(tmp_path / "w2"), "ingest", str(small_clip.video_path), str(shifted))
    assert refused.code == 2 and "--time-offset-us N, or --align-start" in refused.stderr


def _room_pair(folder, small_clip):
    """``folder``/room.mp4 and room.txt: the small clip's video and cameras, line 1 the ``file://``
    URL of that room.mp4 (so its derived clip name is room_0)."""
    import shutil

    folder.mkdir()
    video = folder / "room.mp4"
    shutil.copyfile(small_clip.video_path, video)
    lines = small_clip.cameras_path.read_text().splitlines()
    cams = folder / "room.txt"
    cams.write_text("\n".join([video.resolve().as_uri(), *lines[1:]]) + "\n")
    return video, cams


@pytest.mark.parametrize("name, message", [
    ("room_5", "clip name 'room_5': start 5 µs is not the first timestamp of {cams} (0 µs)"),
    ("my room_0", "clip name 'my room_0': video id 'my room' has characters outside [A-Za-z0-9_-]"),
    ("room", "clip name 'room' is not <video_id>_<start_us>"),
])
def test_a_bad_clip_name_is_refused(tmp_path, small_clip, started, name, message):
    video, cams = _room_pair(tmp_path / "a", small_clip)
    w = tmp_path / "w"
    result = run_cli("-w", str(w), "ingest", str(video), str(cams), "--clip", name)
    assert_clean_error(result, mentions=message.format(cams=cams))
    assert started == [] and warehouse_digest(w) == {}


def test_a_video_id_clash_is_resolved_with_clip(tmp_path, small_clip, started):
    from conftest import table_rows
    from warehouse import Warehouse

    video_a, cams_a = _room_pair(tmp_path / "a", small_clip)
    video_b, cams_b = _room_pair(tmp_path / "b", small_clip)
    w = tmp_path / "w"
    both = run_cli("-w", str(w), "ingest", str(tmp_path / "a"), str(tmp_path / "b"))  # both derive room_0
    a_url, b_url = video_a.resolve().as_uri(), video_b.resolve().as_uri()
    assert_clean_error(both, mentions=f"clips room_0 ({a_url}), room_0 ({b_url}) come from different videos (line 1 of "
                                      "their camera files) but share the video id 'room': give one of them its own name "
                                      "with --clip")
    assert started == []
    Warehouse(w).write("clips", "room_0", table_rows("clips", [{"clip": "room_0", "url": a_url}]))
    clash = run_cli("-w", str(w), "ingest", str(video_b), str(cams_b))  # room_0 of a is registered already
    assert_clean_error(clash, mentions="share the video id 'room': give one of them its own name with --clip")
    resolved = run_cli("-w", str(w), "ingest", str(video_b), str(cams_b), "--clip", "room2_0")
    assert resolved.code == 0, resolved.stderr
    assert [(s.clip, s.video, s.cameras) for s in started[0]] == [("room2_0", video_b, cams_b)]
    help_example = run_cli("-w", str(tmp_path / "w2"), "ingest", str(video_b), str(cams_b), "--clip", "kitchen_0")
    assert help_example.code == 0, help_example.stderr
    assert started[1][0].clip == "kitchen_0"


def test_two_inputs_that_name_one_clip_are_refused(tmp_path, small_clip, started):
    """Two folders each holding a copy of one clip (its name comes from the camera file): one run
    would replace the other's tables, so nothing starts."""
    import shutil

    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
        for f in (small_clip.video_path, small_clip.cameras_path):
            shutil.copy(f, tmp_path / folder / f.name)
    result = run_cli("-w", str(tmp_path / "w"), "ingest", str(tmp_path / "a"), str(tmp_path / "b"))
    a, b = (tmp_path / x / small_clip.video_path.name for x in "ab")
    assert_clean_error(result, mentions=f"is named by 2 inputs ({a}, {b}): one would replace the other")
    assert started == []


def test_a_split_of_no_known_name_is_refused(tmp_path, small_clip, started):
    result = run_cli("-w", str(tmp_path / "w"), "ingest", str(small_clip.video_path), str(small_clip.cameras_path),
                     "--split", "Val")
    assert_clean_error(result, mentions="'Val' is none of train, val, test")
    assert started == []
