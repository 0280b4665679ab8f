"""Live corrections stay small as a session grows: the tracker sends the keyframes that are new or moved
(:class:`PathDeltas`), the whole path every few messages; a subscriber rebuilds the whole path
(:class:`PathAssembler`), and after a lost delta waits for the next full one."""

from __future__ import annotations

import numpy as np

from twohr.geometry import so3_exp
from twohr.messages import PathAssembler, PathDeltas, PathMsg, decode, encode
from twohr.trajectory import Trajectory

WINDOW = 10  # a local bundle adjustment moves the latest keyframes


def keyframe_path(count: int) -> Trajectory:
    poses = np.tile(np.eye(4), (count, 1, 1))
    for i in range(count):
        poses[i, :3, :3] = so3_exp(np.array([0.0, 0.01 * i, 0.0]))
        poses[i, :3, 3] = [0.05 * i, 0.0, 0.01 * np.sin(i)]
    return Trajectory(np.arange(count) * 0.5, poses)


def grow(count: int, rng: np.random.Generator):
    """A session's keyframe paths as its map grows to ``count`` keyframes, the latest WINDOW moved at each."""
    poses = keyframe_path(count).poses
    for n in range(1, count + 1):
        poses[max(0, n - WINDOW):n, :3, 3] += rng.normal(0, 1e-3, (min(n, WINDOW), 3))
        yield Trajectory(np.arange(n) * 0.5, poses[:n].copy())


def message(deltas: PathDeltas, path: Trajectory) -> bytes:
    fields, arrays = deltas.next(path)
    return encode(PathMsg(session_id="s", robot_id="r", frame_index=len(path), stamp=float(path.stamps[-1]),
                          **fields), arrays)


def test_deltas_rebuild_the_whole_path_and_stay_small():
    rng = np.random.default_rng(0)
    deltas, assembler, sizes = PathDeltas(full_every=10), PathAssembler(), {}
    for path in grow(1000, rng):
        payload = message(deltas, path)
        msg, arrays = decode(payload, PathMsg)
        rebuilt = assembler.add(msg, arrays)
        assert rebuilt is not None and len(rebuilt) == len(path)
        np.testing.assert_allclose(rebuilt.poses, path.poses, atol=1e-9)
        sizes.setdefault(len(path), []).append((msg.full, len(payload)))
    full_at_1000 = len(encode(PathMsg(session_id="s", robot_id="r", frame_index=0, stamp=0.0, keyframes=1000),
                              {"stamps": np.zeros(1000), "poses": np.zeros((1000, 7))}))
    (full, delta_at_1000), = sizes[1000]
    assert not full and delta_at_1000 < full_at_1000 / 20, (delta_at_1000, full_at_1000)
    full_sizes = {n: len(encode(PathMsg(session_id="s", robot_id="r", frame_index=0, stamp=0.0),
                                {"stamps": np.zeros(n), "poses": np.zeros((n, 7))})) for n in (10, 100, 1000)}
    print("path message bytes at keyframe 10, 100, 1000: delta", {n: sizes[n][0][1] for n in (10, 100, 1000)},
          "full", full_sizes)


def test_after_a_lost_delta_the_path_is_unknown_until_the_next_full_one():
    rng = np.random.default_rng(1)
    deltas, assembler = PathDeltas(full_every=5), PathAssembler()
    answers = []
    for i, path in enumerate(grow(12, rng)):
        payload = message(deltas, path)
        if i == 6:
            continue  # lost on the way
        msg, arrays = decode(payload, PathMsg)
        answers.append((msg.seq, msg.full, assembler.add(msg, arrays) is not None))
    assert answers == [(0, True, True), (1, False, True), (2, False, True), (3, False, True), (4, False, True),
                       (5, True, True), (7, False, False), (8, False, False), (9, False, False),
                       (10, True, True), (11, False, True)]


def test_a_keyframe_that_went_sends_the_full_path():
    deltas = PathDeltas(full_every=100)
    path = keyframe_path(20)
    assert deltas.next(path)[0]["full"] and not deltas.next(path)[0]["full"]
    culled = path.subset([i for i in range(20) if i != 7])
    fields, arrays = deltas.next(culled)
    assert fields == {"full": True, "seq": 2, "keyframes": 19} and len(arrays["stamps"]) == 19
    fields, arrays = deltas.next(culled)
    assert fields["full"] is False and len(arrays["stamps"]) == 0  # nothing moved
