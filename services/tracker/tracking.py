"""Tracking: the keyframe job's pose of one frame from its 2HR keypoints against the local map.

Per frame (:meth:`Tracker.track`):

1. sample depth at the keypoints (rejecting depth edges) and back-project them;
2. predict the pose with a constant-velocity motion model (or take the caller's prediction);
3. build the local map (landmarks of the latest keyframe and of the keyframes nearest in pose),
   project it with the prediction, match descriptors (injected ``match`` function) and keep only
   matches near the predicted projection and at a consistent depth -- this gate drops most matches
   on moving people;
4. RANSAC PnP on the gated matches, then a robust (Huber) pose refinement on reprojection and
   inverse-depth residuals with the motion model as a weak prior; a pose that jumps implausibly
   far from the prediction is rejected; a guided search by projection adds matches;
5. the keyframe decision; a new keyframe goes to :class:`~.mapping.LocalMapping` (insertion, new landmarks,
   local bundle adjustment), as ORB-SLAM3's Tracking hands keyframes to its LocalMapping;
6. when a frame cannot be tracked it is reported ``lost`` and its pose coasts on the (decaying) motion
   model; the next frames try the local map with a wider gate, then the
   :class:`~.relocalisation.Relocaliser`.

The map itself (landmarks, keyframes, their poses, bundle adjustment) is :class:`~.map.Map`; the per-frame
record of poses is :class:`~.trajectory.AnchoredTrajectory`, kept by the schedules.
"""

from __future__ import annotations

import time

import numpy as np

from twohr.config import TrackerConfig
from twohr.dataset import CameraIntrinsics
from twohr.features import Keypoints
from twohr.geometry import invert_pose
from twohr.pose import MatchFn, PoseEstimate, sample_depth

from .keyframe_policy import Evidence, weakness
from .local_map import LocalMapSearch, TrackerInputError
from .map import Map
from .mapping import LocalMapping
from .motion import MotionModel
from .relocalisation import Relocaliser
from .trajectory import TrackResult

__all__ = ["Tracker", "TrackerInputError"]


class Tracker:
    """Tracking over one :class:`~.map.Map`: the motion model, the keyframe decision and loss, with the local-map
    search of its :class:`~.local_map.LocalMapSearch`; keyframes go to its :class:`~.mapping.LocalMapping`, a lost
    camera to its :class:`~.relocalisation.Relocaliser` (both share the search and the motion model, never the
    tracker)."""

    default_conf = TrackerConfig()

    def __init__(self, camera: CameraIntrinsics, conf: TrackerConfig | None = None, match: MatchFn | None = None,
                 world: Map | None = None) -> None:
        self.camera = camera
        self.conf = conf or self.default_conf
        self.match = match
        self.K = camera.matrix
        self.map = world if world is not None else Map(camera, self.conf)
        self.motion = MotionModel(self.conf.velocity_frames, self.conf.coast_velocity_decay)
        self.search = LocalMapSearch(self.map, self.motion, self.conf, camera)
        self.relocaliser = Relocaliser(self.search)
        self.local_mapping = LocalMapping(self.search, self.motion, match)
        self.given_map = bool(self.map)
        """the map came with the tracker (loaded from a file): its frame is the world, never a new map part"""
        self.relocalising = self.given_map
        """not yet found (or lost for long) in a given map: no pose until a verified relocalisation"""

    # ------------------------------------------------------------------ public

    @property
    def initialised(self) -> bool:
        return bool(self.map)

    @property
    def localised(self) -> bool:
        """True when the camera has a pose in the map (a map exists and the camera is not looking for itself)."""
        return self.initialised and not self.relocalising

    @property
    def keyframes(self):
        """The map's keyframes."""
        return self.map.keyframes

    @property
    def keyframe_poses(self) -> np.ndarray:
        """(K, 4, 4) camera-to-world poses of the keyframes, as bundle adjustment has refined them."""
        return self.map.keyframe_poses

    def track(self, stamp: float, keypoints: Keypoints, depth: np.ndarray, prediction: np.ndarray | None = None,
              force_keyframe: bool = False, match: MatchFn | None = None) -> TrackResult:
        """Estimate the camera pose of one frame from its (dynamic-masked) keypoints and depth image (metres).

        ``prediction`` replaces the motion model's predicted pose (the keyframe pipeline passes the pose
        that optical flow tracked); ``force_keyframe`` makes a tracked frame a keyframe; ``match`` is this
        frame's match function (default: the one the tracker was built with)."""
        match = match or self.match
        if match is None:
            raise TypeError("Tracker needs a match function (descriptors_a, descriptors_b) -> Matches, "
                            "e.g. twohr_services.matcher.core.mutual_nn")
        start = time.perf_counter()
        self.search.check_inputs(keypoints, depth)
        timings: dict[str, float] = {}
        conf = self.conf
        xy = np.asarray(keypoints.xy, dtype=np.float64)
        z = sample_depth(depth, xy, conf.min_depth, conf.max_depth, conf.depth_edge_ratio)
        num_depth = int((z > 0).sum())
        timings["depth"] = _ms(start)

        if not self.initialised:
            result = self._initialise(stamp, keypoints, xy, z, num_depth, "init", np.eye(4))
        elif self.relocalising:
            result = self.relocaliser.find_in_map(stamp, keypoints, xy, z, num_depth, timings, match)
            if result.status == "relocalised":
                self.relocalising = False
                self.motion.restart(result.pose, stamp)
        else:
            predicted = self.motion.predict(stamp) if prediction is None else prediction
            result = self._track_initialised(stamp, keypoints, xy, z, num_depth, timings, predicted, force_keyframe,
                                             match)
        self.motion.advance(stamp, result.pose)
        result.timings = {**timings, **result.timings, "total": _ms(start)}
        result.num_landmarks = self.map.landmarks.num_good
        return result

    # ------------------------------------------------------------------ steps

    def _initialise(self, stamp: float, keypoints: Keypoints, xy: np.ndarray, z: np.ndarray, num_depth: int,
                    status: str, pose: np.ndarray) -> TrackResult:
        counts = dict(num_keypoints=len(keypoints), num_with_depth=num_depth)
        if num_depth < self.conf.init_min_points:
            why = "no keypoints" if len(keypoints) == 0 else (
                f"only {num_depth} of {len(keypoints)} keypoints have depth (need {self.conf.init_min_points})")
            if not self.initialised:
                return TrackResult(stamp, np.eye(4), "uninitialised", reason=f"waiting to start the map: {why}",
                                   **counts)
            return self._coast(stamp, pose, f"lost: {why}", counts)
        keyframe = self.local_mapping.start(stamp, pose, keypoints, xy, z)
        self.motion.restart(pose, stamp)
        reason = "map started" if status == "init" else "new map started at the coasted pose after a long loss"
        observed = keyframe.landmark_ids >= 0
        return TrackResult(stamp, pose, status, num_inliers=num_depth, is_keyframe=True, reason=reason,
                           observed_xy=xy[observed], observed_landmarks=keyframe.landmark_ids[observed], **counts)

    def _track_initialised(self, stamp: float, keypoints: Keypoints, xy: np.ndarray, z: np.ndarray,
                           num_depth: int, timings: dict[str, float], predicted: np.ndarray,
                           force_keyframe: bool, match: MatchFn) -> TrackResult:
        conf = self.conf
        counts = dict(num_keypoints=len(keypoints), num_with_depth=num_depth)
        if len(keypoints) < conf.min_inliers:
            what = "no keypoints" if len(keypoints) == 0 else f"only {len(keypoints)} keypoints"
            return self._coast(stamp, predicted, f"{what} (everything masked or textureless?)", counts)

        t0 = time.perf_counter()
        radius = conf.match_radius_px + conf.lost_radius_growth_px * self.motion.lost_frames
        estimate = self.search.match_local_map(predicted, keypoints, xy, z, radius, True, match)
        timings["local_map"] = _ms(t0)
        status = "tracking"
        if not estimate.ok and conf.relocalisation:
            t0 = time.perf_counter()
            anchor = self.motion.good_pose if self.motion.good_pose is not None else self.map.keyframe_poses[-1]
            relocalised = self.relocaliser.relocalise(keypoints, xy, z, [anchor, predicted], match)
            timings["relocalise"] = _ms(t0)
            if relocalised.ok:
                estimate, status = relocalised, "relocalised"
        if not estimate.ok:
            if self.motion.lost_frames + 1 >= conf.reinit_after_lost_frames and self.given_map:
                self.relocalising = True  # a given map's frame is the world: look for it again, no pose till then
            elif self.motion.lost_frames + 1 >= conf.reinit_after_lost_frames and num_depth >= conf.init_min_points:
                return self._initialise(stamp, keypoints, xy, z, num_depth, "reinitialised", predicted)
            return self._coast(stamp, predicted, estimate.reason, {**counts, "num_matches": estimate.num_matches,
                                                        "num_inliers": estimate.num_inliers})

        pose = invert_pose(estimate.T_cw)
        self.motion.tracked(stamp, pose)
        # a keyframe needs depth: its new landmarks come from back-projected keypoints
        is_keyframe = num_depth >= conf.init_min_points and (
            force_keyframe or self._needs_keyframe(estimate, z, status))
        matched = estimate.keypoint_landmarks[estimate.keypoint_landmarks >= 0]
        covering = self.local_mapping.covering_keyframe(pose, matched) if is_keyframe and status == "tracking" else None
        if covering is not None:  # the map holds this view already: the frame re-seeds the tracks, adds nothing
            is_keyframe = False
        if is_keyframe:
            pose = self.local_mapping.insert(stamp, pose, keypoints, xy, z, estimate, timings)
        reason = estimate.reason if num_depth else f"{estimate.reason} (no depth: tracked from 2-D matches only)"
        if covering is not None:
            reason += f"; keyframe {covering} holds this view already: no keyframe"
        observed = self.keyframes[-1].landmark_ids if is_keyframe else estimate.keypoint_landmarks
        return TrackResult(stamp, pose, status, num_matches=estimate.num_matches, num_inliers=estimate.num_inliers,
                           is_keyframe=is_keyframe, reason=reason, observed_xy=xy[observed >= 0],
                           observed_landmarks=observed[observed >= 0], **counts)

    def _coast(self, stamp: float, predicted: np.ndarray, reason: str, counts: dict) -> TrackResult:
        """An untrackable frame: the pose follows the (decaying) motion model and the frame is reported lost."""
        self.motion.coast()
        return TrackResult(stamp, predicted, "lost", reason=f"{reason}; pose coasts on the motion model "
                           f"({self.motion.lost_frames} frame(s) untracked)", **counts)

    # ------------------------------------------------------------------ the keyframe decision

    def _needs_keyframe(self, estimate: PoseEstimate, z: np.ndarray, status: str) -> bool:
        """The keyframe policy (:mod:`.keyframe_policy`) on a frame tracked from its own keypoints: its inliers
        against those at the latest keyframe, and its close points."""
        if status != "tracking":
            return True
        matched = estimate.keypoint_landmarks >= 0
        evidence = Evidence.of(estimate.num_inliers, z[matched], self.local_mapping.at_keyframe, 0.0, self.conf)
        return weakness(evidence, self.conf) is not None


def _ms(start: float) -> float:
    return (time.perf_counter() - start) * 1000.0
