"""``cadestate stats --html OUT``: the statistics as an HTML report.

``OUT/index.html``: Table 2 and section 4 figures, histograms (matplotlib, PNG), the cost of the
dataset, and a link per clip; ``OUT/clips/<clip>.html``: the clip's key-frames with its accepted
poses drawn over them (the posed CAD models rendered with the frame's camera, blended at 50 %, a
colour per object, its class and track id at its box) and its per-class counts. Images under
``OUT/img/``; every path in the pages is relative, so the folder can be moved or served as is.
"""

from __future__ import annotations

import html
import os
from collections import Counter
from pathlib import Path

import numpy as np

from tasks.dataset.objects import ClipDataset
from tasks.dataset.stats import DatasetTables, cost_lines, dataset_tables, statistics, statistics_lines
from tasks.human.shared import evenly_spaced
from warehouse import Warehouse

KEYFRAMES = 6
TITLE = "cadestate dataset statistics"
"""The index page's title: what marks a folder as holding an earlier report (:func:`check_report_folder`)."""
REPLACED = ("clips", "img", "index.html")
"""What a report replaces in its folder (:func:`write_report`); anything else there is left alone."""
PALETTE = ((230, 25, 75), (60, 180, 75), (255, 225, 25), (0, 130, 200), (245, 130, 48), (145, 30, 180),
           (70, 240, 240), (240, 50, 230), (210, 245, 60), (250, 190, 212))
STYLE = ("body{font-family:sans-serif;margin:2em;max-width:70em} table{border-collapse:collapse} "
         "td,th{border:1px solid #ccc;padding:.2em .6em;text-align:right} td:first-child{text-align:left} "
         "img{max-width:100%;margin:.3em 0}")


def _page(title: str, body: list[str]) -> str:
    return (f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>{html.escape(title)}</title>"
            f"<style>{STYLE}</style></head><body>\n<h1>{html.escape(title)}</h1>\n" + "\n".join(body) + "\n</body></html>\n")


def _table(rows: list[tuple[str, object]], head: tuple[str, str] = ("", "")) -> str:
    cells = "".join(f"<tr><td>{html.escape(str(a))}</td><td>{html.escape(str(b))}</td></tr>" for a, b in rows)
    return f"<table><tr><th>{html.escape(head[0])}</th><th>{html.escape(head[1])}</th></tr>{cells}</table>"


def _histogram(values, title: str, xlabel: str, path: Path, bins=20) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3), dpi=100)
    ax.hist(np.asarray(values, np.float64), bins=bins, color="#3070b0")
    ax.set_title(title)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("count")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def keyframe_stamps(ds: ClipDataset) -> list[int]:
    """The clip's key-frames: its frames its posed objects were clicked on (else the manual-track
    key-frames, else all frames), at most :data:`KEYFRAMES`, evenly spread. A click on a timestamp
    that is no frame of the clip (frames extracted again since) is not one: the report failed on it
    (KeyError)."""
    held = {f.timestamp_us for f in ds.frames}
    stamps = sorted({ts for o in ds.objects if o.pose is not None for ts in o.correspondences} & held)
    stamps = stamps or [f.timestamp_us for f in ds.frames if f.key_frame] or [f.timestamp_us for f in ds.frames]
    return [stamps[i] for i in evenly_spaced(len(stamps), KEYFRAMES)]


def frame_image(path: Path):
    """The frame image ``path`` as an RGB PIL image; :class:`tasks.cad.export.ExportError` naming
    it when it cannot be read (the warehouse's copy removed or damaged): the report said it could
    not write its own folder ("give a folder")."""
    from PIL import Image

    from tasks.cad.export import ExportError

    try:
        with Image.open(path) as image:
            return image.convert("RGB")
    except (OSError, ValueError) as e:  # missing, unreadable, not an image, truncated
        why = ("not an image" if isinstance(e, Image.UnidentifiedImageError)
               else e.strerror if isinstance(e, OSError) and e.strerror else " ".join(str(e).split())[:200])
        raise ExportError(f"{path}: cannot read this frame's image (missing or damaged: {why})") from None


def overlays(wh: Warehouse, ds: ClipDataset, folder: Path) -> list[Path]:
    """Write the clip's key-frames with its accepted poses drawn over them; returns the image paths."""
    from PIL import Image, ImageDraw

    from cadestate.render import Camera, Instance, Renderer, RenderMesh
    from tasks.cad.export import load_mesh

    meshes = {r["cad_id"]: r["mesh_path"] for r in wh.read("cad_models", columns=["cad_id", "mesh_path"]).to_pylist()}
    posed = [o for o in ds.objects if o.pose is not None and o.cad_id in meshes]
    loaded = {c: RenderMesh.from_trimesh(load_mesh(wh.root / meshes[c])) for c in {o.cad_id for o in posed}}
    frames = {f.timestamp_us: f for f in ds.frames}
    h, w = ds.image_size
    paths = []
    with Renderer(w, h) as renderer:
        for ts in keyframe_stamps(ds):
            f = frames[ts]
            image = np.asarray(frame_image(wh.root / f.image_path).resize((w, h)), np.float32)
            if posed:
                ids = renderer.render([Instance(loaded[o.cad_id], o.pose.matrix(), k + 1) for k, o in enumerate(posed)],
                                      Camera(f.K, f.R, f.t, w, h, 0.01, 1000.0)).instance_id
                for k in range(len(posed)):
                    mask = (ids == k + 1)[..., None]
                    image = np.where(mask, 0.5 * image + 0.5 * np.array(PALETTE[k % len(PALETTE)], np.float32), image)
            picture = Image.fromarray(np.clip(image, 0, 255).astype(np.uint8))
            draw = ImageDraw.Draw(picture)
            for k, o in enumerate(posed):
                if ts in o.boxes:
                    y0, x0, _, _ = o.boxes[ts]
                    draw.text((x0 * w + 2, y0 * h + 1), f"{o.class_name} {o.track_id}", fill=PALETTE[k % len(PALETTE)])
            path = folder / f"{ds.clip}_{ts}.jpg"
            picture.save(path, quality=88)
            paths.append(path)
    return paths


def check_report_folder(out: Path) -> None:
    """Refuse (:class:`tasks.cad.export.ExportError`) a folder ``out`` holding a ``clips``, ``img``
    or ``index.html`` that no report wrote (no report's ``index.html``: :data:`TITLE`): a report
    replaces them whole (a web site's own pages and pictures were deleted). What a report killed
    while moving into ``out`` left there is removed first (:func:`tasks.cad.export.remove_unfinished_move`)."""
    from tasks.cad.export import ExportError, remove_unfinished_move

    remove_unfinished_move(out)
    held = [name for name in REPLACED if os.path.lexists(out / name)]
    if held and not _report_index(out / "index.html"):
        raise ExportError(f"{out}: holds {held[0]!r}, which a report replaces, and no earlier report of `cadestate stats "
                          "--html`; choose a new folder (or that of an earlier report)")


def _report_index(path: Path) -> bool:
    """Whether ``path`` is the index page of a report (its title, :data:`TITLE`)."""
    try:
        with open(path, "rb") as f:
            return f"<title>{TITLE}</title>".encode() in f.read(4096)
    except OSError:  # missing, a folder, unreadable
        return False


def write_report(wh: Warehouse, clips: list[str], out: Path) -> tuple[dict, Path]:
    """Write the report (module docstring) of ``clips`` into ``out``; returns their figures
    (:func:`tasks.dataset.stats.statistics`) and ``out/index.html``. Each clip's dataset is read
    once, for its figures and its page together.
    It is made in a folder beside ``out``, then put in place (:func:`tasks.cad.export.publish`: its
    ``clips/``, ``img/`` and ``index.html`` replace those of an earlier report, in that order, the
    index last), so that a report stopped half-way (Ctrl-C) leaves ``out`` as it was. A folder
    holding a ``clips``, ``img`` or ``index.html`` of something else is refused (:func:`check_report_folder`)."""
    from tasks.cad.export import publish, temp_folder_beside

    out = Path(out).absolute()
    check_report_folder(out)
    out.parent.mkdir(parents=True, exist_ok=True)  # an OSError of its own: the caller names what cannot be written
    with temp_folder_beside(out) as tmp:
        (tmp / "img").mkdir()
        (tmp / "clips").mkdir()
        links: list[str] = []
        tables = dataset_tables(wh, clips, lambda ds: links.append(_write_clip_page(wh, ds, tmp)))
        stats = statistics(tables)
        _write_index(tables, stats, links, tmp)
        publish(tmp, out)
    return stats, out / "index.html"


def _write_clip_page(wh: Warehouse, ds: ClipDataset, out: Path) -> str:
    """Write the clip's page and pictures into the new report folder ``out``; returns its link (HTML)."""
    pictures = overlays(wh, ds, out / "img")
    counts = Counter(o.class_name for o in ds.objects if o.pose is not None)
    posed = sum(counts.values())
    body = [f"<p><a href=\"../index.html\">all clips</a> · {len(ds.frames)} frames · {len(ds.objects)} objects, "
            f"{posed} posed</p>", "<h2>Posed objects per class</h2>",
            _table(sorted(counts.items()), ("class", "posed objects")),
            "<h2>Key-frames with the accepted poses</h2>"]
    body += [f"<img src=\"../img/{html.escape(p.name)}\" alt=\"{html.escape(p.stem)}\">" for p in pictures]
    (out / "clips" / f"{ds.clip}.html").write_text(_page(f"Clip {ds.clip}", body), encoding="utf-8")
    return f"<li><a href=\"clips/{html.escape(ds.clip)}.html\">{html.escape(ds.clip)}</a> ({posed} posed)</li>"


def _write_index(tables: DatasetTables, stats: dict, links: list[str], out: Path) -> None:
    """Write the index page (figures, histograms, cost, ``links`` to the clip pages) into the new report folder ``out``."""
    figures = []
    if len(tables.visible):
        per_frame = tables.visible.groupby(["clip", "timestamp_us"]).size().reindex(
            list(map(tuple, tables.frames[["clip", "timestamp_us"]].to_numpy())), fill_value=0)
        _histogram(per_frame, "Posed objects visible per frame", "objects", out / "img" / "objects_per_frame.png",
                   bins=np.arange(per_frame.max() + 2) - 0.5)
        figures.append("objects_per_frame.png")
        d = tables.visible.dropna(subset=["distance_m"]).groupby(["clip", "timestamp_us"])["distance_m"]
        ratios = (d.min() / d.max())[d.count() >= 2]
        if len(ratios):
            _histogram(ratios, "Nearest / farthest object distance per frame", "ratio", out / "img" / "near_far.png")
            figures.append("near_far.png")
        truncated = tables.visible["truncated"].dropna()
        if len(truncated):
            _histogram(truncated, "Truncation per visible object", "share of its projected box outside the image",
                       out / "img" / "truncation.png")
            figures.append("truncation.png")
    body = ["<h2>Dataset (the paper's Table 2 and section 4)</h2>", _table(statistics_lines(stats), ("", "value")),
            "<h2>Posed objects per class</h2>", _table(list(stats["per_class"].items()), ("class", "posed objects")),
            *[f"<img src=\"img/{f}\" alt=\"{f}\">" for f in figures],
            "<h2>Cost of the dataset</h2>", _table(cost_lines(stats), ("", "")), "<h2>Clips</h2>", "<ul>", *links, "</ul>"]
    (out / "index.html").write_text(_page(TITLE, body), encoding="utf-8")
