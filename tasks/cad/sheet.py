"""Contact sheets: CAD models as pictures (first rendered view, labelled with name, class, symmetry)."""

from __future__ import annotations

from pathlib import Path

from PIL import Image, ImageDraw

from warehouse import Warehouse
from warehouse.query import run_query

TILE = 160
COLUMNS = 8


def contact_sheet(wh: Warehouse, out_file: Path, where: str = "true", limit: int = 48) -> int:
    """Write a PNG of up to ``limit`` models matching the SQL condition ``where``; returns the count."""
    sql = (f"SELECT m.cad_id, m.name, m.class, m.symmetry, v.image_path FROM cad_models m "
           f"JOIN cad_views v USING (library, cad_id) WHERE v.view = 0 AND ({where}) ORDER BY m.cad_id LIMIT {int(limit)}")
    with run_query(wh, sql) as result:  # read-only: ``where`` is the user's SQL
        rows = [row for batch in result.batches for row in batch]
    rows_n = max(1, -(-len(rows) // COLUMNS))
    sheet = Image.new("RGB", (TILE * COLUMNS, TILE * rows_n), "white")
    for i, (cad_id, name, cls, symmetry, image_path) in enumerate(rows):
        tile = Image.open(wh.root / image_path).convert("RGB").resize((TILE, TILE))
        draw = ImageDraw.Draw(tile)
        draw.text((3, 2), f"{name[:22]}", fill=(0, 0, 0))
        draw.text((3, TILE - 12), f"{cls}  sym {symmetry}", fill=(180, 0, 0))
        sheet.paste(tile, ((i % COLUMNS) * TILE, (i // COLUMNS) * TILE))
    out_file.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(out_file)
    return len(rows)
