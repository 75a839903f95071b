"""The stage registry (tasks/registry.py): declarations found in their modules, the graph, code
digests derived from imports, and a stage added by writing one module."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from cadestate.config import Config
from tasks.registry import FUNCTION_FIELDS, ROOT, STAGES, RegistryError, _read_stage, config_hash, logic_imports, stages_markdown, stages_of

README = ROOT / "README.md"


def test_the_declarations_read_from_source_are_the_imported_ones():
    assert len(STAGES) == 16
    for s in STAGES.values():
        d = s.definition
        assert (d.name, d.section, d.scope, d.upstream, d.tables, d.description, d.extra_sections, d.after) == (
            s.name, s.section, s.scope, s.upstream, s.tables, s.description, s.extra_sections, s.after)
        assert s.functions == tuple((f, getattr(d, f).__name__) for f in FUNCTION_FIELDS if getattr(d, f) is not None)
        assert all(getattr(sys.modules[s.module], name) is getattr(d, f) for f, name in s.functions)


def test_pipeline_order_follows_the_graph():
    assert [s.name for s in stages_of("clip")] == [
        "cameras", "ingest", "frames", "detect", "embed", "tracking", "manual_tracks", "retrieval", "cad_selection",
        "correspondence_task", "pose", "verification"]
    assert [s.name for s in stages_of("library")] == ["cad_ingest", "cad_views", "cad_embed", "label_similarity"]
    placed: set[str] = set()
    for s in STAGES.values():
        assert set(s.upstream + s.after) <= placed
        placed.add(s.name)


def test_code_digest_covers_what_a_stage_imports_and_only_logic():
    tracking = logic_imports("tasks.tracking.tracking")
    assert {"tasks.tracking.partition", "tasks.tracking.partition_exact", "tasks.tracking.affinity"} <= tracking
    assert not tracking & {"tasks.stage", "tasks.registry", "cadestate.config", "cadestate.lineage"}
    assert not any(m.split(".")[0] in ("warehouse", "schemas", "flows", "bench") for s in STAGES.values()
                   for m in logic_imports(s.module))
    pose = logic_imports("tasks.pose.pose")  # imports inside functions count
    assert "tasks.human.cad_selection" in pose and "tasks.pose.solver" in pose
    assert "cadestate.render" in logic_imports("tasks.human.verification")
    assert len({s.code_hash for s in STAGES.values()}) == len(STAGES)


def test_config_hash_covers_own_and_extra_sections():
    base = Config()
    changed = replace(base, embed=replace(base.embed, batch_size=base.embed.batch_size + 1))
    assert config_hash("cad_embed", changed) != config_hash("cad_embed", base)  # [embed] is an extra section
    assert config_hash("cad_views", changed) == config_hash("cad_views", base)
    assert config_hash("detect", base) == config_hash("detect", {"detect": base.detect})
    # one key of another section: tracking reads [manual_tracks] keyframes, not its splits
    keyframes = replace(base, manual_tracks=replace(base.manual_tracks, keyframes=base.manual_tracks.keyframes + 1))
    splits = replace(base, manual_tracks=replace(base.manual_tracks, splits=("val",)))
    assert config_hash("tracking", keyframes) != config_hash("tracking", base) == config_hash("tracking", splits)
    assert config_hash("manual_tracks", splits) != config_hash("manual_tracks", base)


def test_readme_stage_tables_are_the_registry_s():
    text = README.read_text()
    for scope in ("clip", "library"):
        assert stages_markdown(scope) in text, f"README's {scope} stage table differs from `cadestate stages --markdown`"


def _project_copy(tmp_path: Path) -> Path:
    """The project's stage code (tasks/, cadestate/) copied to ``tmp_path``, where modules can be added."""
    for package in ("tasks", "cadestate"):
        shutil.copytree(ROOT / package, tmp_path / package, ignore=shutil.ignore_patterns("__pycache__", "webapp", "cli"))
    return tmp_path


def _stages_there(root: Path) -> dict[str, dict]:
    code = ("import json; from tasks.registry import STAGES; print(json.dumps({n: {'upstream': s.upstream, "
            "'code': s.code_hash, 'module': s.module} for n, s in STAGES.items()}))")
    done = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True,
                          env={"PYTHONPATH": str(root), "PATH": "/usr/bin:/bin"})
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


EXAMPLE = '''"""Stage ``track_count``: how many tracks a clip has (an example stage)."""

from cadestate.lineage import digest
from tasks.stage import StageContext, StageDef, StageOutput
from tasks.tracking.clip_tracks import clip_tracks


def _run(ctx: StageContext) -> StageOutput:
    n = len(clip_tracks(ctx.wh, ctx.unit))
    return StageOutput(0, digest("track_count", str(n)), f"{n} tracks")


STAGE = StageDef(
    name="track_count", section=None, scope="clip", upstream=("tracking",), tables=(),
    description="count the clip's tracks", run=_run,
)
'''


def test_a_stage_is_added_by_writing_one_module(tmp_path):
    root = _project_copy(tmp_path)
    before = _stages_there(root)
    assert list(before) == list(STAGES) and {n: s["code"] for n, s in before.items()} == {
        n: s.code_hash for n, s in STAGES.items()}
    (root / "tasks/tracking/track_count.py").write_text(EXAMPLE)
    after = _stages_there(root)
    assert after["track_count"]["upstream"] == ["tracking"] and after["track_count"]["module"] == "tasks.tracking.track_count"
    names = list(after)
    assert names.index("tracking") < names.index("track_count") < names.index("cad_ingest")
    assert {n: s["code"] for n, s in after.items() if n != "track_count"} == {n: s["code"] for n, s in before.items()}
    # a change to a module that only the tracking stage imports makes only it stale
    partition = root / "tasks/tracking/partition_exact.py"
    partition.write_text(partition.read_text() + "\n# changed\n")
    changed = {n for n, s in _stages_there(root).items() if s["code"] != after[n]["code"]}
    assert changed == {"tracking"}


def test_malformed_declarations_are_named(tmp_path, monkeypatch):
    import tasks.registry as registry

    def read(text: str):
        monkeypatch.setattr(registry, "_source", lambda name: text)
        return _read_stage("tasks.example")

    assert read("x = 1\n") is None
    with pytest.raises(RegistryError, match="tasks.example: declare STAGE = StageDef.*keywords"):
        read('STAGE = StageDef("a")\n')
    with pytest.raises(RegistryError, match="tasks.example: StageDef run= must name a module-level function"):
        read('STAGE = StageDef(name="a", run=lambda c: c)\n')
    with pytest.raises(RegistryError, match="tasks.example: StageDef upstream= must be a literal"):
        read('STAGE = StageDef(name="a", upstream=UP)\n')
    with pytest.raises(RegistryError, match="tasks.example: StageDef"):
        read('STAGE = StageDef(name="a")\n')  # fields missing


def test_status_inputs_import_none_of_the_stages_heavy_dependencies(tmp_path):
    """``cadestate status`` digests every stage's inputs: the functions it calls come from light
    modules (a declared function is imported from where the stage's module imports it)."""
    code = ("import sys; from cadestate.config import Config; from tasks.registry import STAGES; from warehouse import Warehouse\n"
            f"wh = Warehouse({str(tmp_path / 'w')!r})\n"
            "for s in STAGES.values(): s.config_inputs(Config()) + s.clip_inputs(wh, 'c')\n"
            "print(sorted(m for m in ('torch', 'onnxruntime', 'moderngl', 'pycolmap', 'trimesh') if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"
    assert STAGES["pose"].function("clip_inputs").__module__ == "tasks.pose.inputs"


def test_stages_are_kept_until_a_source_changes(tmp_path):
    """The registry keeps what it read (tasks/__pycache__/stage-registry.json) and serves it while
    no module of tasks/ or cadestate/ changed; a change reads the sources again."""
    root = _project_copy(tmp_path)
    first = _stages_there(root)
    kept = root / "tasks" / "__pycache__" / "stage-registry.json"
    doc = json.loads(kept.read_text())
    [record] = [r for r in doc["stages"] if r["name"] == "pose"]
    record["code_hash"] = "kept"
    kept.write_text(json.dumps(doc))
    assert _stages_there(root)["pose"]["code"] == "kept"  # served from what was kept
    checks = root / "tasks/pose/checks.py"
    checks.write_text(checks.read_text() + "\n")
    again = _stages_there(root)
    assert again["pose"]["code"] != first["pose"]["code"] and again["tracking"]["code"] == first["tracking"]["code"]
    (root / "cadestate" / "extra.py").write_text("")  # a module added anywhere in the logic packages
    kept.write_text(kept.read_text().replace(again["tracking"]["code"], "kept"))
    assert _stages_there(root)["tracking"]["code"] == again["tracking"]["code"]
