"""Mapping: the keyframe work over the one :class:`~.map.Map`, as ORB-SLAM3's LocalMapping, and the worker that
runs it off the per-frame path.

* :class:`LocalMapping`: keyframe insertion (a tracked frame's keypoints, or a tracked keyframe's tracks and new
  corners, become a keyframe and new landmarks; local bundle adjustment and culling follow) and description (2HR
  keypoints detected later are joined to a tracked keyframe). The :class:`~.tracking.Tracker` hands it the
  keyframes it decides on.
* :class:`Mapper`: the mapping worker's jobs (:class:`KeyframeJob`, :class:`Detected`, a verified
  :class:`~.loops.Loop`), each coming back to the schedule as a :class:`~.flow.MapUpdate`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from twohr.config import PipelineConfig
from twohr.dataset import Frame
from twohr.features import Keypoints, drop_masked
from twohr.geometry import backproject, invert_pose, transform_points

from .flow import MapUpdate, new_corners, on_flat_depth, static_in_reference
from .loops import Loop, LoopClosing, LoopLog, LoopQuery
from .map import Keyframe, MapSnapshot
from .places import Vocabulary, vocabulary_path
from .pose import MatchFn, PoseEstimate, sample_depth
from .stages import Stages
from .trajectory import TrackResult, near_any_keyframe

if TYPE_CHECKING:
    from .tracking import Tracker


class LocalMapping:
    """Keyframe insertion and description over the map of one :class:`~.tracking.Tracker` (whose motion model,
    input checks and local-map matching it shares)."""

    def __init__(self, tracker: Tracker) -> None:
        self.tracker = tracker
        self.map = tracker.map
        self.conf = tracker.conf
        self.K = tracker.K
        self.inliers_at_keyframe = 0
        """inliers of the frame at the latest keyframe: tracking asks for a keyframe when they fall well below"""

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
        self.inliers_at_keyframe = max(estimate.num_inliers, int((keyframe.landmark_ids >= 0).sum()))
        timings["keyframe"] = (time.perf_counter() - t0) * 1000.0
        return self._adjust_after_keyframe(keyframe.id, pose, timings)

    def add_tracked_keyframe(self, stamp: float, pose: np.ndarray, tracked_xy: np.ndarray,
                             tracked_landmarks: np.ndarray, corners_xy: np.ndarray, depth: np.ndarray) -> TrackResult:
        """A keyframe without a network: the per-frame path's pose and inlier tracks (landmark observations found
        by optical flow) make it, and ``corners_xy`` with depth seed new landmarks, without descriptors until a
        2HR detection of a keyframe describes them (:meth:`describe_keyframe`). Local bundle adjustment follows.
        No keyframe where older keyframes already cover the place (see ``keyframe_revisit_min_inliers``)."""
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
        self.tracker.motion.tracked(stamp, pose)
        self.tracker.motion.advance(stamp, pose)
        if self.covered(pose, num_tracked):
            return TrackResult(stamp, pose, "tracking", reason=f"{num_tracked} tracks in a place older keyframes "
                               "cover: no keyframe", observed_xy=tracked_xy, observed_landmarks=tracked_landmarks,
                               **counts)
        # the keyframe keeps its tracks, and the corners with depth, which become landmarks without descriptors
        keep = np.arange(len(xy)) < num_tracked
        keep |= z > 0
        landmark_ids = np.concatenate([tracked_landmarks, np.full(len(corners_xy), -1, np.int64)])[keep]
        no_suspects = np.zeros(len(landmark_ids), bool)
        keyframe = self._add_keyframe(stamp, pose, None, xy[keep], z[keep], landmark_ids, no_suspects)
        self.inliers_at_keyframe = len(landmark_ids)
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
        match = match or self.tracker.match
        conf, landmarks = self.conf, self.map.landmarks
        keyframe = self.map.keyframes[keyframe_id]
        if keyframe.culled or len(keypoints) == 0:
            return np.zeros((0, 2)), np.zeros(0, np.int64)
        self.tracker.check_inputs(keypoints, depth)
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
            estimate = self.tracker.match_local_map(pose, keypoints, xy, z, conf.match_radius_px, False, match)
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

    def covered(self, pose: np.ndarray, num_inliers: int) -> bool:
        """True when older keyframes (outside the BA window, not culled) already cover ``pose`` and the frame
        tracked well against them: a keyframe here would only grow the map (``keyframe_revisit_min_inliers``)."""
        conf, world = self.conf, self.map
        if conf.keyframe_revisit_min_inliers == 0 or num_inliers < conf.keyframe_revisit_min_inliers:
            return False
        older = np.arange(max(0, len(world.keyframes) - conf.ba_window_keyframes))
        older = older[[not world.keyframes[i].culled for i in older]]
        return near_any_keyframe(pose, world.keyframe_poses[older], conf.keyframe_max_translation,
                                 conf.keyframe_max_rotation_deg)

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
        if self.inliers_at_keyframe == 0:
            self.inliers_at_keyframe = int(new.sum())
        return keyframe

    def _adjust_after_keyframe(self, keyframe_id: int, pose: np.ndarray, timings: dict[str, float]) -> np.ndarray:
        """Local bundle adjustment after a new keyframe, then culling of redundant local keyframes; returns the
        keyframe's pose as adjusted."""
        conf = self.conf
        if conf.bundle_adjustment:
            t0 = time.perf_counter()
            self.map.local_bundle_adjustment()
            timings["bundle_adjustment"] = (time.perf_counter() - t0) * 1000.0
            pose = self.map.keyframe_poses[keyframe_id].copy()
            self.tracker.motion.good_pose = pose
        self.map.cull_redundant(self.map.local_keyframes(pose, conf.local_map_keyframes))
        return pose


@dataclass
class KeyframeJob:
    """A frame handed to the mapping worker, with the pose optical flow gave it. With ``tracks`` (the frame's
    inlier tracks: image positions and landmark ids) it becomes a tracked keyframe, without a network; without,
    the 2HR detector runs on it first (the first map, a lost camera, relocalisation)."""

    frame: Frame
    pose: np.ndarray
    tracks: tuple[np.ndarray, np.ndarray] | None = None
    mask: np.ndarray | None = None
    """the dynamic mask the per-frame path used for this frame (None: none fresh enough)"""
    reference: tuple[np.ndarray, int] | None = None
    """(grayscale image, keyframe id) of the latest keyframe: new corners must be static against it"""


@dataclass
class Detected:
    """2HR keypoints of an earlier tracked keyframe, detected off the mapping path, for the map to join."""

    keyframe_id: int
    frame: Frame
    keypoints: Keypoints
    ms_detector: float
    kept: int


class Mapper:
    """The mapping worker: keyframe work, off the per-frame path, over the :class:`~.map.Map` of ``tracker`` (a
    :class:`~.tracking.Tracker` and its :class:`LocalMapping`): tracked keyframes (tracks and new corners, local
    bundle adjustment), 2HR keyframe jobs (YOLO and 2HR detection, then tracking against the local map, keyframe
    insertion, local bundle adjustment and relocalisation), the 2HR keypoints of earlier tracked keyframes joined to
    the map (:meth:`describe`), and verified loops closed (:meth:`close_loop`)."""

    def __init__(self, config: PipelineConfig, tracker: Tracker, stages: Stages) -> None:
        world = tracker.map
        self.stages = stages
        self.map = world
        self.conf = config.tracker
        self.tracker = tracker
        self.local_mapping = tracker.local_mapping
        self.loops = None
        self.loop_log = LoopLog()
        if config.loop_closing.vocabulary is not None:
            vocabulary = Vocabulary.load(vocabulary_path(config.loop_closing.vocabulary))
            self.loops = LoopClosing(world, vocabulary, config.loop_closing)

    def __call__(self, job: KeyframeJob | Detected | Loop) -> MapUpdate:
        if isinstance(job, Detected):
            return self.describe(job)
        if isinstance(job, Loop):
            return self.close_loop(job)
        if job.tracks is not None and self.tracker.localised:
            return self._tracked_keyframe(job)
        return self._detected_keyframe(job)

    def _tracked_keyframe(self, job: KeyframeJob) -> MapUpdate:
        frame = job.frame
        t0 = time.perf_counter()
        mask = job.mask
        if mask is None and self.stages.dynamic_mask is not None:
            mask, _ = self.stages.dynamic_mask(frame)
        t1 = time.perf_counter()
        tracks_xy, tracks_landmark = job.tracks
        corners = new_corners(frame.gray, self.conf.keyframe_corners, self.conf.corner_min_distance_px, mask,
                              tracks_xy)
        corners = corners[on_flat_depth(frame.depth, corners, self.conf.corner_depth_radius_px,
                                        self.conf.depth_edge_ratio)]
        if job.reference is not None and len(corners):
            reference, keyframe_id = job.reference
            z = sample_depth(frame.depth, corners, self.conf.min_depth, self.conf.max_depth,
                             self.conf.depth_edge_ratio)
            corners, z = corners[z > 0], z[z > 0]
            corners = corners[static_in_reference(frame.gray, job.pose, corners, z, reference,
                                                  self.map.keyframe_poses[keyframe_id], self.map.K, self.conf)]
        result = self.local_mapping.add_tracked_keyframe(frame.stamp, job.pose, tracks_xy, tracks_landmark, corners,
                                                   frame.depth)
        keyframe_id = self.map.keyframes[-1].id if result.is_keyframe else -1
        timings = {"detector": 0.0, "yolo": (t1 - t0) * 1000, "mapping": (time.perf_counter() - t1) * 1000,
                   "keypoints": len(corners), "kept": len(corners)}
        return MapUpdate(frame.index, frame.stamp, result, keyframe_id, result.observed_xy, result.observed_landmarks,
                         self.map.snapshot(), frame.gray, timings, kind="tracked", mask=mask)

    def _detected_keyframe(self, job: KeyframeJob) -> MapUpdate:
        frame = job.frame
        t0 = time.perf_counter()
        keypoints = self.stages.detect(frame)
        t1 = time.perf_counter()
        kept = keypoints
        if self.stages.dynamic_mask is not None:
            mask, _ = self.stages.dynamic_mask(frame)
            kept = drop_masked(keypoints, mask)
        t2 = time.perf_counter()
        tracker = self.tracker
        prediction = job.pose if tracker.initialised else None
        result = tracker.track(frame.stamp, kept, frame.depth, prediction=prediction, force_keyframe=True,
                               match=lambda a, b: self.stages.match(frame, a, b))
        seeds_xy, seeds_landmark = np.zeros((0, 2)), np.zeros(0, np.int64)
        if result.observed_landmarks is not None:
            # best observed first
            order = np.argsort(-self.map.landmarks.accepted[result.observed_landmarks], kind="stable")
            seeds_xy, seeds_landmark = result.observed_xy[order], result.observed_landmarks[order]
        keyframe_id = self.map.keyframes[-1].id if result.is_keyframe else -1
        t3 = time.perf_counter()
        timings = {"detector": (t1 - t0) * 1000, "yolo": (t2 - t1) * 1000, "mapping": (t3 - t2) * 1000,
                   "keypoints": len(keypoints), "kept": len(kept)}
        # until the camera is found in a given map, the per-frame path gets none of it
        snapshot = self.map.snapshot() if tracker.localised else MapSnapshot.empty()
        return MapUpdate(frame.index, frame.stamp, result, keyframe_id, seeds_xy, seeds_landmark, snapshot,
                         frame.gray, timings, loop_query=self._loop_query(keyframe_id))

    def _loop_query(self, keyframe_id: int) -> LoopQuery | None:
        """Place recognition for a keyframe whose landmarks have descriptors (off without a vocabulary)."""
        if self.loops is None or keyframe_id < 0 or not self.tracker.localised:
            return None
        return self.loops.query(keyframe_id)

    def close_loop(self, loop: Loop) -> MapUpdate:
        """Correct the map for a verified loop (:meth:`~.loops.LoopClosing.close`); the per-frame path gets the
        corrected map, and its tracks follow the fused landmarks."""
        t0 = time.perf_counter()
        latest = self.map.keyframe_poses[-1].copy()
        closed = self.loops.close(loop, self.loops.conf.ba_iterations)
        self.tracker.motion.move_world(self.map.keyframe_poses[-1] @ invert_pose(latest))  # where the camera is
        self.loop_log.closed += 1
        self.loop_log.loops.append({**closed, "ms": round((time.perf_counter() - t0) * 1000, 1)})
        pose = self.map.keyframe_poses[loop.keyframe_id].copy()
        result = TrackResult(loop.stamp, pose, "loop", reason=f"loop closed at keyframe {loop.keyframe_id} against "
                             f"keyframe {loop.candidate_id}: {closed['correction_m']} m corrected")
        timings = {"detector": 0.0, "yolo": 0.0, "mapping": (time.perf_counter() - t0) * 1000, "keypoints": 0,
                   "kept": 0}
        return MapUpdate(-1, loop.stamp, result, -1, np.zeros((0, 2)), np.zeros(0, np.int64), self.map.snapshot(),
                         None, timings, kind="loop", fused=loop.pairs)

    def detect(self, keyframe_id: int, frame: Frame, mask: np.ndarray | None) -> Detected:
        """The 2HR keypoints of tracked keyframe ``keyframe_id`` (outside its dynamic mask); reads no map, so it
        runs on its own worker while the mapping worker goes on."""
        t0 = time.perf_counter()
        keypoints = self.stages.detect(frame)
        kept = keypoints if mask is None else drop_masked(keypoints, mask)
        return Detected(keyframe_id, frame, kept, (time.perf_counter() - t0) * 1000, len(keypoints))

    def describe(self, detected: Detected) -> MapUpdate:
        """Join a tracked keyframe's 2HR keypoints to the map (:meth:`LocalMapping.describe_keyframe`); the
        landmarks they add come back as seeds for the per-frame path."""
        frame = detected.frame
        t0 = time.perf_counter()
        xy, landmark = self.local_mapping.describe_keyframe(detected.keyframe_id, detected.keypoints, frame.depth,
                                                      match=lambda a, b: self.stages.match(frame, a, b))
        result = TrackResult(frame.stamp, self.map.keyframe_poses[detected.keyframe_id], "described",
                             num_keypoints=detected.kept, num_matches=len(detected.keypoints),
                             reason=f"2HR keypoints of keyframe {detected.keyframe_id} joined to the map")
        timings = {"detector": detected.ms_detector, "yolo": 0.0, "mapping": (time.perf_counter() - t0) * 1000,
                   "keypoints": detected.kept, "kept": len(detected.keypoints)}
        return MapUpdate(frame.index, frame.stamp, result, -1, xy, landmark, self.map.snapshot(), frame.gray,
                         timings, kind="describe", loop_query=self._loop_query(detected.keyframe_id))
