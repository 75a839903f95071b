"""The synthetic benchmark: generate it (once, cached), run the pipeline on it, report.

A benchmark folder holds ``manifest.json`` (seed, clip names, the CAD library it was drawn from),
and per clip ``<name>.mp4``, ``<name>.txt`` and ``<name>/{frames,objects,visibility}.json``
(:mod:`bench.walkthrough`), named ``bench-<S>-<i:02d>_<start_us>`` (:func:`clip_name`). Clip ``i``
of seed ``S`` is generated from seed ``S * 1000 + i``, so
the default benchmark (:data:`DEFAULT_SEED`, :data:`DEFAULT_CLIPS`) is the same everywhere the
same CAD library is. Splits are not stored: clip ``i`` is ``val`` when ``i % VAL_EVERY`` is
``VAL_EVERY - 1`` (:func:`clip_split`), so every benchmark, old manifests included, has them.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from bench.eval_detection import FrameBoxes, evaluate_detections
from bench.ignore import box_fractions, is_ignored
from bench.labels import label_statistics
from bench.seeds import DEFAULT_SEED, seed_note
from bench.stats import dataset_statistics, statistics_markdown
from bench.walkthrough import WalkthroughSpec, generate_clip
from cadestate.atomic import atomic_write_bytes
from cadestate.lineage import digest
from cadestate.progress import progress
from schemas.official import ObjectAnnotation, TrackEntry, read_frames, read_objects
from tasks.cad.classes import CLASSES
from tasks.video.clip_names import derive_clip_name
from tasks.video.decode import decode_at, frame_timestamp_us
from tasks.video.ingest import ClipSource
from warehouse import Warehouse

DEFAULT_CLIPS = 12
MANIFEST = "manifest.json"
VAL_EVERY = 4
CLASS_NAMES = {c.id: c.name for c in CLASSES}


class BenchmarkError(ValueError):
    """A benchmark folder that cannot be used (no manifest, missing files, no CAD library)."""


@dataclass(frozen=True)
class Manifest:
    seed: int
    clips: tuple[str, ...]
    library: str  # digest of the cad_ids drawn from

    def to_json(self) -> dict:
        return {"seed": self.seed, "clips": list(self.clips), "library": self.library}


def library_models(wh: Warehouse) -> list[dict]:
    """The CAD library rows scenes are drawn from (every ingested library)."""
    models = wh.read("cad_models").to_pylist()
    if not models:
        raise BenchmarkError(f"no CAD model in {wh.root}: run `cadestate cad ingest` first")
    return models


def read_manifest(bench_dir: Path) -> Manifest:
    path = Path(bench_dir) / MANIFEST
    if not path.is_file():
        raise BenchmarkError(f"{bench_dir}: not a benchmark folder (no {MANIFEST}); see `cadestate bench generate`")
    try:
        data = json.loads(path.read_text())
        manifest = Manifest(int(data["seed"]), tuple(str(c) for c in data["clips"]), str(data["library"]))
    except (ValueError, KeyError, TypeError) as e:  # JSONDecodeError is a ValueError
        what = f"no field {e}" if isinstance(e, KeyError) else str(e)
        raise BenchmarkError(f"{path}: not a benchmark manifest ({what}); `cadestate bench generate` writes one") from None
    return manifest


def generate(bench_dir: Path, seed: int, clips: int, wh: Warehouse, spec: WalkthroughSpec = WalkthroughSpec(),
             show_progress: bool = True) -> tuple[Manifest, list[float]]:
    """Generate the clips that are missing; returns the manifest and the seconds each new clip took."""
    bench_dir = Path(bench_dir)
    models = library_models(wh)
    try:
        bench_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:  # a file of that name (or above it), or a folder it may not write in
        raise BenchmarkError(f"{bench_dir}: cannot be the benchmark folder ({e.strerror})") from None
    manifest = Manifest(seed, tuple(clip_name(seed, i, spec) for i in range(clips)), digest(*sorted(m["cad_id"] for m in models)))
    if (bench_dir / MANIFEST).is_file() and read_manifest(bench_dir).library != manifest.library:
        raise BenchmarkError(f"{bench_dir} was generated from another CAD library; choose a new folder")
    if (bench_dir / MANIFEST).is_file() and (held := read_manifest(bench_dir).seed) != seed:  # its clips were forgotten
        raise BenchmarkError(f"{bench_dir} holds the benchmark of seed {held}; choose a new folder for seed {seed}")
    # a clip is whole once its ground truth is: objects.json, then visibility.json, written last
    # (bench/walkthrough.py, whose bytes key the trained models, writes them in that order)
    todo = [(i, name) for i, name in enumerate(manifest.clips)
            if not all((bench_dir / name / f).is_file() for f in ("objects.json", "visibility.json"))]
    for name in sorted(set(manifest.clips) - {name for _, name in todo}):
        _require_spec(bench_dir, name, spec)
    seconds = []
    for i, name in progress(todo, total=len(todo), description="bench clips", enabled=show_progress):
        try:
            seconds.append(generate_clip(bench_dir, name, seed * 1000 + i, models, wh.root, spec).timings["total"])
        except RuntimeError as e:  # bench.walkthrough.camera_path: a room no camera walk fits in
            if "camera path" not in str(e):
                raise
            fewer = f", or --clips {i} (the clips before it are kept)" if i else ""
            raise BenchmarkError(f"{bench_dir}: clip {i} of seed {seed} cannot be generated ({e}): use another --seed{fewer}") from None
    atomic_write_bytes(bench_dir / MANIFEST, json.dumps(manifest.to_json(), indent=1).encode())
    return manifest, seconds


def require_library(bench_dir: Path, clips: list[str], wh: Warehouse) -> None:
    """Raise :class:`BenchmarkError` unless ``wh`` holds every CAD model of the ground truth of
    ``clips`` (the simulated annotators click on them, and pick them among the candidates)."""
    have = {r["cad_id"] for r in wh.read("cad_models", columns=["cad_id"]).to_pylist()}
    missing = sorted({o.cad_id for c in clips for o in read_objects(Path(bench_dir) / c / "objects.json").objects} - have)
    if missing:
        raise BenchmarkError(f"{bench_dir}: {len(missing)} CAD model(s) of its ground truth are not in the warehouse "
                             f"{wh.root} (e.g. {missing[0]}): use the warehouse it was generated from (-w), or "
                             "`cadestate cad ingest` its library there")


def _require_spec(bench_dir: Path, clip: str, spec: WalkthroughSpec) -> None:
    """Raise :class:`BenchmarkError` unless the clip already in ``bench_dir`` was made as ``spec``
    makes clips (its camera frames and image size): a clip's name does not say, so ``--frames 60``
    and then ``--frames 276`` into one folder kept the short clips without a word."""
    frames = read_frames(bench_dir / clip / "frames.json")
    made = (len(frames.frames), tuple(frames.image_size))
    asked = (len(range(0, spec.num_video_frames, spec.sample_every)), (spec.height, spec.width))
    if made != asked:
        raise BenchmarkError(f"{bench_dir}: clip {clip} has {made[0]} camera frames of {made[1][1]}x{made[1][0]} px, "
                             f"not the {asked[0]} of {asked[1][1]}x{asked[1][0]} px asked for (--frames "
                             f"{spec.num_video_frames}): choose a new folder, or the --frames it was generated with")


def clip_name(seed: int, index: int, spec: WalkthroughSpec = WalkthroughSpec()) -> str:
    """The benchmark's clip ``index`` named as the official CAD-Estate convention wants,
    ``<video_id>_<start_us>``: video id ``bench-<seed>-<index:02d>`` (one video per clip: no two
    clips share a video id, so none shares frame files in the official layout), start = its first
    camera timestamp."""
    return derive_clip_name(f"synthetic://walkthrough/bench-{seed}-{index:02d}", frame_timestamp_us(0, spec.fps))


def clip_split(index: int) -> str:
    """The split of the benchmark's clip ``index``: every ``VAL_EVERY``-th clip (3, 7, 11, ...) is
    ``val`` (it gets the manual-track task), the others ``train``. A function of the index alone,
    so generating more clips never moves one to another split."""
    return "val" if index % VAL_EVERY == VAL_EVERY - 1 else "train"


def clip_sources(bench_dir: Path) -> list[ClipSource]:
    """The benchmark's clips as pipeline inputs, with their splits (:func:`clip_split`)."""
    bench_dir = Path(bench_dir)
    return [ClipSource(name, bench_dir / f"{name}.mp4", bench_dir / f"{name}.txt", clip_split(i))
            for i, name in enumerate(read_manifest(bench_dir).clips)]


def ignore_rule(bench_dir: Path, clip: str) -> Callable[[ObjectAnnotation, TrackEntry], bool]:
    """``gt_ignore(object, entry)`` for one clip, from its visibility file and the class vocabulary."""
    fractions = box_fractions(bench_dir, clip)

    def gt_ignore(obj: ObjectAnnotation, entry: TrackEntry) -> bool:
        visible, truncated = fractions.get((entry.timestamp, obj.track_id), (0.0, 1.0))
        return is_ignored(CLASS_NAMES.get(obj.cls, "other"), visible, truncated)

    return gt_ignore


def example_frame(bench_dir: Path, clip: str, out_file: Path) -> None:
    """The middle camera-line frame of ``clip`` with its ground-truth boxes (green: evaluated, grey: ignore)."""
    frames, objects = read_frames(Path(bench_dir) / clip / "frames.json"), read_objects(Path(bench_dir) / clip / "objects.json")
    ts = frames.frames[len(frames.frames) // 2].timestamp
    rgb = next(decode_at(Path(bench_dir) / f"{clip}.mp4", np.array([ts]))).rgb
    image = Image.fromarray(rgb)
    draw = ImageDraw.Draw(image)
    gt_ignore = ignore_rule(bench_dir, clip)
    H, W = rgb.shape[:2]
    for obj in objects.objects:
        for entry in obj.track:
            if entry.timestamp == ts:
                y0, x0, y1, x1 = entry.box
                colour = (150, 150, 150) if gt_ignore(obj, entry) else (0, 220, 0)
                draw.rectangle([x0 * W, y0 * H, x1 * W, y1 * H], outline=colour, width=2)
                draw.text((x0 * W + 3, y0 * H + 2), CLASS_NAMES.get(obj.cls, obj.cls), fill=colour)
    out_file.parent.mkdir(parents=True, exist_ok=True)
    image.save(out_file)


def detection_frames(bench_dir: Path, clip: str, wh: Warehouse) -> list[FrameBoxes]:
    """Ground truth (with the ignore rule) and the ``detections`` of one clip, frame by frame."""
    objects = read_objects(Path(bench_dir) / clip / "objects.json")
    gt_ignore = ignore_rule(bench_dir, clip)
    gt: dict[int, list[tuple[tuple, str, bool]]] = {}
    for obj in objects.objects:
        for e in obj.track:
            gt.setdefault(e.timestamp, []).append((e.box, CLASS_NAMES.get(obj.cls, "other"), gt_ignore(obj, e)))
    preds: dict[int, list[dict]] = {}
    for d in wh.read("detections", partitions=[clip], columns=["timestamp_us", "box", "label"]).to_pylist():
        preds.setdefault(d["timestamp_us"], []).append(d)
    frames = read_frames(Path(bench_dir) / clip / "frames.json")
    return [FrameBoxes(np.array([b for b, _, _ in gt.get(f.timestamp, [])], np.float64).reshape(-1, 4),
                       [c for _, c, _ in gt.get(f.timestamp, [])],
                       np.array([i for _, _, i in gt.get(f.timestamp, [])], bool),
                       np.array([d["box"] for d in preds.get(f.timestamp, [])], np.float64).reshape(-1, 4),
                       [d["label"] for d in preds.get(f.timestamp, [])]) for f in frames.frames]


def unfinished_clips(clips: list[str], wh: Warehouse) -> dict[str, str]:
    """The clips of ``clips`` that have not run to the end in ``wh``, clip -> where it stands: "not
    run" (no run of it in the warehouse), or its first stage, in pipeline order, whose last run did
    not complete ("waits at cad_selection", "failed at pose", "failed at cameras": before ingest
    registered it) or that never ran ("never ran pose")."""
    from tasks.registry import stages_of
    from tasks.status import read_runs

    ran = set(wh.partitions("runs"))
    present = [c for c in clips if c in ran]
    last = {(r["clip"], r["stage"]): r["status"] for r in read_runs(wh, present)} if present else {}
    out = {}
    for clip in clips:
        if clip not in present:
            out[clip] = "not run"
            continue
        for stage in (s.name for s in stages_of("clip")):
            status = last.get((clip, stage))
            if status != "completed":
                out[clip] = f"never ran {stage}" if status is None else f"{'waits' if status == 'paused' else status} at {stage}"
                break
    return out


def report(bench_dir: Path, examples: int = 3, wh: Warehouse | None = None) -> dict:
    """The dataset's yield first (:mod:`bench.dataset_yield`), then metrics of what the pipeline
    can do so far (of the clips in ``wh``), dataset statistics, and example frames."""
    from bench.dataset_yield import dataset_yield  # imports this module
    from bench.pose_bench import pose_accuracy  # imports this module
    from bench.retrieval_bench import retrieval_accuracy  # imports this module
    from bench.track_bench import tracking_accuracy  # imports this module

    bench_dir = Path(bench_dir)
    manifest = read_manifest(bench_dir)
    pairs = [(read_frames(bench_dir / c / "frames.json"), read_objects(bench_dir / c / "objects.json")) for c in manifest.clips]
    boxes = ignored = 0
    for clip, (_, objects) in zip(manifest.clips, pairs):
        gt_ignore = ignore_rule(bench_dir, clip)
        for obj in objects.objects:
            boxes += len(obj.track)
            ignored += sum(gt_ignore(obj, e) for e in obj.track)
    pictures = []
    for clip in manifest.clips[:examples]:
        out = bench_dir / "report" / f"{clip}.png"
        example_frame(bench_dir, clip, out)
        pictures.append(str(out.relative_to(bench_dir)))
    detected = [c for c in manifest.clips if wh is not None and c in wh.partitions("detections")]
    detection = evaluate_detections([f for c in detected for f in detection_frames(bench_dir, c, wh)]) if detected else None
    return {
        "yield": dataset_yield(bench_dir, wh) if wh is not None else None,
        "benchmark": {"seed": manifest.seed, "clips": len(manifest.clips)},
        "unfinished": unfinished_clips(list(manifest.clips), wh) if wh is not None else None,
        "detection": detection and {"clips": len(detected), **detection},
        "tracking": tracking_accuracy(bench_dir, wh) if wh is not None else None,
        "pose": pose_accuracy(bench_dir, wh) if wh is not None else None,
        "statistics": dataset_statistics(pairs),
        "simulated_labels": label_statistics(bench_dir, list(manifest.clips)),
        "ground_truth_boxes": {"total": boxes, "ignore": ignored},
        "examples": pictures,
        "retrieval": retrieval_accuracy(bench_dir, wh) if wh is not None else None,
    }


def report_markdown(result: dict) -> str:
    """The report as markdown (pictures linked relative to the benchmark folder)."""
    from bench.dataset_yield import yield_markdown  # imports this module
    from bench.pose_bench import pose_markdown  # imports this module
    from bench.retrieval_bench import retrieval_markdown  # imports this module
    from bench.track_bench import tracking_markdown  # imports this module

    lines = [f"# Synthetic benchmark (seed {result['benchmark']['seed']}, {result['benchmark']['clips']} clips)", "",
             seed_note(result["benchmark"]["seed"]), "",
             *unfinished_markdown(result.get("unfinished"), result["benchmark"]["clips"]),
             *yield_markdown(result.get("yield")),
             "## The benchmark's ground truth (the paper's Table 2 statistics; what the dataset built holds is above and in `cadestate stats`)", "", statistics_markdown(result["statistics"]), "",
             f"Ground-truth boxes: {result['ground_truth_boxes']['total']}, of which "
             f"{result['ground_truth_boxes']['ignore']} are ignore regions (mostly hidden or cut off, or of a class no detector is asked to find).", "",
             "## Simulated annotators' clicks on every ground-truth object (`bench/labels.py`: the noise model as "
             "measured; the answers to the pipeline's own tasks are what the yield above counts)", "",
             "| | |", "|---|---:|", *[f"| {k.replace('_', ' ')} | {v} |" for k, v in result["simulated_labels"].items()], "",
             *detection_markdown(result.get("detection")),
             *tracking_markdown(result.get("tracking")),
             *retrieval_markdown(result.get("retrieval")),
             *pose_markdown(result.get("pose")),
             "## Examples (green: evaluated boxes, grey: ignore regions)", ""]
    lines += [f"![{p}]({p})" for p in result["examples"]]
    return "\n".join(lines) + "\n"


def unfinished_markdown(unfinished: dict[str, str] | None, clips: int) -> list[str]:
    """Lines saying which clips have not run to the end (:func:`unfinished_clips`), first in the
    report: its numbers leave out a clip not run and count a clip that waits as far as it got."""
    if not unfinished:
        return []
    if sum(why == "not run" for why in unfinished.values()) == clips:
        return [f"**No clip of this benchmark is in the warehouse** ({clips} not run): `cadestate bench run` on it runs "
                "them; the dataset's yield leads this report once they have run.", ""]
    return [f"**{len(unfinished)} of {clips} clips {'has' if len(unfinished) == 1 else 'have'} not run to the end**: the numbers below leave out a clip not run "
            "and count a clip that waits as far as it got (`cadestate bench run` on the benchmark goes on): "
            + "; ".join(f"{clip} {why}" for clip, why in unfinished.items()) + ".", ""]


def detection_markdown(detection: dict | None) -> list[str]:
    """Lines of the report's detection section (empty before the detect stage ran)."""
    if not detection:
        return []
    rows = [f"| {c} | {m['ground_truth']} | {m['predictions']} | {m['recall'] if m['recall'] is not None else '-'} "
            f"| {m['precision'] if m['precision'] is not None else '-'} |" for c, m in detection["per_class"].items()]
    return [f"## Detection (IoU >= {detection['iou']}, {detection['clips']} clips, ignore regions excluded)", "",
            f"Recall {detection['recall']}, precision {detection['precision']}, class-agnostic recall "
            f"{detection['class_agnostic_recall']} ({detection['ground_truth']} ground-truth boxes, "
            f"{detection['predictions']} kept predictions).", "",
            "| class | ground truth | predictions | recall | precision |", "|---|---:|---:|---:|---:|", *rows, ""]
