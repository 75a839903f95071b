"""`cadestate stats` on a hand-built 3-clip benchmark warehouse, against numbers computed by hand
from the clips' ground truth; the HTML report (its pages and pictures; Chromium renders it where
installed). Needs the Sweet Home 3D furniture (tests/conftest.py)."""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from bench.benchmark import clip_name
from bench.seeds import seed_note
from bench.walkthrough import WalkthroughSpec, generate_clip
from conftest import table_rows
from dataset_fixture import CLASS_NAME, write_accepted, write_frames, write_tracks
from schemas.official import read_objects
from tasks.dataset.stats import dataset_tables, select_clips, statistics
from tasks.registry import stages_of
from tasks.video.camera_file import parse_camera_file
from warehouse import Warehouse

CLIP_STAGES = [s.name for s in stages_of("clip")]

SPEC = WalkthroughSpec(width=256, height=144, num_video_frames=24, sample_every=3, alone_scale=0.5)
CHROMIUM = Path("/usr/bin/chromium")


@pytest.fixture(scope="module")
def bench3(small_cad_library, tmp_path_factory):
    """(warehouse, [(clip name, generated clip, posed ground-truth objects, objects with a track)]):
    a 3-clip benchmark folder (``tmp/bench``, its manifest written), one track per ground-truth
    object that has boxes (the track id is the object's), every other one posed (accepted); the
    solver's ``poses`` are the ground truth for every tracked object, but for the first unaccepted
    object of clip 0, solved with the mirror flag wrong."""
    lib, rows = small_cad_library
    tmp = tmp_path_factory.mktemp("stats")
    shutil.copytree(lib.root, tmp / "wh")
    wh = Warehouse(tmp / "wh")
    clips = []
    for i in range(3):
        name = clip_name(31, i, SPEC)
        clip = generate_clip(tmp / "bench", name, 31000 + i, rows, lib.root, SPEC)
        cams = write_frames(wh, name, clip.video_path, clip.cameras_path, SPEC.width, SPEC.height)
        gt = [o for o in read_objects(clip.objects_path).objects if o.track]
        write_tracks(wh, name, cams, {int(o.track_id): (o, o.track) for o in gt})
        posed = {int(o.track_id): o for k, o in enumerate(gt) if k % 2 == 0}
        write_accepted(wh, name, posed)
        write_solved(wh, name, {int(o.track_id): o for o in gt}, wrong_mirror=gt[1].track_id if i == 0 else None)
        timed = {"frames": 2.5, "detect": 4.0, "pose": 1.0, "verification": 0.0}  # every stage ran to the end
        wh.write("runs", name, table_rows("runs", [{"clip": name, "run_id": f"r{i}{s}", "stage": s, "duration_s": timed.get(s, 0.0),
                                                    "status": "completed"} for s in CLIP_STAGES]))
        clips.append((name, clip, list(posed.values()), len(gt)))
    (tmp / "bench" / "manifest.json").write_text(json.dumps({"seed": 31, "clips": [c[0] for c in clips], "library": "x"}))
    write_labels(wh, clips[0][0], [("verification", 3, [12.5, 7.5]), ("manual_track", 4, [30.0]),
                                   ("cad_selection", 2, [])])
    write_labels(wh, clips[2][0], [("correspondences", 1, [40.0])])
    return wh, clips


def write_solved(wh: Warehouse, clip: str, solved: dict, wrong_mirror: str | None) -> None:
    """``poses`` of the solver (status ok): ``{track id: object}`` posed as the object is, the
    object of track id ``wrong_mirror`` with its mirror flag flipped."""
    wh.write("poses", clip, table_rows("poses", [
        {"clip": clip, "track_id": str(t), "cad_id": o.cad_id, "class": CLASS_NAME[o.cls], "status": "ok",
         "translation": list(o.translation), "rotation": list(o.rotation), "scale": list(o.scale),
         "is_mirrored": o.is_mirrored != (o.track_id == wrong_mirror), "num_keyframes": 2} for t, o in solved.items()]))


def write_labels(wh: Warehouse, clip: str, files: list[tuple[str, int, list[float]]]) -> None:
    """``label_files`` rows (kind, answers in the file) and the ``label_effort`` rows of the seconds
    each gave (one per item: a manual_track label is track -1)."""
    effort = []
    for k, (kind, answers, seconds) in enumerate(files):
        effort += [{"clip": clip, "label_sha256": f"l{k}", "kind": kind, "track_id": -1 if kind == "manual_track" else t,
                    "seconds": sec} for t, sec in enumerate(seconds)]
    wh.write("label_files", clip, table_rows("label_files", [
        {"clip": clip, "label_sha256": f"l{k}", "task_id": f"t{k}", "kind": kind, "num_answers": n}
        for k, (kind, n, _) in enumerate(files)]))
    wh.write("label_effort", clip, table_rows("label_effort", effort))


def test_statistics_match_a_hand_count(bench3):
    wh, clips = bench3
    assert select_clips(wh).chosen == sorted(c[0] for c in clips) and select_clips(wh).unfinished == []
    assert select_clips(wh, f"clip = '{clips[1][0]}'").chosen == [clips[1][0]]
    s = statistics(dataset_tables(wh, select_clips(wh).chosen))
    frames = sum(len(parse_camera_file(c.cameras_path).timestamps_us) for _, c, _, _ in clips)
    posed = [o for _, _, p, _ in clips for o in p]
    boxes = sum(len(o.track) for o in posed)
    classes = {CLASS_NAME[o.cls] for o in posed}
    ratios = []
    for _, clip, objs, _ in clips:
        cams = parse_camera_file(clip.cameras_path)
        for i, ts in enumerate(cams.timestamps_us.tolist()):
            centre = -cams.R[i].T @ cams.t[i]
            d = [np.linalg.norm(np.array(o.translation) - centre) for o in objs if any(e.timestamp == ts for e in o.track)]
            if len(d) >= 2:
                ratios.append(min(d) / max(d))
    assert s["scenes"] == 3 and s["frames"] == frames and s["frames_per_scene"] == pytest.approx(frames / 3)
    assert s["objects"] == sum(n for *_, n in clips) and s["posed_objects"] == len(posed)
    assert s["classes"] == len(classes) and s["classes_over_100"] == 0 and s["classes_over_1000"] == 0
    assert s["objects_per_scene"] == pytest.approx(len(posed) / 3)
    assert s["objects_per_frame"] == pytest.approx(boxes / frames)
    assert s["cad_models"] == len({o.cad_id for o in posed})
    assert s["frames_with_two_posed"] == len(ratios) and s["near_far_ratio_median"] == pytest.approx(np.median(ratios))
    assert 0 <= s["truncated_share"] <= 1
    assert s["compute_s_per_stage"] == {**dict.fromkeys(CLIP_STAGES, 0.0), "detect": 12.0, "frames": 7.5, "pose": 3.0}
    # a manual-track answer is one item whatever it draws (here 4 objects); a kind no item of which gave
    # seconds has no figure (not 0 s), nor has the cost per posed object while any item's time is missing
    assert s["human_items"] == {"cad_selection": 2, "correspondences": 1, "manual_track": 1, "verification": 3}
    assert s["annotation_s_per_kind"] == {"cad_selection": None, "correspondences": 40.0, "manual_track": 30.0,
                                          "verification": 20.0}
    assert s["annotation_s"] == 90.0 and s["annotation_s_per_posed_object"] is None
    assert s["items_without_seconds"] == 3  # one verification track, both cad_selection tracks
    assert s["yield"] == pytest.approx(len(posed) / s["objects"]) and s["compute_s_cad_libraries"] >= 0
    one = statistics(dataset_tables(wh, [clips[2][0]]))
    assert one["annotation_s"] == 40.0 and one["items_without_seconds"] == 0
    assert one["annotation_s_per_posed_object"] == pytest.approx(40.0 / len(clips[2][2]))
    none = statistics(dataset_tables(wh, [clips[1][0]]))
    assert none["human_items"] == {} and none["annotation_s_per_posed_object"] is None


def test_html_report_pages_and_pictures(bench3, tmp_path):
    from tasks.dataset.stats_report import write_report

    wh, clips = bench3
    chosen = select_clips(wh).chosen
    figures, index = write_report(wh, chosen, tmp_path / "report")
    assert figures == statistics(dataset_tables(wh, chosen))
    text = index.read_text()
    assert "#Posed objects" in text and "Cost of the dataset" in text
    assert "<td>annotation s per posed object (shown when every item is timed)</td><td>-</td>" in text  # 3 items untimed
    assert "<td>answered items with no seconds recorded (missing from the sums)</td><td>3</td>" in text
    for name, _, posed, _ in clips:
        assert f'href="clips/{name}.html"' in text
        page = (tmp_path / "report" / "clips" / f"{name}.html").read_text()
        images = re.findall(r'src="([^"]+)"', page)
        assert images and all((tmp_path / "report" / "clips" / src).resolve().is_file() for src in images)
        for cls in {o.cls for o in posed}:
            assert f"<td>{CLASS_NAME[cls]}</td>" in page
    # Written again into the same folder, stopped half-way (a clip the warehouse does not hold: its
    # page fails): the first report is left whole, nothing half-written beside it; then a report
    # of one clip replaces it whole (the other clips' pages and pictures go with it).
    before = {p: p.read_bytes() for p in (tmp_path / "report").rglob("*") if p.is_file()}
    with pytest.raises(Exception):
        write_report(wh, [*chosen, "no_such_clip"], tmp_path / "report")
    assert {p: p.read_bytes() for p in (tmp_path / "report").rglob("*") if p.is_file()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report"]
    write_report(wh, [clips[0][0]], tmp_path / "report")
    assert sorted(p.name for p in (tmp_path / "report" / "clips").iterdir()) == [f"{clips[0][0]}.html"]
    for src in re.findall(r'src="([^"]+)"', text):
        assert (tmp_path / "report" / src).is_file()


def test_html_report_reads_each_clips_dataset_once(bench3, tmp_path, monkeypatch):
    """`stats --html`: each clip's dataset (~0.4 s a clip) is read once, for its figures and its
    page together; it was read twice (hours more at 20,000 clips)."""
    import tasks.dataset.objects
    from fuzz.harness import run_cli

    read = []

    def counted(wh, clip):
        read.append(clip)
        return real(wh, clip)

    real = tasks.dataset.objects.clip_dataset
    for module in ("tasks.dataset.stats", "tasks.dataset.stats_report"):
        monkeypatch.setattr(f"{module}.clip_dataset", counted, raising=False)
    wh, clips = bench3
    result = run_cli("-w", str(wh.root), "stats", "--html", str(tmp_path / "r"))
    assert result.code == 0, result.stderr
    assert sorted(read) == sorted(c[0] for c in clips)
    assert "#Scenes (clips): 3" in result.stdout and (tmp_path / "r" / "clips" / f"{clips[0][0]}.html").is_file()


def test_a_damaged_frame_image_is_named_not_read_as_a_folder_not_written(bench3, tmp_path):
    """A frame image of the warehouse missing or damaged: `stats --html` names it in one line; it
    said "<report>: cannot write the HTML report there: cannot identify image file ...; give a folder"."""
    from fuzz.harness import assert_clean_error, run_cli

    wh, _ = bench3
    shutil.copytree(wh.root, tmp_path / "w", ignore=shutil.ignore_patterns("catalog.duckdb", "_cache"))
    copy = Warehouse(tmp_path / "w")
    for damaged in (tmp_path / "w" / "media" / "frames").rglob("*.*"):
        damaged.unlink()
        damaged.write_bytes(b"not an image")  # a file of its own: the copy's images may be hard links
    result = run_cli("-w", str(copy.root), "stats", "--html", str(tmp_path / "r"))
    line = assert_clean_error(result, mentions=f"error: {tmp_path / 'w' / 'media' / 'frames'}")
    assert ": cannot read this frame's image (missing or damaged: " in line and "give a folder" not in line, line
    assert not (tmp_path / "r").exists()


def test_a_click_on_no_frame_is_no_key_frame_of_the_report(bench3, tmp_path):
    """A posed object's clicks on a timestamp that is no frame of the clip (frames extracted again
    since the clicks): the report's key-frames are frames (its overlays failed on a KeyError)."""
    from tasks.dataset.objects import clip_dataset
    from tasks.dataset.stats_report import keyframe_stamps, overlays

    wh, clips = bench3
    ds = clip_dataset(wh, clips[0][0])
    posed = next(o for o in ds.objects if o.pose is not None)
    clicked = dataclasses.replace(posed, correspondences={**posed.correspondences, 1: ((0.5, 0.5), (0.0, 0.0, 0.0))})
    moved = dataclasses.replace(ds, objects=tuple(clicked if o is posed else o for o in ds.objects))
    stamps = keyframe_stamps(moved)
    assert 1 not in stamps and set(stamps) <= {f.timestamp_us for f in ds.frames}
    assert len(overlays(wh, moved, tmp_path)) == len(stamps)


def test_bench_report_scores_the_poses_in_every_mode(bench3):
    """`cadestate bench report` on the benchmark folder and its warehouse: the accepted poses (the
    ground truth) are correct in every mode; of the solved ones, the mirrored-wrong pose fails
    `pose` (mirror flags differ) and `scan2cad-exact` (its mirrored model is no ground-truth
    model: a false positive) but not `scan2cad-class` (the mirror flag is not looked at)."""
    from fuzz.harness import run_cli

    wh, clips = bench3
    bench = clips[0][1].objects_path.parent.parent
    objects = sum(1 for _, c, _, _ in clips for o in read_objects(c.objects_path).objects if o.track)  # posed, shown
    accepted, tracked = sum(len(p) for _, _, p, _ in clips), sum(n for *_, n in clips)
    result = run_cli("-w", str(wh.root), "bench", "report", str(bench))
    assert result.code == 0, result.stderr
    rows = {line.split(" | ")[0] + " | " + line.split(" | ")[1]: line for line in result.stdout.splitlines()
            if line.startswith("| `")}
    expected = {("accepted in verification", accepted): {"pose": (accepted, 0), "scan2cad-class": (accepted, 0),
                                                          "scan2cad-exact": (accepted, 0)},
                ("solved (status ok)", tracked): {"pose": (tracked - 1, 0), "scan2cad-class": (tracked, 0),
                                                  "scan2cad-exact": (tracked - 1, 1)}}
    for (label, n), modes in expected.items():
        for mode, (correct, false_positives) in modes.items():
            row = rows[f"| `{mode}` | {label}: {n}"]
            pct = f"{round(100 * correct / objects, 1)} %"
            assert row.startswith(f"| `{mode}` | {label}: {n} | {correct} of {objects} | {pct} | "), row
            assert row.endswith(f" | 0 | {false_positives} |"), row
    assert f"3 clips, {objects} posed ground-truth objects the clips show, {tracked} with correspondences)" in result.stdout
    assert (bench / "report.md").read_text().strip() == result.stdout.strip()


def test_stats_command(bench3, tmp_path):
    """`cadestate stats --where ... --html OUT --json`: the figures of the chosen clips as one JSON
    document on stdout, the report written; a bad --where is one error line and writes nothing."""
    from fuzz.harness import assert_clean_error, run_cli

    wh, clips = bench3
    name = clips[1][0]
    result = run_cli("-w", str(wh.root), "stats", "--where", f"clip = '{name}'", "--html", str(tmp_path / "r"), "--json")
    assert result.code == 0, result.stderr
    figures = json.loads(result.stdout)
    assert figures == json.loads(json.dumps(statistics(dataset_tables(wh, [name]))))
    assert figures["scenes"] == 1 and figures["posed_objects"] == len(clips[1][2])
    assert result.stderr.strip() == f"wrote {tmp_path / 'r' / 'index.html'}"
    assert re.findall(r'href="clips/([^"]+)\.html"', (tmp_path / "r" / "index.html").read_text()) == [name]
    text = run_cli("-w", str(wh.root), "stats")
    assert text.code == 0 and "#Scenes (clips): 3" in text.stdout
    assert text.stdout.startswith(f"Yield (posed of all objects found): {sum(len(p) for _, _, p, _ in clips)} of ")
    assert "annotation s per posed object (shown when every item is timed): -" in text.stdout
    lines = text.stdout.splitlines()  # the cost one figure a line, as the HTML report's table (no Python dict)
    assert "{" not in text.stdout and any(re.fullmatch(r"compute s: detect: \d+\.\d\d", line) for line in lines), lines
    assert any(line.startswith("compute s: CAD libraries (shared by every clip): ") for line in lines)
    assert any(re.fullmatch(r"human items answered: verification: \d+", line) for line in lines), lines
    bad = run_cli("-w", str(wh.root), "stats", "--where", "no_such_column = 1", "--html", str(tmp_path / "bad"), "--json")
    assert_clean_error(bad, mentions="error: --where 'no_such_column = 1': SQL error: ")
    assert bad.stdout == "" and not (tmp_path / "bad").exists()


def test_stats_of_no_clip_are_zeros(tmp_path):
    """A warehouse with no clip yet (or a --where that matches none): zeros and no figure, not a traceback."""
    from fuzz.harness import run_cli

    wh = Warehouse(tmp_path / "w")
    figures = statistics(dataset_tables(wh, select_clips(wh).chosen))
    assert figures["scenes"] == figures["posed_objects"] == figures["classes"] == figures["cad_models"] == 0
    assert figures["per_class"] == {} and figures["truncated_share"] is None
    result = run_cli("-w", str(wh.root), "stats", "--where", "false")
    assert result.code == 0 and "#Posed objects: 0" in result.stdout
    assert result.stderr == "warning: --where 'false': no clip matches it\n"  # said, not all zeros alone
    assert result.stdout.splitlines()[0] == "Yield (posed of all objects found): 0 of 0 (-)"


def test_where_is_one_condition(tmp_path):
    """`stats --where` is one SQL condition on the clips table: a second statement, a parenthesis
    closing the WHERE with a clause after it (a UNION made up a clip 'zz' per frame; ORDER BY, LIMIT),
    an alias or a ';' after it, or nothing, is one error line naming --where; a condition with a
    comment or a ';' in a string works."""
    from fuzz.harness import assert_clean_error, run_cli

    wh = Warehouse(tmp_path / "w")
    select_clips(wh)  # a warehouse with no clip: its catalog made
    for where in ("true; SELECT 1", "true); SELECT 1; --", "true) UNION ALL SELECT 'zz' WHERE (true",
                  "true) ORDER BY clip LIMIT 0 --", "split = 'val') --", " "):
        result = run_cli("-w", str(wh.root), "stats", "--where", where)
        assert_clean_error(result, mentions=f"error: --where {where!r}: ")
        assert result.stdout == ""
    for where in ("true;", "true AS x", "split = 'val' x", "true; -- c"):  # a SELECT list's tail, refused up front
        result = run_cli("-w", str(wh.root), "stats", "--where", where)  # (was 'SQL error: ... syntax error')
        assert_clean_error(result, mentions=f"error: --where {where!r}: not one SQL condition: ")
    for where in ("split = 'a;b) --'", "true -- every clip", "clip IN (SELECT clip FROM frames)"):
        result = run_cli("-w", str(wh.root), "stats", "--where", where)  # none matches (no clip yet): said, not all zeros alone
        assert result.code == 0 and "#Scenes (clips): 0" in result.stdout, (where, result)
        assert result.stderr == f"warning: --where {where!r}: no clip matches it\n", (where, result)
    result = run_cli("-w", str(wh.root), "stats")
    assert result.code == 0 and result.stderr == "" and "#Scenes (clips): 0" in result.stdout, result


def test_a_damaged_table_file_is_not_blamed_on_where(tmp_path):
    """`stats --where` over a damaged clips file: one line naming the table and the file, as the
    warehouse's reads say it, not --where (it said "--where \"split = 'val'\": SQL error: ... No magic
    bytes ..."); a condition that fails is still said to be --where's, and `sql` names the file alike."""
    from fuzz.harness import assert_clean_error, run_cli

    wh = Warehouse(tmp_path / "w")
    for clip, split in (("a", "val"), ("b", "train")):
        wh.write("clips", clip, table_rows("clips", [{"clip": clip, "split": split}]))
    damaged = wh.files("clips", ["a"])[0]
    damaged.write_bytes(b"not parquet at all")
    for args in (("stats", "--where", "split = 'val'"), ("stats",), ("sql", "SELECT count(*) FROM clips")):
        result = run_cli("-w", str(wh.root), *args)
        line = assert_clean_error(result, mentions="error: table clips: cannot read its files: ")
        assert str(damaged) in line and "--where" not in line and result.stdout == "", line
    bad = run_cli("-w", str(wh.root), "stats", "--where", "no_such_column = 1")
    assert_clean_error(bad, mentions="error: --where 'no_such_column = 1': SQL error: Binder Error: ")


@pytest.mark.skipif(not CHROMIUM.exists(), reason="Chromium is not installed (/usr/bin/chromium)")
def test_html_report_renders_in_chromium(bench3, tmp_path):
    from tasks.dataset.stats_report import write_report

    wh, _ = bench3
    _, index = write_report(wh, select_clips(wh).chosen, tmp_path / "report")
    shot = tmp_path / "shot.png"
    subprocess.run([str(CHROMIUM), "--headless", "--no-sandbox", "--disable-gpu", f"--screenshot={shot}",
                    "--window-size=1200,1600", index.as_uri()], check=True, timeout=120, capture_output=True)
    from PIL import Image

    pixels = np.asarray(Image.open(shot).convert("L"))
    assert pixels.std() > 5  # not a blank page


def _in_view(clip) -> set[str]:
    """Hand count of the in-view rule: objects with >= 3 boxes visible >= 30 % and truncated <= 50 %."""
    vis = json.loads((clip.objects_path.parent / "visibility.json").read_text())
    fr = {(f["timestamp"], o["track_id"]): o for f in vis["frames"] for o in f["objects"]}
    out = set()
    for o in read_objects(clip.objects_path).objects:
        good = [e for e in o.track if (e.timestamp, o.track_id) in fr and fr[(e.timestamp, o.track_id)]["visible_fraction"] >= 0.3
                and fr[(e.timestamp, o.track_id)]["truncated_fraction"] <= 0.5]
        if len(good) >= 3:
            out.add(o.track_id)
    return out


def test_bench_report_leads_with_the_yield(bench3, tmp_path, monkeypatch):
    """The yield line of `cadestate bench report` against a hand count: clip 2 `val`, the others `train`; clip 0
    gets two more accepted poses, the pose of its first posed object on the track of the next
    object (in 3D a duplicate of the first; the yield scores by track: a wrong pose of the next
    object, as the dataset publishes it) and one 100 m away on no track (a false annotation);
    descriptors for the detections, so each track maps to its object; task files."""
    from fuzz.harness import run_cli
    from tasks.detection.embed import vectors_array

    wh0, clips = bench3
    shutil.copytree(wh0.root, tmp_path / "wh")
    bench = tmp_path / "bench"
    shutil.copytree(clips[0][1].objects_path.parent.parent, bench)
    wh = Warehouse(tmp_path / "wh")
    names = [c[0] for c in clips]
    for name, split in zip(names, ("train", "train", "val")):
        wh.write("clips", name, table_rows("clips", [{**wh.read("clips", [name]).to_pylist()[0], "split": split}]))
    for name in names:
        det = wh.read("detections", [name], columns=["det_id"]).column("det_id").to_pylist()
        wh.write("embeddings", name, table_rows("embeddings", [
            {"clip": name, "owner": "detection", "owner_id": d, "model_sha256": "x"} for d in det]).set_column(
            3, "vector", vectors_array(np.tile([1.0, 0.0], (len(det), 1)))))
    gt0 = [o for o in read_objects(clips[0][1].objects_path).objects if o.track]
    first, other = gt0[0], gt0[1]  # posed (accepted) and not
    far = dict(first.__dict__, translation=(first.translation[0] + 100.0, *first.translation[1:]), track_id="999")
    write_accepted(wh, names[0], {**{int(o.track_id): o for o in clips[0][2]}, int(other.track_id): first,
                                  999: type(first)(**far)})
    doc = lambda *ids: json.dumps({"items": [{"track_id": t} for t in ids]})  # noqa: E731
    wh.write("label_tasks", names[0], table_rows("label_tasks", [
        {"clip": names[0], "task_id": "s", "kind": "cad_selection", "document": doc(1, 2, 3)},
        {"clip": names[0], "task_id": "v", "kind": "verification", "document": doc(1)}]))
    wh.write("label_tasks", names[2], table_rows("label_tasks", [
        {"clip": names[2], "task_id": "m", "kind": "manual_track", "document": "{}"},
        {"clip": names[2], "task_id": "c", "kind": "correspondences", "document": doc(5, 6)}]))

    result = run_cli("-w", str(wh.root), "bench", "report", str(bench))
    assert result.code == 0, result.stderr
    in_view = [_in_view(c) for _, c, _, _ in clips]
    posed = [{o.track_id for o in p} & v for (_, _, p, _), v in zip(clips, in_view)]
    train_view, train_accepted = len(in_view[0]) + len(in_view[1]), len(clips[0][2]) + len(clips[1][2]) + 2
    # scan2cad-class by track: the borrowed pose is the next object's, wrong; the far pose is false
    train_yield = len(posed[0]) + len(posed[1])
    wrong = int(other.track_id in in_view[0])  # out of view: on another object, not a wrong pose of one in view
    assert first.track_id in in_view[0] and train_yield
    pct = lambda n, d: round(100 * n / d, 1)  # noqa: E731
    lines = result.stdout.splitlines()
    assert lines[2] == seed_note(json.loads((bench / "manifest.json").read_text())["seed"])  # whether it may flatter
    assert lines[4] == "## Dataset yield (accepted poses, `scan2cad-class`)"
    train = next(line for line in lines if line.startswith("**train**"))
    assert train == (f"**train** (2 clips): yield **{pct(train_yield, train_view)} %** (target 60 %): {train_yield} of "
                     f"{train_view} objects in view have exactly one accepted, correct pose; 0 duplicates "
                     f"(0.0 % of {train_accepted} accepted poses); {wrong} wrong poses of objects in view; "
                     f"1 false annotations; 1.0 tracks "
                     f"per object ({train_view} objects found by a track); {round(4 / train_yield, 2)} human items per "
                     f"posed object (4 asked).")
    val = next(line for line in lines if line.startswith("**val**"))
    assert val.startswith(f"**val** (1 clips): yield **{pct(len(posed[2]), len(in_view[2]))} %** (target 80 %): "
                          f"{len(posed[2])} of {len(in_view[2])} objects in view")
    assert val.endswith(f"{round(3 / len(posed[2]), 2)} human items per posed object (3 asked).")
    # `pose` (the track map): the borrowed pose is wrong on the unposed object's track, no duplicate
    pose_row = next(line for line in lines if line.startswith("| train | `pose` |"))
    assert pose_row.startswith(f"| train | `pose` | {train_accepted} | {len(posed[0]) + len(posed[1])} of {train_view} ")
    assert pose_row.split(" | ")[4:6] == ["0", "1"]
    assert lines.index(train) < lines.index("## The benchmark's ground truth (the paper's Table 2 statistics; what the dataset built holds is above and in `cadestate stats`)")
    assert (bench / "report.md").read_text().strip() == result.stdout.strip()
    # the interval resamples these clips' counts, within each split (too few clips for one in the report)
    import bench.dataset_yield as dy

    monkeypatch.setattr(dy, "MIN_CLIPS", 2)
    counts = dict(zip(names, [(train_yield - len(posed[1]), len(in_view[0])), (len(posed[1]), len(in_view[1])),
                              (len(posed[2]), len(in_view[2]))]))
    splits = dict(zip(names, ("train", "train", "val")))
    got = dy.dataset_yield(bench, wh)["splits"]
    assert got["all"]["interval_pct"] == dy.clip_interval([counts[n] for n in sorted(names)], min_clips=2,
                                                          strata=[splits[n] for n in sorted(names)])
    assert got["train"]["interval_pct"] == dy.clip_interval([counts[n] for n in sorted(names) if splits[n] == "train"],
                                                            min_clips=2)
    assert got["all"]["interval_pct"] != dy.clip_interval([counts[n] for n in sorted(names)], min_clips=2)


def test_a_clip_that_failed_before_ingest_counts_in_the_yield(bench3, tmp_path):
    """A clip whose cameras (SfM) failed has runs but no ``clips`` row: its objects in view left the
    yield's denominator and it was said "not run", raising the yield; they count now, none yielded,
    and it is said to have failed at cameras."""
    import bench.dataset_yield as dy
    from bench.benchmark import unfinished_clips

    wh, clips = bench3
    shutil.copytree(wh.root, tmp_path / "w")
    copy = Warehouse(tmp_path / "w")
    failed = clips[2][0]
    bench = wh.root.parent / "bench"
    (before,) = (s["modes"]["scan2cad-class"] for s in dy.dataset_yield(bench, copy)["splits"].values())  # one split
    for table in (tmp_path / "w" / "tables").iterdir():
        shutil.rmtree(table / f"clip={failed}", ignore_errors=True)
    copy.write("runs", failed, table_rows("runs", [{"clip": failed, "run_id": "r9", "stage": "cameras", "status": "failed"}]))
    assert unfinished_clips([c[0] for c in clips], copy) == {failed: "failed at cameras"}
    after = dy.dataset_yield(bench, copy)["splits"]
    assert after["all"]["clips"] == 3 and after["train"]["clips"] == 1  # its split: the benchmark's, by its place
    assert after["all"]["modes"]["scan2cad-class"]["expected_objects"] == before["expected_objects"]
    lost = len(_in_view(clips[2][1]) & {o.track_id for o in clips[2][2]})
    assert lost and after["all"]["modes"]["scan2cad-class"]["yielded_objects"] == before["yielded_objects"] - lost


def test_a_clip_whose_verification_waits_is_not_in_the_dataset(bench3, tmp_path):
    """As `export official` chooses them: a clip whose newest verification run waits for verdicts
    (its poses unjudged) is left out of the figures and named, not counted as objects not posed."""
    from fuzz.harness import run_cli

    wh, clips = bench3
    shutil.copytree(wh.root, tmp_path / "w")
    copy = Warehouse(tmp_path / "w")
    waiting = clips[1][0]
    copy.write("runs", waiting, table_rows("runs", [*copy.read("runs", [waiting]).to_pylist(), {
        "clip": waiting, "run_id": "r9verification", "stage": "verification", "status": "paused", "duration_s": 0.0}]))
    choice = select_clips(copy)
    assert choice.chosen == sorted(c[0] for c in clips if c[0] != waiting) and choice.unfinished == [waiting]
    result = run_cli("-w", str(copy.root), "stats", "--json")
    assert result.code == 0, result.stderr
    figures = json.loads(result.stdout)
    assert figures["scenes"] == 2 and figures["posed_objects"] == sum(len(c[2]) for c in clips if c[0] != waiting)
    assert result.stderr.strip() == (f"warning: left out 1 clip(s) not verified as they stand (verification not completed, or a task waits for "
                                     f"people since): {waiting}")


def test_a_report_never_replaces_pages_and_pictures_it_did_not_write(tmp_path):
    """`stats --html` into a folder holding an ``index.html``, ``img/`` or ``clips/`` of something
    else (a web site) is refused in one line, before any figure, and the folder is left as it was
    (they were replaced whole: the site's pictures deleted); beside an earlier report, or beside
    other files only, it writes."""
    from fuzz.harness import assert_clean_error, run_cli

    wh = Warehouse(tmp_path / "w")
    select_clips(wh)  # a warehouse with no clip: its catalog made
    site = tmp_path / "site"
    (site / "img").mkdir(parents=True)
    (site / "img" / "logo.png").write_bytes(b"precious")
    (site / "index.html").write_text("<title>my site</title>")
    (tmp_path / "page").mkdir()
    (tmp_path / "page" / "index.html").write_text("<title>my page</title>")
    for folder, held in ((site, "img"), (tmp_path / "page", "index.html")):
        result = run_cli("-w", str(wh.root), "stats", "--html", str(folder))
        assert_clean_error(result, mentions=f"error: {folder}: holds {held!r}, which a report replaces")
        assert result.stdout == ""
        assert (folder / "index.html").read_text().startswith("<title>my ")
    assert (site / "img" / "logo.png").read_bytes() == b"precious"
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "stats.json").write_text("{}")  # what the scheduled report writes beside it
    for folder in ("other", "other"):  # the second time beside the first report
        result = run_cli("-w", str(wh.root), "stats", "--html", str(tmp_path / folder))
        assert result.code == 0, result.stderr
    assert sorted(p.name for p in (tmp_path / "other").iterdir()) == ["clips", "img", "index.html", "stats.json"]


def test_a_report_killed_while_moving_in_does_not_block_the_next(tmp_path):
    """SIGKILL (or a power loss) while `stats --html` moves its report into an existing empty folder
    leaves ``clips/`` moved there and no ``index.html``: every later report was refused ("holds
    'clips', which a report replaces, and no earlier report") until the user removed it by hand.
    The next report removes what was moved in, names it on stderr, and writes."""
    from fuzz.harness import killed_at_move, run_cli

    wh = Warehouse(tmp_path / "w")
    select_clips(wh)  # a warehouse with no clip: its catalog made
    out = tmp_path / "report"
    out.mkdir()
    done = killed_at_move(out / "img", "-w", str(wh.root), "stats", "--html", str(out))  # after clips/ is moved in
    assert done.returncode == -9, done.stderr
    assert (out / "clips").is_dir() and not (out / "img").exists() and not (out / "index.html").exists()
    [left] = tmp_path.glob(".report.*.tmp")
    result = run_cli("-w", str(wh.root), "stats", "--html", str(out))
    assert result.code == 0, result.stderr
    assert result.stderr.splitlines() == [
        f"warning: removed clips from {out}: an earlier export into it was stopped while moving them in",
        f"warning: removed {left}: the temporary folder of an earlier export that did not finish"]
    assert sorted(p.name for p in out.iterdir()) == ["clips", "img", "index.html"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report", "w"]
