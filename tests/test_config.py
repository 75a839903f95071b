"""Config validation: every error names the file, section and key; hashes track values only."""

import dataclasses

import pytest

from cadestate.config import (
    SECTIONS, Config, ConfigError, config_from_dict, describe_defaults, load_config, to_toml,
)


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
    ],
)
def test_bad_config_names_the_key(data, message):
    with pytest.raises(ConfigError) as e:
        config_from_dict(data, "my.toml")
    assert str(e.value).startswith("my.toml: ") and message in str(e.value)


def test_section_hash_depends_on_values_only():
    a = config_from_dict({"frames": {"jpeg_quality": 90, "image_format": "jpg"}})
    b = config_from_dict({"frames": {"image_format": "jpg", "jpeg_quality": 90}})
    c = config_from_dict({"frames": {"jpeg_quality": 91}})
    assert a.section_hash("frames") == b.section_hash("frames") != c.section_hash("frames")
    assert a.section_hash("ingest") == c.section_hash("ingest") == Config().section_hash("ingest")
    assert Config().section_hash("frames") != Config().section_hash("ingest")


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
