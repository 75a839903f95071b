"""CAD library: sources, canonical frame, bad input, views, the official export."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh

from cadestate.config import CadIngestConfig, CadViewsConfig
from cadestate.geometry import project
from cadestate.render import Instance, Renderer, RenderMesh, object_to_world
from tasks.cad.classes import BY_NAME, CLASSES, classify
from tasks.cad.export import ExportError, export_official, triangle_soup
from tasks.cad.ingest import CadItemError, ingest_library
from tasks.cad.sources import (
    CadSourceError, class_of_category, default_source, folder_items, guess_kind, items_digest, load_item, read_java_properties,
    shapenet_items, source_items, sweethome3d_items,
)
from tasks.cad.views import render_library, view_camera, viewpoints
from warehouse import Warehouse

SH3D = default_source()
needs_sh3d = pytest.mark.skipif(not SH3D.is_dir(), reason="Sweet Home 3D library not fetched (make cad-library)")


def chair_like() -> trimesh.Trimesh:
    """Seat, a backrest on the -Z side, four legs: no rotational symmetry. Units: cm."""
    parts = [trimesh.creation.box((50, 5, 50), trimesh.transformations.translation_matrix((0, 45, 0))),
             trimesh.creation.box((50, 50, 5), trimesh.transformations.translation_matrix((0, 72, -22.5)))]
    parts += [trimesh.creation.box((4, 45, 4), trimesh.transformations.translation_matrix((x, 22.5, z)))
              for x in (-22, 22) for z in (-22, 22)]
    return trimesh.util.concatenate(parts)


@pytest.fixture(scope="module")
def mesh_folder(tmp_path_factory) -> Path:
    """A folder source: good meshes in four formats, plus an unreadable, an empty and a degenerate one."""
    d = tmp_path_factory.mktemp("meshes")
    trimesh.creation.box((100, 40, 60)).export(d / "crate.obj")  # cm: unit_m 0.01
    cylinder = trimesh.creation.cylinder(radius=0.3, height=0.7, sections=64)
    cylinder.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))
    cylinder.export(d / "stool.ply")
    chair_like().export(d / "chair.stl")
    trimesh.creation.box((0.8, 0.5, 0.8)).export(d / "cube.glb")
    (d / "broken.obj").write_text("v 0 0 0\nv not a number\nf 1 2 3\n")
    (d / "empty.obj").write_text("# nothing\n")
    trimesh.Trimesh([[0, 0, 0]] * 3, [[0, 1, 2]], process=False).export(d / "flat.off")
    (d / "models.csv").write_text(
        "id,class,unit_m,licence,creator\n"
        "crate,box,0.01,CC0-1.0,test\nstool,chair,1,CC0-1.0,test\nchair,chair,0.01,CC0-1.0,test\n"
        "cube,table,1,CC0-1.0,test\nbroken,chair,1,,\nempty,chair,1,,\nflat,table,1,,\nmissing,lamp,1,,\n"
    )
    return d


@pytest.fixture(scope="module")
def ingested(mesh_folder, tmp_path_factory):
    from warehouse import Warehouse

    wh = Warehouse(tmp_path_factory.mktemp("wh"))
    items = list(folder_items(mesh_folder, "testlib"))
    out = ingest_library(wh, CadIngestConfig(samples=2048), "testlib", items, "run1", show_progress=False)
    return wh, out


def test_folder_source_lists_every_row(mesh_folder):
    items = list(folder_items(mesh_folder, "testlib"))
    assert [i.item for i in items] == ["crate", "stool", "chair", "cube", "broken", "empty", "flat", "missing"]
    assert {i.cad_id for i in items} == {f"testlib.{i.item}" for i in items}
    assert items[0].cls == "other" and items[1].cls == "chair" and items[0].unit_m == 0.01
    (mesh_folder / "models.csv").rename(mesh_folder / "models.bak")
    try:  # a ShapeNet synset id names its class
        (mesh_folder / "models.csv").write_text("id,class\ncrate,04379243\nstool,Benches\n")
        assert [i.cls for i in folder_items(mesh_folder)] == ["table", "bench"]  # a plural too (it was 'other')
    finally:
        (mesh_folder / "models.bak").replace(mesh_folder / "models.csv")
    assert guess_kind(mesh_folder) == "folder"


def test_ingest_canonicalises_and_reports_bad_items(ingested):
    wh, out = ingested
    models = {m["cad_id"].split(".")[1]: m for m in wh.read("cad_models").to_pylist()}
    assert sorted(models) == ["chair", "crate", "cube", "stool"] and out.rows_written == 4
    issues = {i["item"]: i for i in wh.read("cad_issues").to_pylist()}
    assert sorted(issues) == ["broken", "crate", "empty", "flat", "missing"]
    assert all(i["severity"] == "skipped" for k, i in issues.items() if k != "crate")
    assert issues["crate"]["severity"] == "warning" and "class 'box' is none of the vocabulary's" in issues["crate"]["problem"]
    assert "not found" in issues["missing"]["problem"] and "degenerate" in issues["flat"]["problem"]
    assert "no triangles" in issues["empty"]["problem"]
    np.testing.assert_allclose(models["crate"]["extent"], [1.0, 0.4, 0.6], atol=1e-6)  # cm -> m
    np.testing.assert_allclose(models["stool"]["extent"], [0.6, 0.7, 0.6], atol=1e-3)
    for m in models.values():  # canonical: centred bounding box
        mesh = trimesh.util.concatenate(list(trimesh.load(wh.root / m["mesh_path"], force="scene").dump()))
        np.testing.assert_allclose(mesh.bounds.mean(axis=0), 0, atol=1e-6)
        np.testing.assert_allclose(mesh.bounds[1] - mesh.bounds[0], m["extent"], atol=1e-6)
    assert {k: models[k]["symmetry"] for k in models} == {"crate": 2, "cube": 4, "stool": 36, "chair": 1}
    samples = wh.read("cad_samples").to_pylist()
    assert all(len(s["points"]) == 2048 for s in samples)
    for s in samples:  # each model's own points: on its surface, so inside its centred box, reaching its sides
        half = np.asarray(models[s["cad_id"].split(".")[1]]["extent"]) / 2
        points = np.asarray(s["points"])
        assert (np.abs(points) <= half + 1e-5).all() and np.allclose(np.abs(points).max(axis=0), half, rtol=0.05)


def test_ingest_rerun_gives_the_same_result(ingested, mesh_folder):
    wh, out = ingested
    before = wh.read("cad_models")
    again = ingest_library(wh, CadIngestConfig(samples=2048), "testlib", list(folder_items(mesh_folder, "testlib")),
                           "run2", show_progress=False)
    assert again.output_hash == out.output_hash and wh.read("cad_models").equals(before)  # the same meshes at the same paths
    assert [p.name for p in (wh.root / "media" / "cad" / "testlib").iterdir()] == [before.column("mesh_path")[0].as_py().split("/")[3]]
    assert wh.read("cad_issues").num_rows == 5  # replaced, not appended


def test_shapenet_layout(tmp_path):
    for synset, model in (("03001627", "abc123"), ("04379243", "def456"), ("99999999", "zzz")):
        folder = tmp_path / synset / model / "models"
        folder.mkdir(parents=True)
        trimesh.creation.box((0.5, 0.9, 0.5)).export(folder / "model_normalized.obj")
    items = list(shapenet_items(tmp_path))
    assert [(i.cad_id, i.cls) for i in items] == [("shapenet.abc123", "chair"), ("shapenet.def456", "table"), ("shapenet.zzz", "other")]
    assert guess_kind(tmp_path) == "shapenet"
    scene, missing = load_item(items[0])
    assert missing == [] and np.allclose(scene.extents, [0.5, 0.9, 0.5])
    with pytest.raises(CadSourceError, match="no <synset>/<model_id>"):
        list(shapenet_items(tmp_path / "03001627"))


def test_a_shapenet_layout_of_named_category_folders_takes_its_classes_from_their_names(tmp_path):
    """<category>/<model_id>/models/model_normalized.obj with a category named, not a synset id (a
    lab's own collection in ShapeNet's layout): its models were none (0 models, exit 0)."""
    for category, model in (("chair", "c1"), ("Dining Tables", "t1"), ("bags", "b1"), ("03001627", "s1")):
        folder = tmp_path / category / model / "models"
        folder.mkdir(parents=True)
        trimesh.creation.box((0.5, 0.9, 0.5)).export(folder / "model_normalized.obj")
    (tmp_path / "notes" / "old").mkdir(parents=True)  # a folder of no model is no category
    assert guess_kind(tmp_path) == "shapenet"
    items = list(shapenet_items(tmp_path))
    assert [(i.cad_id, i.category, i.cls) for i in items] == [
        ("shapenet.s1", "03001627", "chair"), ("shapenet.t1", "Dining Tables", "table"), ("shapenet.b1", "bags", "other"),
        ("shapenet.c1", "chair", "chair")]


@pytest.mark.parametrize("category, cls", [("washers", "washer"), ("Displays", "display"), ("vehicles", "vehicle"),
                                           ("car", "vehicle"), ("cars", "vehicle"), ("couches", "sofa"), ("benches", "bench"),
                                           ("Dining Tables", "table"), ("04379243", "table"), ("bags", "other")])
def test_a_collections_category_names_its_class_in_the_plural_or_by_a_coco_label(category, cls):
    """A class's own name in the plural ("washers") and a COCO label ("car") came out 'other': only
    the rules (:func:`classify`) saw the singular, and they hold no class's own name."""
    assert class_of_category(category) == cls


def test_ids_that_slug_alike_are_made_unique_and_the_others_kept(tmp_path):
    """Rows whose ids slug alike (case, spaces, names in other scripts) each get a cad_id of their
    own; a ShapeNet model id under two synsets too; an id of its own keeps its plain slug."""
    for name in ("Chair A", "chair-a", "椅子", "テーブル", "desk"):
        trimesh.creation.box((1, 1, 1)).export(tmp_path / f"{name}.obj")
    (tmp_path / "models.csv").write_text("id,class\nChair A,chair\nchair-a,chair\n椅子,chair\nテーブル,table\ndesk,table\n",
                                         encoding="utf-8")
    ids = [i.cad_id for i in source_items("folder", tmp_path, "lib")]
    assert len(set(ids)) == 5 and ids[4] == "lib.desk"
    assert ids[0].startswith("lib.chair-a-") and ids[2].startswith("lib.item-")
    assert ids == [i.cad_id for i in source_items("folder", tmp_path, "lib")]  # stable
    for synset in ("03001627", "04379243"):
        (tmp_path / "sn" / synset / "m1" / "models").mkdir(parents=True)
        trimesh.creation.box((1, 1, 1)).export(tmp_path / "sn" / synset / "m1" / "models" / "model_normalized.obj")
    shapenet = source_items("shapenet", tmp_path / "sn")
    assert len({i.cad_id for i in shapenet}) == 2 and all(i.library == "shapenet" for i in shapenet)
    import shutil

    shutil.copytree(tmp_path, tmp_path.parent / f"{tmp_path.name}-moved", ignore=shutil.ignore_patterns("sn"))
    assert [i.cad_id for i in source_items("folder", tmp_path.parent / f"{tmp_path.name}-moved", "lib")] == ids  # moved


def test_a_held_model_keeps_its_id_when_a_new_item_slugs_alike(tmp_path):
    """Ids the warehouse holds do not change on a re-ingest: "Chair A" held as lib.chair-a keeps it
    when "chair-a" joins (the newcomer takes the digest), and one held under its digest keeps that
    when the item it was alike with leaves; two new alike items both take digests, as before."""
    for name in ("Chair A", "chair-a"):
        trimesh.creation.box((1, 1, 1)).export(tmp_path / f"{name}.obj")
    csv = tmp_path / "models.csv"
    csv.write_text("id,class\nChair A,chair\n")
    first = source_items("folder", tmp_path, "lib")
    assert [i.cad_id for i in first] == ["lib.chair-a"]
    held = [(i.cad_id, i.name, i.category) for i in first]
    csv.write_text("id,class\nchair-a,chair\nChair A,chair\n")
    grown = source_items("folder", tmp_path, "lib", held)
    assert grown[1].cad_id == "lib.chair-a" and grown[0].cad_id.startswith("lib.chair-a-")
    unheld = source_items("folder", tmp_path, "lib")  # a new warehouse: both alike take digests
    assert all(i.cad_id.startswith("lib.chair-a-") for i in unheld) and unheld[0].cad_id == grown[0].cad_id
    csv.write_text("id,class\nchair-a,chair\n")  # the one held by its slug leaves: the other keeps its digest
    assert [i.cad_id for i in source_items("folder", tmp_path, "lib", held + [(grown[0].cad_id, "chair-a", "chair")])] \
        == [grown[0].cad_id]
    assert [i.cad_id for i in source_items("folder", tmp_path, "lib")] == ["lib.chair-a"]  # nothing held: plain slug


@pytest.mark.parametrize("table, message", [
    ("id,class,unit_m\nbox,table,nan\n", "models.csv:2: unit_m must be a positive number"),
    ("id,class,unit_m\nbox,table,1\nbox2,table,-1\n", "models.csv:3: unit_m must be a positive number"),
    ("id,class,unit_m\nbox\n", "models.csv:2: 1 field(s), the header has 3"),
    ("id,class\nbox,table,extra\n", "models.csv:2: 3 field(s), the header has 2"),
    ("id,class,unit_m\nbox,table,1,a,b,c,d\n", "models.csv:2: 7 field(s), the header has 3"),  # it said 4
    ("id,class\n,table\n", "models.csv:2: empty id"),
    ('id,class,creator\nbox,table,"A\nB"\n,chair,\n', "models.csv:4: empty id"),  # the line a quoted break moved it to
    ("id,class\nsame,table\n", "models.csv:2: id 'same' has 2 meshes (same.obj, same.ply); name one in a file column"),
    ("id,class,file\nbox,table,box.obj\nbox,chair,same.obj\n", "models.csv:3: id 'box' is on line 2 too; an id names "
                                                                 "one model"),  # it failed at the end: a duplicate key
    ("id,class,unit_m\n", "models.csv: lists no model (a row per model under the header)"),  # it ingested nothing, rc 0
    ("id,class\n,\n", "models.csv: lists no model (a row per model under the header)"),
])
def test_a_bad_models_csv_is_one_line_naming_its_line(tmp_path, table, message):
    trimesh.creation.box((1, 1, 1)).export(tmp_path / "box.obj")
    for suffix in ("obj", "ply"):
        trimesh.creation.box((1, 1, 1)).export(tmp_path / f"same.{suffix}")
    (tmp_path / "models.csv").write_text(table)
    with pytest.raises(CadSourceError) as e:
        list(folder_items(tmp_path))
    assert message in str(e.value) and "\n" not in str(e.value)


def test_a_spreadsheets_empty_rows_are_no_models(tmp_path):
    trimesh.creation.box((1, 1, 1)).export(tmp_path / "box.obj")
    (tmp_path / "models.csv").write_text("id,class,unit_m\nbox,table,1\n,,\n,,\n")
    assert [i.item for i in folder_items(tmp_path)] == ["box"]


def test_a_hand_written_models_csv_with_spaces_after_its_commas_is_read(tmp_path):
    """"id, class, file" was refused for having no class column, and "box, table, box.obj" looked for
    the file " box.obj"."""
    trimesh.creation.box((1, 1, 1)).export(tmp_path / "box.obj")
    (tmp_path / "models.csv").write_text('id, class, file, unit_m\nbox, table, box.obj, 0.5\n"a, b", Chair, box.obj, 1\n')
    assert [(i.item, i.cls, i.path, i.unit_m) for i in folder_items(tmp_path)] == [
        ("box", "table", str(tmp_path / "box.obj"), 0.5), ("a, b", "chair", str(tmp_path / "box.obj"), 1.0)]


def test_spreadsheet_csv_glob_characters_and_a_bang_in_the_path(tmp_path):
    """A byte-order mark (as spreadsheets save UTF-8) is read; Latin-1 is refused by name; an id
    with glob characters finds its mesh; a folder with '!' in its path is no archive."""
    folder = tmp_path / "wow!meshes"
    folder.mkdir()
    trimesh.creation.box((1, 1, 1)).export(folder / "chair[1].obj")
    (folder / "models.csv").write_bytes("id,class\nchair[1],chair\n".encode("utf-8-sig"))
    (item,) = folder_items(folder)
    assert item.path == str(folder / "chair[1].obj")
    scene, missing = load_item(item)
    assert missing == [] and np.allclose(scene.extents, 1)
    assert items_digest([item])  # its folder is walked, not an archive's
    (folder / "models.csv").write_bytes("id,class\nchaise,chair\nfauteuil é,chair\n".encode("latin-1"))
    with pytest.raises(CadSourceError, match=r"models.csv: not UTF-8 text \(byte \d+\); save it as UTF-8"):
        list(folder_items(folder))


def test_a_library_of_no_readable_model_fails_and_keeps_what_it_held(ingested, tmp_path):
    wh, _ = ingested
    before = wh.read("cad_models")
    (tmp_path / "broken.obj").write_text("v 0 0 0\nv not a number\nf 1 2 3\n")
    (tmp_path / "models.csv").write_text("id,class\nbroken,chair\n")
    with pytest.raises(CadItemError, match=r"no model of CAD library 'testlib' could be ingested \(1 skipped; the first, "
                                           r".*broken.obj: "):
        ingest_library(wh, CadIngestConfig(samples=2048), "testlib", list(folder_items(tmp_path, "testlib")), "run3",
                       show_progress=False)
    assert wh.read("cad_models").equals(before) and wh.read("cad_issues").num_rows == 5


def test_items_digest_tracks_files(mesh_folder, tmp_path):
    items = list(folder_items(mesh_folder, "testlib"))
    assert items_digest(items) == items_digest(list(folder_items(mesh_folder, "testlib")))
    assert items_digest(items[:3]) != items_digest(items)


def test_a_repainted_model_is_a_new_input_and_a_new_output(tmp_path):
    """A folder library whose material changes colour (the mesh file untouched): the items' digest
    changes (cad_ingest reruns) and so does the ingest's output (its meshes' bytes: cad_views and
    cad_embed rerun), while the meshes' folder follows their content."""
    import os

    from warehouse import Warehouse

    src = tmp_path / "src"
    src.mkdir()
    trimesh.creation.box((0.5, 0.9, 0.5)).export(src / "chair1.obj")
    obj = (src / "chair1.obj").read_text()
    (src / "chair1.obj").write_text("mtllib m.mtl\nusemtl paint\n" + obj)
    (src / "m.mtl").write_text("newmtl paint\nKd 1 0 0\n")
    (src / "models.csv").write_text("id,class,unit_m,licence,creator\nchair1,chair,1,CC0-1.0,test\n")
    wh = Warehouse(tmp_path / "wh")
    items = list(folder_items(src, "mylib"))
    red_inputs = items_digest(items)
    red = ingest_library(wh, CadIngestConfig(samples=256), "mylib", items, "r1", show_progress=False)
    (src / "m.mtl").write_text("newmtl paint\nKd 0 0 1\n")
    st = (src / "m.mtl").stat()
    os.utime(src / "m.mtl", ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    assert items_digest(items) != red_inputs
    blue = ingest_library(wh, CadIngestConfig(samples=256), "mylib", items, "r2", show_progress=False)
    assert blue.output_hash != red.output_hash
    assert len(list((wh.root / "media" / "cad" / "mylib").iterdir())) == 1


def test_a_repainted_texture_beside_the_meshes_folder_is_a_new_input(tmp_path):
    """``meshes/chair.obj`` whose material names ``../textures/wood.png`` (models.csv: file=meshes/...):
    only the mesh's own folder was walked, so a repainted texture kept the library's digest, and
    cad_ingest went on serving the old one."""
    import os

    from PIL import Image

    (tmp_path / "meshes").mkdir()
    (tmp_path / "textures").mkdir()
    quad = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nusemtl m\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n"
    (tmp_path / "meshes" / "chair.mtl").write_text("newmtl m\nmap_Kd ../textures/wood.png\n")
    (tmp_path / "meshes" / "chair.obj").write_text("mtllib chair.mtl\n" + quad)
    (tmp_path / "models.csv").write_text("id,class,file\nchair,chair,meshes/chair.obj\n")
    Image.new("RGB", (4, 4), (255, 0, 0)).save(tmp_path / "textures" / "wood.png")
    items = list(folder_items(tmp_path))
    assert load_item(items[0])[1] == []  # the texture is found
    red = items_digest(items)
    Image.new("RGB", (4, 4), (0, 0, 255)).save(tmp_path / "textures" / "wood.png")
    st = (tmp_path / "textures" / "wood.png").stat()
    os.utime(tmp_path / "textures" / "wood.png", ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    assert items_digest(items) != red


def test_a_model_that_kills_its_worker_is_skipped_not_the_library(tmp_path):
    """A worker process that dies (the out-of-memory killer on a huge mesh) broke the process pool,
    and the whole library failed with BrokenProcessPool, no model named. Here each process that
    opens one model's texture (a FIFO: it waits there) is killed with SIGKILL: that model is skipped,
    named, and every other is ingested."""
    import signal
    import threading

    for i in range(6):
        trimesh.creation.box((0.5 + i / 10, 0.9, 0.5)).export(tmp_path / f"box{i}.obj")
    quad = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nusemtl m\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n"
    (tmp_path / "killer.mtl").write_text("newmtl m\nmap_Kd killer.png\n")
    (tmp_path / "killer.obj").write_text("mtllib killer.mtl\n" + quad)
    os.mkfifo(tmp_path / "killer.png")
    (tmp_path / "models.csv").write_text("id,class\n" + "".join(f"box{i},table\n" for i in range(3)) + "killer,table\n"
                                         + "".join(f"box{i},table\n" for i in range(3, 6)))
    fifo, done, killed = str(tmp_path / "killer.png"), threading.Event(), []

    def kill_its_readers() -> None:
        while not done.is_set():
            fd = os.open(fifo, os.O_WRONLY)  # waits for a reader
            for pid in (int(d) for d in os.listdir("/proc") if d.isdigit()):
                try:
                    if any(os.readlink(f"/proc/{pid}/fd/{n}") == fifo for n in os.listdir(f"/proc/{pid}/fd")) \
                            and pid != os.getpid():
                        os.kill(pid, signal.SIGKILL)
                        killed.append(pid)
                except OSError:
                    continue
            os.close(fd)

    killer = threading.Thread(target=kill_its_readers, daemon=True)
    killer.start()
    wh = Warehouse(tmp_path / "w")
    try:
        ingest_library(wh, CadIngestConfig(samples=256, workers=2), "lib", list(folder_items(tmp_path, "lib")), "r1",
                       show_progress=False)
    finally:
        done.set()
        os.close(os.open(fifo, os.O_RDONLY | os.O_NONBLOCK))  # wakes the killer's last open
        killer.join(10)
    assert len(killed) >= 2  # in the pool, then alone
    assert sorted(wh.read("cad_models").column("cad_id").to_pylist()) == [f"lib.box{i}" for i in range(6)]
    (issue,) = wh.read("cad_issues").to_pylist()
    assert (issue["item"], issue["severity"]) == ("killer", "skipped") and "worker process died" in issue["problem"]
    assert wh.read("cad_samples").column("cad_id").to_pylist() == wh.read("cad_models").column("cad_id").to_pylist()


def test_java_properties():
    data = "# c\nname#1=Caf\\u00e9 table\nlong=a \\\n   b\nkey\\ with\\ space = v\n! bang\ncolon:x\n".encode("latin-1")
    assert read_java_properties(data) == {"name#1": "Café table", "long": "a b", "key with space": "v", "colon": "x"}


@pytest.mark.parametrize("name, category, expected", [
    ("Armchair", "", "chair"), ("Bedside table", "", "cabinet"), ("Bed", "", "bed"), ("Sofa bed", "", "sofa"),
    ("Coffee table", "", "table"), ("Desk lamp", "", "lamp"), ("Desk", "", "table"), ("Tablet", "", "other"), ("Table fan", "", "other"), ("Washbasin", "", "sink"), ("Toilets unit", "", "toilet"),
    ("Toilet paper dispenser", "", "other"), ("Wall flat TV", "", "display"), ("Ficus", "", "plant"),
    ("Bookcase", "", "bookshelf"), ("Concept Sedan 01", "Vehicles", "vehicle"), ("Spoon", "Kitchen", "other"),
    ("Winchester armchair", "Living room", "chair"), ("Winchester sofa", "", "sofa"), ("Chest", "", "cabinet"),
    ("Chest freezer", "", "refrigerator"), ("Island", "Kitchen", "cabinet"), ("Island bath", "", "bathtub"),
    ("Indoor bike", "", "other"), ("Doormat", "", "other"), ("Screen door", "", "door"), ("Seat Leon", "Vehicles", "vehicle"),
    ("Range hood", "", "other"), ("TV remote control", "", "other"), ("Elevator", "Doors and windows", "other"),
    ("Elevator door", "", "door"), ("Double-hung window", "Doors and windows", "window"), ("Motorbike", "", "vehicle"),
])
def test_classify(name, category, expected):
    assert classify(name, category) == expected


AUDIT = Path(__file__).parent / "data" / "cad_class_audit.tsv"


@needs_sh3d
def test_every_model_of_the_embedded_library_has_its_audited_class():
    """tests/data/cad_class_audit.tsv: every model of the embedded Sweet Home 3D library with its
    catalogue category, name and the class a person checked it against; a rule change that moves
    any model, or a library that gains or loses one, shows here."""
    lines = AUDIT.read_text(encoding="utf-8").splitlines()
    assert lines[0].split("\t") == ["cad_id", "category", "name", "class"]
    audited = {cad_id: (category, name, cls) for cad_id, category, name, cls in (line.split("\t") for line in lines[1:])}
    found = {it.cad_id: (it.category, it.name, it.cls) for it in sweethome3d_items(SH3D)}
    assert set(found) == set(audited)
    moved = {k: (audited[k], found[k]) for k in found if found[k] != audited[k]}
    assert not moved, f"{len(moved)} models differ from the audit: {dict(list(moved.items())[:5])}"
    assert {cls for _, _, cls in audited.values()} <= set(BY_NAME)


def test_class_vocabulary_is_consistent():
    assert len({c.id for c in CLASSES}) == len(CLASSES) == len(BY_NAME)
    assert BY_NAME["chair"].id == "03001627" and BY_NAME["table"].id == "04379243"  # ShapeNet synsets


def test_views_frame_the_model(ingested):
    wh, _ = ingested
    out = render_library(wh, CadViewsConfig(views=3, size=96), "testlib", "v1", show_progress=False)
    views = wh.read("cad_views").to_pylist()
    assert out.rows_written == len(views) == 4 * 3
    assert all((wh.root / v["image_path"]).is_file() for v in views)
    np.testing.assert_array_equal(viewpoints("x", 3, 0), viewpoints("x", 3, 0))
    assert not np.array_equal(viewpoints("x", 3, 0), viewpoints("y", 3, 0))
    crate = next(m for m in wh.read("cad_models").to_pylist() if m["cad_id"] == "testlib.crate")
    mesh = RenderMesh.from_trimesh(trimesh.load(wh.root / crate["mesh_path"], force="scene"))
    camera = view_camera(np.asarray(crate["extent"]), 30.0, 20.0, 96)
    with Renderer(96, 96) as renderer:
        ids = renderer.render([Instance(mesh, np.eye(4), 0)], camera).instance_id
    ys, xs = np.nonzero(ids == 0)
    assert xs.min() > 0 and ys.min() > 0 and xs.max() < 95 and ys.max() < 95  # whole model in view
    assert (xs.max() - xs.min()) > 40  # and it fills a good part of it
    uv, depth = project(camera.K, camera.R, camera.t, np.zeros((1, 3)))
    np.testing.assert_allclose(uv[0], [48, 48], atol=1e-9)  # looking at the canonical origin


def test_export_official_round_trip(ingested, tmp_path):
    wh, _ = ingested
    out = tmp_path / "official"
    assert export_official(wh, out, show_progress=False) == 4
    classes = json.loads((out / "shapenet_classes.json").read_text())
    assert classes[0] == {"id": "03001627", "human_readable": "chair"} and len(classes) == len(CLASSES)
    symmetry = json.loads((out / "symmetry_dict.json").read_text())
    assert symmetry["03001627_testlib.stool"] == 36 and symmetry["cadestate-other_testlib.crate"] == 2
    npz = np.load(out / "03001627" / "testlib.chair.npz")
    assert npz["vertices"].dtype == np.float32 and npz["vertices"].shape[1:] == (3, 3)
    chair = next(m for m in wh.read("cad_models").to_pylist() if m["cad_id"] == "testlib.chair")
    np.testing.assert_array_equal(npz["vertices"], triangle_soup(wh.root / chair["mesh_path"]))
    assert str(npz["label"]) == "03001627" and str(npz["mesh_id"]) == "testlib.chair"
    # The official loader's object-to-world (translate . rotate . scale . mirror) is ours.
    q = np.array([np.cos(0.3), 0, np.sin(0.3), 0])
    M = object_to_world([1, 0, 2], q, [1.1, 0.9, 1.2], True)
    v = npz["vertices"].reshape(-1, 3).astype(np.float64)
    mirrored_scaled = v * [-1, 1, 1] * [1.1, 0.9, 1.2]
    from cadestate.geometry import quaternion_to_matrix
    expected = mirrored_scaled @ quaternion_to_matrix(q).T + [1, 0, 2]
    np.testing.assert_allclose(v @ M[:3, :3].T + M[:3, 3], expected, atol=1e-9)
    with pytest.raises(ExportError, match="not empty"):
        export_official(wh, out, show_progress=False)


def test_attribution_keeps_the_catalogues_copyright_notices(tmp_path, capsys):
    """CC BY asks that copyright notices be kept: the catalogue's licence line was cut to its SPDX
    id, and ATTRIBUTION.csv lost "Copyright © 2003-2008 Andrew Kator & Jennifer Legaz" of 88 models."""
    from tasks.cad.export import catalogue_notices

    catalogues = {p.stem: str(p) for p in default_source().glob("*.sh3f")}
    rows = [{"source": "sweethome3d", "source_path": f"{catalogues[name]}!{name}/model.obj"} for name in ("KatorLegaz", "Scopia")]
    gone = str(tmp_path / "Moved.sh3f")
    notices = catalogue_notices([*rows, {"source": "sweethome3d", "source_path": f"{gone}!a.obj"},
                                 {"source": "folder", "source_path": str(tmp_path / "a.obj")}])
    assert notices == {catalogues["KatorLegaz"]: "Creative Commons Attribution 3.0 United States license  Copyright © "
                                                 "2003-2008 Andrew Kator & Jennifer Legaz",
                       catalogues["Scopia"]: "Creative Commons Attribution 3.0 Unported license  © Emmanuel Puybaret / "
                                             "eTeks and Scopia Visual Interfaces Systems"}
    assert capsys.readouterr().err.startswith(f"warning: {gone}: cannot read its licence line for ATTRIBUTION.csv")
    # a folder above the catalogue with a '!' in its name: the notice was lost (the path cut at the first '!')
    (tmp_path / "lib!x").mkdir()
    moved = shutil.copy(catalogues["Scopia"], tmp_path / "lib!x" / "Scopia.sh3f")
    assert catalogue_notices([{"source": "sweethome3d", "source_path": f"{moved}!Scopia/model.obj"}]) == {
        str(moved): notices[catalogues["Scopia"]]}


def test_export_official_names_a_damaged_mesh(ingested, tmp_path):
    """A model whose mesh in the warehouse is damaged (or gone): one error naming the file, not a
    trimesh traceback ("incorrect header on GLB file", naming nothing), and nothing written."""
    import shutil

    from warehouse import Warehouse

    wh, _ = ingested
    shutil.copytree(wh.root, tmp_path / "wh")
    copy = Warehouse(tmp_path / "wh")
    mesh = copy.root / next(m for m in copy.read("cad_models").to_pylist() if m["cad_id"] == "testlib.chair")["mesh_path"]
    for damage in (lambda: mesh.write_bytes(b"garbage"), mesh.unlink):
        damage()
        with pytest.raises(ExportError, match=f"^{mesh}: cannot read this CAD model's mesh "):
            export_official(copy, tmp_path / "official", show_progress=False)
        assert sorted(p.name for p in tmp_path.iterdir()) == ["wh"]


@needs_sh3d
def test_sweet_home_3d_catalogues():
    items = list(sweethome3d_items(SH3D))
    assert len(items) == 783  # 175 + 135 + 90 + 395, less the people (characters)
    assert {i.library for i in items} == {"sh3d-blendswap-cc-0", "sh3d-blendswap-cc-by", "sh3d-katorlegaz", "sh3d-scopia"}
    assert all(i.category.lower() != "characters" for i in items)
    assert {i.licence for i in items} == {"CC0-1.0", "CC-BY-3.0", "CC-BY-3.0-US"}
    assert len({i.cad_id for i in items}) == len(items)
    armchair = next(i for i in items if i.cad_id == "sh3d-blendswap-cc-0.armchair")
    assert armchair.size_m == pytest.approx((0.594, 1.05, 0.627)) and armchair.creator == "Absfrm"


@needs_sh3d
def test_sweet_home_3d_models_take_their_catalogue_size(tmp_path):
    from warehouse import Warehouse

    items = list(sweethome3d_items(SH3D))
    rotated = [i for i in items if i.rotation is not None and i.rotation != (1, 0, 0, 0, 1, 0, 0, 0, 1)][:2]
    pick = [next(i for i in items if i.cad_id == "sh3d-blendswap-cc-0.armchair"), *rotated]
    wh = Warehouse(tmp_path)
    ingest_library(wh, CadIngestConfig(samples=512), "sh3d-mixed", pick, "r", show_progress=False)
    for m, item in zip(wh.read("cad_models").sort_by("cad_id").to_pylist(), sorted(pick, key=lambda i: i.cad_id)):
        np.testing.assert_allclose(m["extent"], item.size_m, rtol=1e-6)  # width, height, depth in metres
        assert m["licence"] == item.licence and m["creator"] == item.creator


def test_config_default_is_the_calibrated_symmetry_tolerance():
    from tasks.cad.symmetry import DEFAULT_TOLERANCE

    assert CadIngestConfig().symmetry_tolerance == DEFAULT_TOLERANCE


def test_an_item_with_two_problems_is_one_issue_row(tmp_path):
    """A folder item whose material file is missing and whose class is unknown: both problems in
    one cad_issues row (the table's key is the item), where two rows failed the whole library."""
    from warehouse import Warehouse

    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "gizmo.obj").write_text("mtllib absent.mtl\n" + trimesh.creation.box((1, 1, 1)).export(file_type="obj"))
    (tmp_path / "m" / "models.csv").write_text("id,class\ngizmo,widget\n")
    wh = Warehouse(tmp_path / "w")
    out = ingest_library(wh, CadIngestConfig(samples=256), "lib", list(folder_items(tmp_path / "m", "lib")), "r",
                         show_progress=False)
    (issue,) = wh.read("cad_issues").to_pylist()
    assert out.rows_written == 1 and issue["severity"] == "warning"
    assert "missing or unreadable files (rendered without them): absent.mtl; class 'widget' is none" in issue["problem"]


def test_textured_means_a_texture_image_not_a_placeholder(tmp_path):
    """An OBJ with a real texture is textured; one whose material file is missing is not (trimesh
    gives it a 2 x 2 placeholder), and the missing file is named; so is a texture that is no image."""
    from PIL import Image

    from tasks.cad.ingest import _is_textured

    quad = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
    Image.new("RGB", (8, 8), (200, 30, 30)).save(tmp_path / "red.png")
    (tmp_path / "tex.mtl").write_text("newmtl red\nKd 1 1 1\nmap_Kd red.png\n")
    (tmp_path / "tex.obj").write_text("mtllib tex.mtl\n" + quad + "usemtl red\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n")
    (tmp_path / "nomtl.obj").write_text("mtllib absent.mtl\n" + quad + "usemtl red\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n")
    (tmp_path / "broken.png").write_bytes(b"\x89PNG not really")  # trimesh dropped it without a word
    (tmp_path / "broken.mtl").write_text("newmtl red\nKd 1 1 1\nmap_Kd broken.png\n")
    (tmp_path / "broken.obj").write_text("mtllib broken.mtl\n" + quad + "usemtl red\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n")
    (tmp_path / "models.csv").write_text("id,class\ntex,table\nnomtl,table\nbroken,table\n")
    (tex, missing_tex), (nomtl, missing), (broken, unreadable) = (load_item(i) for i in folder_items(tmp_path))
    assert _is_textured(tex) and missing_tex == []
    assert not _is_textured(nomtl) and missing == ["absent.mtl"]
    assert not _is_textured(broken) and unreadable == ["broken.png (unreadable)"]


def test_a_catalogue_item_without_an_id_is_listed(tmp_path):
    """Sweet Home 3D catalogues may leave id#N out (name#N is what every item has): such an item
    was dropped without a word; it gets an id from its name and number."""
    import zipfile

    obj = trimesh.creation.box((50, 90, 40)).export(file_type="obj")
    props = ("name=My catalogue\nlicense=Public domain\nprovider=Me\n"
             "id#1=me#chair1\nname#1=Red chair\ncategory#1=Living room\nmodel#1=/chair1/chair.obj\n"
             "width#1=50\ndepth#1=40\nheight#1=90\n"
             "name#2=Blue table\ncategory#2=Living room\nmodel#2=/table2/table.obj\nwidth#2=120\ndepth#2=80\nheight#2=75\n")
    with zipfile.ZipFile(tmp_path / "Mine.sh3f", "w") as z:
        z.writestr("PluginFurnitureCatalog.properties", props)
        z.writestr("chair1/chair.obj", obj)
        z.writestr("table2/table.obj", obj)
    items = source_items("sweethome3d", tmp_path)
    assert [(i.cad_id, i.cls, i.size_m) for i in items] == [("sh3d-mine.chair1", "chair", (0.5, 0.9, 0.4)),
                                                           ("sh3d-mine.blue-table-2", "table", (1.2, 0.75, 0.8))]
    assert all(load_item(i)[0].extents.max() > 0 for i in items)


def test_entries_of_one_id_and_category_and_a_bang_above_the_catalogue_are_models_apart(tmp_path):
    """Two creators' "#chair" (or a copied entry) in one category were given one cad_id, and the
    library failed after every model was ingested; a '!' in a folder above the catalogue split its
    path there, and no item could be read."""
    import zipfile

    from tasks.cad.ingest import ingest_library

    obj = trimesh.creation.box((50, 90, 40)).export(file_type="obj")
    entries = [("me#chair", "c1"), ("you#chair", "c2"), ("me#chair", "c3")]
    props = "name=Mine\nlicense=Public domain\nprovider=Me\n" + "".join(
        f"id#{i}={id_}\nname#{i}=Chair\ncategory#{i}=Living room\nmodel#{i}=/{m}/c.obj\nwidth#{i}=50\ndepth#{i}=40\n"
        f"height#{i}=90\n" for i, (id_, m) in enumerate(entries, 1))
    folder = tmp_path / "wow!furniture"
    folder.mkdir()
    with zipfile.ZipFile(folder / "Mine.sh3f", "w") as z:
        z.writestr("PluginFurnitureCatalog.properties", props)
        for _, m in entries:
            z.writestr(f"{m}/c.obj", obj)
    items = source_items("sweethome3d", folder)
    assert [i.cad_id for i in items] == ["sh3d-mine.chair", "sh3d-mine.you-chair", "sh3d-mine.me-chair"]
    assert [i.path.rsplit("!", 1)[1] for i in items] == ["c1/c.obj", "c2/c.obj", "c3/c.obj"]
    wh = Warehouse(tmp_path / "w")
    ingest_library(wh, CadIngestConfig(samples=256, workers=1), "sh3d-mine", items, "r1", show_progress=False)
    assert sorted(wh.read("cad_models").column("cad_id").to_pylist()) == sorted(i.cad_id for i in items)
    assert wh.read("cad_issues").num_rows == 0


def test_a_quote_left_open_in_a_long_models_csv_is_one_line(tmp_path):
    """A quote opened and not closed swallows the rest of a long table into one field: csv's
    "field larger than field limit" was a traceback."""
    rows = "".join(f"m{i},chair\n" for i in range(12_000))
    (tmp_path / "models.csv").write_text('id,class\n"Eames chair,chair\n' + rows)
    with pytest.raises(CadSourceError, match=r"models.csv:\d+: field larger than field limit .*\(a quote opened and not closed\?\)$"):
        list(folder_items(tmp_path))


def test_a_malformed_catalogue_entry_or_catalogue_is_one_line_naming_it(tmp_path):
    """A comma decimal in a size, a rotation of 8 numbers, a catalogue with no properties file and
    one that is no zip were tracebacks."""
    import zipfile

    def catalogue(folder, props=None, raw=None):
        folder.mkdir()
        if raw is not None:
            (folder / "Mine.sh3f").write_bytes(raw)
            return folder
        with zipfile.ZipFile(folder / "Mine.sh3f", "w") as z:
            if props is not None:
                z.writestr("PluginFurnitureCatalog.properties", props)
        return folder

    entry = "name#1=Chair\ncategory#1=Living room\nmodel#1=/c/c.obj\nwidth#1={w}\ndepth#1=40\nheight#1=90\n{more}"
    cases = [(catalogue(tmp_path / "a", entry.format(w="50,5", more="")), r"width#1 = '50,5' is not 1 number"),
             (catalogue(tmp_path / "b", entry.format(w="50", more="modelRotation#1=1 0 0 0 1 0 0 0\n")),
              r"modelRotation#1 = '1 0 0 0 1 0 0 0' is not 9 number"),
             (catalogue(tmp_path / "c"), "no PluginFurnitureCatalog.properties in it"),
             (catalogue(tmp_path / "d", raw=b"not a zip"), "not a readable zip")]
    for folder, message in cases:
        with pytest.raises(CadSourceError, match=rf"^{folder / 'Mine.sh3f'}: .*{message}"):
            source_items("sweethome3d", folder)


def test_a_model_whose_texture_cannot_be_written_is_skipped_not_the_library(tmp_path):
    """An OBJ whose texture is a float TIFF: the GLB export raised out of ingest_item, failing the
    whole library (its good models too) with no model named."""
    from PIL import Image

    from tasks.cad.ingest import ingest_item

    Image.fromarray(np.linspace(0, 1, 64, dtype=np.float32).reshape(8, 8)).save(tmp_path / "f32.tif")
    quad = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nusemtl m\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n"
    (tmp_path / "f32.mtl").write_text("newmtl m\nmap_Kd f32.tif\n")
    (tmp_path / "f32.obj").write_text("mtllib f32.mtl\n" + quad)
    (tmp_path / "models.csv").write_text("id,class\nf32,table\n")
    (item,) = folder_items(tmp_path)
    result = ingest_item(item, CadIngestConfig(samples=256), tmp_path)
    assert result.model is None and result.issues[0]["severity"] == "skipped" and "f32" in result.issues[0]["item"]


def test_a_file_name_that_is_not_utf8_is_named_not_a_codec_error(tmp_path):
    """A stray texture named in Latin-1 beside a library's models failed the whole library with
    "'utf-8' codec can't encode character '\\udce9'", naming no file; a model's own such name is
    refused naming it (the tables hold UTF-8 text only)."""
    trimesh.creation.box((0.5, 0.9, 0.5)).export(tmp_path / "cube.obj")
    (tmp_path / "models.csv").write_text("id,class\ncube,chair\n")
    (tmp_path / os.fsdecode(b"textur\xe9.png")).write_bytes(b"")
    items = source_items("folder", tmp_path)
    assert [i.item for i in items] == ["cube"] and len(items_digest(items)) == 16
    model = tmp_path / "sn" / "03001627" / os.fsdecode(b"chaise-\xe9") / "models"
    model.mkdir(parents=True)
    trimesh.creation.box((0.5, 0.9, 0.5)).export(model / "model_normalized.obj")
    with pytest.raises(CadSourceError, match=r"chaise-\\xe9/models/model_normalized.obj: a model's file or folder name "
                                             r"that is not UTF-8: rename it"):
        source_items("shapenet", tmp_path / "sn")


def test_a_warehouse_inside_the_source_folder_is_not_part_of_its_digest(tmp_path):
    """`cadestate cad ingest .` where models.csv sits beside the default data/warehouse: the digest
    walked the warehouse too, so each ingest's own writes made the library new and it was ingested
    again every time. A texture added beside the models still counts."""
    trimesh.creation.box((0.5, 0.9, 0.5)).export(tmp_path / "cube.obj")
    (tmp_path / "models.csv").write_text("id,class\ncube,chair\n")
    items = source_items("folder", tmp_path)
    wh = tmp_path / "data" / "warehouse"
    (wh / "tables" / "runs").mkdir(parents=True)
    (wh / "catalog.duckdb").write_bytes(b"x")
    before = items_digest(items)
    (wh / "tables" / "runs" / "part.parquet").write_bytes(b"written by the ingest")
    assert items_digest(items) == before
    (tmp_path / "wood.png").write_bytes(b"a texture")
    assert items_digest(items) != before


def test_a_model_of_too_long_an_id_or_beyond_float32_is_skipped_not_the_library(tmp_path):
    """An id whose files' names pass 255 bytes raised out of ingest_item (the GLB written outside
    its try) and failed every model of the library, or passed ingest by a few bytes and failed the
    views; a mesh at 1e300 was stored as float32 infinities and read as fully symmetric."""
    from tasks.cad.ingest import ingest_item

    long_id = "oak_dining_chair_with_upholstered_seat_" * 6
    trimesh.creation.box((0.5, 0.9, 0.5)).export(tmp_path / "long.obj")
    (tmp_path / "huge.obj").write_text("v 0 0 0\nv 1e300 0 0\nv 0 1e300 0\nv 0 0 1e300\nf 1 2 3\nf 1 3 4\nf 1 2 4\nf 2 3 4\n")
    (tmp_path / "models.csv").write_text(f"id,class,file\n{long_id},chair,long.obj\nhuge,chair,huge.obj\n")
    by_item = {item.item: item for item in folder_items(tmp_path)}
    out = tmp_path / "out"
    out.mkdir()
    too_long = ingest_item(by_item[long_id], CadIngestConfig(samples=256), out)
    assert too_long.model is None and "its id makes file names longer than 255 bytes" in too_long.issues[0]["problem"]
    huge = ingest_item(by_item["huge"], CadIngestConfig(samples=256), out)
    assert huge.model is None and "beyond float32's range" in huge.issues[0]["problem"] and not list(out.iterdir())


def test_a_shapenet_synset_outside_the_vocabulary_is_named_in_the_message(tmp_path):
    """A ShapeNet pillow (03938244) is ingested as 'other': said once in the stage's message (a row per
    model would be thousands); a model folder without its mesh is a skipped item (it vanished without a trace)."""
    from warehouse import Warehouse

    folder = tmp_path / "sn" / "03938244" / "p1" / "models"
    folder.mkdir(parents=True)
    trimesh.creation.box((0.5, 0.2, 0.4)).export(folder / "model_normalized.obj")
    (tmp_path / "sn" / "03001627" / "nomesh" / "models").mkdir(parents=True)  # vanished without a trace
    wh = Warehouse(tmp_path / "w")
    out = ingest_library(wh, CadIngestConfig(samples=256), "shapenet", list(shapenet_items(tmp_path / "sn")), "r",
                         show_progress=False)
    assert out.message == ("1 item(s) skipped, see cad_issues; 1 model(s) of ShapeNet synsets outside the vocabulary "
                           "(tasks/cad/classes.py) ingested as 'other': 03938244")
    assert [(r["item"], r["severity"]) for r in wh.read("cad_issues").to_pylist()] == [("nomesh", "skipped")]


def test_a_library_name_held_from_another_folder_is_refused_and_the_same_folder_is_not(ingested, mesh_folder, tmp_path):
    """The warehouse holds testlib from mesh_folder: another folder under that name is refused; the
    same folder again, or with models added in a subfolder (its files' common folder moves), is not."""
    import dataclasses

    from cadestate.cli.cad import held_elsewhere
    from cadestate.cli.common import CliError

    wh, _ = ingested
    items = list(folder_items(mesh_folder, "testlib"))
    held_elsewhere(wh.root, items)
    deeper = dataclasses.replace(items[0], item="sofa", path=str(mesh_folder / "more" / "sofa.obj"))
    held_elsewhere(wh.root, [*items, deeper])
    held_elsewhere(wh.root, [deeper])  # only the new one: inside the held folder
    other = [dataclasses.replace(i, path=str(tmp_path / "elsewhere" / Path(i.path).name)) for i in items]
    with pytest.raises(CliError, match=f"library 'testlib' already holds models from {mesh_folder}, not "):
        held_elsewhere(wh.root, other)
    # A Sweet Home 3D library is named after its catalogue, and --library is refused for it: the same
    # catalogue moved (another $CADESTATE_SH3D_DIR, a warehouse copied to another machine) was refused for good.
    moved = [dataclasses.replace(i, source="sweethome3d", path=f"{tmp_path / 'elsewhere' / 'Lib.sh3f'}!{i.item}.obj")
             for i in items]
    held_elsewhere(wh.root, moved)


def test_warnings_are_counted_in_the_message_and_a_mesh_in_millimetres_is_one(tmp_path):
    """A run report said nothing of warned items (a texture missing, a class unknown): only the skipped
    were counted, so a user never learnt of them; a desk in millimetres without unit_m was a 1.2 km
    desk, without a word."""
    from warehouse import Warehouse

    trimesh.creation.box((1200, 750, 800)).export(tmp_path / "desk.stl")
    trimesh.creation.box((0.5, 0.9, 0.5)).export(tmp_path / "crate.stl")
    trimesh.creation.box((1.2, 0.75, 0.8)).export(tmp_path / "small.stl")  # in metres, said to be in millimetres
    trimesh.creation.box((0.5, 0.5, 0.5)).export(tmp_path / "tiny.stl")  # so too: 0.5 mm, skipped
    (tmp_path / "models.csv").write_text("id,class,unit_m\ndesk,table,\ncrate,crate,\nsmall,table,0.001\ntiny,table,0.001\n")
    wh = Warehouse(tmp_path / "w")
    out = ingest_library(wh, CadIngestConfig(samples=256), "lab", list(folder_items(tmp_path, "lab")), "r",
                         show_progress=False)
    assert out.message == "1 item(s) skipped, 3 item(s) with warnings, see cad_issues"
    problems = {r["item"]: r["problem"] for r in wh.read("cad_issues").to_pylist()}
    assert problems["desk"] == ("largest extent 1.2e+03 m, more than 25 m: is the mesh in other units? models.csv's "
                                "unit_m gives metres per mesh unit (0.001 for millimetres)")
    assert problems["small"] == ("largest extent 0.0012 m, less than 0.05 m: is the mesh in other units? models.csv's "
                                 "unit_m gives metres per mesh unit (1 for metres)")
    assert problems["tiny"] == "CadItemError: degenerate: largest extent 0.0005 m (unit_m 0.001: is the mesh in other units?)"
    assert wh.read("cad_models").num_rows == 3  # a warning, not a skip


def test_a_folder_that_is_no_source_says_what_would_make_it_one(tmp_path):
    """Meshes without models.csv, or a ShapeNet synset folder given for its root: the error said only
    'not a CAD source', the user left to guess the models.csv or the folder above."""
    loose = tmp_path / "loose"
    loose.mkdir()
    for name in ("a.stl", "b.obj"):
        trimesh.creation.box((1, 1, 1)).export(loose / name)
    with pytest.raises(CadSourceError) as e:
        guess_kind(loose)
    assert str(e.value) == (f"{loose}: 2 mesh file(s) but no models.csv: write one, a row per model "
                            "(columns id,class[,file,licence,creator,unit_m])")
    folder = tmp_path / "sn" / "03001627" / "m1" / "models"
    folder.mkdir(parents=True)
    trimesh.creation.box((1, 1, 1)).export(folder / "model_normalized.obj")
    with pytest.raises(CadSourceError) as e:
        guess_kind(tmp_path / "sn" / "03001627")
    assert str(e.value) == (f"{tmp_path / 'sn' / '03001627'}: a category folder of the ShapeNet layout: give the folder "
                            f"above it ({tmp_path / 'sn'})")
    (tmp_path / "empty").mkdir()
    with pytest.raises(CadSourceError, match=r"empty: not a CAD source \(no \*.sh3f catalogues, no models.csv, no ShapeNet"):
        guess_kind(tmp_path / "empty")
