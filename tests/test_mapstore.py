"""The map store's folder: a map's latest version under its name, earlier versions kept beside it, never
overwritten in place; what cannot be read is reported, not served."""

from __future__ import annotations

import pytest

from twohr.dataset import CameraIntrinsics
from twohr.mapfile import OPERATOR, MapFileError, MapStore, encode_map, read_map, write_bytes_atomically

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
    write_bytes_atomically(tmp_path / "maps" / "lab.v3.map", versions[3])  # the crash: no link made
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
