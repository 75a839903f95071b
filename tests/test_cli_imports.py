"""Commands that only read import only what they need (issue "Fast commands"): no Prefect, nothing
of bench/, no pandas, and no pyarrow for ``--help``, ``labels schema``, ``sql`` and ``tables``.
Each command runs through the real entry point in a fresh process, which then lists sys.modules."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import table_rows
from warehouse import Warehouse

RUNNER = """
import json, sys
from cadestate.cli import main
sys.argv = ["cadestate", *json.loads(sys.argv[1])]
try:
    main()
except SystemExit as e:
    code = e.code or 0
else:
    code = 0
with open({out!r}, "w") as f:
    json.dump({{"code": code, "modules": sorted(sys.modules)}}, f)
"""

HEAVY = ("prefect", "bench", "pandas", "pyarrow")


def loaded(args: list[str], out: Path) -> tuple[int, set[str]]:
    """Exit code of the command ``args`` and the top-level packages its process had imported."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    done = subprocess.run([sys.executable, "-c", RUNNER.format(out=str(out)), json.dumps(args)],
                          capture_output=True, text=True, env=env)
    assert done.returncode == 0, done.stderr
    result = json.loads(out.read_text())
    return result["code"], {m.split(".")[0] for m in result["modules"]}


@pytest.fixture(scope="module")
def read_wh(tmp_path_factory) -> Path:
    """A warehouse with a frame and a stage run of one clip."""
    wh = Warehouse(tmp_path_factory.mktemp("imports") / "w")
    wh.write("frames", "c", table_rows("frames", [{"clip": "c"}]))
    wh.write("runs", "c", table_rows("runs", [{"clip": "c", "stage": "cameras", "status": "completed"}]))
    return wh.root


@pytest.mark.parametrize("command, absent, present", [
    (["--help"], HEAVY, ("typer",)),
    (["labels", "schema", "correspondences"], HEAVY, ("schemas",)),
    (["labels", "schema"], HEAVY, ("schemas",)),
    (["config", "show"], HEAVY, ("cadestate",)),
    (["sql", "SELECT count(*) FROM frames"], HEAVY, ("duckdb",)),
    (["sql", "SELECT count(*) FROM poses"], HEAVY, ("duckdb",)),  # an empty table: its schema file is current
    (["tables"], HEAVY, ("warehouse",)),  # DuckDB counts the rows only when a file came since the last count
    (["tables", "frames"], ("prefect", "bench", "pandas"), ("pyarrow",)),  # the columns: the pyarrow schema
    (["status"], ("prefect", "bench"), ("tasks",)),
])
def test_read_only_commands_import_only_what_they_need(read_wh, tmp_path, command, absent, present):
    code, modules = loaded(["-w", str(read_wh), *command], tmp_path / "modules.json")
    assert code == 0
    assert sorted(set(absent) & modules) == []
    assert set(present) <= modules  # the probe sees what the command imported


HEAVIER = ("pandas", "av", "torch", "onnxruntime", "prefect", "trimesh", "scipy", "pyarrow", "pydantic")


@pytest.mark.parametrize("command", [
    ["--help"], ["labels", "schema", "correspondences"], ["config", "show"], ["sql", "SELECT count(*) FROM frames"],
    ["tables"],
])
def test_budgeted_commands_import_no_heavy_module(read_wh, tmp_path, command):
    """The commands with a time budget (bench/cli_bench.py) import none of the heavy modules, nor
    Pydantic, which Typer's conversion of values would import (cadestate.cli.params)."""
    code, modules = loaded(["-w", str(read_wh), *command], tmp_path / "modules.json")
    assert code == 0
    assert sorted(set(HEAVIER) & modules) == []


def test_status_reads_runs_without_pyarrow_dataset(read_wh, tmp_path):
    """`status` of a warehouse whose stages need no input digest reads its runs through DuckDB:
    no pyarrow.dataset (which imports pandas), no PyAV, no model runtime."""
    code, modules = loaded(["-w", str(read_wh), "status"], tmp_path / "modules.json")
    assert code == 0
    assert sorted({"pandas", "av", "torch", "onnxruntime", "prefect", "trimesh", "scipy", "pydantic"} & modules) == []


def test_status_reads_runs_again_only_when_a_run_file_came(read_wh, tmp_path):
    """`status` keeps the runs it read with the state of their files (those of every clip, and those
    of each clip named): the next `status` neither imports DuckDB nor opens a run file; a new run is
    read at once (DuckDB), then kept in turn."""
    def status(*clips: str) -> tuple[set[str], str]:
        modules = loaded(["-w", str(read_wh), "status", *clips], tmp_path / "modules.json")[1]
        env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
        return modules, subprocess.run([sys.executable, "-m", "cadestate", "-w", str(read_wh), "status", *clips],
                                       capture_output=True, text=True, env=env, check=True).stdout

    def embed_done(shown: str) -> bool:
        [line] = [line for line in shown.splitlines() if " embed " in line]
        return line.split("│")[4].strip() == "completed"  # clip, stage, last run, status

    for clips in ((), ("c",)):
        status(*clips)
        modules, shown = status(*clips)
        assert "duckdb" not in modules and not embed_done(shown)
    Warehouse(read_wh).write("runs", "c", table_rows("runs", [{"clip": "c", "stage": "embed", "status": "completed"}]))
    for clips in ((), ("c",)):
        modules, shown = status(*clips)
        assert "duckdb" in modules and embed_done(shown)
    assert (read_wh / "_cache" / "reads" / "runs" / "c.json").is_file()  # one file per clip named


def test_status_of_a_registered_clip_imports_no_stage_dependencies(tmp_path):
    """With a clip in ``clips``, `status` computes every stage's input digests: they live in light
    modules (tasks/video/inputs.py, tasks/human/inputs.py, tasks/pose/inputs.py), so no PyAV, no
    model runtime, no mesh library, no Prefect."""
    wh = Warehouse(tmp_path / "w")
    wh.write("clips", "c", table_rows("clips", [{"clip": "c", "video_sha256": "ab", "split": "val"}]))
    wh.write("runs", "c", table_rows("runs", [{"clip": "c", "run_id": f"r{i}", "stage": stage, "status": "completed"}
                                              for i, stage in enumerate(("cameras", "ingest", "frames", "tracking",
                                                                         "manual_tracks"))]))
    code, modules = loaded(["-w", str(wh.root), "status"], tmp_path / "modules.json")
    assert code == 0
    assert sorted({"av", "torch", "onnxruntime", "prefect", "trimesh", "scipy", "cv2", "PIL"} & modules) == []


def test_status_of_a_cad_library_digests_the_learned_descriptor_without_numpy(tmp_path):
    """A library's ``cad_embed`` reads the learned descriptor's file (its SHA-256 is an input):
    `status` digests it through a light module, as the detector's (no numpy)."""
    wh = Warehouse(tmp_path / "w")
    wh.write("cad_models", "lib", table_rows("cad_models", [{"library": "lib", "cad_id": "lib.a"}]))
    wh.write("runs", "lib", table_rows("runs", [{"clip": "lib", "run_id": f"r{i}", "stage": stage, "status": "completed"}
                                                for i, stage in enumerate(("cad_ingest", "cad_views", "cad_embed",
                                                                           "label_similarity"))]))
    code, modules = loaded(["-w", str(wh.root), "status"], tmp_path / "modules.json")
    assert code == 0
    assert "tasks.retrieval.descriptor" in json.loads((tmp_path / "modules.json").read_text())["modules"]
    assert sorted({"numpy", "torch", "onnxruntime", "prefect", "trimesh"} & modules) == []


def test_the_record_of_placed_inputs_imports_nothing_heavy():
    """`status` checks every clip's placed inputs (tasks/video/placed.py): from tasks/video/inputs.py
    that brought pyarrow and numpy (its schema import) into every status, 2x its CPU."""
    done = subprocess.run([sys.executable, "-c", "import sys, tasks.video.placed; "
                           "print(sorted({'pyarrow', 'numpy', 'schemas.core'} & set(sys.modules)))"],
                          capture_output=True, text=True, check=True, cwd=Path(__file__).resolve().parents[1])
    assert done.stdout.strip() == "[]"
