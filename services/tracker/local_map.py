"""The search over the local map that tracking, relocalisation and local mapping share.

As ORB-SLAM3 keeps its ``SearchByProjection`` in ``ORBmatcher`` rather than in Tracking, :class:`LocalMapSearch`
holds what the three use alike: descriptor matching against the landmarks of the keyframes near a pose, gated by
the predicted projection and depth, RANSAC PnP and refinement, a guided search by projection, and the checks on a
frame's inputs. It reads the :class:`~.map.Map`, the :class:`~.motion.MotionModel` (its prior and loss count) and
the camera; it never calls back into the :class:`~.tracking.Tracker`.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from twohr.config import TrackerConfig
from twohr.dataset import CameraIntrinsics
from twohr.errors import TwohrError
from twohr.features import Keypoints
from twohr.geometry import invert_pose, project, transform_points
from twohr.pose import MatchFn, PoseEstimate, estimate_pose, inliers_of, refine_pose

from .map import Map
from .motion import MotionModel


class TrackerInputError(TwohrError, ValueError):
    """Keypoints or depth that do not fit the camera or each other."""


class LocalMapSearch:
    """Matching a frame's keypoints to the local map of one :class:`~.map.Map`, and the input checks of its frames
    (the descriptor kind is fixed by the first frame with keypoints)."""

    def __init__(self, world: Map, motion: MotionModel, conf: TrackerConfig, camera: CameraIntrinsics) -> None:
        self.map = world
        self.motion = motion
        self.conf = conf
        self.camera = camera
        self.K = camera.matrix
        self._descriptor_kind: tuple[int, np.dtype] | None = None

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
