"""Can one robot's keyframes be found in another robot's map, and where does the merge put it? An offline study of
the map server's core (:mod:`twohr_services.mapserver.core`) on maps built in process.

Each robot's map is built with ``twohr run``'s pipeline; then its keyframes are handed to a
:class:`~twohr_services.mapserver.core.SharedMap` one at a time, in the order the robots would have made them had
they started together (:func:`replay_shared`), as the trackers of two live robots send them. The first robot's frame
is the map's; the others are searched for in it and merged.

Against the ground truth (each map's frame placed in the ground truth's by its poses, 0.02 s association), every
match is scored by how far its transform puts the robot's keyframe from where it truly is in the map's frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twohr.dataset import CameraIntrinsics
from twohr.features import mutual_nn
from twohr.geometry import invert_pose
from twohr.keyframe_sender import KeyframeSender
from twohr.mapfile import MapArrays
from twohr.trajectory import Trajectory
from twohr_services.mapserver.core import CrossMatch, KeyframeBatch, MergeEvent, SharedMap, pose_gap


@dataclass
class Robot:
    """One robot of the study: its map's arrays, its camera, and the stamp its run started at."""

    name: str
    arrays: MapArrays
    camera: CameraIntrinsics
    start: float


def _first(arrays: MapArrays, count: int) -> MapArrays:
    """A map's first ``count`` keyframes, as the tracker had them when it made the last of them (poses as finally
    refined: the study's approximation)."""
    end = arrays.keyframe_first[count]
    return MapArrays(
        keyframe_poses=arrays.keyframe_poses[:count], keyframe_stamps=arrays.keyframe_stamps[:count],
        keyframe_culled=arrays.keyframe_culled[:count], keyframe_first=arrays.keyframe_first[:count + 1],
        keypoint_xy=arrays.keypoint_xy[:end], keypoint_depth=arrays.keypoint_depth[:end],
        keypoint_landmark=arrays.keypoint_landmark[:end], landmark_positions=arrays.landmark_positions,
        landmark_descriptors=arrays.landmark_descriptors, landmark_accepted=arrays.landmark_accepted,
        landmark_rejected=arrays.landmark_rejected, landmark_bad=arrays.landmark_bad)


def replay_shared(robots: list[Robot], name: str = "lab") -> tuple[SharedMap, list[MergeEvent]]:
    """The robots' keyframes into one shared map, each when its robot made it (time since its run started); the
    first robot's frame is the map's. Returns the map and its events."""
    shared = SharedMap(name, mutual_nn)
    events = [e for e in (shared.join(robot.name, f"session-{robot.name}") for robot in robots) if e is not None]
    senders = {robot.name: KeyframeSender() for robot in robots}
    order = sorted((stamp - robot.start, i, k) for i, robot in enumerate(robots)
                   for k, stamp in enumerate(robot.arrays.keyframe_stamps))
    for _, i, k in order:
        robot = robots[i]
        first, arrays = senders[robot.name].next(_first(robot.arrays, k + 1))
        event = shared.add(robot.name, KeyframeBatch(first=first, **arrays), robot.camera)
        if event is not None:
            events.append(event)
    return shared, events


def map_to_world(estimate: Trajectory, truth: Trajectory, max_dt: float = 0.02) -> np.ndarray:
    """The SE(3) transform of an estimated trajectory's frame into the ground truth's: the mean of ``G_i E_i^-1``
    over the associated poses (rotations by their chordal mean). From whole poses, not positions alone: a short,
    nearly straight path leaves a positions-only (Umeyama) rotation loose by degrees."""
    from twohr.evaluation import associate_trajectories
    from twohr_services.mapserver.core import mean_transform

    gt, est = associate_trajectories(truth, estimate, max_dt)
    return mean_transform(list(gt.poses @ np.linalg.inv(est.poses)))


def true_T_ab(trajectory_a: Trajectory, truth_a: Trajectory, trajectory_b: Trajectory,
              truth_b: Trajectory) -> np.ndarray:
    """b's map frame into a's, as the ground truth has it (both aligned to the same world)."""
    return invert_pose(map_to_world(trajectory_a, truth_a)) @ map_to_world(trajectory_b, truth_b)


def score_matches(matches: list[CrossMatch], poses_b: np.ndarray, T_ab_true: np.ndarray) -> list[tuple[float, float]]:
    """For each match, (metres, degrees) between where its transform puts b's keyframe in a's frame and where the
    ground truth does (``poses_b``: b's keyframe poses in its own frame)."""
    return [pose_gap(m.T_map_robot @ poses_b[m.keyframe], T_ab_true @ poses_b[m.keyframe]) for m in matches]
