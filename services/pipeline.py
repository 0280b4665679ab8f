"""The in-process pipeline on one machine, in one process: the composition root of ``twohr run`` and
``twohr bench``. The Zenoh services compose the very same cores across processes.

Two schedules (``pipeline.mode``):

* ``keyframes`` (default, :class:`KeyframePipeline`): every frame is tracked by optical flow against the
  map (:class:`~.tracker.flow.FrameTracker`); 2HR detection, YOLO on the keyframe, descriptor matching and
  local bundle adjustment run only on keyframes, in a mapping worker thread; YOLO runs on every n-th frame
  in its own worker and its masks are propagated to the frames between. The per-frame path never waits
  for either worker (except for the very first map).
* ``every_frame`` (:class:`Pipeline`): detector -> yolo mask -> matcher -> tracker on every frame, as in
  the paper; kept for its ablations.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field

import cv2
import numpy as np

from twohr.config import PipelineConfig
from twohr.dataset import CameraIntrinsics, Frame
from twohr.features import Keypoints, drop_masked
from twohr.trajectory import Trajectory
from twohr.workers import Worker, prefetch

from .detector.core import build_detector
from .matcher.core import build_matcher
from .tracker.core import TRACKED_STATUSES, Tracker, TrackResult
from .tracker.flow import FrameTracker, MapUpdate
from .yolo.masks import DynamicMasker, propagated_mask


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
class StageOutput:
    """What the front end produced for a frame; cacheable so that tracker variants can reuse it."""

    keypoints: Keypoints
    mask: np.ndarray | None
    dynamic_objects: int
    ms_detector: float
    ms_yolo: float
    extra: dict = field(default_factory=dict)


class FrontEnd:
    """Keypoints and the dynamic mask of a frame (detector + yolo cores)."""

    def __init__(self, config: PipelineConfig) -> None:
        self.config = config
        self.detector = build_detector(config.detector)
        self.masker = DynamicMasker(config.yolo) if config.yolo.enabled else None

    def __call__(self, frame: Frame) -> StageOutput:
        t0 = time.perf_counter()
        keypoints = self.detector.detect(frame.rgb)
        t1 = time.perf_counter()
        mask, objects = None, 0
        if self.masker is not None:
            regions = self.masker(frame.rgb, frame.depth)
            mask, objects = regions.mask, len(regions.dynamic)
        t2 = time.perf_counter()
        return StageOutput(keypoints, mask, objects, (t1 - t0) * 1000, (t2 - t1) * 1000)


class Pipeline:
    """The whole SLAM pipeline for one camera. ``process(frame)`` returns the tracker's result and stats."""

    def __init__(self, config: PipelineConfig, camera: CameraIntrinsics) -> None:
        self.config = config
        self.front_end = FrontEnd(config)
        self.tracker = Tracker(camera, config.tracker, match=build_matcher(config.matcher))

    def process(self, frame: Frame, front: StageOutput | None = None) -> tuple[TrackResult, FrameStats]:
        """Track one frame; ``front`` reuses a cached front-end output instead of running the networks."""
        t0 = time.perf_counter()
        front = front or self.front_end(frame)
        kept = front.keypoints if front.mask is None else drop_masked(front.keypoints, front.mask)
        t1 = time.perf_counter()
        result = self.tracker.track(frame.stamp, kept, frame.depth)
        ms_tracker = (time.perf_counter() - t1) * 1000
        stats = FrameStats(
            index=frame.index, stamp=frame.stamp, status=result.status, keypoints=len(front.keypoints),
            kept=len(kept), with_depth=result.num_with_depth, matches=result.num_matches,
            inliers=result.num_inliers, keyframe=result.is_keyframe, dynamic_objects=front.dynamic_objects,
            mask_percent=0.0 if front.mask is None else float(100 * front.mask.mean()),
            ms_detector=front.ms_detector, ms_yolo=front.ms_yolo, ms_tracker=ms_tracker,
            ms_total=front.ms_detector + front.ms_yolo + (time.perf_counter() - t0) * 1000, reason=result.reason,
        )
        return result, stats

    def online_trajectory(self, results: Iterable[TrackResult]) -> Trajectory:
        """The poses as they were estimated, frame by frame (what the tracker publishes live)."""
        results = list(results)
        return Trajectory(np.array([r.stamp for r in results]), np.array([r.pose for r in results]).reshape(-1, 4, 4))


@dataclass
class KeyframeJob:
    """A frame handed to the mapping worker, with the pose optical flow gave it."""

    index: int
    stamp: float
    rgb: np.ndarray
    depth: np.ndarray
    pose: np.ndarray
    gray: np.ndarray


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

    def __init__(self, config: PipelineConfig, camera: CameraIntrinsics) -> None:
        self.config = config
        self.detector = build_detector(config.detector)
        self.masker = DynamicMasker(config.yolo) if config.yolo.enabled else None
        self.tracker = Tracker(camera, config.tracker, match=build_matcher(config.matcher))

    def __call__(self, job: KeyframeJob) -> MapUpdate:
        t0 = time.perf_counter()
        keypoints = self.detector.detect(job.rgb)
        t1 = time.perf_counter()
        kept = keypoints
        if self.masker is not None:
            dynamic = self.masker.detect_dynamic(job.rgb)
            mask = propagated_mask(dynamic, 0, job.depth.shape, self.config.yolo, job.depth)
            kept = drop_masked(keypoints, mask)
        t2 = time.perf_counter()
        tracker = self.tracker
        prediction = job.pose if tracker.initialised else None
        result = tracker.track(job.stamp, kept, job.depth, prediction=prediction, force_keyframe=True)
        seeds_xy, seeds_landmark = np.zeros((0, 2)), np.zeros(0, np.int64)
        if result.observed_landmarks is not None:
            order = np.argsort(-tracker.map.accepted[result.observed_landmarks], kind="stable")  # best observed first
            seeds_xy, seeds_landmark = result.observed_xy[order], result.observed_landmarks[order]
        keyframe_id = tracker.keyframes[-1].id if result.is_keyframe else -1
        t3 = time.perf_counter()
        timings = {"detector": (t1 - t0) * 1000, "yolo": (t2 - t1) * 1000, "mapping": (t3 - t2) * 1000,
                   "keypoints": len(keypoints), "kept": len(kept)}
        return MapUpdate(job.index, job.stamp, result, keyframe_id, seeds_xy, seeds_landmark,
                         tracker.map.positions.copy(), ~tracker.map.bad, tracker.keyframe_poses.copy(), job.gray,
                         timings)


class KeyframePipeline:
    """The camera-rate pipeline (see the module docstring). ``process(frame)`` returns the pose and stats."""

    def __init__(self, config: PipelineConfig, camera: CameraIntrinsics, live: bool = False) -> None:
        self.config = config
        self.live = live
        runtime = config.pipeline
        if runtime.opencv_threads:
            cv2.setNumThreads(runtime.opencv_threads)  # process-wide: the LK pool otherwise fights the workers
        self.mapper = Mapper(config, camera)
        self.frames = FrameTracker(camera, config.tracker)
        self.masker = DynamicMasker(config.yolo) if config.yolo.enabled else None
        self.mapping = Worker(self.mapper, "mapping", runtime.synchronous)
        self.masking = Worker(self._detect_dynamic, "yolo", runtime.synchronous) if self.masker else None
        self.keyframe_log: list[KeyframeLog] = []
        self._dynamic: tuple[int, np.ndarray, int] | None = None  # the latest YOLO mask: frame, mask, objects
        self._yolo_requested = -(10**9)
        self._last_index = 0
        self._job_index = 0  # the frame of the latest keyframe job
        self._warm_up(camera)

    def _warm_up(self, camera: CameraIntrinsics) -> None:
        """Compile the networks for the camera's size now, not on the first frames."""
        blank = np.zeros((camera.height, camera.width, 3), np.uint8)
        self.mapper.detector.detect(blank)
        for masker in (self.mapper.masker, self.masker):
            if masker is not None:
                masker.detect_dynamic(blank)

    def _detect_dynamic(self, job: tuple[int, np.ndarray, np.ndarray]) -> tuple[int, np.ndarray, int]:
        """YOLO worker: the dynamic mask of one frame (the frames after it reuse it, see :meth:`_mask`)."""
        index, rgb, depth = job
        dynamic = self.masker.detect_dynamic(rgb)
        return index, propagated_mask(dynamic, 0, depth.shape, self.config.yolo, depth), len(dynamic)

    def _take(self, update: MapUpdate | None, index: int) -> None:
        if update is None:
            return
        self.frames.apply(update)
        t = update.timings
        self.keyframe_log.append(KeyframeLog(update.frame_index, update.result.status, update.keyframe_id >= 0,
                                             int(t["keypoints"]), int(t["kept"]), t["detector"], t["yolo"],
                                             t["mapping"], index - update.frame_index))

    def _mask(self, frame: Frame) -> tuple[np.ndarray | None, int, int]:
        """The freshest dynamic mask for this frame, if it is recent enough: (mask, age, objects)."""
        if self.masking is None:
            return None, -1, 0
        if frame.index - self._yolo_requested >= self.config.pipeline.yolo_every_n and not self.masking.busy:
            self.masking.submit((frame.index, frame.rgb, frame.depth))
            self._yolo_requested = frame.index
        fresh = self.masking.poll()
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

    def process(self, frame: Frame) -> tuple[TrackResult, FrameStats]:
        """Track one frame; hand it to the mapping worker when the map should grow and the worker is free."""
        t0 = time.perf_counter()
        self._last_index = frame.index
        update = self.mapping.poll()
        ms_waited = 0.0
        if update is None and not self.live and self.mapping.busy and (
                frame.index - self._job_index > self.config.pipeline.max_keyframe_lag):
            update = self.mapping.wait()
            ms_waited = (time.perf_counter() - t0) * 1000
        self._take(update, frame.index)
        t_mask = time.perf_counter()
        mask, mask_age, objects = self._mask(frame)
        ms_yolo = (time.perf_counter() - t_mask) * 1000
        gray = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2GRAY)
        result = self.frames.track(frame.stamp, gray, frame.depth, mask)
        ms_detector = 0.0
        wants = self.frames.wants_keyframe(result)
        job = KeyframeJob(frame.index, frame.stamp, frame.rgb, frame.depth, result.pose, gray)
        if not self.frames.initialised:
            # no map yet: this frame waits for its keyframe, there is nothing to track against
            t_wait = time.perf_counter()
            self._take(self.mapping.wait(), frame.index)
            if self.mapping.submit(job):
                update = self.mapping.wait()
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

    def finish(self) -> None:
        """Let the mapping worker finish its job (its bundle adjustment refines the trajectory), then stop."""
        self._take(self.mapping.wait(), self._last_index)
        self.mapping.close()
        if self.masking is not None:
            self.masking.close()

    def trajectory(self) -> Trajectory:
        """Every frame's pose, re-attached to its keyframe as bundle adjustment left it."""
        return self.frames.trajectory(self.mapper.tracker.keyframe_poses)

    online_trajectory = Pipeline.online_trajectory


def stats_rows(stats: list[FrameStats]) -> list[dict]:
    return [asdict(s) for s in stats]


@dataclass
class RunResult:
    """Everything ``twohr run`` produces for one sequence."""

    trajectory: Trajectory
    online: Trajectory
    stats: list[FrameStats]
    skipped: list[int]
    wall_s: float
    keyframe_log: list[KeyframeLog] = field(default_factory=list)

    @property
    def tracked_percent(self) -> float:
        ok = sum(s.status in TRACKED_STATUSES for s in self.stats)
        return 100.0 * ok / max(1, len(self.stats))



def run_sequence(sequence, config: PipelineConfig, start: int = 0, stop: int | None = None, step: int = 1,
                 progress: bool = True, front_cache: dict[int, StageOutput] | None = None) -> RunResult:
    """Run the pipeline over a sequence (``twohr.dataset.RGBDSequence``). Corrupt frames are skipped
    and counted. ``front_cache`` (frame index -> StageOutput) reuses or collects front-end outputs
    (``every_frame`` mode only)."""
    from tqdm import tqdm

    keyframes = config.pipeline.mode == "keyframes"
    pipeline = KeyframePipeline(config, sequence.camera) if keyframes else Pipeline(config, sequence.camera)
    results, stats = [], []
    stop = len(sequence) if stop is None else min(stop, len(sequence))
    t0 = time.perf_counter()
    bar = tqdm(total=len(range(start, stop, step)), disable=not progress, unit="frame", desc=sequence.name,
               dynamic_ncols=True)
    frames = sequence.frames(start, stop, step)
    if keyframes:
        frames = prefetch(frames, config.pipeline.prefetch)
    for frame in frames:
        if keyframes:
            result, row = pipeline.process(frame)
        else:
            front = None if front_cache is None else front_cache.get(frame.index)
            if front is None:
                front = pipeline.front_end(frame)
                if front_cache is not None:
                    front_cache[frame.index] = front
            result, row = pipeline.process(frame, front)
        results.append(result)
        stats.append(row)
        bar.set_postfix(status=row.status, kept=row.kept, inliers=row.inliers, refresh=False)
        bar.update(1)
    bar.update(bar.total - bar.n)
    bar.close()
    if keyframes:
        pipeline.finish()
    wall = time.perf_counter() - t0
    online = pipeline.online_trajectory(results)
    if not results:
        refined = online
    else:
        refined = pipeline.trajectory() if keyframes else pipeline.tracker.trajectory()
    keyframe_log = pipeline.keyframe_log if keyframes else []
    return RunResult(refined, online, stats, list(sequence.skipped), wall, keyframe_log)
