"""Contact sheets: CAD models as pictures (first rendered view, labelled with name, class, symmetry)."""

from __future__ import annotations

import io
from pathlib import Path

from PIL import Image, ImageDraw, UnidentifiedImageError

from warehouse import Warehouse, WarehouseError, atomic_write_bytes
from warehouse.query import run_query, sql_condition

TILE = 160
COLUMNS = 8


def rendered_view(path: Path) -> Image.Image:
    """The rendered view ``path`` as an RGB image; a :class:`WarehouseError` naming it when the
    warehouse's file is missing or damaged (an OSError here read as the sheet's own path failing:
    "<sheet>: cannot write the sheet there: No such file or directory")."""
    try:
        with Image.open(path) as image:
            return image.convert("RGB")
    except (OSError, ValueError) as e:  # missing, unreadable, not an image, truncated
        why = ("not an image" if isinstance(e, UnidentifiedImageError)
               else e.strerror if isinstance(e, OSError) and e.strerror else " ".join(str(e).split())[:200])
        raise WarehouseError(f"{path}: cannot read this CAD model's rendered view (missing or damaged: {why})") from None


def contact_sheet(wh: Warehouse, out_file: Path, where: str = "true", limit: int = 48) -> int:
    """Write a PNG of up to ``limit`` models matching the SQL condition ``where``; returns the count
    (0: no model matches, and nothing is written). :class:`warehouse.query.QueryError` when ``where``
    is not one condition (:func:`warehouse.query.sql_condition`) or fails; a
    :class:`warehouse.WarehouseError` naming a file of the tables, or a rendered view, that cannot be read."""
    sql = (f"SELECT m.cad_id, m.name, m.class, m.symmetry, v.image_path FROM cad_models m JOIN cad_views v "
           f"USING (library, cad_id) WHERE v.view = 0 AND (\n{sql_condition(where)}\n) ORDER BY m.cad_id LIMIT {int(limit)}")
    out_file.parent.mkdir(parents=True, exist_ok=True)  # first: a path that cannot be written is said before anything
    with run_query(wh, sql) as result:  # read-only: ``where`` is the user's SQL
        rows = [row for batch in result.batches for row in batch]
    if not rows:
        return 0
    rows_n = max(1, -(-len(rows) // COLUMNS))
    sheet = Image.new("RGB", (TILE * COLUMNS, TILE * rows_n), "white")
    for i, (cad_id, name, cls, symmetry, image_path) in enumerate(rows):
        tile = rendered_view(wh.root / image_path).resize((TILE, TILE))
        draw = ImageDraw.Draw(tile)
        draw.text((3, 2), f"{name[:22]}", fill=(0, 0, 0))
        draw.text((3, TILE - 12), f"{cls}  sym {symmetry}", fill=(180, 0, 0))
        sheet.paste(tile, ((i % COLUMNS) * TILE, (i // COLUMNS) * TILE))
    picture = io.BytesIO()
    sheet.save(picture, format=Image.registered_extensions()[out_file.suffix.lower()])
    atomic_write_bytes(out_file, picture.getvalue())
    return len(rows)
