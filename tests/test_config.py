"""Config validation: every error names the file, section and key; hashes track values only."""

import dataclasses

import pytest

from cadestate.config import (
    DESCRIPTOR_DIM, SECTIONS, Config, ConfigError, config_from_dict, describe_defaults, load_config, to_toml,
)
from fuzz.harness import assert_clean_error, run_cli


def test_sections_cover_every_config_field():
    fields = [f.name for f in dataclasses.fields(Config) if f.name != "source"]
    assert list(SECTIONS) == fields
    assert all(isinstance(Config().section(n), SECTIONS[n]) for n in fields)


def test_defaults_are_valid_and_documented():
    cfg = load_config(None)
    assert cfg.frames.max_timestamp_error_us == 3000
    text = describe_defaults()
    # The documented defaults are themselves a valid config equal to the defaults.
    parsed = config_from_dict(__import__("tomllib").loads(text), "defaults")
    assert dataclasses.replace(parsed, source=None) == Config()
    assert config_from_dict(__import__("tomllib").loads(to_toml(cfg)), "x").frames == cfg.frames


@pytest.mark.parametrize(
    "data, message",
    [
        ({"framez": {}}, "unknown section [framez]"),
        ({"frames": {"jpg_quality": 90}}, "[frames] unknown key 'jpg_quality'"),
        ({"frames": {"jpeg_quality": "high"}}, "[frames] jpeg_quality: expected int, got str"),
        ({"frames": {"jpeg_quality": 101}}, "[frames] jpeg_quality: must be <= 100"),
        ({"frames": {"max_timestamp_error_us": -1}}, "[frames] max_timestamp_error_us: must be >= 0"),
        ({"frames": {"image_format": "gif"}}, "[frames] image_format: must be one of 'jpg', 'png'"),
        ({"ingest": {"link_inputs": 1}}, "[ingest] link_inputs: expected bool, got int"),
        ({"prefect": {"task_runner": "ray"}}, "[prefect] task_runner: must be one of"),
        ({"frames": 3}, "[frames] must be a table"),
        ({"detect": {"score_threshold": float("nan")}}, "[detect] score_threshold: must be a finite number, got nan"),
        ({"pose": {"alpha": float("inf")}}, "[pose] alpha: must be a finite number, got inf"),
        ({"tracking": {"bias": float("-inf")}}, "[tracking] bias: must be a finite number, got -inf"),
        ({"pose": {"beta": 10**400}}, "[pose] beta: must be a finite number, got 1000000000"),
        ({"frames": {"seek_threshold_us": 2**63}}, "[frames] seek_threshold_us: must fit in 64 bits"),
        ({"cad_views": {"seed": -(2**63) - 1}}, "[cad_views] seed: must fit in 64 bits"),
        ({"frames": {"seek_threshold_us": 16**5000}}, "[frames] seek_threshold_us: must fit in 64 bits, got <int too large to show>"),
        ({"pose": {"lr": 0.01, "lr_final": 0.02}}, "[pose] lr_final: must be <= [pose] lr (0.01), got 0.02"),
        ({"pose": {"lr_final": 0.5}}, "[pose] lr_final: must be <= [pose] lr (0.02)"),
        ({"cameras": {"fov_min_deg": 60.0, "fov_max_deg": 60.0}}, "[cameras] fov_min_deg: must be < [cameras] fov_max_deg (60.0), got 60.0"),
        ({"cameras": {"max_focal_change": 0.0}}, "[cameras] max_focal_change: must be >= 0.001"),
        ({"cad_embed": {"whitening_dims": DESCRIPTOR_DIM + 1}}, "[cad_embed] whitening_dims: must be <= 768, got 769"),
        ({"label_similarity": {"template": "a photo of a {name}"}},
         "[label_similarity] template: not a format string with one '{}' for the name (KeyError: 'name')"),
        ({"label_similarity": {"template": "a photo"}}, "[label_similarity] template: must contain '{}', where the name goes"),
        ({"label_similarity": {"template": "{"}}, "[label_similarity] template: not a format string"),
        ({"warehouse": {"root": " "}}, "[warehouse] root: must not be empty"),
        ({"warehouse": {"root": "a\0b"}}, "[warehouse] root: must not hold a NUL character"),  # a traceback, exit 1
        ({"schedule": {"inbox": ""}}, "[schedule] inbox: must not be empty"),  # was the folder serve ran in
        ({"schedule": {"labels_inbox": ""}}, "[schedule] labels_inbox: must not be empty"),
        ({"schedule": {"report": ""}}, "[schedule] report: must not be empty"),
        ({"embed": {"crop_size": 100}}, "[embed] crop_size: must be a multiple of 32"),  # it failed at the embed stage
        ({"a\nb": {}}, "unknown section ['a\\nb']"),
        ({"detect": {"classes": [1] * 1000}}, "[detect] classes: expected a list of strings, got [" + "1, " * 19 + "1,..."),
        ({"schedule": {"inbox_cron": "bad cron"}}, "[schedule] inbox_cron: not a cron string"),
        ({"schedule": {"labels_cron": "61 * * * *"}}, "[schedule] labels_cron: not a cron string"),
        ({"schedule": {"report_cron": "R 3 * * *"}}, "[schedule] report_cron: random (R) and hashed (H) cron fields"),
        ({"schedule": {"inbox_split": "vall"}}, "[schedule] inbox_split: must be one of 'train', 'val', 'test' (the "
                                                "splits of the dataset and [manual_tracks] splits), got 'vall'"),
    ],
)
def test_bad_config_names_the_key(data, message):
    with pytest.raises(ConfigError) as e:
        config_from_dict(data, "my.toml")
    assert str(e.value).startswith("my.toml: ") and message in str(e.value)


def test_an_inbox_split_of_the_manual_track_splits_is_known():
    cfg = config_from_dict({"manual_tracks": {"splits": ["dev"]}, "schedule": {"inbox_split": "dev"}})
    assert cfg.schedule.inbox_split == "dev"


def test_section_hash_depends_on_values_only():
    a = config_from_dict({"frames": {"jpeg_quality": 90, "image_format": "jpg"}})
    b = config_from_dict({"frames": {"image_format": "jpg", "jpeg_quality": 90}})
    c = config_from_dict({"frames": {"jpeg_quality": 91}})
    assert a.section_hash("frames") == b.section_hash("frames") != c.section_hash("frames")
    assert a.section_hash("ingest") == c.section_hash("ingest") == Config().section_hash("ingest")
    assert Config().section_hash("frames") != Config().section_hash("ingest")


def test_section_hash_is_remembered_by_value_and_type():
    """A long-lived process digests the same sections again and again: remembered, but 1, 1.0 and
    True (equal in Python) stay three digests, as their JSON differs."""
    import hashlib
    import json

    from cadestate.config import section_hash

    sections = [dataclasses.replace(Config().pose, coplanar_tol=v) for v in (1, 1.0, True)]  # equal as dicts keys would be
    fresh = [hashlib.sha256(json.dumps({"section": "pose", **{k: v for k, v in dataclasses.asdict(s).items() if k != "threads"}},
                                       sort_keys=True).encode()).hexdigest()[:16] for s in sections]
    assert len(set(fresh)) == 3
    for _ in range(2):
        assert [section_hash("pose", s) for s in sections] == fresh


def test_a_model_file_counts_by_its_bytes_not_by_where_it_is(tmp_path, monkeypatch):
    """``[detect] model = "models/det.onnx"`` in two project folders holding the same file (a project
    moved, another machine, a command run from elsewhere): its path, made absolute, was in the
    section's digest and every clip's detection ran again. The bytes count (the detect stage's
    inputs), whether the path is given relative or absolute (a Dask worker gets it absolute)."""
    from cadestate.config import absolute_paths
    from tasks.detection.model_inputs import model_file_inputs

    config = config_from_dict({"detect": {"model": "models/det.onnx"}})
    seen = []
    for folder, data in (("a", b"weights"), ("b", b"weights"), ("c", b"other weights")):
        (tmp_path / folder / "models").mkdir(parents=True)
        (tmp_path / folder / "models" / "det.onnx").write_bytes(data)
        monkeypatch.chdir(tmp_path / folder)
        assert absolute_paths(config).section_hash("detect") == config.section_hash("detect")
        seen.append((config.section_hash("detect"), model_file_inputs(config)))
    assert seen[0] == seen[1] and seen[2][0] == seen[0][0] and seen[2][1] != seen[0][1]
    assert config.section_hash("detect") != Config().section_hash("detect")  # a file, not the built-in detector


def test_keys_that_only_say_how_to_run_leave_the_digest_alone():
    """Threads, workers and input links change no result: changing them reruns no stage."""
    from cadestate.config import runtime_keys

    c = Config()
    for name, key, value in [("detect", "threads", 7), ("embed", "threads", 7), ("pose", "threads", 3),
                             ("cameras", "workers", 5), ("cad_ingest", "workers", 5), ("ingest", "link_inputs", False),
                             ("cad_ingest", "source", "lib1")]:  # where to look: the items are digested (a re-ingest each)
        assert key in runtime_keys(c.section(name))
        changed = dataclasses.replace(c, **{name: dataclasses.replace(c.section(name), **{key: value})})
        assert changed.section_hash(name) == c.section_hash(name), (name, key)
    assert "threads" not in runtime_keys(c.cameras)  # SfM's mapping threads do change the cameras
    assert dataclasses.replace(c, cameras=dataclasses.replace(c.cameras, threads=2)).section_hash("cameras") != c.section_hash("cameras")


def test_load_file_env_and_errors(tmp_path, monkeypatch):
    f = tmp_path / "c.toml"
    f.write_text("[frames]\njpeg_quality = 80\n")
    assert load_config(f).frames.jpeg_quality == 80
    monkeypatch.setenv("CADESTATE_CONFIG", str(f))
    monkeypatch.setenv("CADESTATE_WAREHOUSE", str(tmp_path / "w"))
    cfg = load_config()
    assert cfg.frames.jpeg_quality == 80 and cfg.warehouse.root == str(tmp_path / "w")
    f.write_text("[frames\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(f)
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(tmp_path / "missing.toml")


def test_whitening_dims_bound_is_the_descriptor_size():
    from tasks.detection.models.embedder import DIM

    assert DESCRIPTOR_DIM == DIM


def test_unreadable_and_odd_files(tmp_path, monkeypatch):
    f = tmp_path / "c.toml"
    f.write_bytes("\ufeff[frames]\njpeg_quality = 80\n".encode())  # a BOM, as Windows editors write
    assert load_config(f).frames.jpeg_quality == 80
    f.write_text("[frames]\njpeg_quality = " + "1" * 5000 + "\n")  # more digits than Python reads
    with pytest.raises(ConfigError, match="c.toml: not valid TOML: Exceeds the limit"):
        load_config(f)
    monkeypatch.setattr(type(f), "read_text", lambda *a, **k: (_ for _ in ()).throw(PermissionError(13, "Permission denied")))
    with pytest.raises(ConfigError, match="c.toml: cannot read config file: Permission denied"):
        load_config(f)


def test_config_check_checks_the_detect_model(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text('[detect]\nmodel = "coco"\nclasses = ["sofa"]\n')  # COCO-80 says "couch"
    assert_clean_error(run_cli("config", "check", str(f)),
                       mentions=f"{f}: [detect] classes: 'sofa' not in the label map of [detect] model = 'coco'")
    (tmp_path / "m.onnx").write_bytes(b"not a model")
    f.write_text(f'[detect]\nmodel = "{tmp_path / "m.onnx"}"\n')
    assert_clean_error(run_cli("config", "check", str(f)), mentions=f"{f}: [detect] model: {tmp_path / 'm.onnx'}: not an ONNX model")
    f.write_text("[detect]\nscore_threshold = nan\n")
    assert_clean_error(run_cli("config", "check", str(f)), mentions="[detect] score_threshold: must be a finite number, got nan")
    f.write_text("[detect]\nscore_threshold = 0.5\n")
    result = run_cli("config", "check", str(f))
    assert result.code == 0 and f"{f}: ok" in result.stdout
    # a class no CAD model has: taken and never matched, it left chairs out of the up-axis term
    f.write_text('[pose]\nupright_classes = ["Chair", "sofa"]\n')
    assert_clean_error(run_cli("config", "check", str(f)),
                       mentions=f"{f}: [pose] upright_classes: 'Chair' is no class a CAD model has (the classes: bathtub, ")


CRON_STRINGS = ["*/10 * * * *", "0 3 * * *", "@daily", "@hourly", "0 3 * * mon-fri", "0 0 L * *", "0 0 * * 1#2",
                "*/5 * * * * 30", "bad cron", "61 * * * *", "* * * *", "0 24 * * *", "R 3 * * *", "0 r * * *",
                "H 3 * * *", "", "0 0 31 2 *", "*/0 * * * *", "0 0 1 jan,jul *", "R/10 * * * *", "0 h/2 * * *",
                "0 0 * * thu", "0 0 * * mon-fri,sun"]


STRICTER = {"*/5 * * * * 30": "6 fields, not five", "0 3 * * * *": "6 fields, not five",
            "0 0 31 2 *": "names no date that exists", "R/10 * * * *": "random (R) and hashed (H)"}
"""Cron strings Prefect takes that misbehave on its server: a sixth field is seconds (one schedule
ran 60 times a minute), a date that never comes makes the scheduler log an error every loop, and a
random field with a step draws new minutes on each scheduler loop (runs at irregular times)."""


@pytest.mark.parametrize("value", CRON_STRINGS)
def test_cron_keys_are_checked_as_prefect_checks_them(value):
    """cadestate.cron answers as Prefect's own validator does (which `cadestate serve` would hit
    with a traceback), without importing Prefect; and refuses what misbehaves on the server (STRICTER)."""
    from prefect._internal.schemas.validators import validate_cron_string

    from cadestate.cron import cron_problem

    try:
        validate_cron_string(value)
        prefect_ok = True
    except ValueError:
        prefect_ok = False
    assert (cron_problem(value) is None) == (prefect_ok and value not in STRICTER)


@pytest.mark.parametrize("value", sorted(STRICTER))
def test_cron_strings_prefect_takes_but_runs_wrong_are_refused(value):
    from cadestate.cron import cron_problem

    assert STRICTER[value] in cron_problem(value)


def test_loading_a_schedule_does_not_import_prefect(tmp_path):
    import subprocess
    import sys

    (tmp_path / "c.toml").write_text('[schedule]\ninbox_cron = "0 3 * * *"\n')
    code = ("import sys; from cadestate.config import load_config; "
            f"load_config({str(tmp_path / 'c.toml')!r}); assert 'prefect' not in sys.modules, 'prefect imported'")
    subprocess.run([sys.executable, "-c", code], check=True)
