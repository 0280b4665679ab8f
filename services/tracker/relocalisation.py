"""Relocalisation: finding a lost camera again in its map, or a camera in a map it was given.

RANSAC PnP of a frame's keypoints against the landmarks of candidate keyframes (those nearest to the last good pose
and to the coasted prediction, the latest first), then against the whole map; the best candidate's pose is verified
on the local map around it (:meth:`~.local_map.LocalMapSearch.match_local_map`)."""

from __future__ import annotations

import time

import numpy as np

from twohr.features import Keypoints, Matches
from twohr.geometry import invert_pose
from twohr.pose import MatchFn, PoseEstimate, match_each, pnp_on_matches

from .local_map import LocalMapSearch
from .trajectory import TrackResult


class Relocaliser:
    """Finds a lost camera again over the map that ``search`` reads."""

    def __init__(self, search: LocalMapSearch) -> None:
        self.search = search
        self.map = search.map
        self.conf = search.conf

    def relocalise(self, keypoints: Keypoints, xy: np.ndarray, z: np.ndarray, around: list[np.ndarray],
                   match: MatchFn) -> PoseEstimate:
        """The best :meth:`candidate`, verified on the local map around its pose (``around`` empty: no prior pose,
        the whole map)."""
        conf = self.conf
        best = self.candidate(keypoints, xy, around, match)
        if not best.ok:
            return best
        verified = self.search.match_local_map(invert_pose(best.T_cw), keypoints, xy, z, conf.match_radius_px, False,
                                               match)
        if not verified.ok or verified.num_inliers < conf.relocalisation_min_inliers:
            return PoseEstimate(False, f"relocalisation against {best.reason} not confirmed by the local map "
                                f"({verified.num_inliers} inliers)")
        verified.reason = f"relocalised against {best.reason}: {verified.reason}"
        return verified

    def find_in_map(self, stamp: float, keypoints: Keypoints, xy: np.ndarray, z: np.ndarray, num_depth: int,
                    timings: dict[str, float], match: MatchFn) -> TrackResult:
        """A given map, the camera not yet found in it: relocalisation against the whole map, verified on the local
        map around the pose found; a ``relocalising`` result (no pose) until then, ``relocalised`` once found."""
        counts = dict(num_keypoints=len(keypoints), num_with_depth=num_depth)
        t0 = time.perf_counter()
        estimate = self.relocalise(keypoints, xy, z, [], match)
        timings["relocalise"] = (time.perf_counter() - t0) * 1000.0
        if not estimate.ok:
            return TrackResult(stamp, np.eye(4), "relocalising",
                               reason=f"looking for the camera in the map: {estimate.reason}", **counts)
        pose = invert_pose(estimate.T_cw)
        observed = estimate.keypoint_landmarks
        return TrackResult(stamp, pose, "relocalised", num_matches=estimate.num_matches,
                           num_inliers=estimate.num_inliers, reason=f"found in the map: {estimate.reason}",
                           observed_xy=xy[observed >= 0], observed_landmarks=observed[observed >= 0], **counts)

    def candidate(self, keypoints: Keypoints, xy: np.ndarray, around: list[np.ndarray], match: MatchFn) -> PoseEstimate:
        """The keyframe whose landmarks give the most PnP inliers (world-to-camera pose in ``T_cw``), or a failed
        estimate saying why; the caller verifies it on the local map. The keyframes nearest to each pose in
        ``around`` (the last good pose, the coasted prediction; none in a map the camera has yet to find itself in)
        are tried first, then the whole map."""
        conf, world = self.conf, self.map
        candidates = np.unique(np.concatenate([np.zeros(0, np.int64)] + [
            world.local_keyframes(pose, conf.relocalisation_candidates) for pose in around]))
        landmarks = world.landmarks
        tried = []
        for i in candidates[::-1]:  # the latest keyframes first
            kf = world.keyframes[i]
            ids = kf.landmark_ids[kf.landmark_ids >= 0]
            ids = ids[~landmarks.bad[ids] & landmarks.described[ids]]
            if len(ids) >= conf.relocalisation_min_inliers:
                tried.append((f"keyframe {kf.id}", ids))
        # every candidate's landmarks in one match query (one round trip to a matcher service)
        found = match_each(match, keypoints.descriptors, [landmarks.descriptors[ids] for _, ids in tried])
        best: PoseEstimate | None = None
        for (what, ids), matches in zip(tried, found, strict=True):
            estimate = self._pnp(xy, ids, what, matches)
            if estimate is not None and (best is None or estimate.num_inliers > best.num_inliers):
                best = estimate
        if (best is None or best.num_inliers < conf.relocalisation_min_inliers) and conf.relocalisation_max_landmarks:
            # the camera came back somewhere far from where it was lost (a robot carried, a replay played again):
            # the whole map's landmarks at once
            ids = np.flatnonzero(~landmarks.bad & landmarks.described)
            ids = landmarks.most_accepted(ids)[:conf.relocalisation_max_landmarks]
            whole_map = self._attempt(keypoints, xy, ids, "the whole map", match)
            if whole_map is not None and (best is None or whole_map.num_inliers > best.num_inliers):
                best = whole_map
        if best is None or best.num_inliers < conf.relocalisation_min_inliers:
            found = 0 if best is None else best.num_inliers
            return PoseEstimate(False, f"relocalisation failed (best {found} inliers < "
                                f"{conf.relocalisation_min_inliers})")
        return best

    def _attempt(self, keypoints: Keypoints, xy: np.ndarray, ids: np.ndarray, what: str,
                 match: MatchFn) -> PoseEstimate | None:
        """RANSAC PnP of the frame's keypoints against landmarks ``ids``, or None when too few match."""
        if len(ids) < self.conf.relocalisation_min_inliers:
            return None
        return self._pnp(xy, ids, what, match(keypoints.descriptors, self.map.landmarks.descriptors[ids]))

    def _pnp(self, xy: np.ndarray, ids: np.ndarray, what: str, matches: Matches) -> PoseEstimate | None:
        """RANSAC PnP of the frame's keypoints matched to landmarks ``ids``, or None when too few match."""
        conf, world = self.conf, self.map
        found = pnp_on_matches(world.K, matches, xy, world.landmarks.positions[ids], conf.relocalisation_min_inliers,
                               conf.ransac_reprojection_px, conf.ransac_iterations)
        if found is None or found[0] is None:
            return None
        T_cw, kp, _, inliers = found
        return PoseEstimate(True, what, T_cw, len(kp), int(inliers.sum()))
