"""tasks.video.clip_names: clip names <video_id>_<start_us> derived from, and checked against, camera files."""

from __future__ import annotations

import pytest

from bench.benchmark import clip_name
from tasks.video.clip_names import (
    ClipName, ClipNameError, check_clip_name, derive_clip_name, parse_clip_name, shared_video_ids, video_id_from_url,
    video_id_of,
)


@pytest.mark.parametrize("url, vid", [
    ("https://www.youtube.com/watch?v=-0AK9iy8y0c", "-0AK9iy8y0c"),
    ("https://youtube.com/watch?feature=share&v=ZxUv_7CnPBE&t=30", "ZxUv_7CnPBE"),
    ("https://youtu.be/ZxUv_7CnPBE", "ZxUv_7CnPBE"),
    ("https://www.youtube.com/embed/ZxUv_7CnPBE", "ZxUv_7CnPBE"),
    ("https://www.youtube.com/watch?v=tooshort", ""),
    ("synthetic://walkthrough/bench-7-00", "bench-7-00"),
    ("file:///videos/my room.mp4", "my-room"),
    ("file:///videos/my%20room.mp4", "my-20room"),  # Path.as_uri(): escapes kept, so names of other
    ("file:///videos/caf%C3%A9.mp4", "caf-C3-A9"),  # letters stay apart (and as they were named before)
    ("www.youtube.com/watch?v=ZxUv_7CnPBE", "ZxUv_7CnPBE"),  # no scheme: was 'watch'
    ("youtu.be/ZxUv_7CnPBE", "ZxUv_7CnPBE"),
    ("https://youtube.com/watch/?v=ZxUv_7CnPBE", "ZxUv_7CnPBE"),
    ("room_a.mp4", "room_a"),
    ("", ""),
])
def test_video_id_from_url(url, vid):
    assert video_id_from_url(url) == vid


def test_derive_parse_round_trip():
    name = derive_clip_name("https://www.youtube.com/watch?v=0gBW3RDqyMc", 122914456)
    assert name == "0gBW3RDqyMc_122914456"
    assert parse_clip_name(name) == ClipName("0gBW3RDqyMc", 122914456) and str(parse_clip_name(name)) == name
    assert parse_clip_name("a_b_12") == ClipName("a_b", 12)  # the official regex: all before the last _<digits>
    assert parse_clip_name("room") is None and video_id_of("room") == "room"
    with pytest.raises(ClipNameError, match="rooms.txt: line 1 .* names no video"):
        derive_clip_name("", 0, "rooms.txt")


def test_check_clip_name_names_the_problem():
    url = "https://www.youtube.com/watch?v=0gBW3RDqyMc"
    check_clip_name("0gBW3RDqyMc_500", url, 500)
    with pytest.raises(ClipNameError, match=r"'room_01'.* start 1 µs is not the first timestamp of a.txt \(500 µs\)"):
        check_clip_name("room_01", url, 500, "a.txt")
    with pytest.raises(ClipNameError, match=r"not <video_id>_<start_us>.*gives '0gBW3RDqyMc_500'"):
        check_clip_name("room", url, 500)
    with pytest.raises(ClipNameError, match=r"video id 'other' is not the YouTube id line 1 of camera file names"):
        check_clip_name("other_500", url, 500)
    check_clip_name("mine_7", "", 7)  # a URL line naming no video: any video id


def test_a_local_video_may_get_any_safe_video_id():
    check_clip_name("room2_0", "file:///b/room.mp4", 0)  # two files called room.mp4 told apart
    check_clip_name("kitchen_1200000", "file:///videos/room.mp4", 1200000)  # the `cadestate ingest --help` example
    check_clip_name("walk-2_0", "synthetic://walkthrough/bench-7-00", 0)
    with pytest.raises(ClipNameError, match=r"'kitchen_5': start 5 µs is not the first timestamp of r.txt \(0 µs\)"):
        check_clip_name("kitchen_5", "file:///videos/room.mp4", 0, "r.txt")
    with pytest.raises(ClipNameError, match=r"'my room_0': video id 'my room' has characters outside \[A-Za-z0-9_-\]"):
        check_clip_name("my room_0", "file:///videos/room.mp4", 0)
    with pytest.raises(ClipNameError, match="video id '../up' has characters outside"):
        check_clip_name("../up_0", "file:///videos/room.mp4", 0)
    with pytest.raises(ClipNameError, match="is not the YouTube id"):
        check_clip_name("room2_0", "https://youtu.be/ZxUv_7CnPBE", 0)  # YouTube stays strict
    with pytest.raises(ClipNameError, match=r"'kitchen_01200000': write its start without leading zeros \(kitchen_1200000\)"):
        check_clip_name("kitchen_01200000", "file:///videos/room.mp4", 1200000)  # a second name of one clip


def test_shared_video_ids():
    assert shared_video_ids([("a_0", "u1"), ("a_900", "u1"), ("b_0", "u2")]) == {}
    assert shared_video_ids([("a_0", "u1"), ("a_900", "u2")]) == {"a": ["a_0", "a_900"]}
    spellings = ["https://www.youtube.com/watch?v=ZxUv_7CnPBE", "https://youtu.be/ZxUv_7CnPBE",
                 "http://youtube.com/watch?v=ZxUv_7CnPBE&t=65s", "www.youtube.com/watch?v=ZxUv_7CnPBE"]
    assert shared_video_ids([(f"ZxUv_7CnPBE_{i}", u) for i, u in enumerate(spellings)]) == {}  # one video, any spelling


def test_benchmark_clips_have_their_own_videos():
    names = [clip_name(555, i) for i in range(3)]
    assert names == ["bench-555-00_0", "bench-555-01_0", "bench-555-02_0"]
    assert len({video_id_of(n) for n in names}) == 3
    for i, n in enumerate(names):
        assert derive_clip_name(f"synthetic://walkthrough/bench-555-{i:02d}", 0) == n
