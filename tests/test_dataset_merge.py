"""One physical object, one dataset object: accepted poses claim the tracks they cover
(:func:`tasks.dataset.objects.merge_objects`), on hand-made poses and cameras with known boxes."""

from __future__ import annotations

import numpy as np
import pytest

from tasks.dataset.objects import DatasetFrame, DatasetObject, Pose, merge_objects, projected_box

SIZE = (480, 640)
"""(height, width) px."""
FRAMES = tuple(DatasetFrame(t, np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]), np.eye(3),
                            np.array([0.1 * i, 0, 0]), f"{i}.jpg", False) for i, t in enumerate((0, 100_000, 200_000)))
"""Three frames of a camera sliding along +x (world->camera: identity rotation, t moving)."""
CHAIR = Pose((0.0, 0.0, 4.0), (1.0, 0, 0, 0), (1.0, 1.0, 1.0), False)


def _boxes(pose: Pose, extent, shrink: float = 1.0) -> dict[int, tuple]:
    """The projection of ``pose``'s box on every frame, shrunk about its centre to ``shrink`` of its sides."""
    boxes = {}
    for f in FRAMES:
        y0, x0, y1, x1 = projected_box(pose, extent, f, SIZE)
        cy, cx, hh, hw = (y0 + y1) / 2, (x0 + x1) / 2, (y1 - y0) * shrink / 2, (x1 - x0) * shrink / 2
        boxes[f.timestamp_us] = (cy - hh, cx - hw, cy + hh, cx + hw)
    return boxes


def _object(track: int, pose: Pose, extent, keyframes: int, shrink: float = 1.0, posed: bool = True) -> DatasetObject:
    return DatasetObject(track_id=track, automatic=True, class_name="chair", class_id="03001627",
                         boxes=_boxes(pose, extent, shrink), cad_id="lib.chair" if posed else None,
                         pose=pose if posed else None, extent=tuple(extent) if posed else None, keyframes=keyframes)


@pytest.mark.parametrize("keyframes", [(4, 2), (2, 4)])
def test_two_poses_of_one_object_are_one_object_whichever_has_more_keyframes(keyframes):
    """Track 1's boxes are its object's middle 45 % (a partial detection); both tracks' accepted
    poses are the same. Track 0's projection does not cover track 1's boxes (IoU 0.2), track 1's
    covers track 0's: with more key-frames on track 0 both were exported, the chair twice."""
    whole = _object(0, CHAIR, (1.0, 1.0, 1.0), keyframes[0])
    partial = _object(1, CHAIR, (1.0, 1.0, 1.0), keyframes[1], shrink=0.45)
    [merged] = merge_objects([whole, partial], FRAMES, SIZE)
    speaker = 0 if keyframes[0] > keyframes[1] else 1
    assert (merged.track_id, merged.merged) == (speaker, (1 - speaker,))


def test_a_partial_track_without_a_pose_is_not_a_claimer():
    """A track with no accepted pose claims nothing: the tight track joins the posed one only
    where the pose covers its boxes (here it does not: two objects), and a small posed object
    beside a large one stays an object of its own."""
    whole = _object(0, CHAIR, (1.0, 1.0, 1.0), 4)
    partial = _object(1, CHAIR, (1.0, 1.0, 1.0), 0, shrink=0.45, posed=False)
    vase = _object(2, Pose((0.3, -0.2, 4.0), (1.0, 0, 0, 0), (1.0, 1.0, 1.0), False), (0.1, 0.2, 0.1), 3)
    assert [(o.track_id, o.merged) for o in merge_objects([whole, partial, vase], FRAMES, SIZE)] == \
        [(0, ()), (1, ()), (2, ())]
