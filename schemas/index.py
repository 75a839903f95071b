"""What a command that only reads needs of every table, without pyarrow: name, partition column,
key, write mode, description and the digest of its schema, published in ``schemas/tables.json``
from :data:`schemas.TABLES` (:func:`publish_index`; a test keeps it equal to the table specs).

The file records a digest of the schema modules' source; :func:`read_index` ignores a file made
from other sources, so a changed schema module is never described by an old index (its readers
then fall back to the table specs themselves).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from schemas.base import TableSpec

INDEX_FILE = Path(__file__).parent / "tables.json"
SOURCES = Path(__file__).parent


@dataclass(frozen=True)
class TableInfo:
    """One table as :class:`schemas.base.TableSpec` describes it, less its pyarrow schema (but its digest)."""

    name: str
    partition: str
    key: tuple[str, ...]
    mode: str
    description: str
    schema_sha256: str


def schema_sha256(spec: TableSpec) -> str:
    """Digest of the table's pyarrow schema (what the catalog's empty-table files record)."""
    return hashlib.sha256(spec.schema.serialize()).hexdigest()


def table_info(spec: TableSpec) -> TableInfo:
    return TableInfo(spec.name, spec.partition, tuple(spec.key), spec.mode, spec.description, schema_sha256(spec))


def sources_sha256() -> str:
    """Digest of the source of the schema modules (``schemas/*.py``)."""
    h = hashlib.sha256()
    for path in sorted(SOURCES.glob("*.py")):
        h.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


def index_document(tables: dict[str, TableSpec]) -> dict:
    """The index of ``tables`` as published."""
    return {"sources_sha256": sources_sha256(), "tables": [asdict(table_info(spec)) for spec in tables.values()]}


def publish_index(path: Path = INDEX_FILE) -> Path:
    """Write the index of :data:`schemas.TABLES` to ``path``."""
    from schemas import TABLES

    path.write_text(json.dumps(index_document(TABLES), indent=1) + "\n", encoding="utf-8")
    return path


def read_index(path: Path = INDEX_FILE) -> dict[str, TableInfo] | None:
    """The published index by table name; None when it is missing, unreadable, or made from other
    schema sources than these."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        if doc["sources_sha256"] != sources_sha256():
            return None
        return {t["name"]: TableInfo(**{**t, "key": tuple(t["key"])}) for t in doc["tables"]}
    except (OSError, ValueError, KeyError, TypeError):
        return None


if __name__ == "__main__":
    print(publish_index())
