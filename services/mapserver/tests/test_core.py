"""The map server's core on a small synthetic world: points in a room, each with its own descriptor, seen by two
robots whose frames differ by a known transform. Robot b is merged where that transform puts it, not before k
matches agree; a robot that sees other points is never merged; the merged map is one valid map file with each
keyframe's robot, and a matched landmark kept once."""

from __future__ import annotations

import numpy as np

from twohr.config import PipelineConfig
from twohr.dataset import CameraIntrinsics
from twohr.features import mutual_nn
from twohr.geometry import invert_pose, make_pose, project, so3_exp, transform_points
from twohr.keyframe_sender import KeyframeSender
from twohr.mapfile import MapArrays, arrays_file, encode_map, read_map
from twohr.mapstore import without_robot
from twohr_services.mapserver.core import STORED, KeyframeBatch, SharedMap, export, pose_gap

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
