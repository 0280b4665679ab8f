"""The map store's folder: a map's latest version under its name, earlier versions kept beside it, never
overwritten in place; what cannot be read is reported, not served."""

from __future__ import annotations

import pytest

from twohr.dataset import CameraIntrinsics
from twohr.files import write_atomic
from twohr.mapfile import OPERATOR, MapFileError, encode_map, read_map
from twohr.mapstore import MapStore

CAMERA = CameraIntrinsics(fx=500, fy=500, cx=319.5, cy=239.5, width=640, height=480)


def test_saving_under_a_name_keeps_the_earlier_versions(tmp_path, tiny_map):
    store = MapStore(tmp_path)
    first = encode_map(tiny_map("lab", CAMERA))
    assert store.save(first, builder=OPERATOR).version == 1
    second = tiny_map("lab", CAMERA)
    second.arrays.landmark_positions += 1
    entry = store.save(encode_map(second), builder=OPERATOR)
    assert entry.version == 2 and entry.keyframes == 1 and entry.landmarks == 3
    assert [p.name for p in store.versions("lab")] == ["lab.v1.map"]
    assert (read_map(tmp_path / "lab.v1.map").arrays.landmark_positions == 1).all()
    assert (read_map(tmp_path / "lab.map").arrays.landmark_positions == 2).all()
    with pytest.raises(MapFileError, match="holds map 'lab'"):
        store.save(first, name="copy", builder=OPERATOR)  # a map's name is its frame: not another one's
    assert store.save(encode_map(tiny_map("copy", CAMERA)), builder=OPERATOR).name == "copy"
    assert store.names() == ["copy", "lab"]
    (tmp_path / "broken.map").write_bytes(b"garbage")
    good, bad = store.entries()
    assert [e.name for e in good] == ["copy", "lab"] and "not a twohr map file" in bad["broken"]
    assert store.delete("lab") and not store.delete("lab")
    assert store.names() == ["broken", "copy"] and not list(tmp_path.glob("lab*"))
    assert not list(tmp_path.glob(".*.tmp"))  # every write went through a temporary file and a rename


def test_a_bad_upload_or_name_changes_nothing(tmp_path, tiny_map):
    store = MapStore(tmp_path)
    store.save(encode_map(tiny_map("lab", CAMERA)), builder=OPERATOR)
    before = (tmp_path / "lab.map").read_bytes()
    with pytest.raises(MapFileError, match="not a twohr map file"):
        store.save(b"PK\x03\x04 broken", name="lab", builder=OPERATOR)
    for name in ("../escape", "lab.v2", "", "a/b"):
        with pytest.raises(MapFileError, match="not a map name"):
            store.path(name)
    assert (tmp_path / "lab.map").read_bytes() == before and store.versions("lab") == []


def saved(store: MapStore, tiny_map, shift: float) -> bytes:
    """Save one more version of map lab (its landmarks moved by ``shift``); its bytes as stored."""
    made = tiny_map("lab", CAMERA)
    made.arrays.landmark_positions += shift
    entry = store.save(encode_map(made), builder=OPERATOR)
    return store.version_path("lab", entry.version).read_bytes()


def test_a_save_cut_before_its_link_and_a_copied_store_keep_their_numbers(tmp_path, tiny_map):
    """A save cut off between its numbered file and the readers' link (v3 whole, lab.map still v2's): the latest is
    v3, served as such, and the next save is v4. A store copied without its hard links reads the same. A store of
    the earlier layout (lab.map none of the numbered files) has its latest one past them."""
    store = MapStore(tmp_path / "maps")
    versions = {number: saved(store, tiny_map, number) for number in (1, 2)}
    third = tiny_map("lab", CAMERA)
    third.arrays.landmark_positions += 3
    versions[3] = encode_map(third)
    write_atomic(tmp_path / "maps" / "lab.v3.map", versions[3])  # the crash: no link made
    assert (tmp_path / "maps" / "lab.map").read_bytes() == versions[2]
    assert store.numbers("lab") == [1, 2, 3] and store.entry("lab").version == 3
    assert store.latest_file("lab").read_bytes() == versions[3]
    assert saved(store, tiny_map, 4) == (tmp_path / "maps" / "lab.v4.map").read_bytes()
    assert store.numbers("lab") == [1, 2, 3, 4] and (tmp_path / "maps" / "lab.map").read_bytes() != versions[2]

    copied = tmp_path / "copied"  # as `cp -r` leaves it: every file on its own, no links
    copied.mkdir()
    for path in (tmp_path / "maps").glob("lab*"):
        (copied / path.name).write_bytes(path.read_bytes())
    copy = MapStore(copied)
    assert copy.numbers("lab") == [1, 2, 3, 4] and copy.entry("lab").version == 4

    earlier = tmp_path / "earlier"  # lab.v1, lab.v2 kept, lab.map the latest with no number of its own
    earlier.mkdir()
    for number in (1, 2):
        (earlier / f"lab.v{number}.map").write_bytes(versions[number])
    (earlier / "lab.map").write_bytes(versions[3])
    old = MapStore(earlier)
    assert old.numbers("lab") == [1, 2, 3] and old.latest_file("lab") == earlier / "lab.map"
    assert old.version_path("lab", 3).read_bytes() == versions[3]
    saved(old, tiny_map, 5)
    assert old.numbers("lab") == [1, 2, 3, 4] and (earlier / "lab.v3.map").read_bytes() == versions[3]


def two_robots_map():
    """A map of two keyframes, one by robot a's camera, one by b's, each observing landmarks of its own."""
    import numpy as np

    from twohr.config import PipelineConfig
    from twohr.mapfile import MapArrays, arrays_file

    arrays = MapArrays(
        keyframe_poses=np.stack([np.eye(4)] * 2), keyframe_stamps=np.array([0.0, 1.0]),
        keyframe_culled=np.zeros(2, bool), keyframe_first=np.array([0, 3, 5]),
        keypoint_xy=np.ones((5, 2), np.float32), keypoint_depth=np.ones(5, np.float32),
        keypoint_landmark=np.array([0, 1, 2, 3, 4]), landmark_positions=np.arange(15, dtype=float).reshape(5, 3),
        landmark_descriptors=np.ones((5, 128), np.float32), landmark_accepted=np.ones(5, np.int64),
        landmark_rejected=np.zeros(5, np.int64), landmark_bad=np.zeros(5, bool), keyframe_camera=np.array([0, 1]))
    return arrays_file(arrays, CAMERA, PipelineConfig(), "lab", cameras=[CAMERA], camera_robots=["a", "b"])


def test_twohr_maps_exports_a_point_cloud_and_takes_a_robot_out_audited(tmp_path):
    """``twohr maps export --ply``: each landmark with the robot whose keyframe made it; ``remove-robot``: the next
    version without that robot's keyframes, in the audit trail with the version it made."""
    import json
    import subprocess
    import sys

    import numpy as np

    maps = tmp_path / "maps"
    MapStore(maps).save(encode_map(two_robots_map()), builder="a")
    twohr = [sys.executable, "-m", "twohr_app", "maps"]
    done = subprocess.run([*twohr, "export", "lab", "--ply", "--maps", str(maps), "--out", str(tmp_path / "lab.ply")],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and "property source: 0 = a, 1 = b" in done.stdout, done.stderr
    head, _, body = (tmp_path / "lab.ply").read_bytes().partition(b"end_header\n")
    assert b"element vertex 5" in head and (tmp_path / "lab.ply").stat().st_mode & 0o777 == 0o600
    rows = np.frombuffer(body, dtype=[("xyz", "<f4", 3), ("source", "<i4")])
    assert rows["source"].tolist() == [0, 0, 0, 1, 1] and rows["xyz"][4].tolist() == [12.0, 13.0, 14.0]
    done = subprocess.run([*twohr, "remove-robot", "lab", "b", "--maps", str(maps)], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0 and "version 2 without robot b's keyframes" in done.stdout, done.stderr
    left = read_map(maps / "lab.map")
    assert (left.header.camera_robots, left.header.keyframes, left.header.landmarks) == (["a"], 1, 3)
    logged = [json.loads(line) for line in (maps / "audit.jsonl").read_text().splitlines()]
    assert [(e["action"], e["who"], e["robot"], e["version"]) for e in logged] == [
        ("map.remove_robot", OPERATOR, "b", 2)]
