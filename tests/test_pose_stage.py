"""The ``pose`` stage (tasks/pose/pose.py): warehouse in, ``poses`` out; wiring into registry, config, bench."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from bench.labels import correspondence_rows
from cadestate.config import Config, PoseConfig, config_from_dict, section_hash
from cadestate.geometry import camera_to_world
from cadestate.lineage import table_digest
from schemas.cad import CAD_MODELS
from schemas.core import FRAMES
from schemas.pose import CORRESPONDENCES
from tasks.pose.inputs import answered_correspondences, cad_models_digest
from tasks.pose.pose import solve_clip, solver_options
from tasks.registry import STAGES, clip_inputs
from tests.test_pose_solver import K, make_object

W, H = 640, 360


def _frames(clip: str, problem) -> pa.Table:
    rows = []
    for f in range(len(problem.K)):
        Rcw, c = camera_to_world(problem.R[f], problem.t[f])
        rows.append({"clip": clip, "timestamp_us": 1000 * f, "frame_index": f, "image_path": "", "width": W, "height": H,
                     "video_time_us": 1000 * f, "timestamp_error_us": 0, "intrinsics": [K[0, 0] / W, K[1, 1] / H, K[0, 2] / W, K[1, 2] / H],
                     "K": K.ravel().tolist(), "world_to_camera_R": problem.R[f].ravel().tolist(),
                     "world_to_camera_t": problem.t[f].tolist(), "camera_to_world_R": Rcw.ravel().tolist(), "camera_center": c.tolist()})
    return pa.Table.from_pylist(rows, schema=FRAMES.schema)


def _model(cad_id: str, cls: str, symmetry: int) -> dict:
    return {"library": "lib", "cad_id": cad_id, "class": cls, "class_id": cls, "name": cad_id, "source_category": cls,
            "source": "folder", "source_path": "", "licence": "", "creator": "", "extent": [1.0, 1.0, 1.0],
            "symmetry": symmetry, "symmetry_errors": [0.0, 0.0, 0.0], "num_vertices": 8, "num_faces": 12,
            "textured": False, "mesh_path": ""}


def _corr(clip: str, track: str, cad_id: str, problem, n: int | None = None) -> list[dict]:
    rows = []
    for i in range(len(problem.xy) if n is None else n):
        f = int(problem.keyframe[i])
        rows.append({"clip": clip, "track_id": track, "timestamp_us": 1000 * f, "point_index": i, "cad_id": cad_id,
                     "point_2d": (problem.xy[i] / [W, H]).tolist(), "point_3d": problem.xyz[i].tolist(),
                     "is_mirrored": problem.mirrored})
    return rows


@pytest.fixture
def posed_clip(wh):
    problem, gt = make_object(2, mirrored=True, symmetry=2, swap=True)
    wh.write("frames", "c1", _frames("c1", problem))
    wh.write("cad_models", "lib", pa.Table.from_pylist([_model("lib.box", "table", 2)], schema=CAD_MODELS.schema))
    rows = _corr("c1", "1", "lib.box", problem) + _corr("c1", "2", "lib.unknown", problem) + _corr("c1", "3", "lib.box", problem, 4)
    wh.write("correspondences", "c1", pa.Table.from_pylist(rows, schema=CORRESPONDENCES.schema))
    return wh, problem, gt


def test_stage_writes_one_pose_per_track(posed_clip):
    wh, problem, (T, q, s) = posed_clip
    cfg = PoseConfig(proportion_prior=0.0)  # free scales: exact clicks, the exact pose
    out = solve_clip(wh, cfg, "c1", "run")
    poses = {r["track_id"]: r for r in wh.read("poses", ["c1"]).to_pylist()}
    assert out.rows_written == 3 and "1 of 3" in out.message
    ok = poses["1"]
    assert ok["status"] == "ok" and ok["is_mirrored"] and ok["symmetry"] == 2 and ok["upright"] and ok["class"] == "table"
    assert np.linalg.norm(np.array(ok["translation"]) - T) < 1e-3
    assert np.allclose(ok["scale"], s, rtol=1e-3)
    assert len(ok["keyframe_error_px"]) == ok["num_keyframes"] == 4 and max(ok["keyframe_error_px"]) < 0.01
    assert ok["config_hash"] == section_hash("pose", cfg)
    assert ok["floor_prior"] == "no_floor" and ok["floor_height"] is None  # a table, alone in its clip
    assert poses["2"]["floor_prior"] == "none" and ok["loss_floor"] == 0.0
    assert poses["2"]["status"] == "unknown_cad" and poses["2"]["translation"] is None
    assert poses["3"]["status"] == "too_few_points" and poses["3"]["rotation"] is None


def test_clip_without_correspondences_writes_an_empty_partition(wh):
    out = solve_clip(wh, PoseConfig(), "empty", "run")
    assert out.rows_written == 0 and "no correspondences" in out.message
    assert "empty" in wh.partitions("poses") or wh.read("poses", ["empty"]).num_rows == 0


def test_changed_correspondences_change_the_inputs_hash(posed_clip):
    wh, problem, _ = posed_clip
    before = clip_inputs("pose", wh, "c1")
    corr = answered_correspondences(wh, "c1")
    assert before == [table_digest(corr), cad_models_digest(wh, corr)]
    rows = wh.read("correspondences", ["c1"]).to_pylist()
    rows[0]["point_2d"] = [0.5, 0.5]
    wh.write("correspondences", "c1", pa.Table.from_pylist(rows, schema=CORRESPONDENCES.schema))
    assert clip_inputs("pose", wh, "c1") != before


def test_changed_model_facts_change_the_inputs_hash(posed_clip):
    """The class and symmetry the solver uses come from cad_models: a change there re-solves the
    clip (lineage), a change to a model the clip does not use does not."""
    wh, problem, _ = posed_clip
    before = cad_models_digest(wh, answered_correspondences(wh, "c1"))
    other = [_model("lib.box", "table", 2), _model("lib.other", "chair", 1)]
    wh.write("cad_models", "lib", pa.Table.from_pylist(other, schema=CAD_MODELS.schema))
    assert cad_models_digest(wh, answered_correspondences(wh, "c1")) == before  # lib.other is not referenced by c1
    wh.write("cad_models", "lib", pa.Table.from_pylist([_model("lib.box", "table", 4)], schema=CAD_MODELS.schema))
    assert cad_models_digest(wh, answered_correspondences(wh, "c1")) != before
    wh.write("cad_models", "lib", pa.Table.from_pylist([_model("lib.box", "cabinet", 2)], schema=CAD_MODELS.schema))
    assert cad_models_digest(wh, answered_correspondences(wh, "c1")) != before
    assert clip_inputs("pose", wh, "c1")[1] == cad_models_digest(wh, answered_correspondences(wh, "c1"))


def test_registry_and_config():
    from tasks.cad.classes import CLASSES

    assert STAGES["pose"].upstream == ("frames",) and STAGES["pose"].tables == ("poses",)
    assert set(PoseConfig().upright_classes) == {c.name for c in CLASSES if c.upright}
    cfg = config_from_dict({"pose": {"alpha": 0, "upright_classes": ["chair"], "starts": 2}})
    assert cfg.pose.alpha == 0.0 and cfg.pose.upright_classes == ("chair",)
    assert solver_options(cfg.pose).starts == 2 and Config().section_hash("pose") != cfg.section_hash("pose")


def test_bench_labels_map_onto_correspondences():
    labels = {"clip_name": "c", "objects": [{"track_id": "4", "cad_id": "lib.x", "correspondences": [
        {"frame_index": 0, "timestamp": 5, "is_mirrored": True, "coplanar": False, "symmetry_deg": 0.0,
         "correspondences": [{"2d": [0.1, 0.2], "3d": [1.0, 2.0, 3.0]}, {"2d": [0.3, 0.4], "3d": [4.0, 5.0, 6.0]}]}]}]}
    rows = correspondence_rows(labels)
    table = pa.Table.from_pylist(rows, schema=CORRESPONDENCES.schema)
    assert table.num_rows == 2 and rows[1]["point_index"] == 1 and rows[1]["point_3d"] == [4.0, 5.0, 6.0]
    assert rows[0]["is_mirrored"] and rows[0]["timestamp_us"] == 5
