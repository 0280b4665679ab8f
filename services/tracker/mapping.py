"""Local mapping: the keyframe work over the one :class:`~.map.Map`, as ORB-SLAM3's LocalMapping.

:class:`LocalMapping` does keyframe insertion (a tracked frame's keypoints, or a tracked keyframe's tracks and new
corners, become a keyframe and new landmarks; local bundle adjustment and culling follow) and description (2HR
keypoints detected later are joined to a tracked keyframe). The :class:`~.tracking.Tracker` hands it the keyframes
it decides on; the worker that runs it off the per-frame path is :class:`~.mapper.Mapper`.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial import cKDTree

from twohr.features import Keypoints
from twohr.geometry import backproject, transform_points
from twohr.pose import MatchFn, PoseEstimate, sample_depth

from .keyframe_policy import close_points
from .local_map import LocalMapSearch
from .map import Keyframe
from .motion import MotionModel
from .trajectory import TrackResult


class LocalMapping:
    """Keyframe insertion and description over the map that ``search`` reads, sharing its input checks and
    local-map matching with tracking; a new keyframe's pose updates ``motion``. ``match`` is the default match
    function of :meth:`describe_keyframe`."""

    def __init__(self, search: LocalMapSearch, motion: MotionModel, match: MatchFn | None = None) -> None:
        self.search = search
        self.motion = motion
        self.match = match
        self.map = search.map
        self.conf = search.conf
        self.K = search.K
        self.at_keyframe = (0, 0)
        """(landmarks observed, close ones) at the latest keyframe: the keyframe policy's reference"""

    def start(self, stamp: float, pose: np.ndarray, keypoints: Keypoints, xy: np.ndarray, z: np.ndarray) -> Keyframe:
        """The first keyframe of a map (or of a new map part after a long loss): every keypoint with depth becomes
        a landmark."""
        return self._add_keyframe(stamp, pose, keypoints, xy, z, np.full(len(xy), -1), np.zeros(len(xy), bool))

    def insert(self, stamp: float, pose: np.ndarray, keypoints: Keypoints, xy: np.ndarray, z: np.ndarray,
               estimate: PoseEstimate, timings: dict[str, float]) -> np.ndarray:
        """A tracked frame at camera-to-world ``pose`` becomes a keyframe (its unmatched keypoints with depth new
        landmarks), then local bundle adjustment; returns the keyframe's pose as adjusted."""
        t0 = time.perf_counter()
        keyframe = self._add_keyframe(stamp, pose, keypoints, xy, z, estimate.keypoint_landmarks, estimate.suspect)
        timings["keyframe"] = (time.perf_counter() - t0) * 1000.0
        return self._adjust_after_keyframe(keyframe.id, pose, timings)

    def add_tracked_keyframe(self, stamp: float, pose: np.ndarray, tracked_xy: np.ndarray,
                             tracked_landmarks: np.ndarray, corners_xy: np.ndarray, depth: np.ndarray) -> TrackResult:
        """A keyframe without a network: the per-frame path's pose and inlier tracks (landmark observations found
        by optical flow) make it, and ``corners_xy`` with depth seed new landmarks, without descriptors until a
        2HR detection of a keyframe describes them (:meth:`describe_keyframe`). Local bundle adjustment follows."""
        conf = self.conf
        start = time.perf_counter()
        tracked_xy = np.asarray(tracked_xy, np.float64).reshape(-1, 2)
        tracked_landmarks = np.asarray(tracked_landmarks, np.int64)
        usable = ~self.map.landmarks.bad[tracked_landmarks]
        tracked_xy, tracked_landmarks = tracked_xy[usable], tracked_landmarks[usable]
        corners_xy = np.asarray(corners_xy, np.float64).reshape(-1, 2)
        xy = np.concatenate([tracked_xy, corners_xy])
        z = sample_depth(depth, xy, conf.min_depth, conf.max_depth, conf.depth_edge_ratio)
        num_tracked = len(tracked_landmarks)
        counts = dict(num_keypoints=len(xy), num_with_depth=int((z > 0).sum()), num_matches=num_tracked,
                      num_inliers=num_tracked)
        self.motion.tracked(stamp, pose)
        self.motion.advance(stamp, pose)
        covering = self.covering_keyframe(pose, tracked_landmarks)
        if covering is not None:
            return TrackResult(stamp, pose, "tracking", reason=f"{num_tracked} tracks; keyframe {covering} holds this "
                               "view already: no keyframe", observed_xy=tracked_xy,
                               observed_landmarks=tracked_landmarks, **counts)
        # the keyframe keeps its tracks, and the corners with depth, which become landmarks without descriptors
        keep = np.arange(len(xy)) < num_tracked
        keep |= z > 0
        landmark_ids = np.concatenate([tracked_landmarks, np.full(len(corners_xy), -1, np.int64)])[keep]
        no_suspects = np.zeros(len(landmark_ids), bool)
        keyframe = self._add_keyframe(stamp, pose, None, xy[keep], z[keep], landmark_ids, no_suspects)
        timings = {"keyframe": (time.perf_counter() - start) * 1000.0}
        pose = self._adjust_after_keyframe(keyframe.id, pose, timings)
        observed = keyframe.landmark_ids >= 0
        num_new = len(landmark_ids) - num_tracked
        return TrackResult(stamp, pose, "tracking", is_keyframe=True, timings=timings,
                           reason=f"tracked keyframe: {num_tracked} tracks, {num_new} new corner landmarks",
                           observed_xy=keyframe.xy[observed], observed_landmarks=keyframe.landmark_ids[observed],
                           num_landmarks=self.map.landmarks.num_good, **counts)

    def describe_keyframe(self, keyframe_id: int, keypoints: Keypoints, depth: np.ndarray,
                          match: MatchFn | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Join the 2HR keypoints of keyframe ``keyframe_id`` (detected off the mapping path) to the map: the
        landmarks it observes get the descriptor of the keypoint at their observation when they have none;
        other keypoints are matched to the local map at the keyframe's pose (the same gates as tracking) and
        become observations; the rest with depth become new landmarks. Returns the keypoints that now observe a
        landmark: (xy (M, 2), landmark ids (M,))."""
        match = match or self.match
        conf, landmarks = self.conf, self.map.landmarks
        keyframe = self.map.keyframes[keyframe_id]
        if keyframe.culled or len(keypoints) == 0:
            return np.zeros((0, 2)), np.zeros(0, np.int64)
        self.search.check_inputs(keypoints, depth)
        pose = self.map.keyframe_poses[keyframe_id]
        xy = np.asarray(keypoints.xy, np.float64)
        z = sample_depth(depth, xy, conf.min_depth, conf.max_depth, conf.depth_edge_ratio)
        free = np.ones(len(xy), bool)
        observed = np.flatnonzero(keyframe.landmark_ids >= 0)
        if len(observed):  # keypoints at an observation this keyframe already holds: they describe its landmark
            distance, nearest = cKDTree(xy).query(keyframe.xy[observed], distance_upper_bound=conf.describe_radius_px)
            at = np.isfinite(distance)
            ids, kp = keyframe.landmark_ids[observed[at]], nearest[at]
            _, first = np.unique(kp, return_index=True)  # one landmark per keypoint
            ids, kp = ids[first], kp[first]
            undescribed = ~landmarks.described[ids]
            landmarks.describe(ids[undescribed], keypoints.descriptors[kp[undescribed]])
            free[kp] = False
            near_observation = cKDTree(keyframe.xy[observed]).query(xy, distance_upper_bound=conf.describe_radius_px)[0]
            free &= ~np.isfinite(near_observation)
        new_xy, new_z, new_ids = [], [], []
        if match is not None:
            # matched to the local map as a keyframe job would, the keyframe's pose as the prediction
            estimate = self.search.match_local_map(pose, keypoints, xy, z, conf.match_radius_px, False, match)
            if estimate.ok:
                kp = np.flatnonzero((estimate.keypoint_landmarks >= 0) & free)
                lm = estimate.keypoint_landmarks[kp]
                new = ~np.isin(lm, keyframe.landmark_ids)
                kp, lm = kp[new], lm[new]
                new_xy.append(xy[kp])
                new_z.append(z[kp])
                new_ids.append(lm)
                free[kp] = False
                free &= ~estimate.suspect
        fresh = free & (z > 0)
        if fresh.any():
            points_w = transform_points(pose, backproject(xy[fresh], z[fresh], self.K))
            new_xy.append(xy[fresh])
            new_z.append(z[fresh])
            new_ids.append(landmarks.add(points_w, keypoints.descriptors[fresh]))
            self.map.made_landmarks(new_ids[-1])
        if new_ids:
            keyframe.xy = np.concatenate([keyframe.xy, *new_xy])
            keyframe.depth = np.concatenate([keyframe.depth, *new_z])
            keyframe.landmark_ids = np.concatenate([keyframe.landmark_ids, *new_ids])
            if conf.bundle_adjustment:
                latest = len(self.map.keyframes)
                window = np.union1d(np.arange(max(0, latest - conf.ba_window_keyframes), latest), [keyframe_id])
                self.map.bundle_adjust(window, conf.ba_max_iterations)
        seen = keyframe.landmark_ids >= 0
        return keyframe.xy[seen], keyframe.landmark_ids[seen]

    def covering_keyframe(self, pose: np.ndarray, tracked: np.ndarray) -> int | None:
        """A keyframe of the local map at ``pose`` of whose usable landmarks the frame tracks (``tracked``: landmark
        ids) at least ``keyframe_tracked_ratio``: the map holds this view already, and a keyframe here would add
        nothing but memory (a camera that comes back to a place it mapped). None when no keyframe does."""
        world = self.map
        for index in world.local_keyframes(pose, self.conf.local_map_keyframes):
            observed = world.keyframes[index].landmark_ids
            observed = observed[observed >= 0]
            observed = observed[~world.landmarks.bad[observed]]
            if len(observed) and np.isin(observed, tracked).mean() >= self.conf.keyframe_tracked_ratio:
                return int(index)
        return None

    def _add_keyframe(self, stamp: float, pose: np.ndarray, keypoints: Keypoints | None, xy: np.ndarray,
                      z: np.ndarray, keypoint_landmarks: np.ndarray, suspect: np.ndarray) -> Keyframe:
        """Keep this frame; its unmatched, unsuspected keypoints with depth become new landmarks (described by
        ``keypoints``; None: corners of a tracked keyframe, not described yet)."""
        landmark_ids = keypoint_landmarks.copy()
        new = (landmark_ids < 0) & (z > 0) & ~suspect
        if new.any():
            points_w = transform_points(pose, backproject(xy[new], z[new], self.K))
            landmark_ids[new] = self.map.landmarks.add(points_w, None if keypoints is None else
                                                       keypoints.descriptors[new])
        keyframe = self.map.add_keyframe(stamp, pose, xy, z, landmark_ids)
        self.map.made_landmarks(landmark_ids[new])
        self._reference(keyframe)
        return keyframe

    def _reference(self, keyframe: Keyframe) -> None:
        observed = keyframe.landmark_ids >= 0
        self.at_keyframe = (int(observed.sum()), close_points(keyframe.depth[observed], self.conf))

    def _adjust_after_keyframe(self, keyframe_id: int, pose: np.ndarray, timings: dict[str, float]) -> np.ndarray:
        """Local bundle adjustment after a new keyframe, then culling of redundant local keyframes; returns the
        keyframe's pose as adjusted."""
        conf = self.conf
        if conf.bundle_adjustment:
            t0 = time.perf_counter()
            self.map.local_bundle_adjustment()
            timings["bundle_adjustment"] = (time.perf_counter() - t0) * 1000.0
            pose = self.map.keyframe_poses[keyframe_id].copy()
            self.motion.good_pose = pose
        if conf.landmark_culling:
            self.map.retire_unconfirmed()
        self.map.cull_redundant(self.map.local_keyframes(pose, conf.local_map_keyframes))
        return pose
