"""What the tracker room answers per frame, and the one record of every frame's pose.

:class:`TrackResult` is a tracker's answer for one frame. :class:`AnchoredTrajectory` keeps each frame's pose
relative to a keyframe (its anchor), so that bundle adjustment's later corrections of the keyframes reach every
frame; both schedules keep their frames in one.
"""

from __future__ import annotations

from array import array
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from twohr.config import TrackerConfig
from twohr.geometry import invert_pose
from twohr.pose import inliers_of, refine_pose
from twohr.trajectory import Trajectory, interpolate_poses, smooth_trajectory

from .map import MapSnapshot

#: Statuses whose pose was measured (the others coast on the motion model or wait for a first frame).
TRACKED_STATUSES = ("init", "tracking", "relocalised", "reinitialised")
#: Statuses with no pose at all: the camera has yet to be found in a map it was given (nothing is published).
UNPOSED_STATUSES = ("relocalising",)


@dataclass
class TrackResult:
    """The tracker's answer for one frame.

    ``pose`` is the 4x4 camera-to-world pose (world = the first keyframe's camera, or a loaded map's frame).
    ``status`` is one of ``uninitialised`` (no map yet; identity pose), ``init`` (this frame started the map),
    ``tracking``, ``relocalised`` (found again against earlier keyframes or the whole map), ``reinitialised``
    (a new map started
    at the coasted pose after a long loss), ``lost`` (not trackable: the pose is the motion model's prediction) or
    ``relocalising`` (not yet found in a map loaded from a file: no pose at all). ``reason`` says why in words;
    ``timings`` are milliseconds per stage.
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
    observed_depth: np.ndarray | None = None
    """(M,) their measured depth (m; 0 = none), where the pose was measured from optical-flow tracks"""

    @property
    def tracked(self) -> bool:
        """True when the pose was measured from this frame, False when it coasted or there is no map yet."""
        return self.status in TRACKED_STATUSES

    @property
    def posed(self) -> bool:
        """False when the frame has no pose in the map's frame at all (see :data:`UNPOSED_STATUSES`)."""
        return self.status not in UNPOSED_STATUSES


def reattach_to_keyframes(stamps: Sequence[float], anchors: Sequence[int], relative: np.ndarray,
                          keyframe_poses: np.ndarray) -> Trajectory:
    """Frames' poses from their pose relative to an anchor keyframe (-1 = none: the pose itself) and the
    keyframes' current poses, so that bundle adjustment's corrections reach every frame."""
    anchors = np.array(anchors, np.int64)  # copies: a view would pin an AnchoredTrajectory's growable arrays
    base = np.tile(np.eye(4), (len(anchors), 1, 1))
    base[anchors >= 0] = keyframe_poses[anchors[anchors >= 0]]
    return Trajectory(np.array(stamps, np.float64), base @ np.asarray(relative).reshape(-1, 4, 4))


def bridge_coasted(trajectory: Trajectory, measured: np.ndarray, max_gap_s: float = 3.0) -> Trajectory:
    """Replace poses that only coasted on the motion model (``measured`` False) by interpolation between
    the measured poses on either side, for gaps up to ``max_gap_s``: afterwards, the pose found again
    says more about the gap than the extrapolation did. Gaps at the ends are left as they are."""
    if measured.all() or measured.sum() < 2:
        return trajectory
    known = Trajectory(trajectory.stamps[measured], trajectory.poses[measured])
    poses, valid = interpolate_poses(known, trajectory.stamps[~measured], max_gap=max_gap_s)
    out = trajectory.poses.copy()
    out[np.flatnonzero(~measured)[valid]] = poses[valid]
    return Trajectory(trajectory.stamps, out)


@dataclass
class FrameObservations:
    """The landmarks a frame's pose was measured from: image positions, landmark ids and depths (0 = none)."""

    xy: np.ndarray
    landmark: np.ndarray
    depth: np.ndarray

    @classmethod
    def of(cls, result: TrackResult) -> FrameObservations | None:
        """A result's inlier observations, compactly (None unless optical flow tracked it: only then are depths
        kept)."""
        if result.observed_depth is None:
            return None
        return cls(result.observed_xy.astype(np.float32), result.observed_landmarks.astype(np.int32),
                   result.observed_depth.astype(np.float32))


def remeasure_pose(K: np.ndarray, pose: np.ndarray, observed: FrameObservations, positions: np.ndarray,
                   usable: np.ndarray, conf: TrackerConfig) -> np.ndarray | None:
    """A frame's camera-to-world ``pose`` measured again from ``observed`` against landmark ``positions`` (after
    bundle adjustment): robust refinement from ``pose``, the inliers re-classified and refined once more. None where
    fewer than ``min_inliers`` remain or the pose would move more than ``max_jump_m`` (the map changed under it)."""
    ids = observed.landmark.astype(np.int64)
    ok = ids < len(positions)
    ok[ok] = usable[ids[ok]]
    points, xy, depth = positions[ids[ok]], observed.xy[ok].astype(np.float64), observed.depth[ok].astype(np.float64)
    if len(points) < conf.min_inliers:
        return None
    T_cw = refine_pose(K, invert_pose(pose), points, xy, depth, conf.depth_noise, conf.huber_px)
    inliers = inliers_of(K, T_cw, points, xy, depth, conf.ransac_reprojection_px, conf.depth_noise)
    if inliers.sum() < conf.min_inliers:
        return None
    T_cw = refine_pose(K, T_cw, points[inliers], xy[inliers], depth[inliers], conf.depth_noise, conf.huber_px)
    remeasured = invert_pose(T_cw)
    if np.linalg.norm(remeasured[:3, 3] - pose[:3, 3]) > conf.max_jump_m:
        return None
    return remeasured


def smoothed(trajectory: Trajectory, conf: TrackerConfig) -> Trajectory:
    """The refined trajectory under the motion smoother (``smoothing_acceleration``; 0 = as it is). Hand-held
    and robot cameras move smoothly at camera rate, while each frame's pose carries its own few millimetres of
    noise: landmarks entering and leaving the tracked set move it (measured on the dev sequence)."""
    if conf.smoothing_acceleration <= 0:
        return trajectory
    return smooth_trajectory(trajectory, conf.smoothing_acceleration, conf.smoothing_angular_acceleration)


class AnchoredTrajectory:
    """Every frame's pose, kept relative to an anchor keyframe so that the keyframes' refinements reach it.

    Kept in flat arrays (about 113 bytes a frame), since a robot's session runs for hours.
    ``bridge_gaps``: in the refined trajectory, frames that only coasted are interpolated between the measured
    frames around them (the camera-rate schedule, whose keyframe jobs report a loss late)."""

    def __init__(self, conf: TrackerConfig, bridge_gaps: bool = False) -> None:
        self.conf = conf
        self.bridge_gaps = bridge_gaps
        self.stamps = array("d")
        self.anchors = array("q")
        self._relative = array("d")  # the top 3x4 of each frame's pose relative to its anchor, row after row
        self.measured = array("b")  # 0 where the pose only coasted on the motion model
        self.observed: dict[int, FrameObservations] = {}
        """frame number -> what its pose was measured from, for the latest ``refine_frames`` frames tracked by flow
        (oldest first; keyframes leave it, bundle adjustment refines their poses)"""
        self._holding = np.zeros(0, np.int32)  # landmark id -> how many frames in `observed` refer to it

    def __len__(self) -> int:
        return len(self.stamps)

    def held_landmarks(self) -> np.ndarray:
        """The landmark ids the frames kept for refinement refer to (their map rows must not be filled again)."""
        return np.flatnonzero(self._holding)

    def _hold(self, observed: FrameObservations, step: int) -> None:
        ids = observed.landmark[observed.landmark >= 0]
        if len(ids) and ids.max() >= len(self._holding):
            self._holding = np.concatenate([self._holding, np.zeros(max(int(ids.max()) + 1, 2 * len(self._holding))
                                                                    - len(self._holding), np.int32)])
        np.add.at(self._holding, ids, step)

    def relative(self, start: int = 0) -> np.ndarray:
        """(N, 4, 4) the poses relative to their anchors, of frame ``start`` on."""
        top = np.frombuffer(self._relative, np.float64)[12 * start:].reshape(-1, 3, 4)
        poses = np.tile(np.eye(4), (len(top), 1, 1))
        poses[:, :3] = top
        return poses

    def add(self, stamp: float, pose: np.ndarray, measured: bool, anchor: int, keyframe_poses: np.ndarray,
            observed: FrameObservations | None = None) -> None:
        """Record one frame's camera-to-world ``pose``, relative to keyframe ``anchor`` (-1: none yet) as
        ``keyframe_poses`` has it now, and what it was measured from (see ``refine_frames``)."""
        if observed is not None and self.conf.refine_frames > 0:
            self.observed[len(self.stamps)] = observed
            self._hold(observed, 1)
            if len(self.observed) > self.conf.refine_frames:
                self._hold(self.observed.pop(next(iter(self.observed))), -1)
        self.stamps.append(stamp)
        self.anchors.append(anchor)
        relative = pose if anchor < 0 else invert_pose(keyframe_poses[anchor]) @ pose
        self._relative.extend(relative[:3].ravel().tolist())
        self.measured.append(measured)

    def attach_to_keyframe(self, stamp: float, keyframe_id: int, measured: bool, keyframe_poses: np.ndarray) -> None:
        """The frame at ``stamp`` became keyframe ``keyframe_id``: it takes the keyframe's pose (measured from 2HR
        matches and refined by bundle adjustment since), whatever the per-frame path had reported for it. With
        ``reanchor_lagging_frames``, the frames recorded while its keyframe job ran follow it: they keep their
        motion relative to that frame, so the keyframe's correction does not come and go as a spike."""
        for i in range(len(self.stamps) - 1, -1, -1):
            if self.stamps[i] == stamp:
                relative = np.frombuffer(self._relative, np.float64).reshape(-1, 3, 4)  # a view: writes go through
                if self.conf.reanchor_lagging_frames and i + 1 < len(self.stamps):
                    absolute = reattach_to_keyframes(self.stamps[i:], self.anchors[i:], self.relative(i),
                                                     keyframe_poses).poses
                    relative[i + 1:] = (invert_pose(absolute[0]) @ absolute[1:])[:, :3]
                    self.anchors[i + 1:] = array("q", [keyframe_id] * (len(self.stamps) - i - 1))
                self.anchors[i] = keyframe_id
                relative[i] = np.eye(4)[:3]
                released = self.observed.pop(i, None)
                if released is not None:
                    self._hold(released, -1)
                self.measured[i] = measured
                del relative  # the arrays cannot grow while a view of them is alive
                return
            if self.stamps[i] < stamp:
                return

    def trajectory(self, keyframe_poses: np.ndarray, landmarks: MapSnapshot | None = None,
                   K: np.ndarray | None = None) -> Trajectory:
        """Every frame's pose re-attached to its keyframe in ``keyframe_poses`` (as bundle adjustment left them);
        with the map's ``landmarks`` and camera matrix ``K``, the frames kept in :attr:`observed` re-measured against
        them (:func:`remeasure_pose`); coasted gaps bridged where asked, then smoothed (:func:`smoothed`)."""
        trajectory = reattach_to_keyframes(self.stamps, self.anchors, self.relative(), keyframe_poses)
        if landmarks is not None and self.observed:
            for i, observed in self.observed.items():
                remeasured = remeasure_pose(K, trajectory.poses[i], observed, landmarks.landmark_positions,
                                            landmarks.landmark_usable, self.conf)
                if remeasured is not None:
                    trajectory.poses[i] = remeasured
        if self.bridge_gaps:
            trajectory = bridge_coasted(trajectory, np.asarray(self.measured, bool))
        return smoothed(trajectory, self.conf)
