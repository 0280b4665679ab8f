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
from scipy.spatial import cKDTree

from twohr.config import TrackerConfig
from twohr.dataset import CameraIntrinsics
from twohr.errors import TwohrError
from twohr.features import Keypoints
from twohr.geometry import invert_pose, project, transform_points

from .map import Map
from .mapping import LocalMapping
from .motion import MotionModel
from .pose import MatchFn, PoseEstimate, estimate_pose, inliers_of, refine_pose, sample_depth
from .relocalisation import Relocaliser
from .trajectory import TrackResult, near_any_keyframe


class TrackerInputError(TwohrError, ValueError):
    """Keypoints or depth that do not fit the camera or each other."""


class Tracker:
    """Tracking over one :class:`~.map.Map`: local-map matching, gates, guided search, the keyframe decision and
    loss; keyframes go to its :class:`~.mapping.LocalMapping`, a lost camera to its
    :class:`~.relocalisation.Relocaliser`."""

    default_conf = TrackerConfig()

    def __init__(self, camera: CameraIntrinsics, conf: TrackerConfig | None = None, match: MatchFn | None = None,
                 world: Map | None = None) -> None:
        self.camera = camera
        self.conf = conf or self.default_conf
        self.match = match
        self.K = camera.matrix
        self.map = world if world is not None else Map(camera, self.conf)
        self.motion = MotionModel(self.conf.velocity_frames, self.conf.coast_velocity_decay)
        self.relocaliser = Relocaliser(self)
        self.local_mapping = LocalMapping(self)
        self._descriptor_kind: tuple[int, np.dtype] | None = None
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
        self.check_inputs(keypoints, depth)
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
        estimate = self.match_local_map(predicted, keypoints, xy, z, radius, True, match)
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
            force_keyframe or self._needs_keyframe(pose, estimate.num_inliers, status)) and not (
            self.local_mapping.covered(pose, estimate.num_inliers))
        if is_keyframe:
            pose = self.local_mapping.insert(stamp, pose, keypoints, xy, z, estimate, timings)
        reason = estimate.reason if num_depth else f"{estimate.reason} (no depth: tracked from 2-D matches only)"
        observed = self.keyframes[-1].landmark_ids if is_keyframe else estimate.keypoint_landmarks
        return TrackResult(stamp, pose, status, num_matches=estimate.num_matches, num_inliers=estimate.num_inliers,
                           is_keyframe=is_keyframe, reason=reason, observed_xy=xy[observed >= 0],
                           observed_landmarks=observed[observed >= 0], **counts)

    def _coast(self, stamp: float, predicted: np.ndarray, reason: str, counts: dict) -> TrackResult:
        """An untrackable frame: the pose follows the (decaying) motion model and the frame is reported lost."""
        self.motion.coast()
        return TrackResult(stamp, predicted, "lost", reason=f"{reason}; pose coasts on the motion model "
                           f"({self.motion.lost_frames} frame(s) untracked)", **counts)

    # ------------------------------------------------------------------ tracking against the local map

    def match_local_map(self, pose_guess: np.ndarray, keypoints: Keypoints, xy: np.ndarray, z: np.ndarray,
                        radius: float, check_jump: bool, match: MatchFn) -> PoseEstimate:
        """The pose of a frame's keypoints against the local map around ``pose_guess``: descriptor matches gated by
        the predicted projection (within ``radius``) and depth, RANSAC PnP and refinement (``check_jump``: with the
        motion prior and the jump check), then guided search."""
        conf = self.conf
        ids = self.map.usable_landmarks(self.map.local_keyframes(pose_guess, conf.local_map_keyframes), described=True)
        T_guess = invert_pose(pose_guess)
        points_cam = transform_points(T_guess, self.map.landmarks.positions[ids])
        uv = project(points_cam, self.K)
        margin = radius
        visible = (points_cam[:, 2] > conf.min_depth) & (uv[:, 0] > -margin) & (uv[:, 1] > -margin) & (
            uv[:, 0] < self.camera.width + margin) & (uv[:, 1] < self.camera.height + margin)
        ids, uv, pred_z = ids[visible], uv[visible], points_cam[visible, 2]
        if len(ids) < conf.min_inliers:
            return PoseEstimate(False, f"only {len(ids)} map landmarks in view")
        matches = match(keypoints.descriptors, self.map.landmarks.descriptors[ids])
        kp, lm = np.asarray(matches.idx_a, np.int64), np.asarray(matches.idx_b, np.int64)
        # motion-model gates: near the predicted projection, and at a consistent depth where measured (both
        # widen while lost, as the prediction grows uncertain)
        near = np.linalg.norm(xy[kp] - uv[lm], axis=1) <= radius
        depth_gate = conf.match_depth_gate * (1 + self.motion.lost_frames) * pred_z[lm]
        depth_ok = (z[kp] <= 0) | (np.abs(z[kp] - pred_z[lm]) <= depth_gate)
        gated = near & depth_ok
        kp, lm = kp[gated], lm[gated]
        estimate = self._estimate_pose(T_guess, xy, z, kp, ids[lm], check_jump, pose_guess)
        if estimate.ok and conf.guided_search_px > 0:
            estimate = self._guided_search(estimate, keypoints, xy, z, ids)
        return estimate

    def _guided_search(self, estimate: PoseEstimate, keypoints: Keypoints, xy: np.ndarray, z: np.ndarray,
                       candidates: np.ndarray) -> PoseEstimate:
        """Find more matches by projection: local-map landmarks not matched yet are projected with the tracked
        pose and paired with a free keypoint within ``guided_search_px`` whose descriptor is as close as those
        of the accepted matches (their 90th percentile); then the pose is refined on all matches."""
        conf, landmarks = self.conf, self.map.landmarks
        matched_kp = np.flatnonzero(estimate.keypoint_landmarks >= 0)
        matched_lm = estimate.keypoint_landmarks[matched_kp]
        free_kp = np.flatnonzero((estimate.keypoint_landmarks < 0) & ~estimate.suspect)
        todo = np.setdiff1d(candidates, matched_lm)
        if len(free_kp) == 0 or len(todo) == 0:
            return estimate
        points_cam = transform_points(estimate.T_cw, landmarks.positions[todo])
        uv = project(points_cam, self.K)
        in_front = points_cam[:, 2] > conf.min_depth
        todo, uv = todo[in_front], uv[in_front]
        dist, nearest = cKDTree(xy[free_kp]).query(uv, k=3, distance_upper_bound=conf.guided_search_px)
        lm_idx, slot = np.nonzero(np.isfinite(dist))
        if len(lm_idx) == 0:
            return estimate
        pair_lm, pair_kp = todo[lm_idx], free_kp[nearest[lm_idx, slot]]
        desc_dist = descriptor_distance(landmarks.descriptors[pair_lm], keypoints.descriptors[pair_kp])
        limit = np.quantile(descriptor_distance(landmarks.descriptors[matched_lm], keypoints.descriptors[matched_kp]),
                            0.9)
        keep = desc_dist <= limit
        pair_lm, pair_kp, desc_dist = pair_lm[keep], pair_kp[keep], desc_dist[keep]
        # one keypoint per landmark and one landmark per keypoint, the closest descriptors first
        order = np.argsort(desc_dist, kind="stable")
        pair_lm, pair_kp = pair_lm[order], pair_kp[order]
        _, first_lm = np.unique(pair_lm, return_index=True)
        pair_lm, pair_kp = pair_lm[np.sort(first_lm)], pair_kp[np.sort(first_lm)]
        _, first_kp = np.unique(pair_kp, return_index=True)
        pair_lm, pair_kp = pair_lm[np.sort(first_kp)], pair_kp[np.sort(first_kp)]
        if len(pair_lm) == 0:
            return estimate
        kp = np.concatenate([matched_kp, pair_kp])
        landmark = np.concatenate([matched_lm, pair_lm])
        points_w = landmarks.positions[landmark]
        T_cw = refine_pose(self.K, estimate.T_cw, points_w, xy[kp], z[kp], conf.depth_noise, conf.huber_px,
                           prior=estimate.prior)
        inliers = inliers_of(self.K, T_cw, points_w, xy[kp], z[kp], conf.ransac_reprojection_px, conf.depth_noise)
        if inliers.sum() < estimate.num_inliers:
            return estimate
        T_cw = refine_pose(self.K, T_cw, points_w[inliers], xy[kp[inliers]], z[kp[inliers]], conf.depth_noise,
                           conf.huber_px, prior=estimate.prior)
        landmarks.vote(pair_lm[inliers[len(matched_kp):]], np.zeros(0, np.int64), conf.landmark_max_outlier_ratio)
        keypoint_landmarks = np.full(len(xy), -1, np.int64)
        keypoint_landmarks[kp[inliers]] = landmark[inliers]
        num_inliers = int(inliers.sum())
        return PoseEstimate(True, f"{num_inliers} inliers of {estimate.num_matches} matches + {len(pair_lm)} by "
                         "projection", T_cw, estimate.num_matches + len(pair_lm), num_inliers, keypoint_landmarks,
                         estimate.suspect, estimate.prior)

    def _estimate_pose(self, T_guess: np.ndarray, xy: np.ndarray, z: np.ndarray, kp: np.ndarray,
                       landmark: np.ndarray, check_jump: bool, pose_guess: np.ndarray) -> PoseEstimate:
        """RANSAC PnP + robust refinement of matches keypoint ``kp[i]`` <-> landmark ``landmark[i]``."""
        conf = self.conf
        num_matches = len(kp)
        prior = self.motion.prior(T_guess, conf) if check_jump else None
        points_w = self.map.landmarks.positions[landmark]
        T_cw, inliers, why = estimate_pose(self.K, points_w, xy[kp], z[kp], conf.ransac_reprojection_px,
                                           conf.ransac_iterations, conf.min_inliers, conf.depth_noise,
                                           conf.huber_px, prior)
        num_inliers = int(inliers.sum())
        if T_cw is None:
            return PoseEstimate(False, why, num_matches=num_matches, num_inliers=num_inliers)
        if check_jump and (why := self.motion.implausible_jump(pose_guess, invert_pose(T_cw), conf)):
            self.map.landmarks.vote(np.zeros(0, np.int64), landmark[inliers], conf.landmark_max_outlier_ratio)
            return PoseEstimate(False, why, num_matches=num_matches, num_inliers=num_inliers)
        self.map.landmarks.vote(landmark[inliers], landmark[~inliers], conf.landmark_max_outlier_ratio)
        keypoint_landmarks = np.full(len(xy), -1, np.int64)
        keypoint_landmarks[kp[inliers]] = landmark[inliers]
        suspect = np.zeros(len(xy), bool)
        suspect[kp[~inliers]] = True
        return PoseEstimate(True, f"{num_inliers} inliers of {num_matches} matches", T_cw, num_matches, num_inliers,
                         keypoint_landmarks, suspect, prior)

    # ------------------------------------------------------------------ the keyframe decision

    def _needs_keyframe(self, pose: np.ndarray, num_inliers: int, status: str) -> bool:
        conf = self.conf
        if status != "tracking":
            return True
        if num_inliers < conf.keyframe_min_inlier_ratio * self.local_mapping.inliers_at_keyframe:
            return True
        return not near_any_keyframe(pose, self.map.keyframe_poses, conf.keyframe_max_translation,
                                     conf.keyframe_max_rotation_deg)

    # ------------------------------------------------------------------ input checks

    def check_inputs(self, keypoints: Keypoints, depth: np.ndarray) -> None:
        """Raise :class:`TrackerInputError` where the depth does not fit the camera, the keypoints do not fit their
        descriptors, or the descriptors change kind mid-stream."""
        expected = (self.camera.height, self.camera.width)
        if not isinstance(depth, np.ndarray) or depth.ndim != 2:
            raise TrackerInputError(f"depth must be a 2-D array in metres, got {getattr(depth, 'shape', type(depth))}")
        if depth.shape != expected:
            raise TrackerInputError(f"depth is {depth.shape[1]}x{depth.shape[0]} but the camera is "
                                    f"{expected[1]}x{expected[0]}")
        xy = np.asarray(keypoints.xy)
        if xy.ndim != 2 or xy.shape[1] != 2 or len(keypoints.descriptors) != len(xy):
            raise TrackerInputError(f"keypoints need xy (N, 2) and N descriptors, got xy {xy.shape} and "
                                    f"descriptors {np.shape(keypoints.descriptors)}")
        if len(xy) == 0:
            return
        kind = (keypoints.descriptors.shape[1], keypoints.descriptors.dtype)
        if self._descriptor_kind is None:
            self._descriptor_kind = kind
        elif kind != self._descriptor_kind:
            raise TrackerInputError(f"descriptors changed from {self._descriptor_kind} to {kind} mid-sequence")


def descriptor_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise distances of paired descriptors: Euclidean for float, Hamming for packed uint8 bits."""
    if a.dtype == np.uint8:
        return np.unpackbits(np.bitwise_xor(a, b), axis=1).sum(1).astype(np.float64)
    return np.linalg.norm(a.astype(np.float64) - b.astype(np.float64), axis=1)


def _ms(start: float) -> float:
    return (time.perf_counter() - start) * 1000.0
