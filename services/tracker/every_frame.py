"""The every-frame schedule, as in the paper: 2HR detection -> dynamic mask -> matching -> the keyframe job, on
every frame. Kept for the paper's ablations (``twohr bench --ablations``); the default is the camera-rate
schedule (:mod:`.keyframe_schedule`)."""

from __future__ import annotations

import time

import numpy as np

from twohr.config import PipelineConfig
from twohr.dataset import CameraIntrinsics, Frame
from twohr.features import drop_masked
from twohr.mapfile import MapArrays
from twohr.trajectory import Trajectory

from .loops import LoopLog
from .map import Map, MapSnapshot
from .stages import FrameStats, KeyframeLog, Stages
from .tracking import Tracker
from .trajectory import AnchoredTrajectory, TrackResult


class EveryFrameSchedule:
    """Every frame through every stage, in the calling thread. ``process(frame)`` returns the pose and stats."""

    def __init__(self, config: PipelineConfig, camera: CameraIntrinsics, stages: Stages,
                 world: Map | None = None) -> None:
        self.stages = stages
        self.map = world if world is not None else Map(camera, config.tracker)
        self.tracker = Tracker(camera, config.tracker, world=self.map)
        self.record = AnchoredTrajectory(config.tracker)
        self.keyframe_log: list[KeyframeLog] = []  # no keyframe jobs apart from the frames
        self.loop_log = LoopLog()  # no loop closing in this schedule
        self.shed_jobs = 0  # no keyframe queue in this schedule
        self.mask: np.ndarray | None = None
        """the dynamic mask the latest frame was tracked with, for live views"""

    def process(self, frame: Frame) -> tuple[TrackResult, FrameStats]:
        """Detect, mask, match and track one frame."""
        t0 = time.perf_counter()
        keypoints = self.stages.detect(frame)
        t1 = time.perf_counter()
        mask, objects = (None, 0) if self.stages.dynamic_mask is None else self.stages.dynamic_mask(frame)
        self.mask = mask
        t2 = time.perf_counter()
        kept = keypoints if mask is None else drop_masked(keypoints, mask)
        result = self.tracker.track(frame.stamp, kept, frame.depth, match=self.stages.matcher_for(frame))
        if result.posed:
            self.record.add(frame.stamp, result.pose, result.tracked, len(self.map.keyframes) - 1,
                            self.map.keyframe_poses)
        t3 = time.perf_counter()
        stats = FrameStats(
            index=frame.index, stamp=frame.stamp, status=result.status, keypoints=len(keypoints),
            kept=len(kept), with_depth=result.num_with_depth, matches=result.num_matches,
            inliers=result.num_inliers, keyframe=result.is_keyframe, dynamic_objects=objects,
            mask_percent=0.0 if mask is None else float(100 * mask.mean()),
            ms_detector=(t1 - t0) * 1000, ms_yolo=(t2 - t1) * 1000, ms_tracker=(t3 - t2) * 1000,
            ms_total=(t3 - t0) * 1000, reason=result.reason,
        )
        return result, stats

    def map_copy(self) -> MapArrays | None:
        """The whole map as a map file's arrays (this schedule changes it only between frames)."""
        return self.map.arrays() if self.map.keyframes else None

    def map_snapshot(self, since: int = -1) -> MapSnapshot | None:
        """A copy of the map, or None while its version (the number of keyframes) is still ``since``."""
        return None if self.map.version == since else self.map.snapshot()

    def finish(self) -> None:
        """Nothing runs apart from the frames: nothing to wait for."""

    def refine(self) -> None:
        """After the last frame: bundle adjustment over the whole map refines :meth:`trajectory`."""
        self.map.final_bundle_adjustment()

    def close(self) -> None:
        """No worker threads to stop."""

    def trajectory(self) -> Trajectory:
        """Every frame's pose, re-attached to its keyframe as bundle adjustment left it."""
        return self.record.trajectory(self.map.keyframe_poses)
