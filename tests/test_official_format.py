"""The official CAD-Estate JSON files round-trip through our reader and writer; bad files name the field."""

import json

import pytest

from schemas.official import (
    Correspondence, Frame, FramesFile, ObjectAnnotation, ObjectsFile, OfficialFormatError, TrackEntry,
    frames_to_json, objects_from_json, objects_to_json, read_frames, read_objects, write_json,
)


def sample_files():
    frames = FramesFile("abc_123", (360, 640), (
        Frame(0, True, (512.0, 504.0, 320.0, 180.0), (0.1, -1.5, 2.0), (1.0, 0.0, 0.0, 0.0)),
        Frame(33333, False, (512.0, 504.0, 320.0, 180.0), (0.2, -1.5, 2.0), (0.99, 0.0, 0.141, 0.0)),
    ))
    posed = ObjectAnnotation("0", "03001627", True, True, (
        TrackEntry(0, (0.1, 0.2, 0.5, 0.6), (Correspondence((0.3, 0.4), (0.1, 0.2, -0.3)),)),
        TrackEntry(33333, (0.1, 0.25, 0.5, 0.65)),
    ), cad_id="sh3d-scopia.chair", translation=(1.0, 0.4, -2.0), rotation=(1.0, 0.0, 0.0, 0.0), scale=(1.0, 1.1, 0.9))
    unposed = ObjectAnnotation("1", "04379243", False, False, (TrackEntry(0, (0.5, 0.5, 0.9, 0.9)),))
    return frames, ObjectsFile("abc_123", (posed, unposed))


def test_round_trip(tmp_path):
    frames, objects = sample_files()
    write_json(tmp_path / "frames.json", frames_to_json(frames))
    write_json(tmp_path / "objects.json", objects_to_json(objects))
    assert read_frames(tmp_path / "frames.json") == frames
    assert read_objects(tmp_path / "objects.json") == objects


def test_official_field_names_and_absent_pose():
    _, objects = sample_files()
    data = objects_to_json(objects)
    posed, unposed = data["objects"]
    assert set(posed) == {"track_id", "is_track_automatic", "class", "cad_id", "translation", "rotation", "scale",
                          "is_mirrored", "track"}
    assert not {"translation", "rotation", "scale", "cad_id"} & unposed.keys() and "is_mirrored" in unposed
    assert posed["track"][0]["correspondences"] == [{"2d": [0.3, 0.4], "3d": [0.1, 0.2, -0.3]}]
    assert posed["track"][1]["correspondences"] is None


def test_malformed_files_name_the_field(tmp_path):
    _, objects = sample_files()
    data = objects_to_json(objects)
    data["objects"][0]["track"][1]["box"] = [0.1, 0.2]
    with pytest.raises(OfficialFormatError, match=r"objects\[0\].track\[1\].box: expected a list of 4"):
        objects_from_json(data, "objects.json")
    del data["objects"][1]["class"]
    data["objects"][0]["track"][1]["box"] = [0.1, 0.2, 0.3, 0.4]
    with pytest.raises(OfficialFormatError, match="missing field 'class'"):
        objects_from_json(data)
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(OfficialFormatError, match="bad.json: not valid JSON"):
        read_frames(tmp_path / "bad.json")
    json.dumps(data)  # still plain JSON


def test_normalised_intrinsics_are_refused(tmp_path):
    """Intrinsics are pixels in the official format; normalised ones (an old file) name the frame."""
    frames, _ = sample_files()
    data = frames_to_json(frames)
    data["frames"][1]["intrinsics"] = [0.8, 1.4, 0.5, 0.5]
    write_json(tmp_path / "frames.json", data)
    with pytest.raises(OfficialFormatError, match=r"frames.json: frames\[1\].intrinsics: .* look normalised"):
        read_frames(tmp_path / "frames.json")


def _set(data, path, value):
    """``data`` with the field at ``path`` (keys and indices) set to ``value``; ``path`` () replaces it."""
    if not path:
        return value
    data = json.loads(json.dumps(data))
    node = data
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return data


OBJECT_DEFECTS = [  # (path, value, the message names)
    (("objects", 0, "track", 0, "timestamp"), "abc", r"objects\[0\].track\[0\].timestamp: expected a whole number"),
    (("objects", 0, "track", 1, "timestamp"), 1.5, r"objects\[0\].track\[1\].timestamp: expected a whole number"),
    (("objects", 1), 1, r"objects\[1\]: expected an object"),
    (("objects",), None, r"objects.json: objects: expected a list"),
    (("objects", 0, "track"), {"a": 1}, r"objects\[0\].track: expected a list"),
    (("objects", 0, "track", 0, "correspondences"), 5, r"objects\[0\].track\[0\].correspondences: expected a list"),
    (("objects", 0, "track", 0, "correspondences", 0), [1, 2], r"track\[0\].correspondences\[0\]: expected an object"),
    (("objects", 0, "track", 0, "correspondences", 0, "3d"), [1, "x", 2], r"correspondences\[0\].3d: expected numbers"),
    (("objects", 0, "is_mirrored"), "yes", r"objects\[0\].is_mirrored: expected true or false"),
    (("objects", 0, "rotation"), None, r"objects\[0\].rotation: expected a list of 4"),
    ((), [], r"objects.json: expected an object"),
]


@pytest.mark.parametrize("path,value,message", OBJECT_DEFECTS)
def test_every_malformed_objects_field_is_named(path, value, message):
    """Wrong types anywhere in objects.json are one OfficialFormatError naming the field, never a
    TypeError or ValueError from deep inside the reader."""
    _, objects = sample_files()
    with pytest.raises(OfficialFormatError, match=message):
        objects_from_json(_set(objects_to_json(objects), path, value), "objects.json")


FRAME_DEFECTS = [
    (("frames", 0), 1, r"frames\[0\]: expected an object"),
    (("frames", 1, "extrinsics"), [1], r"frames\[1\].extrinsics: expected an object"),
    (("frames", 1, "extrinsics", "rotation"), None, r"frames\[1\].extrinsics.rotation: expected a list of 4"),
    (("frames", 0, "timestamp"), "0", r"frames\[0\].timestamp: expected a whole number"),
    (("frames", 0, "key_frame"), 1, r"frames\[0\].key_frame: expected true or false"),
    (("image_size",), [360.5, 640], r"image_size\[0\]: expected a whole number"),
    (("frames",), "x", r"frames.json: frames: expected a list"),
    ((), [], r"frames.json: expected an object"),
]


@pytest.mark.parametrize("path,value,message", FRAME_DEFECTS)
def test_every_malformed_frames_field_is_named(tmp_path, path, value, message):
    frames, _ = sample_files()
    write_json(tmp_path / "frames.json", _set(frames_to_json(frames), path, value))
    with pytest.raises(OfficialFormatError, match=message):
        read_frames(tmp_path / "frames.json")
