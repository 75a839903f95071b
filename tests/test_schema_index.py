"""The published table index (schemas/tables.json): equal to the table specs, ignored when stale."""

from __future__ import annotations

import json

from schemas import TABLES
from schemas.index import INDEX_FILE, index_document, read_index, table_info
from warehouse import Warehouse


def test_the_published_index_is_the_table_specs():
    published = json.loads(json.dumps(index_document(TABLES)))
    assert json.loads(INDEX_FILE.read_text()) == published, "run `python -m schemas.index`"
    assert read_index() == {name: table_info(spec) for name, spec in TABLES.items()}


def test_an_index_made_from_other_schema_sources_is_not_used(tmp_path):
    doc = json.loads(INDEX_FILE.read_text())
    doc["sources_sha256"] = "0" * 64
    stale = tmp_path / "tables.json"
    stale.write_text(json.dumps(doc))
    assert read_index(stale) is None
    stale.write_text("{")
    assert read_index(stale) is None and read_index(tmp_path / "missing.json") is None


def test_a_warehouse_of_its_own_tables_describes_them_from_their_specs(tmp_path):
    frames = TABLES["frames"]
    wh = Warehouse(tmp_path / "w", tables={"frames": frames})
    assert wh.info == {"frames": table_info(frames)}
    assert Warehouse(tmp_path / "w").info == read_index()
