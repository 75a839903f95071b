"""Videos with PyAV: probing, decoding the frame nearest to each requested timestamp, and writing.

Time frame: microseconds since the start of the video stream (the stream's ``start_time`` is
subtracted), the frame of RealEstate10K timestamps.

Pictures are upright: a stream's display rotation (the display matrix phones write for a video
held in portrait, stored sideways) is applied to every decoded frame, and sizes are the upright
picture's (:func:`upright`), as a player shows it and as a camera file made for it counts pixels.
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import av
import numpy as np


class VideoError(ValueError):
    """An unreadable, corrupt or truncated video, or one that lacks a requested frame."""


@dataclass(frozen=True)
class VideoInfo:
    """Properties of a video's first video stream, upright (sizes in px of the picture as shown,
    times in µs; ``pixel_aspect``: the sample aspect ratio, a shown pixel's width over its height, 1
    when the stream does not say; ``rotation``: degrees counterclockwise applied to the stored
    picture, a multiple of 90)."""

    width: int
    height: int
    fps: float
    duration_us: int
    codec: str
    pixel_aspect: float = 1.0
    rotation: int = 0


@dataclass(frozen=True)
class DecodedFrame:
    """One decoded frame: ``time_us`` (stream time, µs) and ``rgb`` uint8[H, W, 3]."""

    time_us: int
    rgb: np.ndarray


def _open(path: str | os.PathLike) -> av.container.InputContainer:
    try:
        container = av.open(str(path))
    except (av.error.FFmpegError, OSError) as e:
        raise VideoError(f"{path}: cannot open video: {e}") from None
    if not container.streams.video:
        container.close()
        raise VideoError(f"{path}: no video stream")
    codec = container.streams.video[0].codec_context
    if container.format.name == "avi" and codec.has_b_frames:
        # AVI states no presentation times: FFmpeg times B-frame streams' decoded frames in decode
        # order (shifted a frame, or out of order), so every camera would get another frame's picture
        container.close()
        raise VideoError(f"{path}: an AVI whose {codec.name} stream has B-frames: AVI states no presentation times, so "
                         "its frames' times are not known; convert it to MP4 or MKV first")
    return container


def _quarter_turns(frame: av.VideoFrame) -> int:
    """Counterclockwise quarter turns that make ``frame`` upright (its display matrix's rotation,
    rounded to a multiple of 90 degrees; 0 without one)."""
    return round((frame.rotation or 0) / 90) % 4


def upright(frame: av.VideoFrame) -> np.ndarray:
    """``frame`` as RGB uint8[H, W, 3], turned as its display rotation says."""
    rgb = frame.to_ndarray(format="rgb24")
    turns = _quarter_turns(frame)
    return np.ascontiguousarray(np.rot90(rgb, turns)) if turns else rgb


def _length_us(container: av.container.InputContainer, stream: av.video.stream.VideoStream) -> int:
    """The video stream's length, µs (0: unknown): its stated duration, else the end of its last
    packet less its first time (Matroska states none, and its container duration can be the end
    time itself: a 3 s clip cut at 60 s read as 63 s). Seeks: call last."""
    if stream.duration is not None and stream.time_base is not None:
        return int(round(stream.duration * stream.time_base * 1_000_000))
    if stream.time_base is None:
        return int(container.duration or 0)  # AV_TIME_BASE is 1 µs
    start = stream.start_time or 0
    end = None
    try:
        container.seek(start + int((container.duration or 0) / 1e6 / stream.time_base) + 1, stream=stream, backward=True)
        for packet in container.demux(stream):
            if packet.pts is not None:
                end = max(end or packet.pts, packet.pts + (packet.duration or 0))
    except av.error.FFmpegError:
        pass
    if end is None:
        return int(container.duration or 0)
    return max(0, int(round((end - start) * stream.time_base * 1_000_000)))


def probe_video(path: str | os.PathLike) -> VideoInfo:
    """Read the stream properties and decode the first frame (a corrupt file fails here)."""
    with _open(path) as container:
        stream = container.streams.video[0]
        try:
            first = next(container.decode(stream), None)
        except av.error.FFmpegError as e:
            raise VideoError(f"{path}: cannot decode video: {e}") from None
        if first is None:
            raise VideoError(f"{path}: the video stream has no decodable frame")
        duration_us = _length_us(container, stream)
        fps = float(stream.average_rate) if stream.average_rate else 0.0
        sar = stream.sample_aspect_ratio
        pixel_aspect = float(sar) if sar and sar > 0 else 1.0
        turns = _quarter_turns(first)
        width, height = (first.height, first.width) if turns % 2 else (first.width, first.height)
        return VideoInfo(width, height, fps, duration_us, stream.codec_context.name,
                         1.0 / pixel_aspect if turns % 2 else pixel_aspect, 90 * turns)


def _time_us(pts: int, start: int, time_base: Fraction) -> int:
    """A stream timestamp in µs of stream time (its ``start_time`` subtracted), exactly rounded."""
    return int(round((pts - start) * time_base * 1_000_000))


def _frame_time_us(frame: av.VideoFrame, start: int, time_base: Fraction, path: str | os.PathLike) -> int:
    if frame.pts is None:
        raise VideoError(f"{path}: a decoded frame has no timestamp")
    return _time_us(frame.pts, start, time_base)


def decode_at(
    path: str | os.PathLike, timestamps_us: np.ndarray, seek_threshold_us: int = 1_000_000
) -> Iterator[DecodedFrame]:
    """Yield, for each timestamp (strictly increasing, µs), the decoded frame nearest to it.

    Decodes forward while the next timestamp is near; seeks (to the keyframe before it, then
    decodes forward) when it is more than ``seek_threshold_us`` ahead. A seek that lands after the
    timestamp (containers without an exact index, MPEG-TS) is taken again from further back, in
    the end from the start. The caller checks how far each frame's ``time_us`` is from the
    timestamp it asked for. Frames are upright (:func:`upright`).
    """
    container = _open(path)  # from_start swaps in the file opened again: the one open is closed at the end
    try:
        stream = _video_stream(container)
        time_base = stream.time_base
        start = stream.start_time or 0
        frames: Iterator[av.VideoFrame] | None = None
        # (time_us, frame) of the latest decoded frame before the current target, and of the first
        # one at or after it (None at the end). Frames are converted to RGB only when yielded.
        prev: tuple[int, av.VideoFrame] | None = None
        nxt: tuple[int, av.VideoFrame] | None = None

        def advance() -> tuple[int, av.VideoFrame] | None:
            try:
                frame = next(frames, None)
            except av.error.FFmpegError as e:
                raise VideoError(f"{path}: decoding failed (corrupt or truncated video?): {e}") from None
            return None if frame is None else (_frame_time_us(frame, start, time_base, path), frame)

        def from_start() -> None:
            """Decode from the first packet of the file opened again: a seek to 0 in a container
            without an index (MPEG-TS) may land on the first keyframe after it."""
            nonlocal container, stream, frames
            old, container = container, _open(path)
            old.close()
            stream = _video_stream(container)
            frames = container.decode(stream)

        def seek(goal_us: int) -> None:
            nonlocal frames
            try:
                container.seek(start + int(Fraction(goal_us, 1_000_000) / time_base), stream=stream, backward=True)
            except av.error.FFmpegError as e:
                raise VideoError(f"{path}: seek to {goal_us} µs failed: {e}") from None
            frames = container.decode(stream)

        def restart(target: int) -> tuple[int, av.VideoFrame] | None:
            """The first frame decoded after seeking before ``target`` (1 s, 2 s, 4 s, ... before
            it while a seek lands after it or at the end), or from the start when it is that near."""
            nonlocal frames
            back = 0
            while True:
                goal = target - back
                if goal > seek_threshold_us:
                    seek(goal)
                elif frames is None:
                    frames = container.decode(stream)
                else:
                    from_start()
                first = advance()
                if (first is not None and first[0] <= target) or goal <= seek_threshold_us:
                    return first
                back = max(2 * back, seek_threshold_us, 1_000_000)

        for target in np.asarray(timestamps_us, dtype=np.int64).tolist():
            if frames is None or (nxt is not None and target - nxt[0] > seek_threshold_us):
                prev, nxt = None, restart(target)
            while nxt is not None and nxt[0] < target:
                prev, nxt = nxt, advance()
            candidates = [f for f in (prev, nxt) if f is not None]
            if not candidates:
                raise VideoError(f"{path}: no frame could be decoded near {target} µs")
            time_us, frame = min(candidates, key=lambda f: abs(f[0] - target))
            yield DecodedFrame(time_us, upright(frame))
    finally:
        container.close()


def frame_times_us(path: str | os.PathLike) -> np.ndarray | None:
    """int64[F] sorted presentation times (µs, stream time) of every frame of the video stream, read
    from its packets (demuxed, not decoded: a second for an hour of video); None when a packet
    states no time (some AVI files), so that the times cannot be known without decoding."""
    with _open(path) as container:
        stream = container.streams.video[0]
        if stream.time_base is None:
            return None
        start, times = stream.start_time or 0, []
        try:
            for packet in container.demux(stream):
                if packet.size == 0:
                    continue  # the flush packet demux ends with
                if packet.pts is None:
                    return None
                times.append(_time_us(packet.pts, start, stream.time_base))  # as decode_at times its frames
        except av.error.FFmpegError as e:
            raise VideoError(f"{path}: reading its packets failed (corrupt or truncated video?): {e}") from None
    return np.sort(np.asarray(times, np.int64))


def _video_stream(container: av.container.InputContainer) -> av.video.stream.VideoStream:
    """The container's (first) video stream, decoded on threads."""
    stream = container.streams.video[0]
    stream.thread_type = "AUTO"
    return stream


def frame_timestamp_us(index: int, fps: int) -> int:
    """Time of video frame ``index`` in integer µs: ``round(index * 1e6 / fps)``, computed exactly."""
    return round(Fraction(index * 1_000_000, fps))


X264_REPRODUCIBLE = {"x264-params": "mbtree=0"}
"""libx264 options that make an encode a function of its frames: with macroblock-tree rate control
(x264's default) the first GOP came out differently from run to run in this build (PyAV 18, one
clip's 60 frames encoded 30 times: 19 different files, also with ``threads=1``; decoded pixels off
by up to 10 levels), which made a benchmark walkthrough another video each session; without it,
60 of 60 encodes were identical."""


def write_video(path: str | os.PathLike, frames: Iterable[np.ndarray], width: int, height: int, fps: int,
                codec: str = "libx264", options: dict[str, str] | None = None) -> None:
    """Encode the uint8[H, W, 3] RGB ``frames`` into an MP4 at ``path``, replaced atomically.

    Frame ``i`` gets pts ``i`` in time base ``1/fps`` (exact times, see :func:`frame_timestamp_us`);
    one GOP per second. Encoding runs on a worker thread while the caller's thread produces the
    next frame (a renderer's GL context stays on the caller's thread). The same frames give the
    same bytes: libx264 runs without its macroblock-tree rate control (:data:`X264_REPRODUCIBLE`).
    """
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.{secrets.token_hex(8)}{path.suffix}.tmp")
    try:
        with av.open(str(tmp), "w", format="mp4") as container, ThreadPoolExecutor(1) as pool:
            stream = container.add_stream(codec, rate=fps)
            stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
            stream.time_base = Fraction(1, fps)
            stream.codec_context.gop_size = fps
            if codec == "libx264":
                options = {**X264_REPRODUCIBLE, **(options or {})}
            if options:
                stream.codec_context.options = options

            def encode(index: int, image: np.ndarray) -> None:
                frame = av.VideoFrame.from_ndarray(image, format="rgb24")
                frame.pts = index
                container.mux(stream.encode(frame))

            pending: Future | None = None
            for index, image in enumerate(frames):
                if pending is not None:
                    pending.result()
                pending = pool.submit(encode, index, image)
            if pending is not None:
                pending.result()
            container.mux(stream.encode())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
