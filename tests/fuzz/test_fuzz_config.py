"""Fuzz `cadestate config check FILE` (and `cadestate -c FILE ingest`) with broken config files:
every generated case is refused with one `error:` line naming the file and the `[section] key` at
fault (or the TOML syntax error), and the warehouse is left unchanged.

A case is a valid configuration (some keys of some sections set to their defaults) with one thing
broken: an unknown section or key, a value of the wrong type, nan or inf, a value out of range, two
keys that contradict each other, a [detect] model that is not a fitting ONNX file, or broken TOML.
"""

from __future__ import annotations

import dataclasses
import json
import tomllib
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, reject, settings
from hypothesis import strategies as st

from cadestate.config import DESCRIPTOR_DIM, INT_RANGE, SECTIONS
from cadestate.config import DetectConfig
from fuzz.harness import assert_clean_error, count_case, run_cli, warehouse_digest
from tasks.detection.detectors import detector_path
from tasks.detection.model_inputs import detector_labels

SUITE = "config"
FIELDS = {(name, f.name): f for name, cls in SECTIONS.items() for f in dataclasses.fields(cls)}
NAME = st.text("abcdefghijklmnopqrstuvwxyz_0123456789", min_size=1, max_size=12)
Entries = dict[str, dict[str, str]]
"""section -> key -> TOML literal of its value."""


def literal(value) -> str:
    """A Python value (str, bool, int, float, list or tuple of str) as a TOML literal."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)  # nan, inf, -inf and 1e+300 are TOML too
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(map(literal, value)) + "]"
    return json.dumps(value)


def render(entries: Entries) -> str:
    """TOML text of ``entries``, sections and keys in the order given."""
    return "".join(f"[{name}]\n" + "".join(f"{k} = {v}\n" for k, v in keys.items()) + "\n"
                   for name, keys in entries.items())


@st.composite
def valid_entries(draw) -> Entries:
    """Some keys of some sections, each set to its default (a valid configuration)."""
    picked = draw(st.lists(st.sampled_from(sorted(FIELDS)), max_size=8, unique=True))
    entries: Entries = {}
    for name, key in picked:
        entries.setdefault(name, {})[key] = literal(FIELDS[name, key].default)
    return entries


def with_entry(entries: Entries, name: str, key: str, value: str) -> Entries:
    """``entries`` with ``[name] key = value`` (a literal) set, placed last in its section."""
    out = {n: {k: v for k, v in keys.items() if (n, k) != (name, key)} for n, keys in entries.items()}
    out.setdefault(name, {})[key] = value
    return out


Case = tuple[str, str]
"""TOML text of a broken config and what its error must name (after ``{file}: ``)."""


@st.composite
def unknown_name(draw, base: Entries) -> Case:
    if draw(st.booleans()):
        name = draw(NAME.filter(lambda n: n not in SECTIONS))
        return render({**base, name: {}}), f"unknown section [{name}]"
    section, key = draw(st.sampled_from(sorted(FIELDS)))
    bad = draw(NAME.filter(lambda k: (section, k) not in FIELDS))
    return render(with_entry(base, section, bad, "1")), f"[{section}] unknown key '{bad}'"


WRONG_TYPES = {  # the type a key expects -> literals of other types
    int: ['"1"', "true", "1.5", "[1]", "{ a = 1 }", "1979-05-27T07:32:00Z", "nan"],
    float: ['"0.5"', "false", "[0.5]", "{ a = 1 }", "07:32:00"],
    bool: ["1", '"true"', "0.0", "[true]"],
    str: ["1", "true", '["a"]', "{ a = 1 }", "1.5"],
    tuple: ['"chair"', "1", "[1, 2]", '["a", 1]', '[["a"]]', "{ a = 1 }"],
}


@st.composite
def wrong_type(draw, base: Entries) -> Case:
    section, key = draw(st.sampled_from(sorted(FIELDS)))
    value = draw(st.sampled_from(WRONG_TYPES[type(FIELDS[section, key].default)]))
    return render(with_entry(base, section, key, value)), f"[{section}] {key}: expected"


FLOATS = sorted(k for k, f in FIELDS.items() if type(f.default) is float)
INTS = sorted(k for k, f in FIELDS.items() if type(f.default) is int)
BOUNDED = sorted(k for k, f in FIELDS.items() if f.metadata.get("lo") is not None or f.metadata.get("hi") is not None)
CHOICES = sorted(k for k, f in FIELDS.items() if f.metadata.get("choices"))


@st.composite
def not_finite(draw, base: Entries) -> Case:
    section, key = draw(st.sampled_from(FLOATS))
    value = draw(st.sampled_from(["nan", "+nan", "-nan", "inf", "+inf", "-inf", "1e400", "-2e308", "9" * 400]))
    return render(with_entry(base, section, key, value)), f"[{section}] {key}: must be a finite number"


@st.composite
def out_of_range(draw, base: Entries) -> Case:
    kind = draw(st.sampled_from(["bound", "choice", "int64"]))
    if kind == "choice":
        section, key = draw(st.sampled_from(CHOICES))
        value = draw(NAME.filter(lambda v: v not in FIELDS[section, key].metadata["choices"]))
        return render(with_entry(base, section, key, json.dumps(value))), f"[{section}] {key}: must be one of"
    if kind == "int64":
        section, key = draw(st.sampled_from(INTS))
        value = draw(st.integers(INT_RANGE[1] + 1, 2**200) | st.integers(-(2**200), INT_RANGE[0] - 1))
        return render(with_entry(base, section, key, str(value))), f"[{section}] {key}: must fit in 64 bits"
    section, key = draw(st.sampled_from(BOUNDED))
    f = FIELDS[section, key]
    lo, hi = f.metadata.get("lo"), f.metadata.get("hi")
    low = lo is not None and (hi is None or draw(st.booleans()))
    step = draw(st.integers(1, 10**6) if type(f.default) is int else st.floats(1e-3, 1e6))
    value = type(f.default)(lo - step if low else hi + step)
    return render(with_entry(base, section, key, literal(value))), f"[{section}] {key}: must be {'>=' if low else '<='}"


@st.composite
def contradiction(draw, base: Entries) -> Case:
    kind = draw(st.sampled_from(["lr", "whitening", "classes", "template", "root"]))
    if kind == "lr":
        lr = draw(st.floats(1e-6, 0.5))
        final = draw(st.floats(lr, 1.0, exclude_min=True))
        entries = with_entry(with_entry(base, "pose", "lr", literal(lr)), "pose", "lr_final", literal(final))
        return render(entries), "[pose] lr_final: must be <= [pose] lr"
    if kind == "whitening":
        dims = draw(st.integers(DESCRIPTOR_DIM + 1, 10**6))
        return render(with_entry(base, "cad_embed", "whitening_dims", str(dims))), "[cad_embed] whitening_dims: must be <="
    if kind == "classes":
        labels = draw(st.lists(NAME, min_size=1, max_size=5, unique=True))
        extra = draw(NAME.filter(lambda n: n not in labels))
        classes = draw(st.permutations(labels[:2] + [extra]))
        entries = with_entry(with_entry(base, "detect", "labels", literal(labels)), "detect", "classes", literal(classes))
        return render(entries), f"[detect] classes: '{extra}' not in [detect] labels"
    if kind == "template":
        value = draw(st.sampled_from(["a photo", "{name}", "{", "}", "{0}{1}", "{.x}", "{!z}", "{:q}"]))
        return render(with_entry(base, "label_similarity", "template", json.dumps(value))), "[label_similarity] template: "
    value = draw(st.sampled_from(["", " ", "\t"]))
    return render(with_entry(base, "warehouse", "root", json.dumps(value))), "[warehouse] root: must not be empty"


@st.composite
def bad_model(draw, base: Entries, folder: Path) -> Case:
    kinds = ["junk", "missing", "folder"] + (["labels"] if detector_path(DetectConfig()).is_file() else [])
    kind = draw(st.sampled_from(kinds))
    if kind == "labels":  # the default detector scores as many classes as its label map names
        scored = len(detector_labels(DetectConfig()))
        labels = draw(st.lists(NAME, min_size=1, max_size=100, unique=True).filter(lambda ls: len(ls) != scored))
        return render(with_entry(base, "detect", "labels", literal(labels))), f"[detect] labels: the model scores {scored} classes"
    path = {"junk": folder / "model.onnx", "missing": folder / "absent.onnx", "folder": folder}[kind]
    if kind == "junk":
        path.write_bytes(draw(st.sampled_from([b"", b"not a model", b"\x08\x07"]) | st.binary(max_size=64)))
    return render(with_entry(base, "detect", "model", json.dumps(str(path)))), f"[detect] model: {path}"


@st.composite
def broken_toml(draw, base: Entries) -> Case:
    text = render(base)
    breakage = draw(st.sampled_from([
        "[frames]\njpeg_quality = 1\njpeg_quality = 2\n", "[frames\n", "[frames]\nkey = \"open\n", "[frames]\n= 1\n",
        "[frames]\njpeg_quality =\n", "!!!\n", "[frames]\n[frames]\n", "[frames]\njpeg_quality = 1 2\n",
        "[frames]\nimage_format = 'a\x7fb'\n", "[frames]\njpeg_quality = " + "1" * 5000 + "\n", "\x00\n"]))
    where = draw(st.sampled_from(["start", "end"]))
    broken = breakage + text if where == "start" else text + breakage
    if draw(st.booleans()):  # or a random edit of it
        at = draw(st.integers(0, len(broken)))
        broken = broken[:at] + draw(st.sampled_from(["\"", "[", "]", "=", "\n=", "{", "\\", "'''"])) + broken[at:]
    try:
        tomllib.loads(broken)
    except ValueError:
        return broken, "not valid TOML: "
    reject()  # the edit happened to leave valid TOML


@st.composite
def not_a_table(draw, base: Entries) -> Case:
    name = draw(st.sampled_from(sorted(SECTIONS)))
    value = draw(st.sampled_from(["1", '"x"', "[1]", "true"]))
    rest = {n: keys for n, keys in base.items() if n != name}
    return f"{name} = {value}\n" + render(rest), f"[{name}] must be a table of keys"


BROKEN = [unknown_name, wrong_type, not_finite, out_of_range, contradiction, bad_model, broken_toml, not_a_table]
"""Every way of breaking a configuration: each test runs every one of them on random valid bases."""


def broken_config(breakage, folder: Path):
    """``breakage`` applied to a random valid base."""
    if breakage is bad_model:
        return valid_entries().flatmap(lambda base: bad_model(base, folder))
    return valid_entries().flatmap(breakage)


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    """Where the cases write their config (and model) files."""
    return tmp_path_factory.mktemp("fuzz_config")


@pytest.mark.parametrize("breakage", BROKEN, ids=lambda s: s.__name__)
@settings(max_examples=25, derandomize=True, database=None, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(data=st.data())
def test_broken_configs_fail_config_check(small_warehouse, folder, breakage, data):
    text, names = data.draw(broken_config(breakage, folder), label="case")
    config = folder / "cadestate.toml"
    config.write_text(text)
    result = run_cli("-w", str(small_warehouse.root), "config", "check", str(config))
    assert_clean_error(result, mentions=f"error: {config}: {names}")
    assert len(result.stderr.splitlines()) == 1, result.stderr
    assert warehouse_digest(small_warehouse.root) == small_warehouse.digest
    count_case(SUITE)


@pytest.mark.parametrize("breakage", BROKEN, ids=lambda s: s.__name__)
@settings(max_examples=4, derandomize=True, database=None, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(data=st.data())
def test_broken_configs_stop_ingest_before_it_starts(small_warehouse, folder, no_runs, breakage, data):
    text, names = data.draw(broken_config(breakage, folder), label="case")
    config = folder / "cadestate.toml"
    config.write_text(text)
    w = small_warehouse
    result = run_cli("-w", str(w.root), "-c", str(config), "ingest", str(w.video), str(w.cameras), "--clip", "small_0")
    assert_clean_error(result, mentions=f"error: {config}: {names}")
    assert len(result.stderr.splitlines()) == 1, result.stderr
    assert warehouse_digest(w.root) == w.digest
    count_case(SUITE)

