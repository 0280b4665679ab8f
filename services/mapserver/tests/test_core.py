"""The map server's core on a small synthetic world: points in a room, each with its own descriptor, seen by two
robots whose frames differ by a known transform. Robot b is merged where that transform puts it, not before k
matches agree; a robot that sees other points is never merged; the merged map is one valid map file with each
keyframe's robot, and a matched landmark kept once."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from twohr.config import PipelineConfig
from twohr.dataset import CameraIntrinsics
from twohr.features import mutual_nn
from twohr.geometry import invert_pose, make_pose, project, so3_exp, transform_points
from twohr.keyframe_sender import KeyframeSender
from twohr.mapfile import MapArrays, arrays_file, encode_map, read_map
from twohr.mapstore import without_robot
from twohr_services.mapserver.core import (
    STORED,
    BatchRefused,
    KeyframeBatch,
    SharedMap,
    check_batch,
    export,
    pose_gap,
)

CAMERA = CameraIntrinsics(fx=400, fy=400, cx=319.5, cy=239.5, width=640, height=480)
#: robot b's frame in robot a's (the map's): what the merge must find
T_AB = make_pose(so3_exp(np.array([0.02, -0.3, 0.05])), np.array([0.7, -0.1, 0.4]))


def world(seed: int, count: int = 1500) -> tuple[np.ndarray, np.ndarray]:
    """Points on the walls of a 6 x 6 x 3 m room, and a unit descriptor for each."""
    rng = np.random.default_rng(seed)
    points = rng.uniform([-3, -1.5, -3], [3, 1.5, 3], (count, 3))
    wall = rng.integers(0, 4, count)
    points[wall == 0, 0], points[wall == 1, 0], points[wall == 2, 2], points[wall == 3, 2] = -3, 3, -3, 3
    descriptors = rng.normal(size=(count, 128)).astype(np.float32)
    return points, descriptors / np.linalg.norm(descriptors, axis=1, keepdims=True)


def camera_path(count: int, start: float) -> list[np.ndarray]:
    """Camera-to-world poses turning round the room's middle, 8 degrees apart."""
    return [make_pose(so3_exp(np.array([0.0, start + 0.14 * i, 0.0])), np.array([0.02 * i, 0.0, 0.0]))
            for i in range(count)]


def robot_map(points: np.ndarray, descriptors: np.ndarray, poses_world: list[np.ndarray],
              T_world_robot: np.ndarray, rows_of: np.ndarray | None = None) -> MapArrays:
    """The map a robot would have: its keyframes at ``poses_world`` (in its own frame, ``T_world_robot`` being its
    frame in the world), each observing the points in view with depth; a landmark per point seen, its row first in
    ``rows_of`` (the points of a map it tracks in keep that map's rows)."""
    seen_ids, xy_all, depth_all, first = [], [], [], [0]
    for pose in poses_world:
        camera_points = transform_points(invert_pose(pose), points)
        pixels = project(camera_points, CAMERA.matrix)
        visible = np.flatnonzero((camera_points[:, 2] > 0.3) & (pixels[:, 0] >= 0) & (pixels[:, 0] < 640)
                                 & (pixels[:, 1] >= 0) & (pixels[:, 1] < 480))[:400]
        seen_ids.append(visible)
        xy_all.append(pixels[visible])
        depth_all.append(camera_points[visible, 2])
        first.append(first[-1] + len(visible))
    used = np.unique(np.concatenate(seen_ids))
    if rows_of is not None:  # the map's points first, in its rows; the new ones after
        used = np.concatenate([rows_of, np.setdiff1d(used, rows_of)])
    row = {int(i): r for r, i in enumerate(used)}
    T_robot_world = invert_pose(T_world_robot)
    landmarks = len(used)
    return MapArrays(
        keyframe_poses=np.stack([T_robot_world @ pose for pose in poses_world]),
        keyframe_stamps=np.arange(len(poses_world), dtype=float), keyframe_culled=np.zeros(len(poses_world), bool),
        keyframe_first=np.array(first), keypoint_xy=np.concatenate(xy_all).astype(np.float32),
        keypoint_depth=np.concatenate(depth_all).astype(np.float32),
        keypoint_landmark=np.array([row[int(i)] for ids in seen_ids for i in ids], np.int64),
        landmark_positions=transform_points(T_robot_world, points[used]), landmark_descriptors=descriptors[used],
        landmark_accepted=np.ones(landmarks, np.int64), landmark_rejected=np.zeros(landmarks, np.int64),
        landmark_bad=np.zeros(landmarks, bool))


def keyframes_of(arrays: MapArrays) -> list[KeyframeBatch]:
    """One batch per keyframe, as a tracker sends them while its map grows."""
    sender, batches = KeyframeSender(), []
    for count in range(1, len(arrays.keyframe_stamps) + 1):
        end = arrays.keyframe_first[count]
        grown = MapArrays(arrays.keyframe_poses[:count], arrays.keyframe_stamps[:count],
                          arrays.keyframe_culled[:count], arrays.keyframe_first[:count + 1], arrays.keypoint_xy[:end],
                          arrays.keypoint_depth[:end], arrays.keypoint_landmark[:end], arrays.landmark_positions,
                          arrays.landmark_descriptors, arrays.landmark_accepted, arrays.landmark_rejected,
                          arrays.landmark_bad)
        first, parts = sender.next(grown)
        batches.append(KeyframeBatch(first=first, **parts))
    return batches


def test_a_robot_is_merged_where_its_frame_is_and_the_map_is_saved_as_one():
    points, descriptors = world(0)
    a = robot_map(points, descriptors, camera_path(10, 0.0), np.eye(4))
    b = robot_map(points, descriptors, camera_path(8, 0.3), T_AB)
    shared_map = SharedMap("lab", mutual_nn)
    assert shared_map.join("a", "s1").kind == "defines" and shared_map.join("b", "s2") is None
    for batch in keyframes_of(a):
        assert shared_map.add("a", batch, CAMERA) is None
    events = [e for e in (shared_map.add("b", batch, CAMERA) for batch in keyframes_of(b)) if e is not None]
    merged = [e for e in events if e.kind == "merged"]
    assert len(merged) == 1 and len(merged[0].matches) == 3, events
    assert merged[0].keyframes >= 3  # k = 3 matches, one keyframe each
    metres, degrees = pose_gap(shared_map.submaps["b"].T, T_AB)
    assert metres < 0.01 and degrees < 0.2, (metres, degrees)

    exported = export(shared_map, ["a", "b"])
    assert exported.robots == ["a", "b"] and list(np.bincount(exported.arrays.keyframe_camera)) == [10, 8]
    # b's keyframes are in the map's frame: where a's frame has them
    np.testing.assert_allclose(exported.arrays.keyframe_poses[10:, :3, 3],
                               np.stack(camera_path(8, 0.3))[:, :3, 3], atol=0.01)
    # a landmark both robots matched is one landmark: fewer rows than the two maps' together
    assert len(exported.arrays.landmark_positions) < len(a.landmark_positions) + len(b.landmark_positions)
    stored = read_map(encode_map(arrays_file(exported.arrays, exported.cameras[0], PipelineConfig(), "lab",
                                             cameras=exported.cameras[1:], camera_robots=exported.robots)))
    assert stored.header.camera_robots == ["a", "b"] and stored.header.keyframes == 18
    left = without_robot(stored, "b")
    assert left.header.camera_robots == ["a"] and left.header.keyframes == 10
    read_map(encode_map(left))  # still a valid map


def test_a_robot_that_sees_other_places_is_never_merged():
    points, descriptors = world(0)
    elsewhere, other = world(1)
    shared_map = SharedMap("lab", mutual_nn)
    shared_map.join("a", "s1")
    shared_map.join("c", "s3")
    for batch in keyframes_of(robot_map(points, descriptors, camera_path(10, 0.0), np.eye(4))):
        shared_map.add("a", batch, CAMERA)
    for batch in keyframes_of(robot_map(elsewhere, other, camera_path(10, 0.0), T_AB)):
        assert shared_map.add("c", batch, CAMERA) is None
    assert shared_map.submaps["c"].T is None and shared_map.submaps["c"].matches == []


def test_a_robot_that_shares_a_stored_map_tracks_in_its_frame_and_the_map_grows_by_its_keyframes_alone():
    points, descriptors = world(0)
    base_poses = camera_path(10, 0.0)
    base = robot_map(points, descriptors, base_poses, np.eye(4))
    stored = read_map(encode_map(arrays_file(base, CAMERA, PipelineConfig(), "lab", camera_robots=["a"])))
    shared_map = SharedMap("lab", mutual_nn, stored=stored)
    assert shared_map.join("c", "s4").kind == "joined"
    # c's tracker holds the stored map and adds 4 keyframes; the stored map's points keep their rows
    used_by_base = np.array(sorted({int(i) for i in range(len(points))
                                    if np.any(np.all(np.isclose(base.landmark_positions, points[i]), axis=1))}))
    grown = robot_map(points, descriptors, base_poses + camera_path(4, 1.4), np.eye(4), rows_of=used_by_base)
    sender = KeyframeSender(keyframes=10)  # the stored keyframes are the map server's already
    first, parts = sender.next(grown)
    assert first == 10 and shared_map.add("c", KeyframeBatch(first=first, **parts), CAMERA) is None
    exported = export(shared_map, [STORED, "c"])
    assert exported.robots == ["a", "c"] and exported.arrays.keyframe_camera.tolist() == [0] * 10 + [1] * 4
    np.testing.assert_array_equal(exported.arrays.keyframe_poses[:10], base.keyframe_poses)
    # the stored landmarks c saw again are not doubled: only the points new to the map add rows
    new_points = len(grown.landmark_positions) - len(base.landmark_positions)
    assert len(exported.arrays.landmark_positions) == len(base.landmark_positions) + new_points, (
        len(exported.arrays.landmark_positions), len(base.landmark_positions), new_points)


def _malformed(batch: KeyframeBatch) -> dict[str, KeyframeBatch]:
    """One batch made wrong in each way a robot could send it."""
    def changed(**parts) -> KeyframeBatch:
        return dataclasses.replace(batch, **parts)

    poses = batch.poses.copy()
    poses[0, :3, :3] *= 2.0
    nan_positions = batch.positions.copy()
    nan_positions[0, 0] = np.nan
    ragged = batch.keypoint_first.copy()
    ragged[-1] += 5
    return {"poses not rigid": changed(poses=poses),
            "poses not 4x4": changed(poses=batch.poses[:, :3, :]),
            "infinite stamps": changed(stamps=np.full_like(batch.stamps, np.inf)),
            "a position not finite": changed(positions=nan_positions),
            "keypoint_first past the keypoints": changed(keypoint_first=ragged),
            "keyframes beyond the poses": changed(first=len(batch.poses)),
            "descriptors 0 wide": changed(descriptors=np.zeros((len(batch.described), 0), np.float32)),
            "descriptors of bytes": changed(descriptors=batch.descriptors.astype(np.uint8)),
            "a negative landmark id": changed(landmark=-np.ones_like(batch.landmark)),
            "fewer depths than keypoints": changed(depth=batch.depth[:-1]),
            "float ids": changed(described=batch.described.astype(np.float64))}


def test_every_batch_a_tracker_sends_passes_and_each_malformed_one_is_refused_in_one_line():
    points, descriptors = world(0)
    batches = keyframes_of(robot_map(points, descriptors, camera_path(6, 0.0), np.eye(4)))
    for batch in batches:
        check_batch(batch, 128, "float32")
    for what, bad in _malformed(batches[-1]).items():
        with pytest.raises(BatchRefused) as refused:
            check_batch(bad, 128, "float32")
        assert "\n" not in str(refused.value), what
    # the width is the session's network's, not the batch's: 128-D floats are not an ORB session's
    with pytest.raises(BatchRefused, match="want"):
        check_batch(batches[-1], 32, "uint8")


def test_the_map_room_refuses_another_robots_session_and_malformed_keyframes_and_goes_on(bus_config, tmp_path):
    """On a real router: robot b sends keyframes on a's session and malformed keyframes on its own (descriptors 0
    wide, rows of different lengths); the map room refuses each, counts them for b, keeps a's session as it was
    (not final, its keyframes taken), and saves the map when the sessions end."""
    import threading
    import time

    from twohr import keys
    from twohr.bus import open_session, query_health
    from twohr.mapmodes import MapMode
    from twohr.messages import ControlMsg, KeyframesMsg, encode
    from twohr.service import declare_publisher
    from twohr_services.mapserver.room import MapRoomSettings
    from twohr_services.mapserver.service import MapServerService

    room = MapServerService(bus_config, MapRoomSettings(maps=tmp_path / "maps"))
    stop = threading.Event()
    thread = threading.Thread(target=room.run, args=(stop,), daemon=True)
    thread.start()
    client = open_session(bus_config)
    publishers = {key: declare_publisher(client, key) for robot in ("a", "b")
                  for key in (keys.key(robot, keys.CONTROL), keys.key(robot, "keyframes"))}

    def control(robot: str, command: str) -> None:
        publishers[keys.key(robot, keys.CONTROL)].put(encode(ControlMsg(
            session_id=f"s-{robot}", robot_id=robot, frame_index=-1, stamp=time.time(), command=command,
            map_name="lab", map_mode=MapMode.SHARE, config=PipelineConfig())))

    def send(robot: str, session: str, batch: KeyframeBatch, final: bool = False) -> None:
        arrays = {name: getattr(batch, name) for name in KeyframesMsg.required_arrays}
        publishers[keys.key(robot, "keyframes")].put(encode(KeyframesMsg(
            session_id=session, robot_id=robot, frame_index=-1, stamp=time.time(), map_name="lab",
            first=batch.first, camera=CAMERA, final=final), arrays))

    def until(condition, what: str) -> None:
        deadline = time.monotonic() + 30
        while not condition():
            assert time.monotonic() < deadline, what
            time.sleep(0.05)

    try:
        until(lambda: query_health(client, "mapserver", timeout=1.0) is not None, "the map room never answered")
        points, descriptors = world(0)
        a_batches = keyframes_of(robot_map(points, descriptors, camera_path(6, 0.0), np.eye(4)))
        b_batches = keyframes_of(robot_map(points, descriptors, camera_path(6, 0.3), T_AB))
        for robot in ("a", "b"):
            control(robot, "start")
        until(lambda: "lab" in room.maps and len(room.maps["lab"].sessions) == 2, "the sessions did not start")
        send("a", "s-a", a_batches[0])
        ragged = dataclasses.replace(b_batches[0], depth=b_batches[0].depth[:-3])
        zero_wide = dataclasses.replace(b_batches[0], descriptors=np.zeros((len(b_batches[0].described), 0),
                                                                           np.float32))
        send("b", "s-a", b_batches[0], final=True)  # b speaking for a's session
        send("b", "s-b", zero_wide)
        send("b", "s-b", ragged)
        for batch in a_batches[1:]:
            send("a", "s-a", batch)
        until(lambda: room.maps["lab"].sessions["s-a"].keyframes == len(a_batches), "a's keyframes were not taken")
        health = query_health(client, "mapserver", timeout=5.0)
        assert health["refused"] == {"b": 3} and health["errors"] == 0, health
        assert not room.maps["lab"].sessions["s-a"].final and room.maps["lab"].sessions["s-b"].keyframes == 0
        send("b", "s-b", b_batches[0])  # b's own, well formed: taken
        until(lambda: room.maps["lab"].sessions["s-b"].keyframes == 1, "b's own keyframes were not taken")
        send("a", "s-a", a_batches[-1], final=True)
        send("b", "s-b", b_batches[0], final=True)
        for robot in ("a", "b"):
            control(robot, "stop")
        until(lambda: "lab" not in room.maps, "the shared map was not closed")
        assert thread.is_alive()
        assert (tmp_path / "maps").is_dir() and any((tmp_path / "maps").rglob("*")), "the map was not saved"
    finally:
        client.close()
        stop.set()
        thread.join(30)
