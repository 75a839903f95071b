"""Pipeline configuration: one TOML file, one section per stage, validated strictly.

Every key has a default, so an empty file (or none) is a valid configuration. Unknown sections,
unknown keys, wrong types, out-of-range values (nan and inf included; integers must fit in 64 bits)
and keys that contradict each other are errors that name the file, the section and the key.
Checks that need a file the configuration names (the detector model) are
:func:`tasks.config_checks.check_config`'s, run by ``cadestate config check`` and before a run. Each stage section hashes to a short digest that the ``runs`` table records, so a rerun
knows which stages a config change made stale (see :mod:`cadestate.lineage`).

Sections ``warehouse`` and ``prefect`` say *where* and *how* to run; they do not change any
result and take no part in lineage. Every other section belongs to the stage of the same name.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import re
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cadestate.cron import cron_problem

DEFAULT_CONFIG_FILE = "cadestate.toml"
ENV_CONFIG = "CADESTATE_CONFIG"
ENV_WAREHOUSE = "CADESTATE_WAREHOUSE"
INT_RANGE = (-(2**63), 2**63 - 1)
"""Integer values must fit in int64 (the warehouse's and numpy's integers)."""
DESCRIPTOR_DIM = 768
"""Size of the appearance descriptors (tasks/detection/models/embedder.py DIM): the most [cad_embed] whitening_dims keeps."""
_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")


class ConfigError(ValueError):
    """An invalid configuration; the message names the file, section and key."""


def _opt(default: Any, doc: str, *, choices: tuple | None = None, lo: float | None = None, hi: float | None = None,
         check: Callable[[Any], str | None] | None = None, runtime: bool = False,
         file_unless: tuple[str, ...] | None = None):
    """A config key with its documentation and constraints (kept in dataclass field metadata);
    ``check(value)`` says what else is wrong with a value, or None; ``runtime``: the key says how
    to run (threads, workers, links), not what comes out, so it is left out of the section's
    digest (:func:`section_hash`) and changing it reruns nothing; ``file_unless``: the key names a
    file that clip stages read, unless it is one of these names (see :func:`absolute_paths`)."""
    return field(default=default, metadata={"doc": doc, "choices": choices, "lo": lo, "hi": hi, "check": check,
                                            "runtime": runtime, "file_unless": file_unless})


def _non_empty(value: str) -> str | None:
    """A path or name: not empty, and no NUL (no file can be named with one: a traceback at the first open)."""
    return "must not be empty" if not value.strip() else "must not hold a NUL character" if "\0" in value else None


def _template_problem(template: str) -> str | None:
    """What is wrong with a name template (a format string that writes the name), or None."""
    try:
        written = template.format("\0")
    except (IndexError, KeyError, ValueError, AttributeError, TypeError) as e:
        return f"not a format string with one '{{}}' for the name ({type(e).__name__}: {e})"
    return None if "\0" in written else "must contain '{}', where the name goes"


@dataclass(frozen=True)
class WarehouseConfig:
    """Where the warehouse lives (not part of lineage)."""

    root: str = _opt("data/warehouse", "Warehouse root directory; env CADESTATE_WAREHOUSE and --warehouse override it.",
                     check=_non_empty)
    compact_after_files: int = _opt(64, "Files an append-mode partition (runs, label_files, label_tasks) may hold before "
                                    "a write compacts it into one (`cadestate compact` compacts by hand).", lo=2, hi=1_000_000)
    snapshot_after_clips: int = _opt(100, "A batch of at least this many clips (`cadestate ingest FOLDER`, `cadestate run`) "
                                     "ends with what `cadestate compact` does (a new snapshot of the tables in the catalog, so "
                                     "SQL opens only the files written since); 0: never.", lo=0, hi=1_000_000_000)


@dataclass(frozen=True)
class PrefectConfig:
    """How flows run (not part of lineage)."""

    task_runner: str = _opt("threads", "Task runner: 'threads' (local threads) or 'dask' (a Dask cluster: each worker runs whole clips; other flows, the CAD library's, run on local threads).", choices=("threads", "dask"))
    max_workers: int = _opt(2, "Worker threads for the 'threads' runner; worker processes (one thread each) of the local Dask cluster.", lo=1, hi=256)
    dask_address: str = _opt("", "Address of a running Dask scheduler (its workers see the warehouse at the same path); empty starts a local cluster.")
    startup_timeout_s: float = _opt(180.0, "Seconds to wait for Prefect's API to start (`cadestate server start`; ephemeral mode retries once on a new port after a third of them).",
                                    lo=1, hi=3600)


@dataclass(frozen=True)
class ScheduleConfig:
    """What `cadestate serve` schedules on the Prefect server (not part of lineage)."""

    inbox: str = _opt("data/inbox", "Folder of new clips (<name>.mp4, .mkv, .webm, .mov or .avi + <name>.txt) that the build_dataset deployment ingests.", check=_non_empty)
    inbox_cron: str = _opt("*/10 * * * *", "Cron schedule of the build_dataset deployment (UTC).", check=cron_problem)
    inbox_split: str = _opt("train", "Dataset split of the inbox's clips (val and test clips get the manual-track task).")
    labels_inbox: str = _opt("data/labels_inbox", "Folder of label files that the ingest_labels deployment ingests.", check=_non_empty)
    labels_cron: str = _opt("*/5 * * * *", "Cron schedule of the ingest_labels deployment (UTC).", check=cron_problem)
    stable_s: float = _opt(10.0, "A clip's files are taken once neither was modified (mtime) for this long "
                                 "(or at once when <name>.done exists): half-copied files wait.", lo=0, hi=86400)
    report: str = _opt("data/report", "Folder the dataset_report deployment writes the statistics to (stats.json, HTML report).", check=_non_empty)
    report_cron: str = _opt("0 3 * * *", "Cron schedule of the dataset_report deployment (UTC).", check=cron_problem)
    failed_runs: int = _opt(3, "A clip whose same stage failed this many runs in a row, with the config and code of now, "
                               "is not run again by the inbox (it failed again every tick) until its files, the config "
                               "or the code change; 0 runs it again every tick.", lo=0, hi=1000)
    clip_runs: int = _opt(2, "Clips the served annotate_clip deployment runs at once (a clip suspended while it waits "
                             "for people holds no slot); more wait, queued, for a slot.", lo=1, hi=256)
    suspend_timeout_s: int = _opt(7 * 86400, "A served clip waiting for people is suspended this long at most before it fails.",
                                  lo=60, hi=365 * 86400)


@dataclass(frozen=True)
class IngestConfig:
    """Stage ``ingest``: validate a clip's video and camera file and register it."""

    link_inputs: bool = _opt(True, "Hard-link inputs into the warehouse when possible instead of copying them.", runtime=True)
    up: str = _opt("auto", "The camera file's world up: 'auto' estimates it from the cameras (level, upright phones; "
                   "tasks/video/world_up.py), or force an axis of that world ('+y' for worlds built +Y up, '-y' for "
                   "ORB-SLAM worlds whose first camera is level). The world is turned to +Y up at ingest.",
                   choices=("auto", "+x", "-x", "+y", "-y", "+z", "-z"))
    up_line_frames: int = _opt(16, "With up = 'auto': frames (evenly over the clip) searched for vertical lines (wall "
                               "corners, door and window frames, furniture legs) that refine the up the cameras give "
                               "(tasks/video/vertical_lines.py); 0 uses the cameras alone.", lo=0, hi=10000)
    up_line_tolerance_deg: float = _opt(0.5, "How far (degrees) a line segment may lean from the up direction and still "
                                        "count as vertical; raise it for lens distortion or rolling shutter.",
                                        lo=0.01, hi=5.0)


@dataclass(frozen=True)
class CamerasConfig:
    """Stage ``cameras``: structure from motion (pycolmap) for a video ingested without a camera file."""

    sample_fps: float = _opt(15.0, "Frames per second sampled from the video (RealEstate10K: every 2nd frame of 30 fps); "
                             "each sampled frame gets a camera line.", lo=0.1, hi=240.0)
    max_image_size: int = _opt(1024, "Longest image side fed to feature extraction (larger frames are downscaled).",
                               lo=64, hi=8192)
    max_features: int = _opt(4096, "SIFT features per frame.", lo=64, hi=65536)
    overlap: int = _opt(20, "Sequential matching: each frame is matched with the frames 2^k ahead, k = 0 .. overlap - 1 "
                        "(1, 2, 4, 8, ...: pycolmap 4's quadratic overlap; not every frame in between; 20 reaches "
                        "across any clip).", lo=1, hi=1000)
    min_registered_fraction: float = _opt(0.8, "Fail when SfM registers fewer of the sampled frames than this fraction; "
                                          "the rest are interpolated between registered neighbours and flagged.",
                                          lo=0.0, hi=1.0)
    init_min_tri_angle_deg: float = _opt(16.0, "Smallest triangulation angle of the incremental mapper's initial pair "
                                         "(the focal hypotheses, and mapper = 'incremental'; COLMAP's default 16; lower "
                                         "it for videos with very little parallax).", lo=0.5, hi=60.0)
    fov_min_deg: float = _opt(40.0, "Narrowest horizontal field of view (of the image width) SfM tries when no intrinsics "
                              "are given (tasks/video/sfm_focal.py).", lo=5.0, hi=170.0)
    fov_max_deg: float = _opt(100.0, "Widest horizontal field of view SfM tries when no intrinsics are given.", lo=5.0, hi=170.0)
    fov_hypotheses: int = _opt(6, "Focal lengths tried between fov_max_deg and fov_min_deg (even in log focal), each "
                               "mapped with the focal held fixed, then bundle-adjusted with it free; the adjusted "
                               "focal of the lowest mean reprojection error wins.", lo=2, hi=50)
    focal_frames: int = _opt(35, "The focal hypotheses each map about this many of the sampled frames, evenly spaced "
                             "(every k-th, k = round(frames / focal_frames), at least 1).", lo=3, hi=10000)
    global_ba_growth: float = _opt(0.05, "The incremental mapper (the focal hypotheses, and mapper = 'incremental') adjusts "
                                   "the whole model (global bundle adjustment) each time it grows by "
                                   "this fraction of frames or points (COLMAP's default 0.1). With 0.1 a benchmark clip's "
                                   "forward walk of little rotation bent: 3.8 degrees and 19 % of the path off; 0.07 and "
                                   "0.4 % with 0.02, as with 0.05 and the polish below, which maps in about 4/5 of the "
                                   "time.", lo=0.001, hi=10.0)
    keyframe_every: int = _opt(2, "The mapper maps every k-th sampled frame; each frame in between is registered to the "
                               "finished model alone (absolute pose from its matches with the mapped frames, with the "
                               "incremental mapper's inlier thresholds; tasks/video/sfm_register.py). 1 maps every frame.",
                               lo=1, hi=100)
    mapper: str = _opt("global", "How the keyframes are mapped: 'global' (GLOMAP in pycolmap: rotation averaging over "
                       "the matched pairs, then global positioning and bundle adjustment) or 'incremental' (COLMAP's "
                       "incremental mapper, frame by frame; on a benchmark forward walk it bent the path by 18 % "
                       "whenever any of its options moved, global mapping did not).",
                       choices=("global", "incremental"))
    polish_reproj_error_px: float = _opt(2.0, "After mapping, observations reprojecting farther than this many pixels "
                                         "are dropped and the model bundle-adjusted again, three times (the mappers "
                                         "keep looser ones: COLMAP's incremental mapper up to 4 px). On a "
                                         "benchmark clip's sideways walk the stray matches had bent the path by "
                                         "2.2 % and put the focal length 8.6 % low; 1.3 % and 0.4 % polished. "
                                         "0 turns it off.", lo=0.0, hi=100.0)
    max_focal_change: float = _opt(0.1, "The final bundle adjustment frees the focal length and is kept when it moves the "
                                   "focal length the mapping held by less than this fraction.", lo=0.001, hi=1.0)
    focal_remaps: int = _opt(2, "When the final bundle adjustment moves the focal length farther than max_focal_change, "
                             "the keyframes are mapped again holding the focal length it moved to, up to this many "
                             "times (on 21 benchmark clips the hypotheses put 4 focal lengths 18-38 % off; remapped, all "
                             "were within 3 %; a remap costs about a mapping's time). 0: keep the first mapping.", lo=0, hi=10)
    threads: int = _opt(1, "Threads for mapping and bundle adjustment (matching runs on one: more verify pairs with "
                   "other random draws). More than 1 is faster but not reproducible: parallel sums differ run to run, "
                   "and SfM then gives other cameras, at times another model.", lo=1, hi=256)
    workers: int = _opt(2, "Threads for feature extraction and for the focal hypotheses; the cameras do not depend on it "
                        "(the frames enter the database in time order before their features, and each hypothesis maps "
                        "its own copy of the database).", lo=1, hi=256, runtime=True)
    seed: int = _opt(0, "Random seed of two-view verification and the mapper (same seed, same cameras).", lo=0, hi=2**31 - 1)


@dataclass(frozen=True)
class FramesConfig:
    """Stage ``frames``: extract the video frame at every camera timestamp."""

    image_format: str = _opt("jpg", "Frame image format.", choices=("jpg", "png"))
    jpeg_quality: int = _opt(95, "JPEG quality (1-100) when image_format = 'jpg'.", lo=1, hi=100)
    max_timestamp_error_us: int = _opt(
        3000, "Largest accepted |decoded frame time - camera timestamp| in µs (the official tool expects 2,000-3,000).", lo=0
    )
    seek_threshold_us: int = _opt(
        1_000_000, "Seek when the next camera timestamp is further ahead than this; decode forward otherwise.", lo=0
    )


@dataclass(frozen=True)
class CadIngestConfig:
    """Stage ``cad_ingest``: canonicalise a CAD library, detect symmetries, sample surfaces."""

    source: str = _opt("", "CAD source folder (Sweet Home 3D *.sh3f, ShapeNet layout, or meshes + models.csv); empty = the embedded Sweet Home 3D library. Where to look only: the library's items are the stage's input, so naming its folder otherwise reruns nothing.", runtime=True)
    samples: int = _opt(4096, "Surface samples per model (symmetry detection, later geometry).", lo=256, hi=1_000_000)
    symmetry_tolerance: float = _opt(0.008, "Largest symmetric-copy distance, relative to the model size, that counts as symmetric.", lo=0.0, hi=1.0)
    workers: int = _opt(2, "Processes that ingest models in parallel (results do not depend on it).", lo=1, hi=256, runtime=True)


@dataclass(frozen=True)
class CadViewsConfig:
    """Stage ``cad_views``: render every model from random viewpoints (for appearance retrieval)."""

    views: int = _opt(10, "Rendered views per model.", lo=1, hi=100)
    size: int = _opt(224, "Side of the square renders.", lo=32, hi=2048)
    seed: int = _opt(0, "Seed of the random viewpoints.", lo=0)


@dataclass(frozen=True)
class DetectConfig:
    """Stage ``detect``: run an ONNX object detector on every frame of a clip."""

    adapter: str = _opt("nanodet", "Output layout of the ONNX model (see tasks/detection/detectors.py): 'nanodet' or 'yolov8'.", choices=("nanodet", "yolov8"))
    model: str = _opt("furniture", "Detector: 'furniture' (NanoDet-m with class rows for the CAD classes, trained by `make models` on "
                                   "rooms rendered from the CAD library), 'coco' (NanoDet-m, COCO-80), or an ONNX file.",
                       file_unless=("", "furniture", "coco"))
    labels: tuple = _opt((), "Label map: class names in the model's output order; empty = the built-in model's (COCO-80 for a file).")
    input_size: int = _opt(480, "Longer side of the letterboxed network input (NanoDet-m: 480 on the fitted canvas, the default, "
                                "416 on the square it was trained on; usually 640 for YOLOv8).", lo=32, hi=4096)
    canvas: str = _opt("fit", "Network input around the letterboxed image: 'fit' pads it only up to a multiple of 32 (a 640x360 "
                              "frame at input_size 480 runs on 480x288: 0.80 of the pixels of 416x416, and more of them on each "
                              "object), for NanoDet graphs and models whose input height and width are open (others run on the "
                              "square); 'square' pads it to input_size x input_size (what the built-in detectors were trained on, "
                              "at 416).",
                       choices=("square", "fit"))
    score_threshold: float = _opt(0.35, "Lowest detection score kept.", lo=0.0, hi=1.0)
    nms_iou: float = _opt(0.45, "Class-aware NMS: a box overlapping a better one of its class above this IoU is dropped.", lo=0.0, hi=1.0)
    nms_containment: float = _opt(0.8, "Class-aware NMS: a box with more than this share of its area inside a better one of its class "
                                       "is dropped (a part of an object boxed again); 1 = never.", lo=0.0, hi=1.0)
    nms_agnostic_iou: float = _opt(0.6, "NMS across classes: a box overlapping a better one of any class above this IoU is dropped "
                                        "(one object boxed under two names); 1 = never.", lo=0.0, hi=1.0)
    max_detections: int = _opt(100, "Most detections kept per frame (best scores first).", lo=1, hi=10_000)
    classes: tuple = _opt((), "Keep only these labels (e.g. furniture); empty keeps every label.")
    batch_size: int = _opt(8, "Frames per network call (a model whose input batch is fixed takes that many).", lo=1, hi=1024)
    threads: int = _opt(2, "onnxruntime intra-op threads (results do not depend on it).", lo=1, hi=256, runtime=True)


@dataclass(frozen=True)
class EmbedConfig:
    """Stage ``embed``: one appearance descriptor per detection crop, from the detector's own
    backbone (NanoDet-m, average-pooled). ``cad_embed`` embeds the CAD views with these settings too."""

    crop_size: int = _opt(128, "Side of the square letterboxed crop fed to the embedder (a multiple of 32: the "
                               "backbone's stride).", lo=32, hi=1024, check=lambda v: None if v % 32 == 0 else "must be a multiple of 32")
    context: float = _opt(0.1, "Box margin added on every side before cropping, as a fraction of the box size.", lo=0.0, hi=2.0)
    batch_size: int = _opt(32, "Crops per network call.", lo=1, hi=4096)
    threads: int = _opt(2, "onnxruntime intra-op threads (results do not depend on it).", lo=1, hi=256, runtime=True)


@dataclass(frozen=True)
class CadEmbedConfig:
    """Stage ``cad_embed``: embed every CAD view (with the ``[embed]`` settings) and fit the
    centring or whitening that every descriptor goes through before it is compared."""

    whitening: str = _opt("learned", "Transform of the descriptors before they are compared: 'learned' (the projection `make models` "
                                     "trains on rooms rendered from the CAD library, centred on the mean view descriptor of the library it was trained on: one map for every library), or fitted on the "
                                     "library's views: 'none', 'centre', 'whiten' (PCA whitening).",
                          choices=("none", "centre", "whiten", "learned"))
    whitening_dims: int = _opt(128, f"Dimensions kept by 'whiten' (at most the descriptor size, {DESCRIPTOR_DIM}).",
                               lo=1, hi=DESCRIPTOR_DIM)


@dataclass(frozen=True)
class TrackingConfig:
    """Stage ``tracking``: associate a clip's detections into tracks by clique partitioning of the
    graph of pairwise log-odds (cues and their fitted calibration: tasks/tracking/affinity.py,
    tasks/tracking/calibration.py)."""

    window: int = _opt(8, "Detections at most this many frames apart get an edge (farther pairs weigh 0).", lo=1, hi=1000)
    min_score: float = _opt(0.0, "Detections scoring below this are left out of tracking.", lo=0.0, hi=1.0)
    use_cameras: bool = _opt(True, "Compensate box motion for the camera rotation between two frames.")
    appearance_weight: float = _opt(1.0, "Multiplier of the appearance log-likelihood ratio (0 switches the cue off).", lo=0.0, hi=100.0)
    label_weight: float = _opt(1.0, "Multiplier of the label-agreement log-likelihood ratio.", lo=0.0, hi=100.0)
    motion_weight: float = _opt(1.0, "Multiplier of the box-continuity log-likelihood ratio.", lo=0.0, hi=100.0)
    bias: float = _opt(0.0, "Added to every edge's log-odds (negative: fewer, purer merges).", lo=-100.0, hi=100.0)
    refine: bool = _opt(True, "Refine the greedy contraction by Kernighan-Lin moves and joins.")
    min_detections: int = _opt(3, "Tracks with fewer detections are dropped (1 keeps singletons).", lo=1, hi=1_000_000)
    merge: bool = _opt(True, "Join the fragments of one object in 3D after the partition (tasks/tracking/merge.py).")
    merge_min_probability: float = _opt(0.5, "Fragments are joined when the merge model (tasks/tracking/merge_calibration.py) "
                                             "gives them at least this probability of being one object.", lo=0.0, hi=1.0)
    thin_detections: int = _opt(6, "Tracks with fewer detections and no box on a manual-track key-frame ([manual_tracks] "
                                   "keyframes) are too thin to annotate: dropped (1 keeps them).", lo=1, hi=1_000_000)
    shadow_iou: float = _opt(0.5, "A track at least shadow_share of whose boxes overlap the boxes of a stronger track, no less "
                                  "sure of itself (mean score), on their frames this much (IoU) follows that track's object "
                                  "again (tasks/tracking/shadow.py): dropped (1 keeps them).", lo=0.01, hi=1.0)
    shadow_share: float = _opt(0.5, "Share of a track's boxes that must overlap a stronger track's for it to be a shadow.",
                               lo=0.01, hi=1.0)
    min_track_score: float = _opt(0.0, "Tracks whose detections score less than this on average are dropped as too weak to "
                                       "annotate (0 keeps them): mostly boxes on no object or on part of one that the "
                                       "detector barely kept ([detect] score_threshold 0.35). At 0.4, on the three tuning "
                                       "benchmarks, people are asked 4-6 % fewer items per posed object and IDF1 rises a "
                                       "point, but one object of 143 is lost, a sink whose only track scored 0.385 (README, "
                                       "Tracking); off by default, since the yield leads.",
                                  lo=0.0, hi=1.0)


@dataclass(frozen=True)
class ManualTracksConfig:
    """Stage ``manual_tracks`` (human task, paper 3.1): on the val/test clips people draw the objects
    the automatic tracks missed, as boxes on key-frames regularly spaced in time, in one of the
    detector labels retrieval can score; the drawn boxes are embedded with the ``[embed]`` settings."""

    splits: tuple = _opt(("val", "test"), "Clip splits (`cadestate ingest --split`) that get the task; other clips "
                                          "complete at once with no manual track.")
    keyframes: int = _opt(6, "Key-frames of the task, regularly spaced in time over the clip (the paper's 6).", lo=1, hi=1000)


@dataclass(frozen=True)
class PoseConfig:
    """Stage ``pose``: 9-DoF pose of every annotated track from its correspondences (paper 3.4; tasks/pose/solver.py)."""

    alpha: float = _opt(100.0, "Weight of the up-axis term |R e_y - e_y|_1 (px per unit); 0 switches it off.", lo=0.0)
    beta: float = _opt(1000.0, "Weight of the front-of-camera term (px per metre of depth below min_depth).", lo=0.0)
    min_depth: float = _opt(0.05, "Depth (m) below which an annotated point counts as not in front of its camera: "
                            "metres of the object's CAD model, so worlds of any scale (SfM, RealEstate10K) alike.", lo=0.0)
    upright_classes: tuple = _opt(
        ("chair", "sofa", "bed", "table", "cabinet", "bookshelf", "lamp", "display", "bin", "plant", "bathtub", "toilet",
         "sink", "bench", "piano", "stove", "microwave", "washer", "refrigerator", "radiator", "jar", "clock",
         "loudspeaker", "door", "window", "vehicle"),
        "Classes that stand upright: the up-axis term applies to them (default: the upright classes of tasks/cad/classes.py).")
    iterations: int = _opt(400, "Adam iterations (the fallback for objects the LM leaves unusable; all objects when lm_iterations = 0).", lo=1, hi=100_000)
    lr: float = _opt(0.02, "Initial Adam learning rate (rotation 6D, log-scale, translation in units of camera distance).", lo=1e-6, hi=1.0)
    lr_final: float = _opt(1e-5, "Learning rate at the last iteration (exponential decay; at most lr).", lo=1e-9, hi=1.0)
    lm_iterations: int = _opt(20, "Levenberg-Marquardt (IRLS) iterations from the closed-form starts (Adam only as fallback); 0 = Adam only, as in the paper.", lo=0, hi=10_000)
    starts: int = _opt(4, "Starts per object: the linear fit turned by i*360/starts degrees about its up axis.", lo=1, hi=64)
    coplanar: bool = _opt(True, "Tie the scale perpendicular to co-planar 3D points to the mean of the other two.")
    symmetry: bool = _opt(True, "Per key-frame best symmetric rotation (2/4/36-way models); 36-way: sx = sz.")
    coplanar_tol: float = _opt(0.02, "Co-planar (collinear) when the smallest (middle) singular value of the centred 3D points is below this fraction of the largest.", lo=0.0, hi=1.0)
    min_axis_span: float = _opt(0.2, "A CAD axis along which the clicked 3D points span less than this fraction of the model's size hardly tells its size: the correspondences page warns of it, and the scale prior (axis_prior, when on) holds it to the model's proportions; 0 = never.", lo=0.0, hi=1.0)
    axis_prior: float = _opt(0.0, "Weight of the scale prior on such axes: weight x (log-scale - the observed axes' mean log-scale)^2 px, pulling the axis towards the model's proportions against what the clicks say (10 measured best on the solver benchmark, but it cost make run's demo an accepted pose; see README, Pose); 0 = none (the default: free scales, as the paper).", lo=0.0)
    proportion_prior: float = _opt(1.0, "Weight of the chosen model's proportions on every scale the co-planar tie and axis_prior leave free: weight x (log-scale - the mean log-scale of all untied axes)^2 px. A fraction of a pixel where the clicks tell the proportions; it decides where they leave them free (a thin model's depth, clicks on a few centimetres of a chair: free scales made them 0 deep or up to twice as deep). See README, Pose; 0 = free scales, as the paper.", lo=0.0)
    min_points: int = _opt(6, "Fewest correspondences per track to solve it.", lo=5, hi=10_000)
    max_reprojection_px: float = _opt(20.0, "Mean reprojection error (px) above which a pose gets status high_residual.", lo=0.0)
    min_parallax_deg: float = _opt(1.0, "Key-frames seeing the object under less angle than this: status low_parallax (ok when the support prior rests it on a support seen under at least this angle from its cameras, which then fixes its depth).", lo=0.0, hi=180.0)
    threads: int = _opt(1, "Torch threads (1 is fastest for a clip's few objects; results do not depend on it).", lo=1,
                        hi=256, runtime=True)
    huber_px: float = _opt(5.0, "Reprojection loss: Huber, quadratic within this many px and L1 beyond; 0 = the paper's L1.", lo=0.0)
    floor_prior: float = _opt(30.0, "Support prior (tasks/pose/support.py): weight, px per object height, of the distance between a resting object's bottom and its support (world +Y up): its clip's floor (the inverse-variance weighted mean of its solved floor objects' bottoms within floor_max_gap of their weighted median) or the top of another solved object it stands over; 0 switches it off.", lo=0.0)
    floor_classes: tuple = _opt(
        ("chair", "sofa", "bed", "table", "cabinet", "bookshelf", "bin", "bathtub", "toilet", "bench", "piano", "stove",
         "washer", "refrigerator"),
        "Classes that rest on the floor: they estimate their clip's floor (classes often on furniture, e.g. lamp, plant, display, are left out).")
    wall_classes: tuple = _opt(
        ("window", "clock", "radiator"),
        "Upright classes fixed to walls rather than resting on a surface: no support prior (every other upright class rests on the floor or on another object).")
    host_supports: bool = _opt(True, "Besides the floor, the top of another solved, floor-supported object is a support when the object's centre lies over its footprint; false: the floor only.")
    floor_max_gap: float = _opt(0.5, "A resting object whose own bottom is more than this many object heights above the floor and from every host top keeps its own pose (a bottom below the floor always takes the floor); the floor estimate averages the floor objects within this gap of their median.", lo=0.0)
    floor_max_growth: float = _opt(0.5, "The pose re-solved with the support prior is kept only if its reprojection loss grew by at most this fraction.", lo=0.0)


@dataclass(frozen=True)
class LabelSimilarityConfig:
    """Stage ``label_similarity``: cosine of every detector label and every CAD class (sentence encoder)."""

    template: str = _opt("{}", "How a name is written before embedding ('{}' is the name, e.g. 'a photo of a {}').",
                         check=_template_problem)


@dataclass(frozen=True)
class RetrievalConfig:
    """Stage ``retrieval``: the top CAD models of every track (appearance x class-label similarity)."""

    top_k: int = _opt(10, "Candidates kept per track (at most 10, as many as the CAD-selection task shows: the paper shows annotators 10).", lo=1, hi=10)
    class_exponent: float = _opt(0.1, "The class-label similarity enters the score raised to this power: 1 is the paper's "
                                      "product, 0 appearance alone; below 1 the soft class filter weighs less against "
                                      "appearance, for a detector whose labels are often wrong (ours: precision 0.6). 0.1 "
                                      "was chosen on tuning seeds (true model among 10: 0.85 at 1, 0.90 at 0.1, 0.86 at 0).",
                                 lo=0.0, hi=10.0)
    max_per_class: int = _opt(7, "At most this many candidates of one CAD class while other classes have models "
                                 "(the rest go to the best-scoring models of other classes): a track whose boxes the "
                                 "detector misnames still gets a few models of other kinds. top_k or more: no cap. 7 was "
                                 "chosen on tuning seeds (true class among 10: 0.935 without the cap, 0.963 at 7; true "
                                 "model 0.850 both; yield 142 of 212 objects both).",
                              lo=1, hi=1000)
    drawn_class_exponent: float = _opt(1.0, "class_exponent for a manual track, whose class a person drew: 1, the "
                                            "paper's product (the filter is tempered above for a detector's guesses, "
                                            "not for a person's answer).", lo=0.0, hi=10.0)


@dataclass(frozen=True)
class CadSelectionConfig:
    """Stage ``cad_selection`` (human task, paper 3.2): per track, people pick one of its CAD candidates."""

    keyframes: int = _opt(6, "Evenly spaced frames of each track shown with its box.", lo=1, hi=100)


@dataclass(frozen=True)
class CorrespondenceTaskConfig:
    """Stage ``correspondence_task`` (human task, paper 3.3): 3D<->2D clicks on the chosen CAD model."""

    keyframes: int = _opt(6, "Evenly spaced frames of each track offered for clicking (a pose needs two views).", lo=2, hi=100)


@dataclass(frozen=True)
class VerificationConfig:
    """Stage ``verification`` (human task, paper 3.5): people accept or reject each solved pose."""

    keyframes: int = _opt(6, "Key-frames of each posed track rendered with the CAD overlay.", lo=1, hi=100)
    overlay_alpha: float = _opt(0.5, "Opacity of the rendered CAD over the frame.", lo=0.0, hi=1.0)
    duplicate_overlap: float = _opt(0.3, "Two poses of a clip whose posed CAD boxes overlap by at least this fraction of the "
                                         "smaller box's volume are flagged in the verification task as maybe the same object "
                                         "(tasks/pose/duplicates.py); 0 flags every pair, 1 only a box wholly inside the other. "
                                         "On 8 benchmark clips, poses of one object overlapped by 0.50-1.0, of different "
                                         "objects (a chair at a table) by at most 0.17.", lo=0.0, hi=1.0)
    carry_max_px: float = _opt(2.0, "A verdict given on an earlier task of the clip holds for the track's pose now (same model "
                                    "and mirroring) while its overlay moved by at most this many pixels: the corners of the "
                                    "posed model's box, on every key-frame either pose is shown on "
                                    "(tasks/human/verdicts_in_force.py). Poses move a little when another pose of the clip "
                                    "is solved (the floor they share). 0: only the identical pose.", lo=0.0, hi=1000.0)


@dataclass(frozen=True)
class Config:
    """The whole configuration. ``source`` is the file it came from (None for built-in defaults)."""

    warehouse: WarehouseConfig = field(default_factory=WarehouseConfig)
    prefect: PrefectConfig = field(default_factory=PrefectConfig)
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)
    cameras: CamerasConfig = field(default_factory=CamerasConfig)
    ingest: IngestConfig = field(default_factory=IngestConfig)
    frames: FramesConfig = field(default_factory=FramesConfig)
    cad_ingest: CadIngestConfig = field(default_factory=CadIngestConfig)
    cad_views: CadViewsConfig = field(default_factory=CadViewsConfig)
    cad_embed: CadEmbedConfig = field(default_factory=CadEmbedConfig)
    label_similarity: LabelSimilarityConfig = field(default_factory=LabelSimilarityConfig)
    detect: DetectConfig = field(default_factory=DetectConfig)
    embed: EmbedConfig = field(default_factory=EmbedConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    manual_tracks: ManualTracksConfig = field(default_factory=ManualTracksConfig)
    retrieval: RetrievalConfig = field(default_factory=RetrievalConfig)
    cad_selection: CadSelectionConfig = field(default_factory=CadSelectionConfig)
    correspondence_task: CorrespondenceTaskConfig = field(default_factory=CorrespondenceTaskConfig)
    pose: PoseConfig = field(default_factory=PoseConfig)
    verification: VerificationConfig = field(default_factory=VerificationConfig)
    source: str | None = None

    def section(self, name: str) -> Any:
        """The dataclass of section ``name``."""
        if name not in SECTIONS:
            raise KeyError(f"unknown config section {name!r}")
        return getattr(self, name)

    def section_hash(self, name: str) -> str:
        """Digest of one section (see :func:`section_hash`)."""
        return section_hash(name, self.section(name))


SECTIONS: dict[str, type] = {
    "warehouse": WarehouseConfig,
    "prefect": PrefectConfig,
    "schedule": ScheduleConfig,
    "cameras": CamerasConfig,
    "ingest": IngestConfig,
    "frames": FramesConfig,
    "cad_ingest": CadIngestConfig,
    "cad_views": CadViewsConfig,
    "cad_embed": CadEmbedConfig,
    "label_similarity": LabelSimilarityConfig,
    "detect": DetectConfig,
    "embed": EmbedConfig,
    "tracking": TrackingConfig,
    "manual_tracks": ManualTracksConfig,
    "retrieval": RetrievalConfig,
    "cad_selection": CadSelectionConfig,
    "correspondence_task": CorrespondenceTaskConfig,
    "pose": PoseConfig,
    "verification": VerificationConfig,
}
"""Section name -> dataclass; one entry per field of :class:`Config` (a test keeps them in step)."""
RUNTIME_SECTIONS = ("warehouse", "prefect", "schedule")
"""Sections that do not affect results (no lineage)."""


def runtime_keys(section: Any) -> frozenset[str]:
    """The keys of a section dataclass that do not affect results (``_opt(..., runtime=True)``)."""
    return frozenset(f.name for f in dataclasses.fields(section) if f.metadata.get("runtime"))


def section_hash(name: str, section: Any) -> str:
    """Stable 16-hex digest of a section's values that affect results (key order and file formatting
    do not matter; :func:`runtime_keys` are left out; a key naming a file counts as "a file": the
    stages reading it digest its bytes among their inputs (``[detect] model``: the detect stage's
    model fingerprint), and its path, absolute, made every clip's detection run again in another
    folder or on another machine with the same file; a Dask worker, given absolute paths, digests
    what a run here does). Remembered by the section's ``repr`` (which
    tells 1 from 1.0 and True, as the digest does): a long-lived process digests the same sections
    for every stage of every resume."""
    section = _files_unnamed(section)
    key = (name, repr(section))
    known = _SECTION_HASHES.get(key)
    if known is None:
        skip = runtime_keys(section)
        values = {k: v for k, v in dataclasses.asdict(section).items() if k not in skip}
        payload = json.dumps({"section": name, **values}, sort_keys=True)
        known = _SECTION_HASHES[key] = hashlib.sha256(payload.encode()).hexdigest()[:16]
    return known


_SECTION_HASHES: dict[tuple[str, str], str] = {}


def _files_unnamed(section: Any) -> Any:
    """``section`` with each key that names a file (``file_unless``) saying only that it does."""
    changes = {f.name: "<a file: its bytes are digested>" for f in dataclasses.fields(section)
               if (names := f.metadata.get("file_unless")) is not None and getattr(section, f.name) not in names}
    return dataclasses.replace(section, **changes) if changes else section


def absolute_section(section: Any) -> Any:
    """``section`` with each key that names a file (``file_unless``: ``[detect] model`` when not a
    built-in detector's name) absolute, taken from the current folder as a relative path is."""
    changes = {}
    for f in dataclasses.fields(section):
        names, value = f.metadata.get("file_unless"), getattr(section, f.name)
        if names is not None and value not in names and not os.path.isabs(value):
            changes[f.name] = os.path.abspath(os.path.expanduser(value))
    return dataclasses.replace(section, **changes) if changes else section


def absolute_paths(config: Config) -> Config:
    """``config`` with the files its stage sections name made absolute (:func:`absolute_section`;
    ``[warehouse] root`` is not touched): what a process in another folder, a Dask worker, reads."""
    return dataclasses.replace(config, **{name: absolute_section(config.section(name)) for name in SECTIONS})


def _shown(value: Any, limit: int = 60) -> str:
    """``repr(value)``, cut to about ``limit`` characters (errors stay one readable line)."""
    try:
        text = repr(value)
    except ValueError:  # an int of more than sys.get_int_max_str_digits() digits
        return f"<{type(value).__name__} too large to show>"
    return text if len(text) <= limit else text[:limit] + "..."


def _name(key: str) -> str:
    """A section or key name as errors show it: bare, or quoted when TOML needed quotes."""
    return key if _BARE_KEY.fullmatch(key) else _shown(key)


def _check_value(where: str, f: dataclasses.Field, value: Any) -> Any:
    expected = type(f.default)
    if expected is tuple:  # a list of strings in TOML
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise ConfigError(f"{where}: expected a list of strings, got {_shown(value)}")
        return tuple(value)
    if expected is float and isinstance(value, int) and not isinstance(value, bool):
        try:
            value = float(value)
        except OverflowError:
            raise ConfigError(f"{where}: must be a finite number, got {_shown(value)}") from None
    if type(value) is not expected:
        raise ConfigError(f"{where}: expected {expected.__name__}, got {type(value).__name__} {_shown(value)}")
    if expected is float and not math.isfinite(value):
        raise ConfigError(f"{where}: must be a finite number, got {_shown(value)}")
    if expected is int and not INT_RANGE[0] <= value <= INT_RANGE[1]:
        raise ConfigError(f"{where}: must fit in 64 bits, got {_shown(value)}")
    meta = f.metadata
    if meta.get("choices") and value not in meta["choices"]:
        raise ConfigError(f"{where}: must be one of {', '.join(map(repr, meta['choices']))}, got {_shown(value)}")
    if meta.get("lo") is not None and value < meta["lo"]:
        raise ConfigError(f"{where}: must be >= {meta['lo']}, got {value!r}")
    if meta.get("hi") is not None and value > meta["hi"]:
        raise ConfigError(f"{where}: must be <= {meta['hi']}, got {value!r}")
    problem = meta["check"](value) if meta.get("check") else None
    if problem:
        raise ConfigError(f"{where}: {problem}, got {_shown(value)}")
    return value


def dataset_splits(config: Config) -> tuple[str, ...]:
    """The splits a clip may be ingested into: the dataset's, and ``[manual_tracks] splits``."""
    return tuple(dict.fromkeys(("train", "val", "test", *config.manual_tracks.splits)))


def _check_across(config: Config, source: str) -> None:
    """Checks of keys against each other (after each key on its own)."""
    if (split := config.schedule.inbox_split) not in (splits := dataset_splits(config)):
        raise ConfigError(f"{source}: [schedule] inbox_split: must be one of {', '.join(map(repr, splits))} (the "
                          f"splits of the dataset and [manual_tracks] splits), got {_shown(split)}")
    if config.cameras.fov_min_deg >= config.cameras.fov_max_deg:
        raise ConfigError(f"{source}: [cameras] fov_min_deg: must be < [cameras] fov_max_deg ({config.cameras.fov_max_deg!r}), "
                          f"got {config.cameras.fov_min_deg!r} (the focal hypotheses span the fields of view between them)")
    if config.pose.lr_final > config.pose.lr:
        raise ConfigError(f"{source}: [pose] lr_final: must be <= [pose] lr ({config.pose.lr!r}), "
                          f"got {config.pose.lr_final!r} (the learning rate decays from lr to lr_final)")


def config_from_dict(data: dict[str, Any], source: str = "<config>") -> Config:
    """Validate a parsed TOML document into a :class:`Config`."""
    sections: dict[str, Any] = {}
    for name, values in data.items():
        if name not in SECTIONS:
            raise ConfigError(f"{source}: unknown section [{_name(name)}] (known: {', '.join(SECTIONS)})")
        if not isinstance(values, dict):
            raise ConfigError(f"{source}: [{name}] must be a table of keys")
        cls = SECTIONS[name]
        known = {f.name: f for f in dataclasses.fields(cls)}
        kwargs = {}
        for key, value in values.items():
            if key not in known:
                raise ConfigError(f"{source}: [{name}] unknown key {_shown(key)} (known: {', '.join(known)})")
            kwargs[key] = _check_value(f"{source}: [{name}] {key}", known[key], value)
        sections[name] = cls(**kwargs)
    config = Config(**sections, source=source)
    _check_across(config, source)
    return config


def load_config(path: str | os.PathLike | None = None) -> Config:
    """Load the configuration.

    Resolution: ``path`` if given, else ``$CADESTATE_CONFIG``, else ``./cadestate.toml`` if it
    exists, else the built-in defaults. ``$CADESTATE_WAREHOUSE`` overrides ``[warehouse] root``.
    """
    explicit = path or os.environ.get(ENV_CONFIG)
    candidate = Path(explicit) if explicit else Path(DEFAULT_CONFIG_FILE)
    if explicit and not candidate.is_file():
        raise ConfigError(f"{candidate}: config file not found")
    if candidate.is_file():
        try:
            data = tomllib.loads(candidate.read_text(encoding="utf-8-sig"))  # a leading BOM is dropped
        except ValueError as e:  # TOMLDecodeError, UnicodeDecodeError, an int of too many digits
            raise ConfigError(f"{candidate}: not valid TOML: {e}") from None
        except OSError as e:
            raise ConfigError(f"{candidate}: cannot read config file: {e.strerror or e}") from None
        config = config_from_dict(data, str(candidate))
    else:
        config = Config()
    if os.environ.get(ENV_WAREHOUSE):
        config = dataclasses.replace(config, warehouse=dataclasses.replace(config.warehouse, root=os.environ[ENV_WAREHOUSE]))
    return config


def describe_defaults() -> str:
    """The default configuration as commented TOML (``cadestate config show --defaults``)."""
    lines = []
    for name, cls in SECTIONS.items():
        lines.append(f"[{name}]")
        if cls.__doc__:
            lines += [f"# {line.strip()}" for line in cls.__doc__.strip().splitlines()]
        for f in dataclasses.fields(cls):
            lines.append(f"# {f.metadata['doc']}")
            lines.append(f"{f.name} = {json.dumps(f.default)}")
        lines.append("")
    return "\n".join(lines)


def to_toml(config: Config) -> str:
    """The effective configuration as TOML."""
    lines = []
    for name in SECTIONS:
        lines.append(f"[{name}]")
        for key, value in dataclasses.asdict(config.section(name)).items():
            lines.append(f"{key} = {json.dumps(value)}")
        lines.append("")
    return "\n".join(lines)
