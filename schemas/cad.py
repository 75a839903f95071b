"""Tables of the CAD library, partitioned by ``library`` (one Sweet Home 3D set, a ShapeNet copy, a folder).

Canonical CAD frame (every mesh the library stores): metres, +Y up, the model's front facing +Z
(a ShapeNet model keeps ShapeNet's orientation, whatever its front), origin at the centre of its
axis-aligned bounding box. Object-to-world poses (later stages) map
this frame to the world: mirror => scale => rotation => translation (official CAD-Estate order).
"""

from __future__ import annotations

import pyarrow as pa

from schemas.base import LIBRARY, TableSpec, column, vector

CAD_ID = column("cad_id", pa.string(), "Model id, unique over all libraries ('<library>.<item>'); also its file name.")

CAD_MODELS = TableSpec(
    name="cad_models",
    mode="replace",
    key=("library", "cad_id"),
    description="One row per CAD model: class, source, licence, canonical size and symmetry, and its canonical mesh.",
    schema=pa.schema([
        LIBRARY,
        CAD_ID,
        column("class", pa.string(), "Class of the vocabulary (tasks/cad/classes.py)."),
        column("class_id", pa.string(), "Class id: ShapeNet synset, or cadestate-<class> for classes ShapeNet lacks."),
        column("name", pa.string(), "Item name in its source."),
        column("source_category", pa.string(), "Category in its source (kept as given)."),
        column("source", pa.string(), "sweethome3d | shapenet | folder."),
        column("source_path", pa.string(), "Where the mesh came from (file, or archive!member)."),
        column("licence", pa.string(), "Licence of the model."),
        column("creator", pa.string(), "Author / attribution of the model."),
        column("extent", vector(3), "Bounding-box size along x, y, z.", unit="m", frame="canonical CAD (+Y up, front +Z)"),
        column("symmetry", pa.int32(), "Rotational symmetry about +Y: 1, 2, 4 or 36 (Scan2CAD convention)."),
        column("symmetry_errors", vector(3), "Detector errors for orders 2, 4, 36 (relative to the model size)."),
        column("num_vertices", pa.int64(), "Vertices of the canonical mesh."),
        column("num_faces", pa.int64(), "Triangles of the canonical mesh."),
        column("textured", pa.bool_(), "Whether the mesh carries at least one texture image."),
        column("mesh_path", pa.string(), "Canonical mesh (GLB, textures embedded), relative to the warehouse root."),
    ]),
)

CAD_SAMPLES = TableSpec(
    name="cad_samples",
    mode="replace",
    key=("library", "cad_id"),
    description="Surface samples of each canonical mesh (area-uniform, deterministic), for geometry in later stages.",
    schema=pa.schema([
        LIBRARY,
        CAD_ID,
        column("points", pa.list_(vector(3, pa.float32())), "Surface points.", unit="m", frame="canonical CAD (+Y up, front +Z)"),
    ]),
)

CAD_VIEWS = TableSpec(
    name="cad_views",
    mode="replace",
    key=("library", "cad_id", "view"),
    description="Renders of each model from random viewpoints around it (for appearance retrieval), with their cameras.",
    schema=pa.schema([
        LIBRARY,
        CAD_ID,
        column("view", pa.int32(), "View index, 0-based."),
        column("image_path", pa.string(), "Rendered image, relative to the warehouse root."),
        column("width", pa.int32(), "Image width.", unit="px"),
        column("height", pa.int32(), "Image height.", unit="px"),
        column("azimuth_deg", pa.float64(), "Camera azimuth about +Y, 0 = in front of the model (on +Z).", unit="deg"),
        column("elevation_deg", pa.float64(), "Camera elevation above the horizontal.", unit="deg"),
        column("K", vector(9), "Intrinsics, row-major.", unit="px", frame="image, origin top-left"),
        column("world_to_camera_R", vector(9), "R of X_cam = R X + t, X in the canonical CAD frame.", frame="canonical CAD -> camera (OpenCV)"),
        column("world_to_camera_t", vector(3), "t of X_cam = R X + t.", unit="m", frame="canonical CAD -> camera (OpenCV)"),
    ]),
)

CAD_ISSUES = TableSpec(
    name="cad_issues",
    mode="replace",
    key=("library", "item"),
    description="Items of a CAD source that were skipped or ingested with a problem, and why.",
    schema=pa.schema([
        LIBRARY,
        column("item", pa.string(), "Item id in its source."),
        column("source_path", pa.string(), "File or archive member concerned."),
        column("severity", pa.string(), "skipped | warning."),
        column("problem", pa.string(), "What is wrong."),
    ]),
)
