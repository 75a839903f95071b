"""The detector's model file as ``detect`` digests it (tasks/detection/model_inputs.py): its SHA-256,
kept with the file's inode, size and times so that ``cadestate status`` does not hash 15 MB per
call, and hashed again as soon as the file changes."""

from __future__ import annotations

import hashlib
import os

from cadestate.config import DetectConfig
from tasks.detection.model_inputs import default_cache_dir, model_fingerprint


def test_the_kept_digest_serves_until_the_file_changes(tmp_path, monkeypatch):
    monkeypatch.setenv("CADESTATE_MODELS", str(tmp_path / "models"))
    model = tmp_path / "mine.onnx"
    model.write_bytes(b"first model")
    cfg = DetectConfig(model=str(model))
    assert model_fingerprint(cfg) == hashlib.sha256(b"first model").hexdigest()
    [kept] = (default_cache_dir() / ".digests").iterdir()
    stamp, _ = kept.read_text().split("\n")[:2]
    kept.write_text(f"{stamp}\n{'0' * 64}\n")
    assert model_fingerprint(cfg) == "0" * 64  # served from what was kept: nothing changed
    model.write_bytes(b"other model")  # same size, another inode
    assert model_fingerprint(cfg) == hashlib.sha256(b"other model").hexdigest()
    with open(model, "r+b") as f:  # rewritten in place, its modification time set back
        f.write(b"OTHER")
    st = model.stat()
    os.utime(model, ns=(st.st_atime_ns, st.st_mtime_ns - 10**9))
    assert model_fingerprint(cfg) == hashlib.sha256(b"OTHER model").hexdigest()


def test_a_missing_model_has_no_digest_and_an_unwritable_cache_costs_nothing(tmp_path, monkeypatch):
    (tmp_path / "models").write_text("not a folder")
    monkeypatch.setenv("CADESTATE_MODELS", str(tmp_path / "models"))
    assert model_fingerprint(DetectConfig(model=str(tmp_path / "none.onnx"))) == ""
    model = tmp_path / "mine.onnx"
    model.write_bytes(b"a model")
    assert model_fingerprint(DetectConfig(model=str(model))) == hashlib.sha256(b"a model").hexdigest()


def test_the_models_folder_of_the_environment_takes_a_tilde(tmp_path, monkeypatch):
    """$CADESTATE_MODELS='~/models' was a folder named '~' in the current one (the detect stage then
    asked for `make models` though they were there); $CADESTATE_SH3D_DIR expands it."""
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.setenv("CADESTATE_MODELS", "~/models")
    assert default_cache_dir() == tmp_path / "models"
