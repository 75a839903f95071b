"""World up from vertical lines (tasks/video/vertical_lines.py): drawn posts seen through known
cameras, in randomly turned worlds, through the real OpenCV line segment detector."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cadestate.geometry import look_at
from tasks.video.vertical_lines import SegmentNormals, frame_segment_normals, moving_segments, refine_up, stack_frames
from tasks.video.world_up import estimate_up

W, H = 640, 360
K = np.array([500.0, 500.0, 320.0, 180.0])  # fx, fy, cx, cy px


def scene(seed: int, posts: int = 14, rails: int = 10) -> list[tuple[np.ndarray, np.ndarray]]:
    """3D segments (a, b) of a +Y-up room 8 m across: vertical posts (wall corners, legs) and
    horizontal rails at random heights and headings (the distractors every room has)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(posts):
        x, z = rng.uniform(-4, 4, 2)
        y0 = rng.uniform(0.0, 0.6)
        out.append((np.array([x, y0, z]), np.array([x, y0 + rng.uniform(0.8, 2.2), z])))
    for _ in range(rails):
        a = np.array([*rng.uniform(-4, 4, 1), rng.uniform(0.3, 2.4), *rng.uniform(-4, 4, 1)])
        h = rng.uniform(0, np.pi)
        out.append((a, a + rng.uniform(1, 3) * np.array([np.cos(h), 0.0, np.sin(h)])))
    return out


def cameras(n: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """World->camera R float[n, 3, 3] and t float[n, 3] of a camera at eye height looking around, pitched down."""
    Rs, ts = [], []
    for a in np.linspace(0, 2 * np.pi, n, endpoint=False):
        eye = np.array([0.3 * np.cos(a), 1.5, 0.3 * np.sin(a)])
        R, t = look_at(eye, eye + np.array([np.cos(a), -0.2, np.sin(a)]))
        Rs.append(R)
        ts.append(t)
    return np.stack(Rs), np.stack(ts)


def draw(segments, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """uint8[H, W] image of the segments (in front of the camera) seen by the camera (R, t)."""
    import cv2

    img = np.full((H, W), 40, np.uint8)
    for a, b in segments:
        pa, pb = R @ a + t, R @ b + t
        if min(pa[2], pb[2]) < 0.3:
            continue
        uv = [(K[0] * p[0] / p[2] + K[2] - 0.5, K[1] * p[1] / p[2] + K[3] - 0.5) for p in (pa, pb)]
        if max(abs(v) for xy in uv for v in xy) > 4 * W:
            continue
        cv2.line(img, *[(int(round(x * 16)), int(round(y * 16))) for x, y in uv], 220, 2, cv2.LINE_AA, shift=4)
    return img


def normals_of(segments, Rs: np.ndarray, ts: np.ndarray, world: np.ndarray) -> SegmentNormals:
    """The segments drawn through every camera, their normals in the world turned by ``world``
    (X_turned = world X: the cameras' rotations become R world^T)."""
    return stack_frames([frame_segment_normals(draw(segments, R, t), K, R @ world.T) for R, t in zip(Rs, ts)])


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


@pytest.mark.parametrize("seed", range(4))
def test_up_is_found_from_vertical_lines_in_a_turned_world(seed):
    world = Rotation.random(random_state=seed).as_matrix()
    Rs, ts = cameras()
    seg = normals_of(scene(seed, posts=40), Rs, ts, world)
    true_up = world @ [0.0, 1.0, 0.0]
    start = Rotation.from_rotvec(np.radians(6.0) * np.array([1.0, 0.0, 0.0])).as_matrix() @ true_up  # 6° off
    found = refine_up(seg, start, 0.5)
    assert found is not None and found.segments >= 20 and found.frames >= 3
    assert angle_deg(found.up, true_up) < 0.1
    assert abs(found.moved_deg - angle_deg(start, true_up)) < 0.2


def test_too_few_lines_leave_the_cameras_estimate():
    Rs, ts = cameras()
    posts_only_in_one_frame = [(np.array([2.0, 0.0, 0.3]), np.array([2.0, 2.0, 0.3]))]
    seg = normals_of(posts_only_in_one_frame, Rs, ts, np.eye(3))
    assert refine_up(seg, np.array([0.0, 1.0, 0.0]), 0.5) is None
    with_lines, alone = estimate_up(Rs, lines=seg), estimate_up(Rs)
    np.testing.assert_array_equal(with_lines.up, alone.up)
    assert with_lines.line_segments == 0 and with_lines.note == alone.note


def swinging_camera(n: int = 8, swing_deg: float = 4.0, pitch: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """World->camera R float[n, 3, 3], t float[n, 3] of a camera that stands still, pitched down by
    atan(``pitch``), and turns only ``swing_deg`` left and right: it barely pans and does not walk."""
    eye = np.array([0.0, 1.5, 0.0])
    poses = [look_at(eye, eye + np.array([np.sin(a), -pitch, np.cos(a)]))
             for a in np.radians(np.linspace(-swing_deg, swing_deg, n))]
    return np.stack([R for R, _ in poses]), np.stack([t for _, t in poses])


def test_lines_fix_a_pitched_camera_that_barely_pans_and_does_not_walk():
    """The cameras alone put up along their pitched down axes (14° off) and say so; the lines fix
    it, and the note goes."""
    Rs, ts = swinging_camera()
    alone = estimate_up(Rs)
    assert "barely pans" in alone.note and angle_deg(alone.up, np.array([0.0, 1.0, 0.0])) > 10
    seg = normals_of(scene(7, posts=40), Rs, ts, np.eye(3))
    fixed = estimate_up(Rs, lines=seg)
    assert angle_deg(fixed.up, np.array([0.0, 1.0, 0.0])) < 0.1
    assert fixed.reliable and fixed.line_segments >= 50
    assert estimate_up(Rs, "+y", lines=seg).line_segments == 0  # a forced up is kept


def test_a_camera_that_does_not_move_gives_no_lines():
    """Every segment of a still camera stays at one place of the image, like an overlay: no
    estimate, however many there are, and the cameras' note stays."""
    eye = np.array([0.0, 1.5, 0.0])
    R, t = look_at(eye, eye + np.array([0.0, -0.25, 1.0]))
    Rs, ts = np.repeat(R[None], 8, axis=0), np.repeat(t[None], 8, axis=0)
    seg = normals_of(scene(7, posts=40), Rs, ts, np.eye(3))
    assert len(seg.normals) >= 50 and refine_up(seg, estimate_up(Rs).up, 0.5) is None
    assert "barely pans" in estimate_up(Rs, lines=seg).note


def test_an_overlay_fixed_in_the_image_is_left_out():
    """A vertical bar drawn at the same place of every frame (a logo, a letterbox edge) would vote
    for the camera's own down axis, pitched 14°: it is left out, and up is still found."""
    import cv2

    Rs, ts = swinging_camera()
    world = scene(7, posts=40)
    per_frame = []
    for R, t in zip(Rs, ts):
        img = draw(world, R, t)
        for x in (20, 40, 600, 620):
            cv2.line(img, (x, 20), (x, 340), 255, 3)
        per_frame.append(frame_segment_normals(img, K, R))
    seg = stack_frames(per_frame)
    found = refine_up(seg, estimate_up(Rs).up, 0.5)
    assert found is not None and angle_deg(found.up, np.array([0.0, 1.0, 0.0])) < 0.2


    def on_bars(s: SegmentNormals) -> int:
        x = s.endpoints[:, [0, 2]]
        return int(sum(np.all(np.abs(x - bar) < 4, axis=1).sum() for bar in (20, 40, 600, 620)))

    assert on_bars(seg) >= 8 * 4 and on_bars(moving_segments(seg)) <= on_bars(seg) // 4
