"""One writer of whole files (``twohr.files``): a reader finds the old file or the new one, the new one has the mode
its caller asked for from its creation, and a write that fails leaves the old file and no temporary behind."""

from __future__ import annotations

import os
import stat

import numpy as np
import pytest

from twohr.files import AS_OPEN, replacing, umask, write_atomic


def mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.fixture
def umask_022():
    before = os.umask(0o022)
    try:
        yield
    finally:
        os.umask(before)


def test_a_file_is_replaced_whole_and_private_unless_asked(tmp_path, umask_022):
    path = tmp_path / "made" / "here" / "state.json"
    write_atomic(path, '{"a": 1}')
    reader = open(path, "rb")  # a reader that opened the old file keeps reading the old file
    write_atomic(path, b'{"a": 2}')
    assert reader.read() == b'{"a": 1}' and path.read_bytes() == b'{"a": 2}'
    reader.close()
    assert mode(path) == 0o600 and sorted(p.name for p in path.parent.iterdir()) == ["state.json"]
    write_atomic(path, "public", AS_OPEN)
    assert mode(path) == 0o644 == 0o666 & ~umask() and path.read_text() == "public"
    write_atomic(tmp_path / "private" / "key", "k", durable=True, folder_mode=0o700)
    assert mode(tmp_path / "private") == 0o700 and mode(tmp_path / "private" / "key") == 0o600


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    path = tmp_path / "cache.npz"
    write_atomic(path, b"old")
    with pytest.raises(RuntimeError, match="half way"), replacing(path) as out:
        out.write(b"new, but")
        raise RuntimeError("half way")
    assert path.read_bytes() == b"old" and [p.name for p in tmp_path.iterdir()] == ["cache.npz"]


def test_a_tool_that_writes_by_name_writes_the_temporary(tmp_path):
    path = tmp_path / "arrays.npz"
    with replacing(path, AS_OPEN, suffix=".npz") as out:
        assert out.name.endswith(".npz") and os.path.dirname(out.name) == str(tmp_path)
        np.savez(out.name, xy=np.arange(6).reshape(3, 2))  # numpy adds .npz to a name without it
    assert np.load(path)["xy"].tolist() == [[0, 1], [2, 3], [4, 5]]
    assert [p.name for p in tmp_path.iterdir()] == ["arrays.npz"]
