"""The benchmark driver: generate (cached), run through the real flow, report with pictures."""

from __future__ import annotations

import json

import pytest

from bench.benchmark import MANIFEST, BenchmarkError, clip_sources, generate, ignore_rule, read_manifest, report, report_markdown
from bench.seeds import seed_note
from bench.walkthrough import WalkthroughSpec
from cadestate.config import Config, WarehouseConfig
from schemas.official import read_objects

SPEC = WalkthroughSpec(width=320, height=180, num_video_frames=24, sample_every=2, alone_scale=0.5)

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def benchmark(small_cad_library, tmp_path_factory):
    wh, _ = small_cad_library
    folder = tmp_path_factory.mktemp("bench")
    manifest, made = generate(folder, 5, 2, wh, SPEC, show_progress=False)
    return folder, manifest, made


def test_a_room_no_camera_walk_fits_in_is_one_error_naming_the_clip_and_writes_no_manifest(small_cad_library, tmp_path):
    with pytest.raises(BenchmarkError, match=r"clip 0 of seed 117 cannot be generated \(no collision-free camera path "
                                             r"in scene 117000\): use another --seed$"):
        generate(tmp_path, 117, 1, small_cad_library[0], SPEC, show_progress=False)
    assert not (tmp_path / MANIFEST).exists()


def test_generate_is_cached_and_named_by_seed(benchmark, small_cad_library):
    folder, manifest, made = benchmark
    assert len(made) == 2 and manifest.clips == ("bench-5-00_0", "bench-5-01_0")
    before = (folder / "bench-5-00_0" / "objects.json").read_bytes()
    again, made_again = generate(folder, 5, 2, small_cad_library[0], SPEC, show_progress=False)
    assert made_again == [] and again == manifest == read_manifest(folder)
    assert (folder / "bench-5-00_0" / "objects.json").read_bytes() == before


def test_generate_refuses_clips_there_made_with_other_frames(benchmark, small_cad_library):
    """Clip names do not say how many frames a clip has: `--frames 60` and then `--frames 276` into
    one folder kept the short clips, '0 generated now, 2 already there'."""
    import dataclasses

    folder, manifest, _ = benchmark
    before = (folder / MANIFEST).read_bytes()
    longer = dataclasses.replace(SPEC, num_video_frames=40)
    with pytest.raises(BenchmarkError, match=rf"^{folder}: clip bench-5-00_0 has 12 camera frames of 320x180 px, not "
                                             r"the 20 of 320x180 px asked for \(--frames 40\): choose a new folder, or "
                                             r"the --frames it was generated with$"):
        generate(folder, 5, 2, small_cad_library[0], longer, show_progress=False)
    assert (folder / MANIFEST).read_bytes() == before


def test_generate_refuses_a_folder_of_another_seed(benchmark, small_cad_library):
    """Another --seed into a folder of seed 5 rewrote its manifest: seed 5's clips were forgotten
    there (a report then said they were not run) and its report overwritten."""
    folder, manifest, _ = benchmark
    before = (folder / MANIFEST).read_bytes()
    with pytest.raises(BenchmarkError, match=rf"^{folder} holds the benchmark of seed 5; choose a new folder for seed 6$"):
        generate(folder, 6, 1, small_cad_library[0], SPEC, show_progress=False)
    assert (folder / MANIFEST).read_bytes() == before


def test_ignore_rule_uses_visibility_and_class(benchmark):
    from bench.benchmark import CLASS_NAMES
    from bench.ignore import DETECTABLE_CLASSES, MAX_TRUNCATED_FRACTION, MIN_VISIBLE_FRACTION

    folder, manifest, _ = benchmark
    seen = set()
    for clip in manifest.clips:
        visibility = json.loads((folder / clip / "visibility.json").read_text())
        fractions = {(f["timestamp"], o["track_id"]): (o["visible_fraction"], o["truncated_fraction"])
                     for f in visibility["frames"] for o in f["objects"]}
        gt_ignore = ignore_rule(folder, clip)
        for obj in read_objects(folder / clip / "objects.json").objects:
            coco = CLASS_NAMES[obj.cls] in DETECTABLE_CLASSES
            for entry in obj.track:
                visible, truncated = fractions[(entry.timestamp, obj.track_id)]
                expected = not coco or visible < MIN_VISIBLE_FRACTION or truncated > MAX_TRUNCATED_FRACTION
                assert gt_ignore(obj, entry) == expected
                seen.add((coco, expected))
    assert {(True, False), (True, True)} <= seen  # both outcomes occur for detectable classes


def test_detector_eval_scores_both_built_in_detectors_on_the_same_ground_truth(benchmark):
    from bench.detector_eval import DETECTORS, markdown, run
    from tasks.cad.classes import class_of_label
    from tasks.detection.model_inputs import detector_labels
    from tasks.detection.models import furniture_files, nanodet

    if not furniture_files.is_built(nanodet.default_cache_dir()):
        pytest.skip("the furniture detector is not built (run `make models`)")
    folder, manifest, _ = benchmark
    result = run([folder])[str(folder)]
    assert set(result) == set(DETECTORS) == {"coco", "furniture", "furniture, square canvas"}
    for name, r in result.items():  # each detector's boxes are scored under the classes its label map names
        nameable = {class_of_label(label) or "(other label)" for label in detector_labels(DETECTORS[name])}
        assert {c for c, v in r["per_class"].items() if v["predictions"]} <= nameable
    truth = [{c: v["ground_truth"] for c, v in r["per_class"].items() if v["ground_truth"]} for r in result.values()]
    assert truth[0] and all(t == truth[0] for t in truth)
    for r in result.values():
        assert 0 <= (r["recall"] or 0) <= r["class_agnostic_recall"] <= 1
    assert result["furniture"] != result["furniture, square canvas"]  # another canvas, other boxes
    table = "\n".join(markdown({str(folder): result}))
    assert "| coco |" in table and "| furniture |" in table and "| furniture, square canvas |" in table


def test_report_has_statistics_and_pictures(benchmark):
    folder, manifest, _ = benchmark
    result = report(folder, examples=1)
    assert result["statistics"]["clips"] == 2 and result["statistics"]["frames"] == 24
    assert (folder / result["examples"][0]).stat().st_size > 1000
    markdown = report_markdown(result)
    assert "Table 2" in markdown and result["examples"][0] in markdown
    assert markdown.splitlines()[2] == seed_note(manifest.seed)  # under the title: whether the seed may flatter
    json.dumps(result)


def test_report_says_which_clips_have_not_run_to_the_end(benchmark, tmp_path):
    """A report on a benchmark the warehouse ran in part (or not at all) gave its yield over the clips
    that ran, or no yield section at all, without a word of the clips left out."""
    import datetime as dt

    from bench.benchmark import unfinished_clips
    from conftest import table_rows
    from tasks.registry import stages_of
    from warehouse import Warehouse

    folder, manifest, _ = benchmark
    wh = Warehouse(tmp_path / "w")
    none_run = report_markdown(report(folder, examples=0, wh=wh))
    assert none_run.split("\n\n")[2] == ("**No clip of this benchmark is in the warehouse** (2 not run): `cadestate bench "
                                         "run` on it runs them; the dataset's yield leads this report once they have run.")
    first, second = manifest.clips
    wh.write("clips", first, table_rows("clips", [{"clip": first, "split": "train"}]))
    at = dt.datetime(2026, 1, 1, tzinfo=dt.timezone.utc)
    stages = [s.name for s in stages_of("clip")]
    runs = [{"clip": first, "run_id": f"r{i}", "stage": stage, "status": "completed", "started_at": at}
            for i, stage in enumerate(stages[:-1])]
    wh.write("runs", first, table_rows("runs", runs))
    assert unfinished_clips(list(manifest.clips), wh) == {first: f"never ran {stages[-1]}", second: "not run"}
    wh.write("runs", first, table_rows("runs", [{**runs[-1], "run_id": "p", "status": "paused",
                                                 "started_at": at + dt.timedelta(seconds=1)}]))
    assert unfinished_clips(list(manifest.clips), wh) == {first: f"waits at {stages[-2]}", second: "not run"}
    wh.write("runs", first, table_rows("runs", [{**runs[-1], "run_id": "c", "started_at": at + dt.timedelta(seconds=2)},
                                                {"clip": first, "run_id": "v", "stage": stages[-1], "status": "completed",
                                                 "started_at": at + dt.timedelta(seconds=3)}]))
    assert unfinished_clips(list(manifest.clips), wh) == {second: "not run"}
    assert report_markdown(report(folder, examples=0, wh=wh)).split("\n\n")[2] == (
        f"**1 of 2 clips has not run to the end**: the numbers below leave out a clip not run and count a clip that "
        f"waits as far as it got (`cadestate bench run` on the benchmark goes on): {second} not run.")


def test_simulated_labels_match_the_noise_model(benchmark, small_cad_library):
    from bench.labels import label_statistics, simulate_labels

    folder, manifest, _ = benchmark
    assert simulate_labels(folder, list(manifest.clips), small_cad_library[0], show_progress=False) == 2
    assert simulate_labels(folder, list(manifest.clips), small_cad_library[0], show_progress=False) == 0  # kept
    stats = label_statistics(folder, list(manifest.clips))
    assert stats["objects_with_correspondences"] >= 2
    assert 4 <= stats["points_per_keyframe"] <= 6
    # 2D Gaussian clicks of sigma 3 px: mean distance 3 * sqrt(pi / 2) = 3.76 px
    assert 2.5 < stats["click_error_px_mean"] < 5.0


def test_bench_run_ingests_every_clip(benchmark, tmp_path):
    from flows.annotate_clip import run_clips
    from tasks.registry import stages_of
    from warehouse import Warehouse

    folder, _, _ = benchmark
    config = Config(warehouse=WarehouseConfig(root=str(tmp_path / "w")))
    reports = run_clips(clip_sources(folder), config, show_progress=False)
    assert {r.state for r in reports} == {"completed"} and len(reports) == 2 * len(stages_of("clip"))
    frames = Warehouse(config.warehouse.root).read("frames")
    assert frames.num_rows == 24 and max(abs(v) for v in frames.column("timestamp_error_us").to_pylist()) == 0


def test_not_a_benchmark_folder(tmp_path):
    with pytest.raises(BenchmarkError, match="not a benchmark folder"):
        read_manifest(tmp_path)


@pytest.mark.parametrize(("text", "why"), [("{", "Expecting property name"), ('{"seed": 1}', "no field 'clips'"),
                                           ('{"seed": "x", "clips": [], "library": ""}', "invalid literal")])
def test_a_broken_manifest_is_one_error_naming_it(tmp_path, text, why):
    (tmp_path / MANIFEST).write_text(text)
    with pytest.raises(BenchmarkError, match=rf"^{tmp_path / MANIFEST}: not a benchmark manifest \(.*{why}"):
        read_manifest(tmp_path)


def test_a_file_as_the_benchmark_folder_is_one_error(small_cad_library, tmp_path):
    (tmp_path / "b").write_text("notes")
    with pytest.raises(BenchmarkError, match=rf"^{tmp_path / 'b'}: cannot be the benchmark folder \(File exists\)$"):
        generate(tmp_path / "b", 5, 1, small_cad_library[0], SPEC, show_progress=False)
    assert (tmp_path / "b").read_text() == "notes"


def test_cli_defaults_are_the_default_benchmark():
    import inspect

    from bench.benchmark import DEFAULT_CLIPS, DEFAULT_SEED
    from cadestate.cli.bench import bench_generate

    params = inspect.signature(bench_generate).parameters
    assert params["seed"].default == DEFAULT_SEED and params["clips"].default == DEFAULT_CLIPS


def test_simulated_annotators_answer_through_label_files(benchmark, small_cad_library, tmp_path):
    """`bench run` (its default loop): run, answer the open tasks with label files, ingest, rerun,
    until no clip waits; every label file written is valid and ingested."""
    import shutil

    from bench.simulated_labels import annotate_until_done, label_dir, open_tasks
    from flows.annotate_clip import run_clips
    from tasks.human.labels import validate_label
    from warehouse import Warehouse

    folder, manifest, _ = benchmark
    shutil.copytree(small_cad_library[0].root, tmp_path / "w")
    wh = Warehouse(tmp_path / "w")
    config = Config(warehouse=WarehouseConfig(root=str(tmp_path / "w")))
    sources = {s.clip: s for s in clip_sources(folder)}
    clips = [manifest.clips[0]]  # one clip: the test's time
    reports, waiting = annotate_until_done(
        folder, wh, clips, lambda clips: run_clips([sources[c] for c in clips], config, show_progress=False))
    assert waiting == [] and not [r for r in reports if r.state == "failed"]
    for clip in clips:
        assert open_tasks(wh, clip) == []
        for path in sorted(label_dir(folder, clip).glob("*.json")):
            validate_label(path, wh)
    files = wh.read("label_files")
    assert files.num_rows == sum(len(list(label_dir(folder, c).glob("*.json"))) for c in clips)
    if wh.read("label_tasks").num_rows:  # the tiny benchmark's detector found objects: they went all the way
        verified = wh.read("verified_poses")
        assert verified.num_rows >= 1 or wh.read("poses").num_rows == 0
    _answer_each_task_kind(folder, wh, manifest.clips[0])
    _draw_missing_objects(folder, wh, manifest.clips[0])


def _answer_each_task_kind(folder, wh, clip):
    """The human-task stages of one clip, with candidates written here (the small library has no
    retrieval embeddings): each task is answered by label files, ingested, and the stage completes."""
    import pyarrow as pa

    from bench.retrieval_bench import track_truth
    from bench.simulated_labels import answer_tasks, label_dir, open_tasks
    from cadestate.config import CadSelectionConfig, CorrespondenceTaskConfig, PoseConfig, VerificationConfig
    from schemas.official import read_objects
    from tasks.human.cad_selection import cad_selection_stage, selected_models
    from tasks.human.correspondence_task import correspondence_task_stage
    from tasks.human.verification import verification_stage
    from tasks.human.label_ingest import ingest_labels
    from tasks.pose.pose import solve_clip

    truth = track_truth(folder, wh, clip)
    objects = {o.track_id: o for o in read_objects(folder / clip / "objects.json").objects}
    models = {r["cad_id"]: r for r in wh.read("cad_models").to_pylist()}
    tracks = sorted(wh.read("tracks", [clip], columns=["track_id"]).column("track_id").to_pylist())
    assert truth, "the tiny benchmark's tracks should match ground-truth objects"
    other = sorted(models)[0]
    rows = []
    for t in tracks:
        first = objects[truth[t]].cad_id if t in truth else other
        for rank, cad_id in enumerate(dict.fromkeys([first, other]), 1):
            rows.append({"clip": clip, "track_id": t, "rank": rank, "library": models[cad_id]["library"], "cad_id": cad_id,
                         "cad_class": models[cad_id]["class"], "score": 0.5, "appearance": 0.5, "class_similarity": 0.5})
    wh.write("cad_candidates", clip, pa.Table.from_pylist(rows, schema=wh.spec("cad_candidates").schema))

    def answer(stage):
        assert stage().paused
        assert answer_tasks(folder, wh, clip)
        assert ingest_labels(wh, label_dir(folder, clip)).ok
        return stage()

    done = answer(lambda: cad_selection_stage(wh, CadSelectionConfig(), clip, "t"))
    assert not done.paused
    chosen = selected_models(wh, clip)
    assert {t for t, c in chosen.items() if c is not None} == {t for t in truth if objects[truth[t]].cad_id in models}
    assert not answer(lambda: correspondence_task_stage(wh, CorrespondenceTaskConfig(), clip, "t")).paused
    assert wh.read("correspondences", [clip]).num_rows > 0
    solve_clip(wh, PoseConfig(), clip, "t")
    assert not answer(lambda: verification_stage(wh, VerificationConfig(), clip, "t")).paused
    assert wh.read("verified_poses", [clip]).num_rows >= 1
    assert open_tasks(wh, clip) == []
    # taking a model back (a newer cad_selection label: none fits) takes the track's pose back too
    from tasks.human.cad_selection import cad_selection_task_id
    from tasks.human.labels import label_document
    from tasks.registry import clip_inputs

    posed = sorted(int(t) for t in wh.read("poses", [clip]).column("track_id").to_pylist())
    before = clip_inputs("pose", wh, clip)[0]
    doc = label_document("cad_selection", clip, cad_selection_task_id(wh, clip), [{"track_id": posed[0], "cad_id": None}],
                         annotator="t", created_at="2030-01-01T00:00:00+00:00")
    (label_dir(folder, clip) / "take-back.json").write_text(json.dumps(doc))
    assert ingest_labels(wh, label_dir(folder, clip) / "take-back.json").ok
    assert clip_inputs("pose", wh, clip)[0] != before  # the pose stage is stale
    solve_clip(wh, PoseConfig(), clip, "t")
    assert sorted(int(t) for t in wh.read("poses", [clip]).column("track_id").to_pylist()) == posed[1:]


def _draw_missing_objects(folder, wh, clip):
    """The manual-track task on the clip taken as val, with the longest matched automatic track taken
    out: the simulated annotator draws that track's object (through a label file), the stage
    completes, and track_truth maps the new manual track to the object by its boxes."""
    import pyarrow as pa

    from bench.retrieval_bench import track_truth
    from bench.simulated_labels import answer_tasks, label_dir
    from cadestate.config import DetectConfig, EmbedConfig, ManualTracksConfig
    from schemas.tracking import MANUAL_TRACK_BASE
    from tasks.human.label_ingest import ingest_labels
    from tasks.retrieval.label_similarity import detector_labels
    from tasks.human.manual_tracks import manual_tracks_stage

    members = wh.read("track_detections", [clip]).to_pylist()
    truth = track_truth(folder, wh, clip)
    gone = max(truth, key=lambda t: (sum(m["track_id"] == t for m in members), -t))
    wh.write("track_detections", clip, pa.Table.from_pylist([m for m in members if m["track_id"] != gone],
                                                            schema=wh.spec("track_detections").schema))
    cfg = ManualTracksConfig(splits=("train",))

    def stage():
        return manual_tracks_stage(wh, cfg, EmbedConfig(), detector_labels(DetectConfig()), clip, "t")

    assert stage().paused
    [path] = answer_tasks(folder, wh, clip)
    drawn = {a["source_id"]: a for a in json.loads(path.read_text())["answers"]}
    assert f"gt:{truth[gone]}" in drawn and drawn[f"gt:{truth[gone]}"]["label"] in detector_labels(DetectConfig())
    assert not set(drawn) & {f"gt:{g}" for t, g in truth.items() if t != gone}  # found objects are not drawn again
    assert ingest_labels(wh, label_dir(folder, clip)).ok
    done = stage()
    assert not done.paused and done.rows_written == sum(len(a["boxes"]) for a in drawn.values())
    manual = {g for t, g in track_truth(folder, wh, clip).items() if t >= MANUAL_TRACK_BASE}
    assert truth[gone] in manual


def test_bench_run_in_a_warehouse_without_the_benchmarks_models_is_one_line(benchmark, tmp_path):
    """A warehouse without the library the benchmark was drawn from (another -w) was a KeyError traceback
    from the simulated annotators; now one line naming a missing model and the fix, before any clip runs."""
    from typer.testing import CliRunner

    from cadestate.cli import app
    from warehouse import Warehouse

    folder, _, _ = benchmark
    result = CliRunner().invoke(app, ["-w", str(tmp_path / "w"), "bench", "run", str(folder), "--no-progress"])
    assert isinstance(result.exception, BenchmarkError)  # main() prints it as one line
    assert str(result.exception).startswith(f"{folder}: ") and "CAD model(s) of its ground truth are not in the warehouse" in str(result.exception)
    assert str(result.exception).endswith("use the warehouse it was generated from (-w), or `cadestate cad ingest` its library there")
    assert Warehouse(tmp_path / "w").partitions("clips") == []


def test_bench_run_refuses_a_cad_library_the_configuration_makes_stale(small_library_warehouse, tmp_path):
    """A warehouse whose library was embedded with another [cad_embed] (copied from elsewhere, a
    descriptor retrained since) would have its retrieval measured against descriptors the
    configuration no longer makes: tasks.status.stale_libraries names it, and `bench run` stops
    with one line naming the library and the fix, before any clip runs."""
    import dataclasses

    from typer.testing import CliRunner

    from cadestate.cli import app
    from cadestate.config import to_toml
    from conftest import warehouse_copy
    from tasks.status import stale_libraries
    from warehouse import Warehouse

    config = warehouse_copy(small_library_warehouse, tmp_path / "w")
    wh = Warehouse(config.warehouse.root)
    assert stale_libraries(wh, config) == {}
    other = dataclasses.replace(config, cad_embed=dataclasses.replace(config.cad_embed, whitening="whiten"))
    stale = stale_libraries(wh, other)
    libraries = sorted(wh.partitions("cad_models"))  # the small library's models come from several catalogues
    assert sorted(stale) == libraries and all(stale[lib][0].startswith("cad_embed: config changed") for lib in libraries)
    library = libraries[0]
    toml = tmp_path / "other.toml"
    toml.write_text(to_toml(other))
    result = CliRunner().invoke(app, ["-c", str(toml), "-w", str(wh.root), "bench", "run", str(tmp_path / "bench")])
    lines = result.output.strip().splitlines()
    assert result.exit_code == 1 and len(lines) == 1, result.output
    assert lines[0].startswith(f"CAD library {library} is stale (cad_embed: config changed")
    more = len(libraries) - 1
    assert lines[0].endswith(f"(and {more} more librar{'y' if more == 1 else 'ies'}): run `cadestate cad ingest` first")
    assert not (tmp_path / "bench").exists() and wh.partitions("clips") == []
