"""Per-frame tracking between keyframes: optical flow of map landmarks, then PnP. The camera-rate path.

Per frame (:meth:`FrameTracker.track`):

1. predict the pose with the constant-velocity motion model;
2. move the image positions of the tracked landmarks from the previous frame to this one with pyramidal
   Lucas-Kanade flow (sub-pixel), started at their projection under the prediction; keep a track only if
   it flows back to where it started (forward-backward check) and lies outside the dynamic mask;
3. RANSAC PnP and a robust refinement (reprojection + inverse depth, motion prior) against the landmarks'
   3-D positions; a pose that jumps implausibly far from the prediction is rejected and the frame coasts;
4. :meth:`FrameTracker.keyframe_evidence` says what the frame shows of the map for the keyframe policy
   (:mod:`.keyframe_policy`): its inlier tracks against those of its reference keyframe, and its close points.

Keyframes are built off this path (the keyframe job: :class:`~.tracking.Tracker` on 2HR keypoints, descriptor
matching and bundle adjustment, in the mapping worker); each one comes back as a :class:`MapUpdate` whose
:class:`~.map.MapSnapshot` refreshes the landmark positions and whose observations re-seed the tracks. The
per-frame record of poses is the schedule's (:class:`~.trajectory.AnchoredTrajectory`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np

from twohr.config import TrackerConfig
from twohr.dataset import CameraIntrinsics
from twohr.features import masked
from twohr.geometry import backproject, invert_pose, project, transform_points
from twohr.mapfile import MapArrays
from twohr.places import PlaceQuery
from twohr.pose import estimate_pose, sample_depth

from .keyframe_policy import VERY_WEAK, Evidence, close_points
from .map import MapSnapshot
from .motion import MotionModel
from .trajectory import TrackResult


@dataclass
class MapUpdate:
    """What the mapping worker hands back after a keyframe job on frame ``frame_index``."""

    frame_index: int
    stamp: float
    result: TrackResult
    """the keyframe job's answer for that frame (``init``, ``tracking``, ``relocalised``, ``lost`` ...)"""
    keyframe_id: int
    """the new keyframe's id, -1 when the frame did not become one"""
    seeds_xy: np.ndarray
    """(M, 2) the keyframe's keypoints that observe a landmark, in that frame's pixels"""
    seeds_landmark: np.ndarray
    """(M,) their landmark ids, best observed first"""
    snapshot: MapSnapshot
    """the map after the job (landmark positions and keyframe poses after bundle adjustment)"""
    gray: np.ndarray | None = None
    """the frame's grayscale image, to carry the seeds to a later frame by optical flow"""
    timings: dict[str, float] | None = None
    """milliseconds per stage of the job (``detector``, ``yolo``, ``mapping``, ``job``)"""
    keypoints: int = 0
    """the keypoints the job detected (a tracked keyframe: its new corners)"""
    kept: int = 0
    """of them, those kept (outside the dynamic mask)"""
    kind: str = "2hr"
    """``2hr``, ``tracked``, ``describe`` or ``loop`` (see :class:`~.stages.KeyframeLog`)"""
    mask: np.ndarray | None = None
    """the dynamic mask of a tracked keyframe, for its 2HR detection later"""
    loop_query: PlaceQuery | None = None
    """place-recognition candidates of the job's keyframe, for the loop worker to verify"""
    fused: np.ndarray | None = None
    """(M, 2) landmark ids a closed loop fused: (retired duplicate, the landmark that replaces it)"""
    arrays: MapArrays | None = None
    """the whole map after the job, as a map file's arrays, when the per-frame path asked for a copy
    (:meth:`~.keyframe_schedule.KeyframePipeline.map_copy`)"""
    idle_rows: np.ndarray | None = None
    """landmark rows the map no longer refers to (:meth:`~.map.Map.idle_rows`), for the per-frame path to give back
    those it does not hold"""


@dataclass
class RecentKeyframe:
    """A recent keyframe whose landmarks reacquisition looks for again (:meth:`FrameTracker._reacquire`)."""

    gray: np.ndarray
    """its grayscale image"""
    xy: np.ndarray
    """(M, 2) float32 its observations of landmarks"""
    landmark: np.ndarray
    """(M,) their landmark ids"""
    retry_at: np.ndarray
    """(M,) the frame number from which each may be tried again (after a try that did not find it)"""


def flow_points(source: np.ndarray, target: np.ndarray, xy: np.ndarray, guess: np.ndarray,
                conf: TrackerConfig) -> tuple[np.ndarray, np.ndarray]:
    """Track points ``xy`` of grayscale image ``source`` into ``target`` by pyramidal Lucas-Kanade, starting
    at ``guess``; returns (positions, ok) where
    ok needs convergence both ways and a forward-backward error below ``flow_fb_px``."""
    if len(xy) == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    window = (conf.flow_window_px, conf.flow_window_px)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 10, 0.03)
    # copies: OpenCV writes the tracked positions into the initial-guess array
    start = np.array(xy, np.float32).reshape(-1, 1, 2)
    forward, ok_f, _ = cv2.calcOpticalFlowPyrLK(
        source, target, start, np.array(guess, np.float32).reshape(-1, 1, 2), winSize=window,
        maxLevel=conf.flow_levels, criteria=criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    back, ok_b, _ = cv2.calcOpticalFlowPyrLK(target, source, forward, start.copy(), winSize=window,
                                             maxLevel=conf.flow_levels, criteria=criteria,
                                             flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    forward, back = forward.reshape(-1, 2), back.reshape(-1, 2)
    fb_error = np.linalg.norm(back - start.reshape(-1, 2), axis=1)
    height, width = target.shape[:2]
    inside = (forward[:, 0] >= 0) & (forward[:, 1] >= 0) & (forward[:, 0] <= width - 1) & (
        forward[:, 1] <= height - 1)
    ok = ok_f.reshape(-1).astype(bool) & ok_b.reshape(-1).astype(bool) & (fb_error < conf.flow_fb_px) & inside
    return forward, ok


def new_corners(gray: np.ndarray, count: int, min_distance: int, mask: np.ndarray | None = None,
                avoid_xy: np.ndarray | None = None) -> np.ndarray:
    """(M, 2) float32 Shi-Tomasi corners of ``gray``, strongest first, at most ``count``, outside the dynamic
    ``mask`` (True = moving) and at least ``min_distance`` pixels from each other and from ``avoid_xy``."""
    if count <= 0:
        return np.zeros((0, 2), np.float32)
    allowed = np.full(gray.shape[:2], 255, np.uint8)
    if mask is not None:
        allowed[mask] = 0
    if avoid_xy is not None:
        for x, y in np.round(avoid_xy).astype(int):
            cv2.circle(allowed, (int(x), int(y)), min_distance, 0, -1)
    corners = cv2.goodFeaturesToTrack(gray, count, 0.01, min_distance, mask=allowed, blockSize=7)
    if corners is None:
        return np.zeros((0, 2), np.float32)
    return corners.reshape(-1, 2).astype(np.float32)


def static_in_reference(gray: np.ndarray, pose: np.ndarray, xy: np.ndarray, z: np.ndarray, reference: np.ndarray,
                        reference_pose: np.ndarray, K: np.ndarray, conf: TrackerConfig) -> np.ndarray:
    """(N,) True for points ``xy`` (depth ``z``) of image ``gray`` at camera-to-world ``pose`` that optical flow finds
    in an earlier image ``reference`` (at ``reference_pose``) where a static point would be: within
    ``ransac_reprojection_px`` of its projection. A corner on someone walking past fails (or its flow does)."""
    if len(xy) == 0:
        return np.zeros(0, bool)
    points_w = transform_points(pose, backproject(xy, z, K))
    expected = project(transform_points(invert_pose(reference_pose), points_w), K)
    inside = np.isfinite(expected).all(axis=1)
    found, ok = flow_points(gray, reference, xy, np.where(inside[:, None], expected, xy), conf)
    return inside & ok & (np.linalg.norm(found - expected, axis=1) <= conf.ransac_reprojection_px)


def on_flat_depth(depth: np.ndarray, xy: np.ndarray, radius: int, ratio: float) -> np.ndarray:
    """(N,) True where the depth in the (2 radius + 1)-pixel square around ``xy`` is all valid and spreads by less
    than ``ratio`` of its value: corners love occlusion edges, where a pixel has no single depth."""
    if len(xy) == 0:
        return np.zeros(0, bool)
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    filled = np.where(depth > 0, depth, np.inf).astype(np.float32)  # a missing reading spoils its square
    nearest = cv2.erode(filled, kernel, borderType=cv2.BORDER_REPLICATE)
    farthest = cv2.dilate(filled, kernel, borderType=cv2.BORDER_REPLICATE)
    x, y = np.round(xy).astype(int).T
    near, far = nearest[y, x], farthest[y, x]
    flat = np.zeros(len(xy), bool)
    valid = np.isfinite(far)  # inf - inf would be NaN: squares with a hole are decided here already
    flat[valid] = far[valid] - near[valid] < ratio * near[valid]
    return flat


class FrameTracker:
    """Camera-rate tracking: landmarks followed by optical flow, pose by PnP; keyframes come from outside."""

    default_conf = TrackerConfig()

    def __init__(self, camera: CameraIntrinsics, conf: TrackerConfig | None = None) -> None:
        self.camera = camera
        self.conf = conf or self.default_conf
        self.K = camera.matrix
        self.motion = MotionModel(self.conf.velocity_frames, self.conf.coast_velocity_decay)
        self.snapshot = MapSnapshot.empty()  # the map as the latest MapUpdate described it (read-only)
        # the tracks: landmark ids and their sub-pixel positions in the previous frame
        self.track_xy = np.zeros((0, 2), np.float32)
        self.track_landmark = np.zeros(0, np.int64)
        self.previous: np.ndarray | None = None  # the previous frame's grayscale image
        self.keyframe_stamp: float | None = None
        """camera time of the latest keyframe (or job that re-seeded the tracks)"""
        self.reference_inliers = (0, 0)
        """(inlier tracks, close ones) at the latest keyframe job's own frame: the keyframe policy's reference"""
        self._carried = 1.0  # the share of its frame's inlier tracks still tracked when the latest job came back
        self._inliers_at: dict[float, np.ndarray] = {}  # the latest frames' inlier landmarks, by stamp
        self._recent_keyframes: list[RecentKeyframe] = []  # to find lost landmarks again
        self._frame_number = 0
        self.reacquisition = {"tried": 0, "found": 0}
        """landmarks reacquisition looked for, and found, so far"""
        self.latest_keyframe: tuple[np.ndarray, int] | None = None
        """(grayscale image, keyframe id) of the latest keyframe, to check new corners against"""

    @property
    def landmarks(self) -> np.ndarray:
        """(L, 3) the landmarks' world positions, as of the latest map update."""
        return self.snapshot.landmark_positions

    @property
    def usable(self) -> np.ndarray:
        """(L,) False for landmarks retired as outliers."""
        return self.snapshot.landmark_usable

    @property
    def keyframe_poses(self) -> np.ndarray:
        """(K, 4, 4) the keyframes' camera-to-world poses, as of the latest map update."""
        return self.snapshot.keyframe_poses

    @property
    def initialised(self) -> bool:
        return len(self.keyframe_poses) > 0

    # ------------------------------------------------------------------ per frame

    def track(self, stamp: float, gray: np.ndarray, depth: np.ndarray, mask: np.ndarray | None = None) -> TrackResult:
        """The pose of one frame from its grayscale image, depth (metres) and dynamic mask (True = moving)."""
        start = time.perf_counter()
        predicted = self.motion.predict(stamp)
        if not self.initialised or self.previous is None:
            result = TrackResult(stamp, predicted, "uninitialised", reason="waiting for the first keyframe")
        else:
            result = self._track_flow(stamp, gray, depth, mask, predicted)
        self.motion.advance(stamp, result.pose)
        self.previous = gray
        if result.status == "tracking" and self.reference_inliers[0] == 0:
            # the first frame tracked since a keyframe job came back; the tracks lost while the job ran (its frame's
            # inlier tracks not tracked any more: self._carried) count against the reference, which is scaled back
            # to the job's own frame, so that a slow mapping worker does not thin the keyframes
            close = close_points(result.observed_depth, self.conf)
            self.reference_inliers = (round(result.num_inliers / self._carried), round(close / self._carried))
        self._frame_number += 1
        result.timings = {"total": (time.perf_counter() - start) * 1000}
        result.num_landmarks = len(self.track_landmark)
        return result

    def _track_flow(self, stamp: float, gray: np.ndarray, depth: np.ndarray, mask: np.ndarray | None,
                    predicted: np.ndarray) -> TrackResult:
        conf = self.conf
        tracks = len(self.track_landmark)
        T_guess = invert_pose(predicted)
        guess = self._flow_start(T_guess, self.track_landmark, self.track_xy)
        xy, ok = flow_points(self.previous, gray, self.track_xy, guess, conf)
        xy, landmark = xy[ok], self.track_landmark[ok]
        if len(landmark) < conf.flow_reacquire_below:
            found_xy, found = self._reacquire(gray, T_guess, landmark)
            xy, landmark = np.concatenate([xy, found_xy]), np.concatenate([landmark, found])
        if mask is not None and len(xy):
            keep = ~masked(xy, mask)
            xy, landmark = xy[keep], landmark[keep]
        z = sample_depth(depth, xy, conf.min_depth, conf.max_depth, conf.depth_edge_ratio)
        counts = dict(num_keypoints=tracks, num_with_depth=int((z > 0).sum()), num_matches=len(xy))
        T_cw, inliers, why = estimate_pose(self.K, self.landmarks[landmark], xy.astype(np.float64), z,
                                           conf.ransac_reprojection_px, conf.ransac_iterations, conf.min_inliers,
                                           conf.depth_noise, conf.huber_px, self.motion.prior(T_guess, conf),
                                           initial=T_guess if self.motion.lost_frames == 0 else None)
        if T_cw is not None and (jump := self.motion.implausible_jump(predicted, invert_pose(T_cw), conf)):
            T_cw, why = None, jump
        if T_cw is None:
            # keep the flowed tracks: the next keyframe or frame may still use them
            self.track_xy, self.track_landmark = xy, landmark
            self.motion.coast()
            return TrackResult(stamp, predicted, "lost", num_inliers=int(inliers.sum()),
                               reason=f"{why}; pose coasts on the motion model "
                               f"({self.motion.lost_frames} frame(s) untracked)", **counts)
        self.track_xy, self.track_landmark = xy[inliers], landmark[inliers]
        self._inliers_at[stamp] = self.track_landmark
        if len(self._inliers_at) > 64:  # a keyframe job comes back within a few frames
            del self._inliers_at[next(iter(self._inliers_at))]
        pose = invert_pose(T_cw)
        self.motion.tracked(stamp, pose)
        num_inliers = int(inliers.sum())
        reason = f"{num_inliers} inliers of {len(xy)} flowed tracks"
        if counts["num_with_depth"] == 0:
            reason += " (no depth: tracked from 2-D flow only)"
        return TrackResult(stamp, pose, "tracking", num_inliers=num_inliers, reason=reason,
                           observed_xy=self.track_xy, observed_landmarks=self.track_landmark,
                           observed_depth=z[inliers], **counts)

    def held_landmarks(self) -> list[np.ndarray]:
        """The landmark ids this tracker refers to: its tracks, the latest frames' inliers and the recent
        keyframes' observations (a map row it holds must not be filled again)."""
        return [self.track_landmark, *self._inliers_at.values(), *(k.landmark for k in self._recent_keyframes)]

    def _reacquire(self, gray: np.ndarray, T_guess: np.ndarray, tracked: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Find landmarks of the latest keyframes again that the flow has lost (a person walked past them):
        flow from their observation in the keyframe's image straight to this frame, starting at their
        projection under the prediction (at the observation itself while lost)."""
        found_xy, found = [np.zeros((0, 2), np.float32)], [np.zeros(0, np.int64)]
        taken = set(tracked.tolist())
        height, width = gray.shape[:2]
        for keyframe in reversed(self._recent_keyframes):  # newest first
            landmark_kf = keyframe.landmark
            todo = self.usable[landmark_kf] & ~np.isin(landmark_kf, list(taken))
            todo &= keyframe.retry_at <= self._frame_number  # not one that failed a moment ago
            if self.motion.lost_frames == 0:
                # only landmarks the prediction puts in view: the flow could not keep the others (it costs the
                # same per point, found or not, and this runs on every frame while tracks are short)
                uv = project(transform_points(T_guess, self.landmarks[landmark_kf]), self.K)
                todo &= (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] <= width - 1) & (uv[:, 1] <= height - 1)
            if not todo.any():
                continue
            xy_kf, landmark_kf = keyframe.xy[todo], landmark_kf[todo]
            xy, ok = flow_points(keyframe.gray, gray, xy_kf, self._flow_start(T_guess, landmark_kf, xy_kf),
                                 self.conf)
            keyframe.retry_at[np.flatnonzero(todo)[~ok]] = self._frame_number + self.conf.flow_reacquire_backoff
            self.reacquisition["tried"] += len(ok)
            self.reacquisition["found"] += int(ok.sum())
            found_xy.append(xy[ok])
            found.append(landmark_kf[ok])
            taken.update(landmark_kf[ok].tolist())
        return np.concatenate(found_xy), np.concatenate(found)

    def _flow_start(self, T_cw: np.ndarray, landmark: np.ndarray, fallback: np.ndarray) -> np.ndarray:
        """Where the flow of landmarks starts: their projection under ``T_cw`` (world-to-camera), or ``fallback``
        (their last image position) for points behind the camera and while lost, when the pose is poor."""
        if self.motion.lost_frames > 0:
            return fallback
        projected = project(transform_points(T_cw, self.landmarks[landmark]), self.K)
        return np.where(np.isfinite(projected), projected, fallback)

    def keyframe_evidence(self, result: TrackResult) -> Evidence | None:
        """What a tracking frame says of the map for the keyframe policy (None: not tracking, or no map yet; such
        a frame always asks for a keyframe job, which starts the map or relocalises)."""
        if not self.initialised or result.status != "tracking":
            return None
        since = np.inf if self.keyframe_stamp is None else result.stamp - self.keyframe_stamp
        return Evidence.of(result.num_inliers, result.observed_depth, self.reference_inliers, since, self.conf)

    # ------------------------------------------------------------------ keyframes

    def apply(self, update: MapUpdate) -> None:
        """Take a finished keyframe job: refreshed landmarks and keyframe poses, and new tracks seeded from the
        keyframe's observations (carried by optical flow from the keyframe's image to the latest frame)."""
        found = not self.initialised  # the first map, or the camera found (again) in a given map
        if update.kind == "loop" and len(self.snapshot.keyframe_poses) and len(update.snapshot.keyframe_poses):
            # the map moved under the camera: it moves with the latest keyframe, where it is
            latest = len(self.snapshot.keyframe_poses) - 1
            self.motion.move_world(update.snapshot.keyframe_poses[latest] @ invert_pose(
                self.snapshot.keyframe_poses[latest]))
        self.snapshot = update.snapshot
        if not self.initialised:  # no map yet, or the camera looks for itself in a given map (again): no tracks
            self.track_xy, self.track_landmark = np.zeros((0, 2), np.float32), np.zeros(0, np.int64)
            self._recent_keyframes = []
            self.latest_keyframe = None
            return
        if update.fused is not None and len(update.fused):  # follow the landmark that replaced a fused duplicate
            rename = dict(update.fused.tolist())

            def renamed(ids: np.ndarray) -> np.ndarray:
                return np.array([rename.get(i, i) for i in ids.tolist()], np.int64)

            self.track_landmark = renamed(self.track_landmark)
            for keyframe in self._recent_keyframes:
                keyframe.landmark = renamed(keyframe.landmark)
        keep = self.usable[self.track_landmark]
        self.track_xy, self.track_landmark = self.track_xy[keep], self.track_landmark[keep]
        new_map = found or (update.keyframe_id >= 0 and update.result.status in ("init", "reinitialised"))
        if new_map:
            self.track_xy, self.track_landmark = np.zeros((0, 2), np.float32), np.zeros(0, np.int64)
        if update.result.tracked:
            self.motion.correct(update.result.pose, update.stamp, new_map)
        seeds = self.usable[update.seeds_landmark] & ~np.isin(update.seeds_landmark, self.track_landmark)
        if update.keyframe_id >= 0 or update.result.tracked:  # a keyframe job, keyframe or not
            self.keyframe_stamp = update.stamp
            self.reference_inliers = (0, 0)  # the next tracked frame measures it
            then = self._inliers_at.get(update.stamp)  # the job's frame's inlier tracks: how many are left now
            self._carried = 1.0 if then is None or len(then) == 0 else max(
                VERY_WEAK, float(np.isin(then, self.track_landmark).mean()))
        xy, landmark = update.seeds_xy[seeds].astype(np.float32), update.seeds_landmark[seeds]
        if update.gray is not None and self.previous is not None and update.gray is not self.previous:
            # the keyframe is some frames old: carry its observations to the latest frame
            guess = xy if self.motion.last_pose is None else self._flow_start(
                invert_pose(self.motion.last_pose), landmark, xy)
            xy, ok = flow_points(update.gray, self.previous, xy, guess, self.conf)
            xy, landmark = xy[ok], landmark[ok]
        if update.keyframe_id >= 0 and update.gray is not None:
            self.latest_keyframe = (update.gray, update.keyframe_id)
            observed = self.usable[update.seeds_landmark]
            self._recent_keyframes = [*self._recent_keyframes, RecentKeyframe(
                update.gray, update.seeds_xy[observed].astype(np.float32), update.seeds_landmark[observed],
                np.zeros(int(observed.sum()), np.int64))][-self.conf.flow_reacquire_keyframes:]
        room = max(0, self.conf.flow_max_tracks - len(self.track_landmark))
        self.track_xy = np.concatenate([self.track_xy, xy[:room].astype(np.float32)])
        self.track_landmark = np.concatenate([self.track_landmark, landmark[:room]])
