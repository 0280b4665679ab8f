"""The camera-rate schedule of one camera: optical-flow tracking on every frame, keyframes off the per-frame path.

Every frame is tracked by optical flow against the map (:class:`~.flow.FrameTracker`). 2HR detection, the
dynamic mask of the keyframe, descriptor matching, keyframe insertion, local bundle adjustment and
relocalisation run only on keyframes, in a mapping worker thread (:class:`~.mapper.Mapper`); dynamic masks for the
frames between come from a second worker on every n-th frame. With ``pipeline.keyframes=tracked`` (or ``auto`` on a
slow detector) a keyframe is made from the tracks and new corners instead, and a third worker runs the 2HR
detector on the latest such keyframe for the mapping worker to join to the map (:meth:`~.mapper.Mapper.describe`).
The per-frame path never waits for either
(except for the very first map, while the camera is not yet found in a map it was given, and in a replay whose
keyframe job is too many frames late).

Where the networks run is injected (:class:`~.stages.Stages`): in this process for ``twohr run``, or in the
detector, yolo and matcher services over Zenoh for the tracker service. The map is one :class:`~.map.Map`, owned
by the mapping worker's keyframe job; the per-frame path reads :class:`~.map.MapSnapshot` copies of it.
"""

from __future__ import annotations

import logging
import time

import cv2
import numpy as np

from twohr.config import PipelineConfig
from twohr.dataset import CameraIntrinsics, Frame
from twohr.mapfile import MapArrays
from twohr.messages import MessageError
from twohr.places import PlaceMatch, PlaceQuery, PlaceVerdict, verify
from twohr.trajectory import Trajectory
from twohr.workers import Worker

from .flow import FrameTracker, MapUpdate
from .keyframe_policy import KeyframeQueue, may_queue, weakness
from .loops import LoopLog
from .map import Map, MapSnapshot
from .mapper import Detected, KeyframeJob, Mapper
from .stages import FrameStats, KeyframeLog, Stages
from .tracking import Tracker
from .trajectory import AnchoredTrajectory, FrameObservations, TrackResult

log = logging.getLogger("twohr.keyframes")


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
        self.mapper = Mapper(config, Tracker(camera, config.tracker, world=self.map), stages)
        self.frames = FrameTracker(camera, config.tracker)
        self.record = AnchoredTrajectory(config.tracker, bridge_gaps=True)
        self.mapping = Worker(self.mapper, "mapping", runtime.synchronous)
        self.masking = None
        if stages.dynamic_mask is not None:
            self.masking = Worker(self._dynamic_mask, "yolo", runtime.synchronous)
        self._detector_ms: list[float] = []  # the latest 2HR detections' latencies, for keyframes=auto
        # 2HR detection of tracked keyframes, on its own worker: the latest keyframe waiting for it, and the
        # detection waiting for the mapping worker to join it to the map
        self.detecting = Worker(lambda job: self.mapper.detect(*job), "detector", runtime.synchronous)
        # loop closing: the loop worker verifies the latest keyframe's place-recognition candidates, and a verified
        # loop waits for the mapping worker to correct the map
        self.closing = Worker(self._verify_loop, "loops", runtime.synchronous)
        self._loop_query: PlaceQuery | None = None
        self._loop: PlaceMatch | None = None
        self._to_detect: tuple[int, Frame, np.ndarray | None] | None = None
        self._detected: Detected | None = None
        self._job_frame: Frame | None = None
        self._detect_number = 0  # of the frame when the latest detection started
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
        self._map_copy: MapArrays | None = None  # the latest copy of the map the mapping worker made
        self.queue: KeyframeQueue[KeyframeJob] = KeyframeQueue(runtime.keyframe_queue, config.tracker)
        """keyframe jobs waiting for the busy mapping worker (:mod:`.keyframe_policy`)"""

    def _dynamic_mask(self, numbered: tuple[int, Frame]) -> tuple[int, np.ndarray, int]:
        """YOLO worker: the dynamic mask of one frame (the frames after it reuse it, see :meth:`_mask`)."""
        number, frame = numbered
        return (number, *self.stages.dynamic_mask(frame))

    @property
    def shed_jobs(self) -> int:
        """Keyframe jobs the queue dropped as stale (:class:`~.keyframe_policy.KeyframeQueue`)."""
        return self.queue.shed

    @property
    def loop_log(self) -> LoopLog:
        """Loops detected, accepted, rejected and closed so far, and every loop closed."""
        return self.mapper.loop_log

    def _verify_loop(self, job: tuple[PlaceQuery, Frame]) -> PlaceVerdict:
        """Loop worker: geometric verification of one keyframe's candidates (reads no map)."""
        query, frame = job
        try:
            return verify(query, self.map.K, self.config.loop_closing, self.config.tracker,
                          match=self.stages.matcher_for(frame))
        except (MessageError, TimeoutError) as exc:  # the matcher behind the bus failed: a loop not verified
            return PlaceVerdict(None, f"verification failed: {exc}")

    def _close_loops(self, frame: Frame, wait: bool = False) -> None:
        """Collect the loop worker's verdict and start it on the latest keyframe's candidates."""
        verdict = self._collect(self.closing, wait=wait)
        if verdict is not None:
            if verdict.match is not None:
                self.loop_log.accepted += 1
                self._loop = verdict.match  # no query waits now (_take keeps none while a loop is pending)
                self._loop_query = None  # built before the loop closes: its candidates are about to be joined
            else:
                self.loop_log.rejected += 1
            log.debug("loop verification: %s (%.0f ms)", verdict.reason, verdict.ms)
        if self._loop_query is not None and self._loop is None and not self.closing.busy:
            query, self._loop_query = self._loop_query, None
            self.loop_log.detected += 1
            self.closing.submit((query, frame))

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
        if update.timings and update.timings["detector"] > 0:
            self._detector_ms = [*self._detector_ms, update.timings["detector"]][-5:]
        if update.kind == "tracked" and update.keyframe_id >= 0 and self._job_frame is not None:
            self._to_detect = (update.keyframe_id, self._job_frame, update.mask)  # the latest one wins
        if update.loop_query is not None and self._loop is None:
            self._loop_query = update.loop_query  # the latest keyframe's wins
        self.frames.apply(update)
        if update.arrays is not None:
            self._map_copy = update.arrays
        if update.idle_rows is not None and len(update.idle_rows):
            self._give_back(update.idle_rows)
        if update.keyframe_id >= 0:
            self._anchor = update.keyframe_id
            self.record.attach_to_keyframe(update.stamp, update.keyframe_id, update.result.tracked,
                                           update.snapshot.keyframe_poses)
        t = update.timings
        self.keyframe_log.append(KeyframeLog(update.frame_index, update.result.status, update.keyframe_id >= 0,
                                             update.keypoints, update.kept, t["detector"], t["yolo"],
                                             t["mapping"], self._number - self._job_number, update.kind,
                                             t.get("job", 0.0)))

    def _give_back(self, idle: np.ndarray) -> None:
        """Give the mapping worker back the idle landmark rows that nothing on this side refers to: not the tracks,
        not the frames kept for refinement, not a waiting job. Called while the mapping worker is idle; while a loop
        is being verified or waits to close, none (its landmark pairs were found before the rows went idle)."""
        if self._loop is not None or self._loop_query is not None or self.closing.busy:
            return
        held = np.zeros(len(self.frames.landmarks), bool)
        for ids in (*self.frames.held_landmarks(), *self.queue.landmarks(), self.record.held_landmarks()):
            held[ids[ids < len(held)]] = True
        idle = idle[idle < len(held)]
        self.mapper.release(idle[~held[idle]])

    @property
    def tracked_keyframes(self) -> bool:
        """Whether keyframes are made from the tracks now (``pipeline.keyframes``; ``auto``: while the detector's
        median latency over the latest detections exceeds ``keyframe_budget_ms``)."""
        mode = self.config.pipeline.keyframes
        if mode != "auto":
            return mode == "tracked"
        return bool(self._detector_ms) and float(np.median(self._detector_ms)) > self.config.pipeline.keyframe_budget_ms

    def _detect_keyframes(self) -> None:
        """Collect the detector worker's keypoints (for the mapping worker) and start it on the latest tracked
        keyframe waiting for it."""
        done = self._collect(self.detecting)
        if done is None and not self.live and self.detecting.busy and (
                self._number - self._detect_number > self.config.pipeline.max_detection_lag):
            done = self._collect(self.detecting, wait=True)
        if done is not None:
            self._detected = done
        if self._to_detect is not None and not self.detecting.busy and self.detecting.submit(self._to_detect):
            self._to_detect = None
            self._detect_number = self._number

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
        in_given_map = not self.frames.initialised and self.mapper.given_map
        if in_given_map:  # no pose before the camera is found in a given map
            result = TrackResult(frame.stamp, np.eye(4), "relocalising", reason="looking for the camera in the map")
        else:
            self.record.add(frame.stamp, result.pose, result.tracked, self._anchor, self.frames.keyframe_poses,
                            FrameObservations.of(result))
        ms_detector = 0.0
        # the keyframe policy: a weak frame asks for a keyframe; a lost one (no evidence) asks at once
        evidence = self.frames.keyframe_evidence(result)
        wants = evidence is None or weakness(evidence, self.config.tracker) is not None
        tracks = None
        if result.status == "tracking" and self.tracked_keyframes:
            tracks = (self.frames.track_xy.copy(), self.frames.track_landmark.copy())
        # new corners need the frame's own dynamic mask: people move in the frames an older one lags
        job = KeyframeJob(frame, result.pose, tracks, mask if mask_age == 0 else None, self.frames.latest_keyframe,
                          self._number)
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
            self.queue.clear()
        ms_detector += ms_waited
        self._detect_keyframes()
        self._close_loops(frame)
        if not self.mapping.busy:
            if self._loop is not None and result.tracked:  # a verified loop corrects the map first
                if self.mapping.submit(self._loop):
                    self._loop = None
            elif self._detected is not None and result.tracked:  # an earlier keyframe's keypoints join the map
                if self.mapping.submit(self._detected):
                    self._detected = None
                    self._job_number = self._number
            else:
                if wants:
                    self.queue.push(job, self._seen(result))
                self._submit_waiting()
        elif wants and (evidence is None or may_queue(evidence, self.config.tracker)):
            self.queue.push(job, self._seen(result))
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

    def _seen(self, result: TrackResult) -> np.ndarray | None:
        """The landmarks a frame tracks, by which the keyframe queue judges redundancy (None: not tracking)."""
        return self.frames.track_landmark.copy() if result.status == "tracking" else None

    def _submit_waiting(self) -> None:
        """Start the idle mapping worker on the oldest waiting keyframe job."""
        job = self.queue.pop()
        if job is not None and self.mapping.submit(job):
            self._job_number = job.number
            self._job_frame = job.frame

    def map_copy(self) -> MapArrays | None:
        """The copy of the whole map the mapping worker made after its latest job, once (None: none since the last
        call); each call asks for the next one."""
        copy, self._map_copy = self._map_copy, None
        self.mapper.copy_wanted = True
        return copy

    def map_snapshot(self, since: int = -1) -> MapSnapshot | None:
        """The map as of the latest keyframe job taken, or None while its version is still ``since``."""
        snapshot = self.frames.snapshot
        return None if snapshot.version == since else snapshot

    def finish(self) -> None:
        """Let the workers finish their jobs (the mapping worker's bundle adjustment refines the trajectory; a
        detection still running joins the map; a replay's waiting keyframe jobs are mapped, a live camera's shed),
        then stop."""
        self._take(self._collect(self.mapping, wait=True))
        if self.live:  # the camera is gone, and the stages behind the bus may have closed its session: shed them
            self.queue.shed += len(self.queue)
            self.queue.clear()
        while len(self.queue):  # a replay's keyframes still waiting are the map's too
            self._submit_waiting()
            self._take(self._collect(self.mapping, wait=True))
        done = self._collect(self.detecting, wait=True)
        for detected in (self._detected, done):
            if detected is not None and self.mapping.submit(detected):
                self._take(self._collect(self.mapping, wait=True))
        self._detected = None
        if self._job_frame is not None:  # a loop found at the end still corrects the map
            for _ in range(2):  # a verification running, then one waiting
                self._close_loops(self._job_frame, wait=True)
            if self._loop is not None and self.mapping.submit(self._loop):
                self._take(self._collect(self.mapping, wait=True))
            self._loop = None
        self.close()

    def refine(self) -> None:
        """After :meth:`finish`: bundle adjustment over the whole map refines :meth:`trajectory`."""
        self.map.final_bundle_adjustment()

    def close(self) -> None:
        """Stop the worker threads (after their running jobs)."""
        self.mapping.close()
        self.detecting.close()
        self.closing.close()
        if self.masking is not None:
            self.masking.close()
        self.mapper.close()

    def trajectory(self) -> Trajectory:
        """Every frame's pose, re-attached to its keyframe as bundle adjustment left it, the latest frames measured
        again against the map's landmarks (``tracker.refine_frames``), smoothed."""
        return self.record.trajectory(self.map.keyframe_poses, self.map.snapshot(), self.map.K)
