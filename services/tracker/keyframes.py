"""The camera-rate schedule of one camera: optical-flow tracking on every frame, keyframes off the per-frame path.

Every frame is tracked by optical flow against the map (:class:`~.flow.FrameTracker`). 2HR detection, the
dynamic mask of the keyframe, descriptor matching, keyframe insertion, local bundle adjustment and
relocalisation run only on keyframes, in a mapping worker thread (:class:`Mapper`); dynamic masks for the
frames between come from a second worker on every n-th frame. The per-frame path never waits for either
(except for the very first map, while the camera is not yet found in a map it was given, and in a replay whose
keyframe job is too many frames late).

Where the networks run is injected (:class:`~.stages.Stages`): in this process for ``twohr run``, or in the
detector, yolo and matcher services over Zenoh for the tracker service. The map is one :class:`~.map.Map`, owned
by the mapping worker's keyframe job; the per-frame path reads :class:`~.map.MapSnapshot` copies of it.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import cv2
import numpy as np

from twohr.config import PipelineConfig
from twohr.dataset import CameraIntrinsics, Frame
from twohr.features import drop_masked
from twohr.messages import MessageError
from twohr.trajectory import Trajectory
from twohr.workers import Worker

from .core import Tracker
from .flow import FrameTracker, MapUpdate
from .map import Map, MapSnapshot
from .stages import FrameStats, KeyframeLog, Stages
from .trajectory import AnchoredTrajectory, TrackResult

log = logging.getLogger("twohr.keyframes")


@dataclass
class KeyframeJob:
    """A frame handed to the mapping worker, with the pose optical flow gave it."""

    frame: Frame
    pose: np.ndarray


class Mapper:
    """Keyframe work, off the per-frame path: YOLO and 2HR detection on the keyframe, masking, and the keyframe
    job (:class:`~.core.Tracker`: matching to the local map, keyframe insertion, local bundle adjustment and
    relocalisation) over the :class:`~.map.Map`."""

    def __init__(self, config: PipelineConfig, world: Map, stages: Stages) -> None:
        self.stages = stages
        self.map = world
        self.tracker = Tracker(world.camera, config.tracker, world=world)

    def __call__(self, job: KeyframeJob) -> MapUpdate:
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
                         frame.gray, timings)


class KeyframePipeline:
    """The camera-rate schedule (see the module docstring). ``process(frame)`` returns the pose and stats."""

    def __init__(self, config: PipelineConfig, camera: CameraIntrinsics, stages: Stages, live: bool = False,
                 world: Map | None = None) -> None:
        self.config = config
        self.live = live
        runtime = config.pipeline
        if runtime.opencv_threads:
            cv2.setNumThreads(runtime.opencv_threads)  # process-wide: the LK pool otherwise fights the workers
        self.stages = stages
        self.map = world if world is not None else Map(camera, config.tracker)
        self.mapper = Mapper(config, self.map, stages)
        self.frames = FrameTracker(camera, config.tracker)
        self.record = AnchoredTrajectory(config.tracker, bridge_gaps=True)
        self.mapping = Worker(self.mapper, "mapping", runtime.synchronous)
        self.masking = None
        if stages.dynamic_mask is not None:
            self.masking = Worker(self._dynamic_mask, "yolo", runtime.synchronous)
        self.keyframe_log: list[KeyframeLog] = []
        self.worker_errors = 0
        self.mask: np.ndarray | None = None
        """the dynamic mask the latest frame was tracked with, for live views"""
        self._dynamic: tuple[int, np.ndarray, int] | None = None  # the latest YOLO mask: frame number, mask, objects
        self._yolo_requested = -(10**9)
        # the schedule counts frames itself: a camera's frame indices may start again (a replay played once more,
        # a driver restarted) and must not stall the mask and keyframe timing
        self._number = -1  # of the latest frame
        self._job_number = 0  # of the latest keyframe job
        self._anchor = -1  # the latest keyframe taken: new frames' poses are kept relative to it

    def _dynamic_mask(self, numbered: tuple[int, Frame]) -> tuple[int, np.ndarray, int]:
        """YOLO worker: the dynamic mask of one frame (the frames after it reuse it, see :meth:`_mask`)."""
        number, frame = numbered
        return (number, *self.stages.dynamic_mask(frame))

    def _collect(self, worker: Worker, wait: bool = False):
        """A worker's finished result; a failed job (say, a stage behind the bus timed out) is logged and
        counted, and the per-frame path goes on without it."""
        try:
            return worker.wait() if wait else worker.poll()
        except (MessageError, TimeoutError) as exc:  # a stage behind the bus failed or is gone: no traceback
            self.worker_errors += 1
            log.warning("the %s worker's job failed (%s); going on without its result", worker.name, exc)
        except Exception:
            self.worker_errors += 1
            log.exception("the %s worker failed; going on without its result", worker.name)
        return None

    def _take(self, update: MapUpdate | None) -> None:
        if update is None:
            return
        self.frames.apply(update)
        if update.keyframe_id >= 0:
            self._anchor = update.keyframe_id
            self.record.attach_to_keyframe(update.stamp, update.keyframe_id, update.result.tracked,
                                           update.snapshot.keyframe_poses)
        t = update.timings
        self.keyframe_log.append(KeyframeLog(update.frame_index, update.result.status, update.keyframe_id >= 0,
                                             int(t["keypoints"]), int(t["kept"]), t["detector"], t["yolo"],
                                             t["mapping"], self._number - self._job_number))

    def _mask(self, frame: Frame) -> tuple[np.ndarray | None, int, int]:
        """The freshest dynamic mask for this frame, if it is recent enough: (mask, age, objects)."""
        if self.masking is None:
            return None, -1, 0
        if self._number - self._yolo_requested >= self.config.pipeline.yolo_every_n and not self.masking.busy:
            self.masking.submit((self._number, frame))
            self._yolo_requested = self._number
        fresh = self._collect(self.masking)
        if fresh is not None:
            self._dynamic = fresh
        if self._dynamic is None:
            return None, -1, 0
        detected_at, mask, objects = self._dynamic
        age = self._number - detected_at
        if age > self.config.pipeline.mask_max_age:
            return None, -1, 0
        # the mask as detected, not grown with its age: grown boxes soon cover a crowded view and starve the
        # flow of tracks; a track that a person has since covered fails the forward-backward check or RANSAC
        return mask, age, objects

    def process(self, frame: Frame) -> tuple[TrackResult, FrameStats]:
        """Track one frame; hand it to the mapping worker when the map should grow and the worker is free."""
        t0 = time.perf_counter()
        self._number += 1
        update = self._collect(self.mapping)
        ms_waited = 0.0
        if update is None and not self.live and self.mapping.busy and (
                self._number - self._job_number > self.config.pipeline.max_keyframe_lag):
            update = self._collect(self.mapping, wait=True)
            ms_waited = (time.perf_counter() - t0) * 1000
        self._take(update)
        t_mask = time.perf_counter()
        mask, mask_age, objects = self._mask(frame)
        self.mask = mask
        ms_yolo = (time.perf_counter() - t_mask) * 1000
        result = self.frames.track(frame.stamp, frame.gray, frame.depth, mask)
        in_given_map = not self.frames.initialised and self.mapper.tracker.given_map
        if in_given_map:  # no pose before the camera is found in a given map
            result = TrackResult(frame.stamp, np.eye(4), "relocalising", reason="looking for the camera in the map")
        else:
            self.record.add(frame.stamp, result.pose, result.tracked, self._anchor, self.frames.keyframe_poses)
        ms_detector = 0.0
        wants = self.frames.wants_keyframe(result)
        job = KeyframeJob(frame, result.pose)
        if not self.frames.initialised:
            # no map yet: this frame waits for its keyframe, there is nothing to track against
            t_wait = time.perf_counter()
            self._take(self._collect(self.mapping, wait=True))
            self._job_number = self._number
            if self.mapping.submit(job):
                update = self._collect(self.mapping, wait=True)
                self._take(update)
                if update is not None and (update.keyframe_id >= 0 or in_given_map):
                    result = update.result
            if in_given_map and result.tracked:
                self.record.add(frame.stamp, result.pose, True, self._anchor, self.frames.keyframe_poses)
            ms_detector = (time.perf_counter() - t_wait) * 1000
            wants = False
        ms_detector += ms_waited
        if wants and not self.mapping.busy and self.mapping.submit(job):
            self._job_number = self._number
        if result.observed_xy is None:
            result.observed_xy = self.frames.track_xy  # the map points optical flow followed into this frame
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

    def map_snapshot(self, since: int = -1) -> MapSnapshot | None:
        """The map as of the latest keyframe job taken, or None while its version is still ``since``."""
        snapshot = self.frames.snapshot
        return None if snapshot.version == since else snapshot

    def finish(self) -> None:
        """Let the mapping worker finish its job (its bundle adjustment refines the trajectory), then stop."""
        self._take(self._collect(self.mapping, wait=True))
        self.close()

    def refine(self) -> None:
        """After :meth:`finish`: bundle adjustment over the whole map refines :meth:`trajectory`."""
        self.map.final_bundle_adjustment()

    def close(self) -> None:
        """Stop the worker threads (after their running jobs)."""
        self.mapping.close()
        if self.masking is not None:
            self.masking.close()

    def trajectory(self) -> Trajectory:
        """Every frame's pose, re-attached to its keyframe as bundle adjustment left it."""
        return self.record.trajectory(self.map.keyframe_poses)
