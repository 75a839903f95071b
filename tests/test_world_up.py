"""World up: estimated from the cameras, the world turned to +Y up at ingest, undone by the export."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cadestate.config import FramesConfig, IngestConfig
from cadestate.geometry import look_at, matrix_to_quaternion, quaternion_to_matrix
from cadestate.lineage import file_sha256
from tasks.video.camera_file import CameraTrack, parse_camera_file, write_camera_file
from tasks.video.frames import extract_frames
from tasks.video.ingest import ClipSource, ingest_clip
from tasks.video.world_up import (align_extrinsics, estimate_up, pose_to_input_world, rotation_to_y, stored_rotation,
                            unalign_extrinsics)


def walk(n: int = 60, pitch: float = -0.25, pan: float = 1.2) -> np.ndarray:
    """World->camera rotations float[n, 3, 3] of a level camera (+Y up world) panning by ``pan`` rad, pitched down."""
    eye = np.array([0.0, 1.5, 0.0])
    return np.stack([look_at(eye, eye + np.array([np.sin(a), pitch, np.cos(a)]))[0] for a in np.linspace(0, pan, n)])


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


@pytest.mark.parametrize("seed", range(5))
def test_up_is_found_in_a_randomly_turned_world(seed):
    W = Rotation.random(random_state=seed).as_matrix()  # X_turned = W X
    est = estimate_up(walk() @ W.T)
    assert angle_deg(est.up, W @ [0, 1, 0]) < 1.5  # despite the 14° downward pitch of every camera
    assert est.reliable
    np.testing.assert_allclose(est.rotation @ est.up, [0, 1, 0], atol=1e-12)


def test_orb_slam_like_world_with_minus_y_up():
    est = estimate_up(walk() @ np.diag([1.0, -1.0, -1.0]))  # up is -Y
    assert angle_deg(est.up, np.array([0, -1.0, 0])) < 1.5


def test_a_camera_that_does_not_pan_or_leans_is_unreliable():
    assert "barely pans" in estimate_up(walk(pan=0.01)).note
    rolls = Rotation.from_euler("z", np.resize([20.0, -20.0], 60)[:, None], degrees=True).as_matrix()  # cameras rolled ±20°
    assert "lean" in estimate_up(np.einsum("nij,njk->nik", rolls, walk())).note
    assert estimate_up(walk() @ Rotation.from_euler("z", 25, degrees=True).as_matrix()).reliable  # a tilted world is fine


def straight_walk(n: int = 138, pitch_deg: float = 12.0, heading_deg: float = 0.0, step: float = 0.01,
                  bob: float = 0.015, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(world->camera R float[n, 3, 3], centres float[n, 3]) of a camera that looks along +Z pitched
    down by ``pitch_deg``, never pans, and walks ``step`` m per frame along the heading
    ``heading_deg`` from +Z (0: forward, 90: sideways), bobbing up and down by ``bob`` m, +Y up."""
    rng = np.random.default_rng(seed)
    view = np.array([0.0, -np.tan(np.radians(pitch_deg)), 1.0])
    h = np.radians(heading_deg)
    t = np.arange(n)
    centres = np.stack([np.sin(h) * step * t, 1.5 + bob * np.sin(2 * np.pi * t / 40 + rng.uniform(0, 6)),
                        np.cos(h) * step * t], axis=1)
    R = np.stack([look_at(c, c + view)[0] for c in centres])
    return R, centres


@pytest.mark.parametrize("seed", range(3))
def test_a_forward_walk_fixes_the_pitch_the_rotations_alone_cannot(seed):
    """A camera 12° down that never pans: its rotations alone put up 12° off (and say so); its
    walk, level but for a bob, finds it within 1° in any turned world, and the estimate is reliable."""
    W = Rotation.random(random_state=seed).as_matrix()
    R, c = straight_walk(seed=seed)
    alone = estimate_up(R @ W.T)
    assert angle_deg(alone.up, W @ [0, 1, 0]) > 10 and "barely pans" in alone.note
    walked = estimate_up(R @ W.T, centres=c @ W.T)
    assert angle_deg(walked.up, W @ [0, 1, 0]) < 1.0
    assert walked.reliable and walked.walk_deg > 80


@pytest.mark.parametrize("slope_deg, noted", [(0.0, False), (8.0, False), (35.0, True), (60.0, True)])
def test_a_walk_that_climbs_is_noted(slope_deg, noted):
    """The walk holds up level with the path: up stairs (35°) or a steep ramp (60°) it put up
    that far off and said nothing (the camera walks forward, so the pitch's note stayed quiet); now
    it is noted. A level walk or an 8° driveway stays unnoted (the axes alone are off by the pitch)."""
    R, c = straight_walk(pitch_deg=12.0)
    climbing = c.copy()
    climbing[:, 1] += np.tan(np.radians(slope_deg)) * c[:, 2]
    est = estimate_up(R, centres=climbing)
    assert angle_deg(est.up, np.array([0, 1.0, 0])) == pytest.approx(slope_deg, abs=1.5)
    assert ("the path climbs (stairs, a ramp)" in est.note) == noted, est.note


def test_a_sideways_walk_or_a_shaking_camera_leaves_the_pitch_to_the_rotations():
    R, c = straight_walk(heading_deg=90.0)  # along the camera's right axis: no new direction
    est = estimate_up(R, centres=c)
    assert est.walk_deg < 1 and "does not walk forward or back" in est.note
    shaking = 1.5 + np.random.default_rng(1).normal(0, 0.003, (len(R), 3))  # stands still, hand shaking
    assert estimate_up(R, centres=shaking).up == pytest.approx(estimate_up(R).up, abs=0.02)


def test_forced_up_and_bad_values():
    est = estimate_up(walk(), "-z")
    np.testing.assert_array_equal(est.up, [0, 0, -1])
    assert est.source == "-z" and est.reliable
    with pytest.raises(ValueError, match="up must be"):
        estimate_up(walk(), "up")


def test_round_trips():
    rng = np.random.default_rng(0)
    for up in [rng.normal(size=3) for _ in range(5)] + [np.array([0, -1.0, 0]), np.array([0, 1.0, 0])]:
        Q = rotation_to_y(up)
        np.testing.assert_allclose(Q @ Q.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(Q) == pytest.approx(1)
        np.testing.assert_allclose(Q @ (up / np.linalg.norm(up)), [0, 1, 0], atol=1e-12)
    Q = Rotation.random(random_state=1).as_matrix()
    R, t = Rotation.random(random_state=2).as_matrix(), rng.normal(size=3)
    X = rng.normal(size=3)
    Ra, ta = align_extrinsics(R, t, Q)
    np.testing.assert_allclose(Ra @ (Q @ X) + ta, R @ X + t)  # the same point seen the same in both worlds
    np.testing.assert_allclose(unalign_extrinsics(Ra, ta, Q)[0], R)
    q = matrix_to_quaternion(Rotation.random(random_state=3).as_matrix())
    T, q_in = pose_to_input_world(Q @ X, q, Q)
    np.testing.assert_allclose(T, X)
    np.testing.assert_allclose(quaternion_to_matrix(np.array(q_in)), Q.T @ quaternion_to_matrix(q), atol=1e-12)
    np.testing.assert_array_equal(stored_rotation(None), np.eye(3))


def turned(track: CameraTrack, W: np.ndarray) -> CameraTrack:
    """``track`` in a world turned by ``W`` (X_turned = W X)."""
    R, t = align_extrinsics(track.R, track.t, W)
    return dataclasses.replace(track, world_to_camera=np.concatenate([R, t[:, :, None]], axis=2))


def test_ingest_turns_a_rotated_world_back_to_y_up(wh, small_clip, tmp_path):
    """The small clip's camera file with its world turned by a random rotation: after ingest, the
    frames' world is the original one up to a turn about +Y (same up, same heights), and the
    clip's rotation maps it back to the camera file's world."""
    cams = parse_camera_file(small_clip.cameras_path)
    W = Rotation.random(random_state=7).as_matrix()
    path = tmp_path / "turned.txt"
    write_camera_file(path, turned(cams, W))
    for clip, cameras in (("plain", small_clip.cameras_path), ("turned", path)):
        ingest_clip(wh, IngestConfig(), ClipSource(clip, small_clip.video_path, cameras), file_sha256(small_clip.video_path),
                    file_sha256(cameras), "r0")
        extract_frames(wh, FramesConfig(), clip, "r1", show_progress=False)
    rows = {c: wh.read("frames", [c]).to_pylist() for c in ("plain", "turned")}
    heights = {c: np.array([r["camera_center"][1] for r in rows[c]]) for c in rows}
    np.testing.assert_allclose(heights["turned"] - heights["turned"].mean(), heights["plain"] - heights["plain"].mean(),
                               atol=0.02)
    for a, b in zip(rows["plain"], rows["turned"]):
        down_a, down_b = np.reshape(a["camera_to_world_R"], (3, 3))[:, 1], np.reshape(b["camera_to_world_R"], (3, 3))[:, 1]
        assert abs(down_a[1] - down_b[1]) < 0.02  # each camera's pitch against +Y is the same
    clip_row = wh.read("clips", ["turned"]).to_pylist()[0]
    assert clip_row["up_source"] == "auto" and clip_row["up_note"] == ""
    # The small clip (320x192) shows too few vertical edges: the cameras' estimate stands, within 0.5° of the true up.
    assert clip_row["up_line_segments"] == 0 and angle_deg(stored_rotation(clip_row["up_rotation"]).T @ [0, 1.0, 0],
                                                           W @ [0, 1.0, 0]) < 0.5
    Q = stored_rotation(clip_row["up_rotation"])
    R0 = np.reshape(rows["turned"][0]["world_to_camera_R"], (3, 3))
    np.testing.assert_allclose(unalign_extrinsics(R0, np.zeros(3), Q)[0], turned(cams, W).R[0], atol=1e-9)


def test_forced_up_is_kept_and_noted_in_clips(wh, small_clip):
    ingest_clip(wh, IngestConfig(up="+y"), ClipSource("small", small_clip.video_path, small_clip.cameras_path),
                file_sha256(small_clip.video_path), file_sha256(small_clip.cameras_path), "r0")
    row = wh.read("clips").to_pylist()[0]
    assert row["up_source"] == "+y" and row["up_line_segments"] is None
    np.testing.assert_array_equal(stored_rotation(row["up_rotation"]), np.eye(3))


def test_status_notes_an_unreliable_up():
    from tasks.status import StageStatus, clip_notes

    note = estimate_up(walk(pan=0.01)).note
    rows = [StageStatus("room_0", "ingest", "completed", "", 1, (), f"world up: {note}"),
            StageStatus("hall_0", "ingest", "completed", "", 1, (), "")]
    assert clip_notes(rows) == [f"room_0: world up unreliable: {note}"]


def test_export_world_projects_the_same_pixels():
    """ClipDataset.in_input_world (what `export official` writes): frames and poses in the camera
    file's world, where each posed corner projects to the pixel it did in the aligned world."""
    from cadestate.geometry import project
    from tasks.dataset.objects import ClipDataset, DatasetFrame, DatasetObject, Pose

    Q = Rotation.random(random_state=5).as_matrix()
    K = np.array([[500.0, 0, 320], [0, 500, 180], [0, 0, 1]])
    R, t = look_at(np.array([0, 1.5, -3.0]), np.zeros(3))
    pose = Pose((0.2, 0.4, 0.1), tuple(matrix_to_quaternion(Rotation.from_euler("y", 30, degrees=True).as_matrix())),
                (1.0, 0.8, 0.5), True)
    ds = ClipDataset("c_0", "file:///c.mp4", (360, 640), (DatasetFrame(0, K, R, t, "x.jpg", False),),
                     (DatasetObject(1, True, "chair", "03001627", {}, True, "m", pose),), Q)
    out = ds.in_input_world()
    corners = np.array([[x, y, z, 1.0] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * [0.5, 0.5, 0.5, 1]
    before = project(K, R, t, (corners @ pose.matrix().T)[:, :3])[0]
    f, p = out.frames[0], out.objects[0].pose
    after = project(f.K, f.R, f.t, (corners @ p.matrix().T)[:, :3])[0]
    np.testing.assert_allclose(after, before, atol=1e-9)
    np.testing.assert_allclose(f.R, R @ Q)
    np.testing.assert_array_equal(out.up_rotation, np.eye(3))
