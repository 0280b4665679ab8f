"""The tracker core: RGB-D camera tracking against a local map of landmarks. Keypoints and depth in, poses out.

Per frame (:meth:`Tracker.track`):

1. sample depth at the keypoints (rejecting depth edges) and back-project them;
2. predict the pose with a constant-velocity motion model;
3. build the local map (landmarks of the latest keyframe and of the keyframes nearest in pose),
   project it with the prediction, match descriptors (injected ``match`` function) and keep only
   matches near the predicted projection and at a consistent depth -- this gate drops most matches
   on moving people;
4. RANSAC PnP on the gated matches, then a robust (Huber) pose refinement on reprojection and
   inverse-depth residuals with the motion model as a weak prior; a pose that jumps implausibly
   far from the prediction is rejected;
5. keyframe policy; a new keyframe adds landmarks from its unmatched keypoints with depth, and a
   local bundle adjustment refines the latest keyframes and their landmarks;
6. when a frame cannot be tracked it is reported ``lost`` and its pose coasts on the (decaying) motion
   model; the next frames try the local map with a wider gate, then relocalisation by RANSAC PnP
   against the keyframes nearest to the last good pose.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from twohr.config import TrackerConfig
from twohr.dataset import CameraIntrinsics
from twohr.errors import TwohrError
from twohr.features import Keypoints, Matches
from twohr.geometry import backproject, invert_pose, project, transform_points
from twohr.trajectory import Trajectory, smooth_trajectory

from .motion import MotionModel
from .optim import (
    MotionPrior,
    bundle_adjust,
    estimate_pose,
    observation_errors,
    pnp_ransac,
    refine_pose,
    sample_depth,
)

MatchFn = Callable[[np.ndarray, np.ndarray], Matches]
"""(descriptors_a, descriptors_b) -> Matches; injected so the tracker does not depend on the matcher service."""

#: Statuses whose pose was measured (the others coast on the motion model or wait for a first frame).
TRACKED_STATUSES = ("init", "tracking", "relocalised", "reinitialised")


class TrackerInputError(TwohrError, ValueError):
    """Keypoints or depth that do not fit the camera or each other."""


@dataclass
class TrackResult:
    """The tracker's answer for one frame.

    ``pose`` is the 4x4 camera-to-world pose (world = the first keyframe's camera). ``status`` is one of
    ``uninitialised`` (no map yet; identity pose), ``init`` (this frame started the map), ``tracking``,
    ``relocalised`` (found again against an earlier keyframe), ``reinitialised`` (a new map started at the
    coasted pose after a long loss) or ``lost`` (not trackable: the pose is the motion model's
    prediction). ``reason`` says why in words; ``timings`` are milliseconds per stage.
    """

    stamp: float
    pose: np.ndarray
    status: str
    num_keypoints: int = 0
    num_with_depth: int = 0
    num_matches: int = 0
    num_inliers: int = 0
    is_keyframe: bool = False
    reason: str = ""
    timings: dict[str, float] = field(default_factory=dict)
    num_landmarks: int = 0
    observed_xy: np.ndarray | None = None
    """(M, 2) keypoints of this frame matched to a landmark (inliers of the pose), when tracked"""
    observed_landmarks: np.ndarray | None = None
    """(M,) the landmark id of each of those keypoints"""

    @property
    def tracked(self) -> bool:
        """True when the pose was measured from this frame, False when it coasted or there is no map yet."""
        return self.status in TRACKED_STATUSES


@dataclass
class Keyframe:
    """A frame kept in the map: its pose (camera-to-world, refined by BA) and its keypoints with depth
    and the landmark each one observes (-1 = none)."""

    id: int
    stamp: float
    pose: np.ndarray
    xy: np.ndarray
    depth: np.ndarray
    descriptors: np.ndarray
    landmark_ids: np.ndarray


class LandmarkMap:
    """3-D landmarks in growable arrays: world positions, one descriptor each, and vote counts."""

    def __init__(self) -> None:
        self.positions = np.zeros((0, 3))
        self.descriptors: np.ndarray | None = None
        self.accepted = np.zeros(0, np.int64)
        self.rejected = np.zeros(0, np.int64)
        self.bad = np.zeros(0, bool)

    def __len__(self) -> int:
        return len(self.positions)

    @property
    def num_good(self) -> int:
        return int((~self.bad).sum())

    def good_positions(self) -> np.ndarray:
        """(N, 3) world positions of the landmarks not retired as outliers."""
        return self.positions[~self.bad]

    def add(self, positions: np.ndarray, descriptors: np.ndarray) -> np.ndarray:
        """Append landmarks; returns their ids."""
        start = len(self)
        self.positions = np.concatenate([self.positions, positions])
        self.descriptors = descriptors.copy() if self.descriptors is None else np.concatenate(
            [self.descriptors, descriptors])
        self.accepted = np.concatenate([self.accepted, np.zeros(len(positions), np.int64)])
        self.rejected = np.concatenate([self.rejected, np.zeros(len(positions), np.int64)])
        self.bad = np.concatenate([self.bad, np.zeros(len(positions), bool)])
        return np.arange(start, len(self))

    def vote(self, accepted: np.ndarray, rejected: np.ndarray, max_outlier_ratio: float) -> None:
        """Count matches that agreed / disagreed with the tracked pose; retire landmarks that mostly disagree
        (moving objects that slipped past the mask, or repeated texture)."""
        np.add.at(self.accepted, accepted, 1)
        np.add.at(self.rejected, rejected, 1)
        ids = np.unique(rejected)
        self.bad[ids] |= (self.rejected[ids] >= 3) & (self.rejected[ids] > max_outlier_ratio * self.accepted[ids])


@dataclass
class _Estimate:
    """Internal: the outcome of one pose estimation attempt."""

    ok: bool
    reason: str
    T_cw: np.ndarray | None = None
    num_matches: int = 0
    num_inliers: int = 0
    keypoint_landmarks: np.ndarray | None = None  # (N,) landmark id per keypoint, -1 = none
    suspect: np.ndarray | None = None  # (N,) keypoints matched but rejected: not used for new landmarks
    prior: MotionPrior | None = None  # the motion-model prior the pose was refined with


class Tracker:
    """RGB-D tracker with a local map, keyframes, local bundle adjustment and relocalisation."""

    default_conf = TrackerConfig()

    def __init__(self, camera: CameraIntrinsics, conf: TrackerConfig | None = None,
                 match: MatchFn | None = None) -> None:
        if match is None:
            raise TypeError("Tracker needs a match function (descriptors_a, descriptors_b) -> Matches, "
                            "e.g. twohr_services.matcher.core.mutual_nn")
        self.camera = camera
        self.conf = conf or self.default_conf
        self.match = match
        self.K = camera.matrix
        self.map = LandmarkMap()
        self.keyframes: list[Keyframe] = []
        self._kf_poses = np.zeros((0, 4, 4))
        self.motion = MotionModel(self.conf.velocity_frames, self.conf.coast_velocity_decay)
        self._inliers_at_keyframe = 0
        self._descriptor_kind: tuple[int, np.dtype] | None = None
        # every frame's pose relative to the latest keyframe when it was tracked, for trajectory()
        self._frame_stamps: list[float] = []
        self._frame_anchor: list[int] = []
        self._frame_relative: list[np.ndarray] = []

    # ------------------------------------------------------------------ public

    @property
    def initialised(self) -> bool:
        return bool(self.keyframes)

    @property
    def keyframe_poses(self) -> np.ndarray:
        """(K, 4, 4) camera-to-world poses of the keyframes, as bundle adjustment has refined them."""
        return self._kf_poses

    def reset(self) -> None:
        """Forget the map and the motion: the next frame with enough depth starts a new map."""
        self.__init__(self.camera, self.conf, self.match)

    def track(self, stamp: float, keypoints: Keypoints, depth: np.ndarray, prediction: np.ndarray | None = None,
              force_keyframe: bool = False) -> TrackResult:
        """Estimate the camera pose of one frame from its (dynamic-masked) keypoints and depth image (metres).

        ``prediction`` replaces the motion model's predicted pose (the keyframe pipeline passes the pose
        that optical flow tracked); ``force_keyframe`` makes a tracked frame a keyframe."""
        start = time.perf_counter()
        self._check_inputs(keypoints, depth)
        timings: dict[str, float] = {}
        conf = self.conf
        xy = np.asarray(keypoints.xy, dtype=np.float64)
        z = sample_depth(depth, xy, conf.min_depth, conf.max_depth, conf.depth_edge_ratio)
        num_depth = int((z > 0).sum())
        timings["depth"] = _ms(start)

        if not self.initialised:
            result = self._initialise(stamp, keypoints, xy, z, num_depth, "init", np.eye(4))
        else:
            predicted = self.motion.predict(stamp) if prediction is None else prediction
            result = self._track_initialised(stamp, keypoints, xy, z, num_depth, timings, predicted, force_keyframe)
        self.motion.advance(stamp, result.pose)
        anchor = len(self.keyframes) - 1
        self._frame_stamps.append(stamp)
        self._frame_anchor.append(anchor)
        self._frame_relative.append(result.pose if anchor < 0 else invert_pose(self._kf_poses[anchor]) @ result.pose)
        result.timings = {**timings, **result.timings, "total": _ms(start)}
        result.num_landmarks = self.map.num_good
        return result

    def trajectory(self) -> Trajectory:
        """All frames' poses so far, each re-attached to its keyframe as bundle adjustment has refined it since
        (the ``TrackResult`` poses are online: final when reported). On the dev sequence the two score alike."""
        return smoothed(reattach_to_keyframes(self._frame_stamps, self._frame_anchor, self._frame_relative,
                                              self._kf_poses), self.conf)

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
        keyframe = self._insert_keyframe(stamp, pose, keypoints, xy, z, np.full(len(xy), -1), np.zeros(len(xy), bool))
        self.motion.restart(pose, stamp)
        reason = "map started" if status == "init" else "new map started at the coasted pose after a long loss"
        observed = keyframe.landmark_ids >= 0
        return TrackResult(stamp, pose, status, num_inliers=num_depth, is_keyframe=True, reason=reason,
                           observed_xy=xy[observed], observed_landmarks=keyframe.landmark_ids[observed], **counts)

    def _track_initialised(self, stamp: float, keypoints: Keypoints, xy: np.ndarray, z: np.ndarray,
                           num_depth: int, timings: dict[str, float], predicted: np.ndarray,
                           force_keyframe: bool) -> TrackResult:
        conf = self.conf
        counts = dict(num_keypoints=len(keypoints), num_with_depth=num_depth)
        if len(keypoints) < conf.min_inliers:
            what = "no keypoints" if len(keypoints) == 0 else f"only {len(keypoints)} keypoints"
            return self._coast(stamp, predicted, f"{what} (everything masked or textureless?)", counts)

        t0 = time.perf_counter()
        radius = conf.match_radius_px + conf.lost_radius_growth_px * self.motion.lost_frames
        estimate = self._track_local_map(predicted, keypoints, xy, z, radius, check_jump=True)
        timings["local_map"] = _ms(t0)
        status = "tracking"
        if not estimate.ok and conf.relocalisation:
            t0 = time.perf_counter()
            relocalised = self._relocalise(keypoints, xy, z, predicted)
            timings["relocalise"] = _ms(t0)
            if relocalised.ok:
                estimate, status = relocalised, "relocalised"
        if not estimate.ok:
            if self.motion.lost_frames + 1 >= conf.reinit_after_lost_frames and num_depth >= conf.init_min_points:
                return self._initialise(stamp, keypoints, xy, z, num_depth, "reinitialised", predicted)
            return self._coast(stamp, predicted, estimate.reason, {**counts, "num_matches": estimate.num_matches,
                                                        "num_inliers": estimate.num_inliers})

        pose = invert_pose(estimate.T_cw)
        self.motion.tracked(stamp, pose)
        t0 = time.perf_counter()
        # a keyframe needs depth: its new landmarks come from back-projected keypoints
        is_keyframe = num_depth >= conf.init_min_points and (
            force_keyframe or self._needs_keyframe(pose, estimate.num_inliers, status))
        if is_keyframe:
            self._insert_keyframe(stamp, pose, keypoints, xy, z, estimate.keypoint_landmarks, estimate.suspect)
            self._inliers_at_keyframe = max(estimate.num_inliers, int((self.keyframes[-1].landmark_ids >= 0).sum()))
            timings["keyframe"] = _ms(t0)
            if conf.bundle_adjustment:
                t0 = time.perf_counter()
                self._local_bundle_adjustment()
                timings["bundle_adjustment"] = _ms(t0)
                pose = self.keyframes[-1].pose
                self.motion.good_pose = pose
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

    def _local_keyframes(self, pose: np.ndarray, count: int) -> np.ndarray:
        """Indices of the latest keyframe and the keyframes nearest to ``pose`` (translation + weighted angle)."""
        rel = np.einsum("ij,njk->nik", invert_pose(pose), self._kf_poses)
        cos = np.clip((np.trace(rel[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1)
        distance = np.linalg.norm(rel[:, :3, 3], axis=1) + self.conf.keyframe_distance_per_rad * np.arccos(cos)
        distance[-1] = -1.0  # always keep the latest keyframe
        return np.argsort(distance, kind="stable")[:count]

    def _track_local_map(self, pose_guess: np.ndarray, keypoints: Keypoints, xy: np.ndarray, z: np.ndarray,
                         radius: float, check_jump: bool) -> _Estimate:
        conf = self.conf
        kf_idx = self._local_keyframes(pose_guess, conf.local_map_keyframes)
        ids = np.unique(np.concatenate([self.keyframes[i].landmark_ids for i in kf_idx]))
        ids = ids[ids >= 0]
        ids = ids[~self.map.bad[ids]]
        T_guess = invert_pose(pose_guess)
        points_cam = transform_points(T_guess, self.map.positions[ids])
        uv = project(points_cam, self.K)
        margin = radius
        visible = (points_cam[:, 2] > conf.min_depth) & (uv[:, 0] > -margin) & (uv[:, 1] > -margin) & (
            uv[:, 0] < self.camera.width + margin) & (uv[:, 1] < self.camera.height + margin)
        ids, uv, pred_z = ids[visible], uv[visible], points_cam[visible, 2]
        if len(ids) < conf.min_inliers:
            return _Estimate(False, f"only {len(ids)} map landmarks in view")
        matches = self.match(keypoints.descriptors, self.map.descriptors[ids])
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

    def _guided_search(self, estimate: _Estimate, keypoints: Keypoints, xy: np.ndarray, z: np.ndarray,
                       candidates: np.ndarray) -> _Estimate:
        """Find more matches by projection: local-map landmarks not matched yet are projected with the tracked
        pose and paired with a free keypoint within ``guided_search_px`` whose descriptor is as close as those
        of the accepted matches (their 90th percentile); then the pose is refined on all matches."""
        conf = self.conf
        matched_kp = np.flatnonzero(estimate.keypoint_landmarks >= 0)
        matched_lm = estimate.keypoint_landmarks[matched_kp]
        free_kp = np.flatnonzero((estimate.keypoint_landmarks < 0) & ~estimate.suspect)
        todo = np.setdiff1d(candidates, matched_lm)
        if len(free_kp) == 0 or len(todo) == 0:
            return estimate
        points_cam = transform_points(estimate.T_cw, self.map.positions[todo])
        uv = project(points_cam, self.K)
        in_front = points_cam[:, 2] > conf.min_depth
        todo, uv = todo[in_front], uv[in_front]
        dist, nearest = cKDTree(xy[free_kp]).query(uv, k=3, distance_upper_bound=conf.guided_search_px)
        lm_idx, slot = np.nonzero(np.isfinite(dist))
        if len(lm_idx) == 0:
            return estimate
        pair_lm, pair_kp = todo[lm_idx], free_kp[nearest[lm_idx, slot]]
        desc_dist = descriptor_distance(self.map.descriptors[pair_lm], keypoints.descriptors[pair_kp])
        limit = np.quantile(descriptor_distance(self.map.descriptors[matched_lm], keypoints.descriptors[matched_kp]),
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
        points_w = self.map.positions[landmark]
        T_cw = refine_pose(self.K, estimate.T_cw, points_w, xy[kp], z[kp], conf.depth_noise, conf.huber_px,
                           prior=estimate.prior)
        reproj, depth_err = observation_errors(self.K, T_cw, points_w, xy[kp], z[kp], conf.depth_noise)
        inliers = (reproj < conf.ransac_reprojection_px) & (depth_err < conf.ransac_reprojection_px)
        if inliers.sum() < estimate.num_inliers:
            return estimate
        T_cw = refine_pose(self.K, T_cw, points_w[inliers], xy[kp[inliers]], z[kp[inliers]], conf.depth_noise,
                           conf.huber_px, prior=estimate.prior)
        self.map.vote(pair_lm[inliers[len(matched_kp):]], np.zeros(0, np.int64), conf.landmark_max_outlier_ratio)
        keypoint_landmarks = np.full(len(xy), -1, np.int64)
        keypoint_landmarks[kp[inliers]] = landmark[inliers]
        num_inliers = int(inliers.sum())
        return _Estimate(True, f"{num_inliers} inliers of {estimate.num_matches} matches + {len(pair_lm)} by "
                         "projection", T_cw, estimate.num_matches + len(pair_lm), num_inliers, keypoint_landmarks,
                         estimate.suspect, estimate.prior)

    def _estimate_pose(self, T_guess: np.ndarray, xy: np.ndarray, z: np.ndarray, kp: np.ndarray,
                       landmark: np.ndarray, check_jump: bool, pose_guess: np.ndarray) -> _Estimate:
        """RANSAC PnP + robust refinement of matches keypoint ``kp[i]`` <-> landmark ``landmark[i]``."""
        conf = self.conf
        num_matches = len(kp)
        prior = self.motion.prior(T_guess, conf) if check_jump else None
        points_w = self.map.positions[landmark]
        T_cw, inliers, why = estimate_pose(self.K, points_w, xy[kp], z[kp], conf.ransac_reprojection_px,
                                           conf.ransac_iterations, conf.min_inliers, conf.depth_noise,
                                           conf.huber_px, prior)
        num_inliers = int(inliers.sum())
        if T_cw is None:
            return _Estimate(False, why, num_matches=num_matches, num_inliers=num_inliers)
        if check_jump and (why := self.motion.implausible_jump(pose_guess, invert_pose(T_cw), conf)):
            self.map.vote(np.zeros(0, np.int64), landmark[inliers], conf.landmark_max_outlier_ratio)
            return _Estimate(False, why, num_matches=num_matches, num_inliers=num_inliers)
        self.map.vote(landmark[inliers], landmark[~inliers], conf.landmark_max_outlier_ratio)
        keypoint_landmarks = np.full(len(xy), -1, np.int64)
        keypoint_landmarks[kp[inliers]] = landmark[inliers]
        suspect = np.zeros(len(xy), bool)
        suspect[kp[~inliers]] = True
        return _Estimate(True, f"{num_inliers} inliers of {num_matches} matches", T_cw, num_matches, num_inliers,
                         keypoint_landmarks, suspect, prior)

    def _relocalise(self, keypoints: Keypoints, xy: np.ndarray, z: np.ndarray, predicted: np.ndarray) -> _Estimate:
        """RANSAC PnP against the keyframes nearest to the last good pose and to the coasted prediction, then
        verification on the local map around the best candidate's pose."""
        conf = self.conf
        anchor = self.motion.good_pose if self.motion.good_pose is not None else self._kf_poses[-1]
        candidates = np.unique(np.concatenate([self._local_keyframes(anchor, conf.relocalisation_candidates),
                                               self._local_keyframes(predicted, conf.relocalisation_candidates)]))
        best: _Estimate | None = None
        for i in candidates[::-1]:  # the latest keyframes first
            kf = self.keyframes[i]
            ids = kf.landmark_ids[kf.landmark_ids >= 0]
            ids = ids[~self.map.bad[ids]]
            if len(ids) < conf.relocalisation_min_inliers:
                continue
            matches = self.match(keypoints.descriptors, self.map.descriptors[ids])
            if len(matches) < conf.relocalisation_min_inliers:
                continue
            kp, lm = np.asarray(matches.idx_a, np.int64), ids[np.asarray(matches.idx_b, np.int64)]
            T_cw, inliers = pnp_ransac(self.K, self.map.positions[lm], xy[kp], conf.ransac_reprojection_px,
                                       conf.ransac_iterations)
            if T_cw is not None and (best is None or inliers.sum() > best.num_inliers):
                best = _Estimate(True, f"keyframe {kf.id}", T_cw, len(kp), int(inliers.sum()))
        if best is None or best.num_inliers < conf.relocalisation_min_inliers:
            found = 0 if best is None else best.num_inliers
            return _Estimate(False, f"relocalisation failed (best {found} inliers < {conf.relocalisation_min_inliers})")
        verified = self._track_local_map(invert_pose(best.T_cw), keypoints, xy, z, conf.match_radius_px,
                                         check_jump=False)
        if not verified.ok or verified.num_inliers < conf.relocalisation_min_inliers:
            return _Estimate(False, f"relocalisation against {best.reason} not confirmed by the local map "
                             f"({verified.num_inliers} inliers)")
        verified.reason = f"relocalised against {best.reason}: {verified.reason}"
        return verified

    # ------------------------------------------------------------------ keyframes and map

    def _needs_keyframe(self, pose: np.ndarray, num_inliers: int, status: str) -> bool:
        conf = self.conf
        if status != "tracking":
            return True
        if num_inliers < conf.keyframe_min_inlier_ratio * self._inliers_at_keyframe:
            return True
        return not near_any_keyframe(pose, self._kf_poses, conf.keyframe_max_translation,
                                     conf.keyframe_max_rotation_deg)

    def _insert_keyframe(self, stamp: float, pose: np.ndarray, keypoints: Keypoints, xy: np.ndarray, z: np.ndarray,
                         keypoint_landmarks: np.ndarray, suspect: np.ndarray) -> Keyframe:
        """Keep this frame; its unmatched, unsuspected keypoints with depth become new landmarks."""
        landmark_ids = keypoint_landmarks.copy()
        new = (landmark_ids < 0) & (z > 0) & ~suspect
        if new.any():
            points_w = transform_points(pose, backproject(xy[new], z[new], self.K))
            landmark_ids[new] = self.map.add(points_w, keypoints.descriptors[new])
        kf = Keyframe(len(self.keyframes), stamp, pose.copy(), xy, z, keypoints.descriptors, landmark_ids)
        self.keyframes.append(kf)
        self._kf_poses = np.concatenate([self._kf_poses, pose[None]])
        if self._inliers_at_keyframe == 0:
            self._inliers_at_keyframe = int(new.sum())
        return kf

    def _local_bundle_adjustment(self) -> None:
        """Refine the latest keyframes and the landmarks they share; keyframes outside the window that see
        those landmarks are held fixed."""
        window = np.arange(max(0, len(self.keyframes) - self.conf.ba_window_keyframes), len(self.keyframes))
        self._bundle_adjust(window, self.conf.ba_max_iterations)

    def final_bundle_adjustment(self) -> None:
        """Bundle adjustment over every keyframe (at most ``final_ba_max_keyframes`` latest) and the landmarks
        they see, for the end of a run (``final_ba_iterations``; 0 = off). It refines :meth:`trajectory`; the
        poses already reported stay as they were."""
        conf = self.conf
        if conf.final_ba_iterations > 0:
            first = max(0, len(self.keyframes) - conf.final_ba_max_keyframes)
            self._bundle_adjust(np.arange(first, len(self.keyframes)), conf.final_ba_iterations)

    def _bundle_adjust(self, window: np.ndarray, iterations: int) -> None:
        """Refine the keyframes in ``window`` and the landmarks they see; other keyframes that see those
        landmarks are held fixed, and so is the oldest keyframe of any part of the map that has none held (the
        gauge). Landmarks seen only once move rigidly with their keyframe, and outlying observations are cut
        from their keyframe."""
        conf = self.conf
        if len(self.keyframes) < 2:
            return
        in_window = np.zeros(len(self.map), bool)
        for i in window:
            ids = self.keyframes[i].landmark_ids
            in_window[ids[ids >= 0]] = True
        in_window &= ~self.map.bad
        frame_parts, keypoint_parts = [], []  # (keyframe index, keypoint index) of every observation
        for i, kf in enumerate(self.keyframes):
            seen = np.flatnonzero((kf.landmark_ids >= 0) & in_window[np.maximum(kf.landmark_ids, 0)])
            frame_parts.append(np.full(len(seen), i))
            keypoint_parts.append(seen)
        obs_frame, obs_keypoint = np.concatenate(frame_parts), np.concatenate(keypoint_parts)
        obs_landmark = np.concatenate([self.keyframes[i].landmark_ids[k] for i, k in
                                       zip(range(len(self.keyframes)), keypoint_parts, strict=True)])
        shared = np.bincount(obs_landmark, minlength=len(self.map)) >= 2
        keep = shared[obs_landmark]  # a landmark seen once constrains no pose
        obs_frame, obs_keypoint, obs_landmark = obs_frame[keep], obs_keypoint[keep], obs_landmark[keep]
        if len(obs_frame) == 0:
            return
        used_frames, obs_pose = np.unique(obs_frame, return_inverse=True)
        landmark_ids, obs_point = np.unique(obs_landmark, return_inverse=True)
        fixed = hold_gauge(~np.isin(used_frames, window), obs_pose, obs_point)
        xy = np.concatenate([self.keyframes[f].xy[obs_keypoint[obs_frame == f]] for f in used_frames])
        depth = np.concatenate([self.keyframes[f].depth[obs_keypoint[obs_frame == f]] for f in used_frames])
        order = np.argsort(obs_frame, kind="stable")  # xy and depth were gathered frame by frame
        obs_pose, obs_point, obs_frame, obs_keypoint = obs_pose[order], obs_point[order], obs_frame[order], \
            obs_keypoint[order]
        poses_cw = invert_pose(self._kf_poses[used_frames])
        result = bundle_adjust(self.K, poses_cw, self.map.positions[landmark_ids], obs_pose, obs_point, xy, depth,
                               fixed, conf.depth_noise, conf.huber_px, iterations,
                               outlier_threshold=2 * conf.ransac_reprojection_px)
        self.map.positions[landmark_ids] = result.points_w
        for j, f in enumerate(used_frames):
            if fixed[j]:
                continue
            kf = self.keyframes[f]
            new_pose = invert_pose(result.poses_cw[j])
            alone = kf.landmark_ids[(kf.landmark_ids >= 0)]
            alone = alone[~shared[alone]]
            self.map.positions[alone] = transform_points(new_pose @ invert_pose(kf.pose), self.map.positions[alone])
            kf.pose = new_pose
            self._kf_poses[f] = new_pose
        for f in np.unique(obs_frame[result.outliers]):
            cut = obs_keypoint[result.outliers & (obs_frame == f)]
            self.keyframes[f].landmark_ids[cut] = -1

    # ------------------------------------------------------------------ input checks

    def _check_inputs(self, keypoints: Keypoints, depth: np.ndarray) -> None:
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


def hold_gauge(fixed: np.ndarray, obs_pose: np.ndarray, obs_point: np.ndarray) -> np.ndarray:
    """``fixed`` (P,) with the first pose of every connected part of the problem held where that part holds
    none: poses joined by shared points form a part, and a part with nothing fixed could drift freely (a map
    restarted after a long loss shares no landmark with the one before)."""
    n_poses = len(fixed)
    n_nodes = n_poses + int(obs_point.max()) + 1
    graph = coo_matrix((np.ones(len(obs_pose)), (obs_pose, n_poses + obs_point)), shape=(n_nodes, n_nodes))
    _, part = connected_components(graph, directed=False)
    fixed = fixed.copy()
    for label in np.unique(part[:n_poses]):
        members = np.flatnonzero(part[:n_poses] == label)
        if not fixed[members].any():
            fixed[members[0]] = True
    return fixed


def reattach_to_keyframes(stamps: list[float], anchors: list[int], relative: list[np.ndarray],
                          keyframe_poses: np.ndarray) -> Trajectory:
    """Frames' poses from their pose relative to an anchor keyframe (-1 = none: the pose itself) and the
    keyframes' current poses, so that bundle adjustment's corrections reach every frame."""
    anchors = np.asarray(anchors, np.int64)
    base = np.tile(np.eye(4), (len(anchors), 1, 1))
    base[anchors >= 0] = keyframe_poses[anchors[anchors >= 0]]
    return Trajectory(np.asarray(stamps), base @ np.asarray(relative).reshape(-1, 4, 4))


def smoothed(trajectory: Trajectory, conf: TrackerConfig) -> Trajectory:
    """The refined trajectory under the motion smoother (``smoothing_acceleration``; 0 = as it is). Hand-held
    and robot cameras move smoothly at camera rate, while each frame's pose carries its own few millimetres of
    noise: landmarks entering and leaving the tracked set move it (measured on the dev sequence)."""
    if conf.smoothing_acceleration <= 0:
        return trajectory
    return smooth_trajectory(trajectory, conf.smoothing_acceleration, conf.smoothing_angular_acceleration)


def near_any_keyframe(pose: np.ndarray, keyframe_poses: np.ndarray, max_translation: float,
                      max_rotation_deg: float) -> bool:
    """True when some keyframe lies within ``max_translation`` metres and ``max_rotation_deg`` of ``pose``."""
    if len(keyframe_poses) == 0:
        return False
    rel = np.einsum("ij,njk->nik", invert_pose(pose), keyframe_poses)
    moved = np.linalg.norm(rel[:, :3, 3], axis=1)
    turned = np.degrees(np.arccos(np.clip((np.trace(rel[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1)))
    return bool(((moved < max_translation) & (turned < max_rotation_deg)).any())


def descriptor_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise distances of paired descriptors: Euclidean for float, Hamming for packed uint8 bits."""
    if a.dtype == np.uint8:
        return np.unpackbits(np.bitwise_xor(a, b), axis=1).sum(1).astype(np.float64)
    return np.linalg.norm(a.astype(np.float64) - b.astype(np.float64), axis=1)


def _ms(start: float) -> float:
    return (time.perf_counter() - start) * 1000.0
