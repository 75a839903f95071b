"""Stage ``cameras``: the clip's RealEstate10K camera file, given or made by structure from motion.

Reads: the clip's video (and its camera file when one was given). Writes, for a video ingested
without a camera file: ``inputs/<clip>/cameras.sfm.txt`` (one camera line per frame sampled at
``[cameras] sample_fps``, timestamps = the frames' video times, SfM's world, :mod:`tasks.video.sfm`) and
``inputs/<clip>/cameras.sfm.json`` (which lines were interpolated, the models found, timings, the
focal length found), each atomically; the ``ingest`` stage then takes that file as the clip's camera file. A given camera
file is passed on untouched. The output digest is that of the camera file in force.
"""

from __future__ import annotations

import json

from cadestate.config import CamerasConfig
from cadestate.lineage import digest, file_sha256, known_file_sha256
from tasks.stage import StageContext, StageDef, StageOutput
from tasks.video.camera_file import write_camera_file
from tasks.video.ingest import SFM_REPORT_FILE, ClipSource, sfm_cameras_path
from warehouse import Warehouse, atomic_write_bytes


def cameras_output_hash(kind: str, cameras_sha256: str) -> str:
    """The stage's output digest: how the camera file came (``file`` or ``sfm``) and its SHA-256."""
    return digest("cameras", kind, cameras_sha256)


def cameras_stage(wh: Warehouse, cfg: CamerasConfig, source: ClipSource, cameras_sha256: str | None,
                  run_id: str) -> StageOutput:
    """The stage body (module docstring); ``cameras_sha256``: that of the given camera file (None
    for SfM). ``run_id`` is unused."""
    if source.cameras is not None:
        return StageOutput(0, cameras_output_hash("file", cameras_sha256 or file_sha256(source.cameras)),
                           message=f"given: {source.cameras}")
    from tasks.video.sfm import run_sfm, sfm_report

    path = sfm_cameras_path(wh, source.clip)
    path.parent.mkdir(parents=True, exist_ok=True)
    with wh.staging() as work_dir:  # its frames (gigabytes) go with a killed run: a later write sweeps _staging/
        result = run_sfm(source.video, cfg, source.intrinsics, url=_sfm_url(wh, source), work_dir=work_dir)
    report = sfm_report(result) | {"given_intrinsics": list(source.intrinsics) if source.intrinsics else None}
    atomic_write_bytes(path.with_name(SFM_REPORT_FILE), json.dumps(report).encode())
    write_camera_file(path, result.track)
    interpolated = int((~result.registered).sum())
    dropped = (f"; {len(result.models) - 1} disconnected model(s) dropped ({', '.join(map(str, result.models[1:]))} frames)"
               if len(result.models) > 1 else "")
    message = (f"SfM: {int(result.registered.sum())} of {len(result.registered)} frames registered "
               f"({result.registered_fraction:.1%}), {interpolated} interpolated{dropped}, {result.seconds['total']:.0f} s")
    return StageOutput(len(result.registered), cameras_output_hash("sfm", file_sha256(path)), message=message)


def _sfm_url(wh: Warehouse, source: ClipSource) -> str:
    """Line 1 of an SfM clip's camera file: the ``file://`` URI of the video as ingested. A rerun
    (``cadestate run``, the app, label ingest) reads the warehouse's copy, whose URI would make
    the clip another video (a re-ingest of the first file was then refused as a clash)."""
    video = source.video.resolve()
    if video.is_relative_to(wh.root) and source.clip in wh.partitions("clips"):
        rows = wh.read("clips", partitions=[source.clip], columns=["url"]).column("url").to_pylist()
        if rows and rows[0]:
            return rows[0]
    return video.as_uri()


def _run(ctx: StageContext) -> StageOutput:
    return cameras_stage(ctx.wh, ctx.cfg, ctx.source, None, ctx.run_id)


def _source_inputs(source: ClipSource) -> list[str]:
    """The video, the given camera file (else "sfm") and the given intrinsics."""
    cameras = known_file_sha256(source.cameras) if source.cameras is not None else "sfm"
    return ["cameras-inputs", source.video_sha256, cameras, str(source.intrinsics)]


STAGE = StageDef(
    name="cameras", section="cameras", scope="clip", upstream=(), tables=(),
    description="the clip's camera file: the given one, else structure from motion on the video (pycolmap)",
    run=_run, source_inputs=_source_inputs,
)
