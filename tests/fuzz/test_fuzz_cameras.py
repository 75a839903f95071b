"""Fuzz `cadestate ingest VIDEO CAMERAS` with broken camera files: every generated case is refused
up front (before Prefect or anything else starts) with one `error:` line naming the camera file and
the line at fault, and the warehouse (holding the clip, ingested once) is left unchanged.

Each strategy breaks a valid camera file of the small demo clip in one known way and says which
line must be named (0: the whole file, named without a line) and what the error must say.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fuzz.harness import assert_clean_error, count_case, run_cli, warehouse_digest
from tasks.video.camera_file import COLUMNS

SUITE = "cameras"
END_US = 3_100_000  # the 3 s clip's end plus END_TOLERANCE_US: a later camera is past the end
FINITE = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
COL = {name: i for i, name in enumerate(COLUMNS)}  # column name -> 0-based field index


@dataclass(frozen=True)
class Ingested:
    """The warehouse holding the small clip, its digest, and where the cases write their camera file."""

    root: Path
    video: Path
    cameras: Path
    lines: tuple[str, ...]  # the valid camera file: URL, then one line per camera
    digest: dict[str, str]


@pytest.fixture(scope="module")
def ingested(small_warehouse, tmp_path_factory, no_runs) -> Ingested:
    """Where the cases write their camera file; `cadestate ingest` must never start a run."""
    w = small_warehouse
    lines = tuple(w.cameras.read_text().splitlines())
    return Ingested(w.root, w.video, tmp_path_factory.mktemp("fuzz_cameras") / "cams.txt", lines, w.digest)


Case = tuple[bytes, int, tuple[str, ...]]
"""A broken camera file, the line its error must name, and words one of which the error must hold."""


def text(lines: list[str]) -> bytes:
    return ("\n".join(lines) + "\n").encode()


def with_field(lines: tuple[str, ...], camera: int, column: str, value: str) -> list[str]:
    """``lines`` with one field of camera ``camera`` (0-based) replaced."""
    out = list(lines)
    fields = out[camera + 1].split()
    fields[COL[column]] = value
    out[camera + 1] = " ".join(fields)
    return out


def camera_index(draw, lines: tuple[str, ...], first: int = 0) -> int:
    return draw(st.integers(first, len(lines) - 2))


TOKEN = st.text(st.characters(blacklist_categories=("Cs",)), min_size=1, max_size=12).filter(
    lambda t: t.split() == [t] and not FINITE.fullmatch(t))


@st.composite
def missing_url(draw, lines) -> Case:
    rest = list(lines[1:])
    bom = draw(st.booleans())
    return (b"\xef\xbb\xbf" if bom else b"") + text(rest), 1, ("the URL line is missing",)


@st.composite
def repeated_or_swapped(draw, lines) -> Case:
    i = camera_index(draw, lines, first=0)
    out = list(lines)
    if draw(st.booleans()) or i == len(lines) - 2:
        out.insert(i + 2, out[i + 1])  # camera i twice
        return text(out), i + 3, ("duplicate timestamp",)
    j = draw(st.integers(i + 1, len(lines) - 2))
    out[i + 1], out[j + 1] = out[j + 1], out[i + 1]
    return text(out), i + 3, ("is not after", "duplicate timestamp")


@st.composite
def blank_line(draw, lines) -> Case:
    i = camera_index(draw, lines, first=1)
    out = list(lines)
    out.insert(i + 1, draw(st.sampled_from(["", " ", "\t", "\r"])))
    return text(out), i + 2, ("blank line",)


@st.composite
def field_count(draw, lines) -> Case:
    i = camera_index(draw, lines)
    fields = lines[i + 1].split()
    n = draw(st.integers(0, 40).filter(lambda k: k not in (0, len(COLUMNS))))
    fields = (fields * 3)[:n]
    out = list(lines)
    out[i + 1] = " ".join(fields) if n else draw(st.sampled_from(["http://x", "url"]))
    return text(out), i + 2, ("columns",)


@st.composite
def not_a_number(draw, lines) -> Case:
    i, column = camera_index(draw, lines), draw(st.sampled_from(COLUMNS))
    value = draw(TOKEN | st.sampled_from(["nan", "NaN", "inf", "-inf", "Infinity", "1e999", "-1e400", "1,0", "0x1f"]))
    words = ("is not a non-negative integer", "does not fit") if column == "timestamp" else ("is not a finite number",)
    return text(with_field(lines, i, column, value)), i + 2, words


@st.composite
def out_of_range(draw, lines) -> Case:
    i = camera_index(draw, lines)
    column, value, words = draw(st.sampled_from([
        ("fx", "0", "must be > 0"), ("fy", "-1.5", "must be > 0"), ("fx", "1e300", "field of view"),
        ("fy", "1e-5", "field of view"), ("fx", "100", "field of view"), ("cx", "-40", "principal point"),
        ("cy", "1.5", "principal point"), ("cx", "-0.2", "principal point"), ("t1", "1e200", "too far"),
        ("t2", "-2e6", "too far"), ("t3", "1.0000001e6", "too far")]))
    return text(with_field(lines, i, column, value)), i + 2, (words,)


@st.composite
def not_a_rotation(draw, lines) -> Case:
    i = camera_index(draw, lines)
    fields = lines[i + 1].split()
    scale = draw(st.sampled_from([0.0, -1.0, 0.9, 1.01, 2.0, 1e6]))
    row = draw(st.sampled_from([("r11", "r12", "r13"), ("r21", "r22", "r23"), ("r31", "r32", "r33")]))
    out = list(lines)
    for name in row:
        out = with_field(tuple(out), i, name, repr(float(fields[COL[name]]) * scale))
    return text(out), i + 2, ("not a rotation",)


@st.composite
def another_aspect(draw, lines) -> Case:
    i = camera_index(draw, lines)
    fy = float(lines[i + 1].split()[COL["fy"]]) * draw(st.sampled_from([0.5, 0.75, 0.85, 1.15, 4 / 3, 2.0]))
    return text(with_field(lines, i, "fy", repr(fy))), i + 2, ("another video's",)


@st.composite
def bad_timestamps(draw, lines) -> Case:
    i = camera_index(draw, lines, first=1)
    out = list(lines)
    if draw(st.booleans()):  # from camera i on, past the end of the video
        start = draw(st.integers(END_US + 1, 2**62))
        for k in range(i, len(lines) - 1):
            out = with_field(tuple(out), k, "timestamp", str(start + (k - i)))
        return text(out), i + 2, ("past the end",)
    previous = int(lines[i].split()[0])
    value = draw(st.integers(0, previous))
    return text(with_field(lines, i, "timestamp", str(value))), i + 2, ("is not after", "duplicate timestamp")


@st.composite
def garbage_bytes(draw, lines) -> Case:
    i = camera_index(draw, lines)
    junk = draw(st.binary(min_size=0, max_size=40).map(lambda b: b.replace(b"\n", b"")))
    cut = draw(st.integers(0, len(junk)))
    never_utf8 = draw(st.sampled_from([b"\xff", b"\xfe", b"\xed\xa0\x80"]))  # invalid after any byte
    bad = junk[:cut] + never_utf8 + junk[cut:]
    head, tail = text(list(lines[: i + 1])), text(list(lines[i + 2:])) if i + 2 < len(lines) else b""
    return head + bad + b"\n" + tail, i + 2, ("not valid UTF-8",)


@st.composite
def stray_bom(draw, lines) -> Case:
    i = camera_index(draw, lines)
    out = list(lines)
    out[i + 1] = "\ufeff" + out[i + 1]
    return text(out), i + 2, ("is not a non-negative integer",)


@st.composite
def truncated(draw, lines) -> Case:
    i = camera_index(draw, lines)
    keep = draw(st.integers(1, len(COLUMNS) - 1))
    out = list(lines[: i + 1]) + [" ".join(lines[i + 1].split()[:keep])]
    return "\n".join(out).encode(), i + 2, ("columns",)


@st.composite
def whole_file(draw, lines) -> Case:
    content, line, words = draw(st.sampled_from([
        (b"", 0, "empty file"), (b" \n\t\r\n", 0, "empty file"), (b"\xef\xbb\xbf", 0, "empty file"),
        (lines[0].encode() + b"\n", 2, "no camera lines"), (lines[0].encode() + b"\n\n \n", 2, "no camera lines")]))
    return content, line, (words,)


BROKEN = [missing_url, repeated_or_swapped, blank_line, field_count, not_a_number, out_of_range, not_a_rotation,
          another_aspect, bad_timestamps, garbage_bytes, stray_bom, truncated, whole_file]


@pytest.mark.parametrize("breakage", BROKEN, ids=lambda s: s.__name__)
@settings(max_examples=16, derandomize=True, database=None, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(data=st.data())
def test_broken_camera_files_are_refused_up_front(ingested, breakage, data):
    content, line, words = data.draw(breakage(ingested.lines), label="case")
    ingested.cameras.write_bytes(content)
    result = run_cli("-w", str(ingested.root), "ingest", str(ingested.video), str(ingested.cameras), "--clip", "small_0")
    error = assert_clean_error(result, mentions=f"error: {ingested.cameras}:{line}: " if line else f"error: {ingested.cameras}: ")
    assert any(w in error for w in words), (error, words)
    assert len(result.stderr.splitlines()) == 1, result.stderr
    assert warehouse_digest(ingested.root) == ingested.digest
    count_case(SUITE)


@settings(max_examples=30, derandomize=True, database=None, deadline=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(content=st.binary(min_size=1, max_size=2000))
def test_random_bytes_are_refused_naming_a_line(ingested, content):
    ingested.cameras.write_bytes(content)
    result = run_cli("-w", str(ingested.root), "ingest", str(ingested.video), str(ingested.cameras), "--clip", "small_0")
    error = assert_clean_error(result)
    assert re.match(rf"error: {re.escape(str(ingested.cameras))}(:\d+)?: ", error), error  # no line: the whole file
    assert len(result.stderr.splitlines()) == 1, result.stderr
    assert warehouse_digest(ingested.root) == ingested.digest
    count_case(SUITE)
