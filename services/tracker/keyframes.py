"""The camera-rate schedule of one camera: optical-flow tracking on every frame, keyframes off the per-frame path.

Every frame is tracked by optical flow against the map (:class:`~.flow.FrameTracker`). 2HR detection, the
dynamic mask of the keyframe, descriptor matching, keyframe insertion, local bundle adjustment and
relocalisation run only on keyframes, in a mapping worker thread (:class:`Mapper`); dynamic masks for the
frames between come from a second worker on every n-th frame. The per-frame path never waits for either
(except for the very first map, and in a replay from disk whose keyframe job is too many frames late).

Where the networks run is injected (:class:`Stages`): in this process for ``twohr run``, or in the detector
and yolo services over Zenoh for the tracker service.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import cv2
import numpy as np

from twohr.config import PipelineConfig
from twohr.dataset import CameraIntrinsics, Frame
from twohr.features import Keypoints, drop_masked
from twohr.trajectory import Trajectory
from twohr.workers import Worker

from .core import Tracker, TrackResult
from .flow import FrameTracker, MapUpdate

log = logging.getLogger("twohr.keyframes")


@dataclass
class FrameStats:
    """One row of ``stats.csv``: what each stage did with a frame, and how long it took (ms)."""

    index: int
    stamp: float
    status: str
    keypoints: int
    kept: int
    with_depth: int
    matches: int
    inliers: int
    keyframe: bool
    dynamic_objects: int
    mask_percent: float
    ms_detector: float
    ms_yolo: float
    ms_tracker: float
    ms_total: float
    reason: str = ""
    mask_age: int = -1
    """frames since the YOLO detection behind this frame's mask (-1: no mask)"""


@dataclass
class KeyframeJob:
    """A frame handed to the mapping worker, with the pose optical flow gave it."""

    frame: Frame
    pose: np.ndarray
    gray: np.ndarray
    source: object = None
    """the frame as it arrived (the bus message), for stages that run in another process"""


@dataclass
class Stages:
    """Where the networks of the keyframe schedule run: in this process (:func:`local_stages`) or in the
    detector and yolo services, asked over the bus (the tracker service builds those). Each stage takes
    the frame and its ``source`` (the bus message it came in, or None)."""

    detect: Callable[[Frame, object], Keypoints]
    """(frame, source) -> the frame's keypoints"""
    dynamic_mask: Callable[[Frame, object], tuple[np.ndarray, int]] | None
    """(frame, source) -> (the frame's dynamic mask, True = moving; how many dynamic objects), or None = no mask"""
    match: Callable[[np.ndarray, np.ndarray], object]
    """(descriptors a, descriptors b) -> Matches"""


@dataclass
class KeyframeLog:
    """What one keyframe job cost and how late its map arrived (``lag_frames``), for the bench."""

    index: int
    status: str
    keyframe: bool
    keypoints: int
    kept: int
    ms_detector: float
    ms_yolo: float
    ms_mapping: float
    lag_frames: int = 0


class Mapper:
    """Keyframe work, off the per-frame path: YOLO and 2HR detection on the keyframe, masking, matching to
    the local map, keyframe insertion, local bundle adjustment and relocalisation (the keyframe tracker)."""

    def __init__(self, config: PipelineConfig, camera: CameraIntrinsics, stages: Stages) -> None:
        self.config = config
        self.stages = stages
        self.tracker = Tracker(camera, config.tracker, match=stages.match)

    def __call__(self, job: KeyframeJob) -> MapUpdate:
        frame = job.frame
        t0 = time.perf_counter()
        keypoints = self.stages.detect(frame, job.source)
        t1 = time.perf_counter()
        kept = keypoints
        if self.stages.dynamic_mask is not None:
            mask, _ = self.stages.dynamic_mask(frame, job.source)
            kept = drop_masked(keypoints, mask)
        t2 = time.perf_counter()
        tracker = self.tracker
        prediction = job.pose if tracker.initialised else None
        result = tracker.track(frame.stamp, kept, frame.depth, prediction=prediction, force_keyframe=True)
        seeds_xy, seeds_landmark = np.zeros((0, 2)), np.zeros(0, np.int64)
        if result.observed_landmarks is not None:
            order = np.argsort(-tracker.map.accepted[result.observed_landmarks], kind="stable")  # best observed first
            seeds_xy, seeds_landmark = result.observed_xy[order], result.observed_landmarks[order]
        keyframe_id = tracker.keyframes[-1].id if result.is_keyframe else -1
        t3 = time.perf_counter()
        timings = {"detector": (t1 - t0) * 1000, "yolo": (t2 - t1) * 1000, "mapping": (t3 - t2) * 1000,
                   "keypoints": len(keypoints), "kept": len(kept)}
        return MapUpdate(frame.index, frame.stamp, result, keyframe_id, seeds_xy, seeds_landmark,
                         tracker.map.positions.copy(), ~tracker.map.bad, tracker.keyframe_poses.copy(), job.gray,
                         timings)


class KeyframePipeline:
    """The camera-rate pipeline (see the module docstring). ``process(frame)`` returns the pose and stats."""

    def __init__(self, config: PipelineConfig, camera: CameraIntrinsics, stages: Stages, live: bool = False) -> None:
        self.config = config
        self.live = live
        runtime = config.pipeline
        if runtime.opencv_threads:
            cv2.setNumThreads(runtime.opencv_threads)  # process-wide: the LK pool otherwise fights the workers
        self.stages = stages
        self.mapper = Mapper(config, camera, self.stages)
        self.frames = FrameTracker(camera, config.tracker)
        self.mapping = Worker(self.mapper, "mapping", runtime.synchronous)
        self.masking = None
        if self.stages.dynamic_mask is not None:
            self.masking = Worker(self._dynamic_mask, "yolo", runtime.synchronous)
        self.keyframe_log: list[KeyframeLog] = []
        self.worker_errors = 0
        self._dynamic: tuple[int, np.ndarray, int] | None = None  # the latest YOLO mask: frame, mask, objects
        self._yolo_requested = -(10**9)
        self._last_index = 0
        self._job_index = 0  # the frame of the latest keyframe job
        self.map_version = 0
        """counts the map updates taken; a live view sends the map points again when it changes"""
        self.mask: np.ndarray | None = None

    def _dynamic_mask(self, job: tuple[Frame, object]) -> tuple[int, np.ndarray, int]:
        """YOLO worker: the dynamic mask of one frame (the frames after it reuse it, see :meth:`_mask`)."""
        frame, source = job
        return (frame.index, *self.stages.dynamic_mask(frame, source))

    def _collect(self, worker: Worker, wait: bool = False):
        """A worker's finished result; a failed job (say, a stage behind the bus timed out) is logged and
        counted, and the per-frame path goes on without it."""
        try:
            return worker.wait() if wait else worker.poll()
        except Exception:
            self.worker_errors += 1
            log.exception("the %s worker failed; going on without its result", worker.name)
            return None

    def _take(self, update: MapUpdate | None, index: int) -> None:
        if update is None:
            return
        self.frames.apply(update)
        self.map_version += 1
        t = update.timings
        self.keyframe_log.append(KeyframeLog(update.frame_index, update.result.status, update.keyframe_id >= 0,
                                             int(t["keypoints"]), int(t["kept"]), t["detector"], t["yolo"],
                                             t["mapping"], index - update.frame_index))

    def _mask(self, frame: Frame, source: object) -> tuple[np.ndarray | None, int, int]:
        """The freshest dynamic mask for this frame, if it is recent enough: (mask, age, objects)."""
        if self.masking is None:
            return None, -1, 0
        if frame.index - self._yolo_requested >= self.config.pipeline.yolo_every_n and not self.masking.busy:
            self.masking.submit((frame, source))
            self._yolo_requested = frame.index
        fresh = self._collect(self.masking)
        if fresh is not None:
            self._dynamic = fresh
        if self._dynamic is None:
            return None, -1, 0
        detected_at, mask, objects = self._dynamic
        age = frame.index - detected_at
        if age > self.config.pipeline.mask_max_age:
            return None, -1, 0
        # the mask as detected, not grown with its age: grown boxes soon cover a crowded view and starve the
        # flow of tracks; a track that a person has since covered fails the forward-backward check or RANSAC
        return mask, age, objects

    def process(self, frame: Frame, source: object = None, gray: np.ndarray | None = None
                ) -> tuple[TrackResult, FrameStats]:
        """Track one frame; hand it to the mapping worker when the map should grow and the worker is free.
        ``gray``, when the caller has it (decoded straight from the JPEG), saves the conversion; then the stages
        get the image from ``source`` and ``frame.rgb`` may be None."""
        t0 = time.perf_counter()
        self._last_index = frame.index
        update = self._collect(self.mapping)
        ms_waited = 0.0
        if update is None and not self.live and self.mapping.busy and (
                frame.index - self._job_index > self.config.pipeline.max_keyframe_lag):
            update = self._collect(self.mapping, wait=True)
            ms_waited = (time.perf_counter() - t0) * 1000
        self._take(update, frame.index)
        t_mask = time.perf_counter()
        mask, mask_age, objects = self._mask(frame, source)
        self.mask = mask  # the dynamic mask this frame was tracked with, for live views
        ms_yolo = (time.perf_counter() - t_mask) * 1000
        if gray is None:
            gray = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2GRAY)
        result = self.frames.track(frame.stamp, gray, frame.depth, mask)
        ms_detector = 0.0
        wants = self.frames.wants_keyframe(result)
        job = KeyframeJob(frame, result.pose, gray, source)
        if not self.frames.initialised:
            # no map yet: this frame waits for its keyframe, there is nothing to track against
            t_wait = time.perf_counter()
            self._take(self._collect(self.mapping, wait=True), frame.index)
            if self.mapping.submit(job):
                update = self._collect(self.mapping, wait=True)
                self._take(update, frame.index)
                if update is not None and update.keyframe_id >= 0:
                    result = update.result
            ms_detector = (time.perf_counter() - t_wait) * 1000
            wants = False
        ms_detector += ms_waited
        if wants and not self.mapping.busy and self.mapping.submit(job):
            self._job_index = frame.index
        ms_total = (time.perf_counter() - t0) * 1000
        stats = FrameStats(
            index=frame.index, stamp=frame.stamp, status=result.status, keypoints=result.num_keypoints,
            kept=result.num_matches, with_depth=result.num_with_depth, matches=result.num_matches,
            inliers=result.num_inliers, keyframe=bool(wants or result.is_keyframe), dynamic_objects=objects,
            mask_percent=0.0 if mask is None else float(100 * np.count_nonzero(mask) / mask.size),
            ms_detector=ms_detector, ms_yolo=ms_yolo, ms_tracker=ms_total - ms_detector - ms_yolo,
            ms_total=ms_total, reason=result.reason, mask_age=mask_age,
        )
        return result, stats

    def map_points(self) -> np.ndarray:
        """(N, 3) world positions of the map's usable landmarks, as of the latest map update taken."""
        return self.frames.landmarks[self.frames.usable]

    def finish(self) -> None:
        """Let the mapping worker finish its job (its bundle adjustment refines the trajectory), then stop."""
        self._take(self._collect(self.mapping, wait=True), self._last_index)
        self.close()

    def refine(self) -> None:
        """After :meth:`finish`: bundle adjustment over the whole map refines :meth:`trajectory`."""
        self.mapper.tracker.final_bundle_adjustment()

    def close(self) -> None:
        """Stop the worker threads (after their running jobs)."""
        self.mapping.close()
        if self.masking is not None:
            self.masking.close()

    def trajectory(self) -> Trajectory:
        """Every frame's pose, re-attached to its keyframe as bundle adjustment left it."""
        return self.frames.trajectory(self.mapper.tracker.keyframe_poses)


def map_snapshot(schedule: KeyframePipeline | Tracker, since: int = -1) -> tuple[int, np.ndarray | None]:
    """(version, (N, 3) world points) of a schedule's map; the version changes when the map does (keyframes).
    The points are None when the version is still ``since``."""
    if isinstance(schedule, KeyframePipeline):
        version = schedule.map_version
        return version, None if version == since else schedule.map_points()
    version = len(schedule.keyframes)
    return version, None if version == since else schedule.map.good_positions()


def online_trajectory(results: Iterable[TrackResult]) -> Trajectory:
    """The poses as they were estimated, frame by frame (what the tracker publishes live)."""
    results = list(results)
    return Trajectory(np.array([r.stamp for r in results]), np.array([r.pose for r in results]).reshape(-1, 4, 4))
