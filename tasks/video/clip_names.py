"""Clip names in the official CAD-Estate convention: ``<video_id>_<start timestamp µs>``.

The official code takes a clip's video from its name (everything before the last ``_<digits>``)
and keeps frames as ``<video_id>/<video_id>_<timestamp>.jpg``, so two clips share a video id only
when they really are cut from one video. The video id comes from line 1 of the RealEstate10K
camera file (its URL):

- YouTube (``youtube.com/watch?v=ID``, ``youtu.be/ID``, ``youtube.com/embed/ID``, ``/shorts/ID``,
  ``/live/ID``; with or without ``https://``): the 11-character video id;
- any other URL or path (``synthetic://walkthrough/bench-7-00``, ``file:///videos/room.mp4``): its
  last path segment without the extension, every character outside ``[A-Za-z0-9_-]`` replaced by
  ``-`` (percent-escapes are kept as written: ``living%20room.mp4`` is ``living-20room``, and
  ``café``'s and ``cafè``'s names stay apart; names already given stay the same).

The start timestamp is the first camera line's timestamp (µs since the start of the video).

A name given by the user (``--clip``) must start at that first timestamp. Its video id must be the
URL's for a YouTube URL (the official convention: frames live under the YouTube id); for any other
URL it may be any id of ``[A-Za-z0-9_-]`` characters, so two local files both called ``room.mp4``
can be told apart.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import PurePosixPath
from urllib.parse import SplitResult, parse_qs, urlsplit

_CLIP = re.compile(r"^(?P<video>.+)_(?P<start>\d+)$")
_YOUTUBE_ID = re.compile(r"^[A-Za-z0-9_-]{11}$")
_SAFE_VIDEO_ID = re.compile(r"^[A-Za-z0-9_-]+$")
_YOUTUBE_HOSTS = {"youtube.com", "www.youtube.com", "m.youtube.com", "music.youtube.com", "youtube-nocookie.com",
                  "www.youtube-nocookie.com"}
_YOUTU_BE_HOSTS = {"youtu.be", "www.youtu.be"}


class ClipNameError(ValueError):
    """A clip name that is not ``<video_id>_<start_us>`` of its camera file (one line, names the file)."""


@dataclass(frozen=True)
class ClipName:
    """A parsed clip name: ``video_id`` and ``start_us`` (the first camera timestamp, µs)."""

    video_id: str
    start_us: int

    def __str__(self) -> str:
        return f"{self.video_id}_{self.start_us}"


def parse_clip_name(name: str) -> ClipName | None:
    """``name`` split the official way (video id: all before the last ``_<digits>``), or None."""
    match = _CLIP.match(name)
    return ClipName(match.group("video"), int(match.group("start"))) if match else None


def video_id_of(name: str) -> str:
    """The video id of a clip name (the whole name when it has no ``_<start_us>`` suffix)."""
    parsed = parse_clip_name(name)
    return parsed.video_id if parsed else name


def _split(url: str) -> SplitResult:
    """``url`` split; a YouTube address written without its scheme (``www.youtube.com/watch?v=ID``)
    is read as https."""
    url = url.strip()
    if "://" not in url and url.split("/", 1)[0].lower() in _YOUTUBE_HOSTS | _YOUTU_BE_HOSTS:
        url = "https://" + url
    return urlsplit(url)


def is_youtube_url(url: str) -> bool:
    """Whether ``url`` is on a YouTube host (``youtube.com``, ``youtu.be`` and their variants)."""
    return _split(url).netloc.lower() in _YOUTUBE_HOSTS | _YOUTU_BE_HOSTS


def source_video(url: str) -> str:
    """What a URL line names as one video: ``youtube:<id>`` for any spelling of a YouTube video
    (``youtu.be/ID``, ``http://``, ``&t=65s``), else the line itself."""
    vid = video_id_from_url(url)
    return f"youtube:{vid}" if vid and is_youtube_url(url) else url.strip()


def video_id_from_url(url: str) -> str:
    """The video id of a camera file's URL line (module docstring); "" when it names none."""
    url = url.strip()
    parts = _split(url)
    host = parts.netloc.lower()
    if host in _YOUTUBE_HOSTS:
        if parts.path.rstrip("/") == "/watch":
            vid = parse_qs(parts.query).get("v", [""])[0]
        else:
            segments = [s for s in parts.path.split("/") if s]
            vid = segments[1] if len(segments) >= 2 and segments[0] in ("embed", "shorts", "live", "v") else ""
        return vid if _YOUTUBE_ID.match(vid) else ""
    if host in _YOUTU_BE_HOSTS:
        vid = parts.path.strip("/")
        return vid if _YOUTUBE_ID.match(vid) else ""
    last = PurePosixPath(parts.path or url).name
    stem = last.rsplit(".", 1)[0] if "." in last else last
    return re.sub(r"[^A-Za-z0-9_-]", "-", stem)


def derive_clip_name(url: str, first_timestamp_us: int, source: str = "camera file") -> str:
    """``<video_id>_<first_timestamp_us>`` of a camera file (its URL line and first timestamp)."""
    vid = video_id_from_url(url)
    if not vid:
        raise ClipNameError(f"{source}: line 1 ({url!r}) names no video to take the clip name from; give the clip "
                            "name as <video_id>_<start_us>")
    if first_timestamp_us < 0:
        raise ClipNameError(f"{source}: first timestamp {first_timestamp_us} is negative")
    return str(ClipName(vid, int(first_timestamp_us)))


def check_clip_name(name: str, url: str, first_timestamp_us: int, source: str = "camera file") -> None:
    """Raise :class:`ClipNameError` unless ``name`` is ``<video_id>_<start_us>`` with the camera
    file's first timestamp and a video id of ``[A-Za-z0-9_-]``, which for a YouTube URL must be
    the URL's own id (any other URL, e.g. ``file://``, leaves the video id to the user)."""
    parsed = parse_clip_name(name)
    if parsed is None:
        raise ClipNameError(f"clip name {name!r} is not <video_id>_<start_us> (the official CAD-Estate convention); "
                            f"{source} gives {_suggest(url, first_timestamp_us, source)}")
    if parsed.start_us != first_timestamp_us:
        raise ClipNameError(f"clip name {name!r}: start {parsed.start_us} µs is not the first timestamp of {source} "
                            f"({first_timestamp_us} µs)")
    if name != f"{parsed.video_id}_{parsed.start_us}":  # leading zeros: a second name of the same clip
        raise ClipNameError(f"clip name {name!r}: write its start without leading zeros "
                            f"({parsed.video_id}_{parsed.start_us})")
    if not _SAFE_VIDEO_ID.match(parsed.video_id):
        raise ClipNameError(f"clip name {name!r}: video id {parsed.video_id!r} has characters outside "
                            "[A-Za-z0-9_-] (it names the clip's frame folder)")
    vid = video_id_from_url(url)
    if vid and is_youtube_url(url) and parsed.video_id != vid:
        raise ClipNameError(f"clip name {name!r}: video id {parsed.video_id!r} is not the YouTube id line 1 of "
                            f"{source} names ({vid!r})")


def _suggest(url: str, first_timestamp_us: int, source: str) -> str:
    try:
        return repr(derive_clip_name(url, first_timestamp_us, source))
    except ClipNameError:
        return "no video id (line 1 names no video)"


def shared_video_ids(clips: Iterable[tuple[str, str]]) -> dict[str, list[str]]:
    """Video ids that clips of *different* videos share (URL lines told apart by
    :func:`source_video`): ``clips`` (clip name, URL line) -> {video id: clip names}. Empty when
    every video id belongs to one source video."""
    urls: dict[str, set[str]] = {}
    names: dict[str, list[str]] = {}
    for name, url in clips:
        vid = video_id_of(name)
        urls.setdefault(vid, set()).add(source_video(url))
        names.setdefault(vid, []).append(name)
    return {v: sorted(names[v]) for v, u in urls.items() if len(u) > 1}
