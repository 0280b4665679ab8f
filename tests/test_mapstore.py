"""The map store's folder: a map's latest version under its name, earlier versions kept beside it, never
overwritten in place; what cannot be read is reported, not served."""

from __future__ import annotations

import pytest

from twohr.dataset import CameraIntrinsics
from twohr.mapfile import MapFileError, MapStore, encode_map, read_map

CAMERA = CameraIntrinsics(fx=500, fy=500, cx=319.5, cy=239.5, width=640, height=480)


def test_saving_under_a_name_keeps_the_earlier_versions(tmp_path, tiny_map):
    store = MapStore(tmp_path)
    first = encode_map(tiny_map("lab", CAMERA))
    assert store.save(first).version == 1
    second = tiny_map("lab", CAMERA)
    second.arrays.landmark_positions += 1
    entry = store.save(encode_map(second))
    assert entry.version == 2 and entry.keyframes == 1 and entry.landmarks == 3
    assert [p.name for p in store.versions("lab")] == ["lab.v1.map"]
    assert (read_map(tmp_path / "lab.v1.map").arrays.landmark_positions == 1).all()
    assert (read_map(tmp_path / "lab.map").arrays.landmark_positions == 2).all()
    with pytest.raises(MapFileError, match="holds map 'lab'"):
        store.save(first, name="copy")  # a map's name is its frame: not another one's
    assert store.save(encode_map(tiny_map("copy", CAMERA))).name == "copy" and store.names() == ["copy", "lab"]
    (tmp_path / "broken.map").write_bytes(b"garbage")
    good, bad = store.entries()
    assert [e.name for e in good] == ["copy", "lab"] and "not a twohr map file" in bad["broken"]
    assert store.delete("lab") and not store.delete("lab")
    assert store.names() == ["broken", "copy"] and not list(tmp_path.glob("lab*"))
    assert not list(tmp_path.glob(".*.tmp"))  # every write went through a temporary file and a rename


def test_a_bad_upload_or_name_changes_nothing(tmp_path, tiny_map):
    store = MapStore(tmp_path)
    store.save(encode_map(tiny_map("lab", CAMERA)))
    before = (tmp_path / "lab.map").read_bytes()
    with pytest.raises(MapFileError, match="not a twohr map file"):
        store.save(b"PK\x03\x04 broken", name="lab")
    for name in ("../escape", "lab.v2", "", "a/b"):
        with pytest.raises(MapFileError, match="not a map name"):
            store.path(name)
    assert (tmp_path / "lab.map").read_bytes() == before and store.versions("lab") == []
